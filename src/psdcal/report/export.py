"""Export a psdcal calibration to other tools: OpenCV, ROS ``camera_info``.

psdcal's lens + PSD model is an *undistortion* model: a measured impact point
``d`` (mm on the sensor) maps to the ideal pinhole point ``x = undistort(d)``
(Eq 7-16) and to the normalised ray ``(xn, yn, 1) = A^-1 (x, y, 1)``.
OpenCV's model (``k1, k2, p1, p2[, k3[, k4, k5, k6]]``) is a *forward*
distortion model: the normalised ray ``n`` maps to the distorted normalised
point ``n_d``::

    n_d = n (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
          + [2 p1 xn yn + p2 (r^2 + 2 xn^2),  p1 (r^2 + 2 yn^2) + 2 p2 xn yn]

and ``n_d`` to pixels through the camera matrix K.  The two families are not
the same functions, so the OpenCV coefficients are *fitted*: over a dense grid
of the sensor, psdcal's rays ``n(d)`` and the distorted points
``n_d(d) = ((dx - cx) / f, (dy - cy) / fy)`` (what OpenCV computes from the
pixel of ``d`` through K) are known exactly; the coefficients minimise the
least-squares misfit of ``n_d`` (linear in them for 4 and 5 coefficients).
The fit error is then *measured*, not estimated: at every grid point the
fitted OpenCV model is inverted (Newton's method, to 1e-14) and the angle
between its ray and psdcal's ray is taken; the forward misfit is also given
in micrometres on the sensor.

Pixels: a PSD has none; a pitch ``pixel_um`` is chosen (default 1 um, so
pixel coordinates are micrometres).  OpenCV's pixel ``(u, v)`` is the centre
of a pixel, ``(0, 0)`` the first one; the image spans ``[-0.5, W - 0.5]``::

    u = (dx + Lx/2) / p - 0.5,   v = (dy + Ly/2) / p - 0.5     (p = pixel_um / 1000)

so ``u`` grows along the sensor's +x and ``v`` along its +y (no flip: OpenCV's
camera frame is then psdcal's sensor frame, z towards the scene).  With
``pixel_um = 1000`` pixels are millimetres.  OpenCV ignores a skew term of the
camera matrix, so a calibration with skew exports K with ``K[0, 1] = 0`` and the
skew's effect is part of the stated fit error.  Points are the gain-corrected
impact points (as for :func:`psdcal.measure.aoa.angles_from_points`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psdcal.errors import InputError

#: OpenCV's coefficient names in its order.
OPENCV_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
#: Allowed numbers of OpenCV coefficients.
OPENCV_COUNTS = (4, 5, 8)


@dataclass(frozen=True)
class OpenCVModel:
    """An OpenCV camera model fitted to a psdcal calibration.

    Attributes
    ----------
    camera_matrix : (3, 3) ndarray, pixels.
    dist_coeffs : (n,) ndarray, ``k1, k2, p1, p2[, k3[, k4, k5, k6]]`` (dimensionless, normalised coordinates).
    image_size : (width, height), pixels.
    pixel_um : float, the pixel pitch chosen, micrometres.
    fit_max_um, fit_rms_um : float
        Forward misfit on the sensor (where OpenCV puts the spot minus where
        psdcal does), max and RMS over the grid, micrometres.
    fit_max_deg, fit_rms_deg : float
        Angle between OpenCV's ray (its model inverted) and psdcal's ray, max and RMS over the grid, degrees.
    grid_points : int, number of sensor points of the fit.
    skew_dropped : float, the calibration's skew (mm) that K cannot carry.
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    image_size: tuple
    pixel_um: float
    fit_max_um: float
    fit_rms_um: float
    fit_max_deg: float
    fit_rms_deg: float
    grid_points: int
    skew_dropped: float = 0.0

    def fit_summary(self) -> dict:
        """The fit error as a JSON-able dict."""
        return {"fit_max_um": self.fit_max_um, "fit_rms_um": self.fit_rms_um, "fit_max_deg": self.fit_max_deg,
                "fit_rms_deg": self.fit_rms_deg, "grid_points": self.grid_points, "pixel_um": self.pixel_um}


def sensor_to_pixels(d_mm, sensor_mm, pixel_um: float) -> np.ndarray:
    """OpenCV pixel coordinates (..., 2) of sensor points ``d_mm`` (..., 2) (see the module docstring)."""
    p = pixel_um * 1e-3
    d = np.asarray(d_mm, dtype=float)
    return np.stack([(d[..., 0] + sensor_mm[0] / 2) / p - 0.5, (d[..., 1] + sensor_mm[1] / 2) / p - 0.5], axis=-1)


def opencv_distort(n, coeffs) -> np.ndarray:
    """OpenCV's forward distortion of normalised points ``n`` (..., 2) with ``coeffs`` (4, 5 or 8,)."""
    c = np.zeros(8)
    c[: len(coeffs)] = coeffs
    k1, k2, p1, p2, k3, k4, k5, k6 = c
    x, y = n[..., 0], n[..., 1]
    r2 = x * x + y * y
    rad = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    return np.stack([x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y],
                    axis=-1)


def opencv_undistort(nd, coeffs, *, tol: float = 1e-14, max_iter: int = 100) -> np.ndarray:
    """Invert :func:`opencv_distort` by Newton's method (central-difference Jacobian).

    Returns (..., 2) normalised points; NaN where it does not converge.
    """
    nd = np.asarray(nd, dtype=float)
    n = nd.copy()
    h = 1e-7
    for _ in range(max_iter):
        r = opencv_distort(n, coeffs) - nd
        if np.all(np.abs(r) <= tol * np.maximum(1.0, np.abs(nd))):
            break
        J = np.empty(n.shape + (2,))
        for k in range(2):
            e = np.zeros(2)
            e[k] = h
            J[..., :, k] = (opencv_distort(n + e, coeffs) - opencv_distort(n - e, coeffs)) / (2 * h)
        det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        with np.errstate(invalid="ignore", divide="ignore"):
            dx = (J[..., 1, 1] * r[..., 0] - J[..., 0, 1] * r[..., 1]) / det
            dy = (-J[..., 1, 0] * r[..., 0] + J[..., 0, 0] * r[..., 1]) / det
        n = n - np.stack([dx, dy], axis=-1)
    r = opencv_distort(n, coeffs) - nd
    bad = ~np.all(np.abs(r) <= 1e-10 * np.maximum(1.0, np.abs(nd)), axis=-1)
    return np.where(bad[..., None], np.nan, n)


def _linear_fit(n, nd, n_coeffs):
    """Least-squares k1, k2, p1, p2[, k3] of ``opencv_distort(n) = nd`` (linear in them)."""
    x, y = n[:, 0], n[:, 1]
    r2 = x * x + y * y
    zx = np.stack([x * r2, x * r2**2, 2 * x * y, r2 + 2 * x * x, x * r2**3], axis=1)
    zy = np.stack([y * r2, y * r2**2, r2 + 2 * y * y, 2 * x * y, y * r2**3], axis=1)
    A = np.concatenate([zx, zy])[:, : min(n_coeffs, 5)]
    b = np.concatenate([nd[:, 0] - x, nd[:, 1] - y])
    return np.linalg.lstsq(A, b, rcond=None)[0]


def _refine(n, d, kc, coeffs, refine_k, tie_f):
    """Least squares of the spot position on the sensor, ``K(opencv_distort(n)) - d`` (mm), over D (and K).

    ``kc`` is ``(fx, fy, cx, cy)`` in mm; with ``tie_f`` one focal length serves both axes.
    """
    from scipy.optimize import least_squares

    nk = (3 if tie_f else 4) if refine_k else 0

    def kvec(z):
        if not refine_k:
            return kc
        return np.array([z[0], z[0], z[1], z[2]]) if tie_f else z[:4]

    def spot(z):
        k = kvec(z)
        nd = opencv_distort(n, z[nk:])
        return np.stack([k[0] * nd[:, 0] + k[2], k[1] * nd[:, 1] + k[3]], axis=1)

    head = ([kc[0], kc[2], kc[3]] if tie_f else list(kc)) if refine_k else []
    z0 = np.concatenate([head, coeffs])
    sol = least_squares(lambda z: (spot(z) - d).ravel(), z0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return kvec(sol.x), sol.x[nk:]


def fit_opencv(result, *, pixel_um: float = 1.0, n_coeffs: int = 5, n_grid: int = 61,
               refine_k: bool = True) -> OpenCVModel:
    """Fit OpenCV's camera model to a calibration over the whole sensor.

    Parameters
    ----------
    result : CalibrationResult
    pixel_um : float
        Pixel pitch of the exported model, micrometres (1000: pixels are mm).
    n_coeffs : 4, 5 or 8
        ``k1, k2, p1, p2`` / ``+ k3`` (ROS ``plumb_bob``) / ``+ k3, k4, k5, k6``
        (OpenCV's rational model, ROS ``rational_polynomial``).
    n_grid : int
        Grid points per side of the sensor for the fit and its error.
    refine_k : bool
        Also adjust ``fx, fy, cx, cy`` of K (from psdcal's ``f, fy, C``) in the
        fit: OpenCV has a single distortion centre, psdcal two (the lens' C and
        the PSD's electrical centre), and a shifted K absorbs part of the
        difference (``fx = fy`` unless the calibration has a separate ``fy_mm``).  With False, K is psdcal's and only the coefficients are fitted.

    Returns
    -------
    OpenCVModel
    """
    from psdcal.measure.aoa import angles_from_points
    from psdcal.measure.sensor_model import SensorModel
    from psdcal.model.readout import sensor_grid_mm

    if n_coeffs not in OPENCV_COUNTS:
        raise InputError(f"the number of OpenCV coefficients must be one of {OPENCV_COUNTS}, got {n_coeffs}",
                         field="coeffs")
    if not (np.isfinite(pixel_um) and pixel_um > 0):
        raise InputError(f"the pixel pitch must be a positive number of micrometres, got {pixel_um!r}", field="pixel_um")
    intr = result.intrinsics
    sensor = tuple(float(v) for v in result.sensor_mm)
    d = sensor_grid_mm(sensor, n_grid).reshape(-1, 2)
    a = angles_from_points(d, SensorModel(intrinsics=intr, distortion=result.distortion), derivatives=False)
    ok = np.all(np.isfinite(a.n), axis=1)
    d, n = d[ok], a.n[ok]
    f, fy = intr.f_mm, intr.fy
    nd = np.stack([(d[:, 0] - intr.cx_mm) / f, (d[:, 1] - intr.cy_mm) / fy], axis=1)
    coeffs = _linear_fit(n, nd, n_coeffs)
    if n_coeffs == 8:
        coeffs = np.concatenate([coeffs, np.zeros(3)])
    kc = np.array([f, fy, intr.cx_mm, intr.cy_mm])
    if refine_k or n_coeffs == 8:
        kc, coeffs = _refine(n, d, kc, coeffs, refine_k, tie_f=intr.fy_mm is None)
    f, fy, cx, cy = kc
    nd = np.stack([(d[:, 0] - cx) / f, (d[:, 1] - cy) / fy], axis=1)
    # the fit error, measured
    fwd = (opencv_distort(n, coeffs) - nd) * np.array([f, fy])
    e_um = np.linalg.norm(fwd, axis=1) * 1e3
    n_cv = opencv_undistort(nd, coeffs)
    ray_cv = np.concatenate([n_cv, np.ones((len(n_cv), 1))], axis=1)
    ray = np.concatenate([n, np.ones((len(n), 1))], axis=1)
    ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(ray_cv, ray), axis=1), np.sum(ray_cv * ray, axis=1)))
    if np.any(~np.isfinite(ang)):  # the fitted model folds over inside the sensor: no inverse there
        raise InputError(
            f"the fitted {n_coeffs}-coefficient OpenCV model has no inverse over the whole sensor (it folds over at "
            f"{int(np.sum(~np.isfinite(ang)))} of {len(ang)} grid points; forward misfit up to {e_um.max():.3g} um)"
            + ("; use 8 coefficients (OpenCV's rational model)" if n_coeffs < 8 else ""),
            field="coeffs")
    p = pixel_um * 1e-3
    c_px = sensor_to_pixels(np.array([cx, cy]), sensor, pixel_um)
    K = np.array([[f / p, 0.0, c_px[0]], [0.0, fy / p, c_px[1]], [0.0, 0.0, 1.0]])
    size = (int(round(sensor[0] / p)), int(round(sensor[1] / p)))
    return OpenCVModel(K, np.asarray(coeffs, dtype=float), size, float(pixel_um), float(e_um.max()),
                       float(np.sqrt(np.mean(e_um**2))), float(ang.max()), float(np.sqrt(np.mean(ang**2))),
                       int(len(d)), float(intr.skew))


def _fmt(v: float) -> str:
    return repr(float(v))


def _row(values) -> str:
    return "[ " + ", ".join(_fmt(v) for v in np.ravel(values)) + " ]"


def _fit_comment(m: OpenCVModel) -> list[str]:
    return [
        f"# fitted to psdcal's model over {m.grid_points} points of the sensor; fit error:",
        f"#   forward misfit on the sensor: max {m.fit_max_um:.4g} um, RMS {m.fit_rms_um:.4g} um",
        f"#   ray angle (OpenCV's model inverted vs psdcal): max {m.fit_max_deg:.3g} deg, RMS {m.fit_rms_deg:.3g} deg",
        f"# pixel pitch {m.pixel_um:g} um: u = (x_mm + Lx/2) / pitch - 0.5, v = (y_mm + Ly/2) / pitch - 0.5",
    ] + ([f"# the calibration's skew ({m.skew_dropped:.3g} mm) is not in K (OpenCV ignores it); it is in the fit error"]
         if m.skew_dropped else [])


def opencv_yaml(m: OpenCVModel, *, source: str = "") -> str:
    """The model as an OpenCV ``FileStorage`` YAML file (``camera_matrix``, ``distortion_coefficients``).

    Extra keys ``psdcal_*`` carry the pixel pitch and the fit error; read it with
    ``cv2.FileStorage(path, cv2.FILE_STORAGE_READ).getNode("camera_matrix").mat()``.
    """
    lines = ["%YAML:1.0", "---"]
    lines += [f"# psdcal export of {source}" if source else "# psdcal export"] + _fit_comment(m)
    lines += [f"image_width: {m.image_size[0]}", f"image_height: {m.image_size[1]}"]
    lines += ["camera_matrix: !!opencv-matrix", "   rows: 3", "   cols: 3", "   dt: d", f"   data: {_row(m.camera_matrix)}"]
    lines += ["distortion_coefficients: !!opencv-matrix", "   rows: 1", f"   cols: {m.dist_coeffs.size}", "   dt: d",
              f"   data: {_row(m.dist_coeffs)}"]
    lines += [f"psdcal_pixel_um: {_fmt(m.pixel_um)}", f"psdcal_fit_max_um: {_fmt(m.fit_max_um)}",
              f"psdcal_fit_rms_um: {_fmt(m.fit_rms_um)}", f"psdcal_fit_max_deg: {_fmt(m.fit_max_deg)}",
              f"psdcal_fit_rms_deg: {_fmt(m.fit_rms_deg)}"]
    return "\n".join(lines) + "\n"


def ros_camera_info(m: OpenCVModel, *, camera_name: str = "psd_sensor", source: str = "") -> str:
    """The model as a ROS ``camera_info`` YAML (the format of ``camera_calibration_parsers``).

    ``distortion_model`` is ``plumb_bob`` (5 coefficients; a 4-coefficient fit
    gets ``k3 = 0``) or ``rational_polynomial`` (8); R is the identity and
    ``P = [K | 0]`` (a single sensor, no rectification).
    """
    D = m.dist_coeffs
    if D.size == 4:
        D = np.concatenate([D, [0.0]])
    model = "plumb_bob" if D.size == 5 else "rational_polynomial"
    K = m.camera_matrix
    P = np.concatenate([K, np.zeros((3, 1))], axis=1)
    lines = [f"# psdcal export of {source}" if source else "# psdcal export"] + _fit_comment(m)
    lines += [f"image_width: {m.image_size[0]}", f"image_height: {m.image_size[1]}", f"camera_name: {camera_name}"]
    lines += ["camera_matrix:", "  rows: 3", "  cols: 3", f"  data: {_row(K)}"]
    lines += [f"distortion_model: {model}", "distortion_coefficients:", "  rows: 1", f"  cols: {D.size}",
              f"  data: {_row(D)}"]
    lines += ["rectification_matrix:", "  rows: 3", "  cols: 3", f"  data: {_row(np.eye(3))}"]
    lines += ["projection_matrix:", "  rows: 3", "  cols: 4", f"  data: {_row(P)}"]
    return "\n".join(lines) + "\n"


__all__ = ["OPENCV_COUNTS", "OPENCV_NAMES", "OpenCVModel", "fit_opencv", "opencv_distort", "opencv_undistort",
           "opencv_yaml", "ros_camera_info", "sensor_to_pixels"]
