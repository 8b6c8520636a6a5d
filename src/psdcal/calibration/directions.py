"""Calibration from known directions: a rotation stage, goniometer or collimated source on a two-axis mount.

The sensor sits on a platform (the *stage frame*); a source is seen at known
azimuth ``az`` and elevation ``el``. The direction to the source in the stage
frame is

    u(az, el) = (cos(el) sin(az), sin(el), cos(el) cos(az)) = R_y(az) R_x(-el) e_z,

i.e. ``az`` turns about the stage's vertical y axis (from +z towards +x) and
``el`` then raises the direction towards +y; ``az = el = 0`` is the stage's
+z axis. The sensor frame is rotated from the stage frame by the fitted
rotation ``R_s = rodrigues(stage_rx, stage_ry, stage_rz)``; a source at
infinity is seen along ``v = R_s u``. With a source at a finite distance
``D`` from the point where the stage's axes meet (``distance_mm``), and the
lens' projection centre offset by ``t`` (``offset_*_mm``, stage frame) from
that point, ``v = R_s (D u - t)`` (the offsets are fitted only then: for a
source at infinity they do not matter).

Then the template calibration's model (Eq 4 pinhole, the docs/model.md#distortion
distortion, Eq 1-2 readout through the channel gains) gives the measured
point ``d``. Levenberg-Marquardt over the intrinsics, distortion (same
switches as :func:`psdcal.calibrate`), optional gains, the stage rotation and
the optional offsets minimises ``|d_measured - d_model|^2`` (maximum
likelihood for Gaussian noise on the points). The start is linear: the
homography between the directions (projected on a plane across the sweep) and
the points is ``A R_s`` up to scale; its RQ decomposition gives the
intrinsics and the rotation.
"""
from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from psdcal.errors import ConvergenceError, DegenerateViewsError, InputError
from psdcal.model.params import DISTORTION_NAMES, Distortion, Intrinsics, ModelSpec
from psdcal.model.readout import LX_MM, LY_MM
from psdcal.model.projection import r_from_R

STAGE_NAMES = ("stage_rx", "stage_ry", "stage_rz")
OFFSET_NAMES = ("offset_x_mm", "offset_y_mm", "offset_z_mm")
DIRECTIONS_HEADER = ("az_deg", "el_deg", "x_mm", "y_mm")
DIRECTION_AMPLITUDES_HEADER = ("az_deg", "el_deg", "vx1", "vx2", "vy1", "vy2")
_INTR = ("f_mm", "cx_mm", "cy_mm", "skew", "fy_mm")
_GAINS = ("g_x2", "g_y1", "g_y2")
CONVENTION = "u = (cos(el) sin(az), sin(el), cos(el) cos(az)) in the stage frame; v = R_s (D u - t) in the sensor frame"


def stage_directions(az_deg, el_deg) -> np.ndarray:
    """Unit directions (N, 3) to the source in the stage frame (module docstring)."""
    az = np.radians(np.asarray(az_deg, dtype=float))
    el = np.radians(np.asarray(el_deg, dtype=float))
    return np.stack([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)], axis=-1)


def angles_from_directions(u) -> tuple[np.ndarray, np.ndarray]:
    """``(az_deg, el_deg)`` of directions (..., 3) in the stage frame (inverse of :func:`stage_directions`)."""
    u = np.asarray(u, dtype=float)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    return np.degrees(np.arctan2(u[..., 0], u[..., 2])), np.degrees(np.arcsin(np.clip(u[..., 1], -1, 1)))


# -- input ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DirectionsFile:
    """A directions CSV: ``az_deg,el_deg,x_mm,y_mm`` or ``az_deg,el_deg,vx1,vx2,vy1,vy2``.

    Attributes
    ----------
    az_deg, el_deg : (N,) known directions, degrees
    points_mm : (N, 2) impact points (from the amplitudes by Eq 1-2 when the file carries them)
    amplitudes : (N, 4) or None
    line_numbers : (N,) line of each row in the file
    kind : "points" | "amplitudes"
    path : str
    """

    az_deg: np.ndarray
    el_deg: np.ndarray
    points_mm: np.ndarray
    amplitudes: np.ndarray | None
    line_numbers: np.ndarray
    kind: str
    path: str


def read_directions(path, *, sensor_mm=(LX_MM, LY_MM)) -> DirectionsFile:
    """Read a directions CSV (either format); errors name the file, line and field."""
    from psdcal.io import _header, _number, _read_rows
    from psdcal.model.readout import impact_point

    path, rows = _read_rows(path)
    head = _header(path, rows, [DIRECTIONS_HEADER, DIRECTION_AMPLITUDES_HEADER])
    kind = "points" if head == DIRECTIONS_HEADER else "amplitudes"
    az, el, vals, lines = [], [], [], []
    for lineno, row in rows[1:]:
        if len(row) != len(head):
            raise InputError(f"expected {len(head)} fields, got {len(row)}", path=path, line=lineno)
        v = [_number(row[k], path, lineno, head[k]) for k in range(len(head))]
        if not (-180.0 <= v[0] <= 360.0):
            raise InputError(f"azimuth {v[0]:g} deg out of range", path=path, line=lineno, field="az_deg")
        if not (-90.0 < v[1] < 90.0):
            raise InputError(f"elevation {v[1]:g} deg must be within (-90, 90)", path=path, line=lineno, field="el_deg")
        az.append(v[0])
        el.append(v[1])
        vals.append(v[2:])
        lines.append(lineno)
    if len(az) < 6:
        raise InputError(f"{len(az)} directions; a direction calibration needs at least 6 (a sweep of both axes)", path=path)
    vals = np.array(vals, dtype=float)
    amps = None
    if kind == "amplitudes":
        amps = vals
        s = amps.sum(axis=1)
        bad = ~(np.abs(s) > 1e-12 * np.max(np.abs(amps), axis=1))
        if np.any(bad):
            raise InputError("the sum of the four signals is zero", path=path, line=lines[int(np.argmax(bad))], field="vx1")
        pts = impact_point(amps, *sensor_mm)
    else:
        pts = vals
    half = np.asarray(sensor_mm, dtype=float) / 2
    off = np.any(np.abs(pts) > half, axis=1)
    if np.any(off):
        i = int(np.argmax(off))
        raise InputError(f"point ({pts[i, 0]:.4g}, {pts[i, 1]:.4g}) mm is off the {sensor_mm[0]:g} x {sensor_mm[1]:g} mm sensor",
                         path=path, line=lines[i], field="x_mm" if kind == "points" else "vx1")
    return DirectionsFile(np.array(az), np.array(el), pts, amps, np.array(lines), kind, str(path))


# -- the model ----------------------------------------------------------------------------------
class DirectionsModel:
    """Measured points and their Jacobian for a direction calibration (state = free parameters).

    Parameters
    ----------
    u : (N, 3) stage-frame directions; meas : (N, 2) measured points, mm
    spec : ModelSpec; base : dict name -> value of every parameter (the fixed ones' values)
    fixed : names held at their base value
    distance_mm : source distance from the stage's axes (None: at infinity, no offsets)
    sensor_mm : PSD active lengths
    """

    def __init__(self, u, meas, spec: ModelSpec, base: dict, fixed=(), distance_mm=None, sensor_mm=(LX_MM, LY_MM)):
        self.u = np.asarray(u, dtype=float)
        self.meas = np.asarray(meas, dtype=float)
        self.spec = spec
        self.base = dict(base)
        self.distance_mm = None if distance_mm is None else float(distance_mm)
        self.sensor_mm = tuple(float(v) for v in sensor_mm)
        extra = STAGE_NAMES + (OFFSET_NAMES if self.distance_mm is not None else ())
        self.global_names = tuple(n for n in spec.global_names if n not in fixed)
        self.names = self.global_names + tuple(n for n in extra if n not in fixed)
        self._anchor = None

    def values(self, z) -> dict:
        vals = dict(self.base)
        vals.update(zip(self.names, np.asarray(z, dtype=float)))
        return vals

    def pack(self, vals: dict) -> np.ndarray:
        return np.array([vals[n] for n in self.names], dtype=float)

    def parts(self, vals):
        intr = Intrinsics(f_mm=float(vals["f_mm"]), cx_mm=float(vals["cx_mm"]), cy_mm=float(vals["cy_mm"]),
                          skew=float(vals["skew"]), fy_mm=float(vals["fy_mm"]) if self.spec.aspect else None)
        coef = np.array([vals[n] for n in DISTORTION_NAMES])
        gains = np.array([1.0, vals["g_x2"], vals["g_y1"], vals["g_y2"]])
        rvec = np.array([vals[n] for n in STAGE_NAMES])
        t = np.array([vals[n] for n in OFFSET_NAMES])
        return intr, coef, gains, rvec, t

    def source(self, t):
        """Stage-frame vectors from the projection centre to the source, (N, 3)."""
        return self.u if self.distance_mm is None else self.distance_mm * self.u - t

    def ideal(self, vals):
        """Ideal pinhole points x (N, 2) and the sensor-frame rays v (N, 3)."""
        from psdcal.calibration._refine import rodrigues_batch

        intr, coef, gains, rvec, t = self.parts(vals)
        R = rodrigues_batch(rvec[None], derivatives=False)[0][0]
        v = self.source(t) @ R.T
        xn, yn = v[:, 0] / v[:, 2], v[:, 1] / v[:, 2]
        x = np.stack([intr.f_mm * xn + intr.skew * yn + intr.cx_mm, intr.fy * yn + intr.cy_mm], axis=1)
        return x, v

    def _distort(self, x, coef, c):
        from psdcal.model.distortion import distort

        d = np.full(x.shape, np.nan)
        todo = np.arange(x.shape[0])
        for st in (self._anchor, self.meas, None):
            if st is None and todo.size == 0:
                break
            res = distort(x[todo], coef, c, d0_mm=None if st is None else st[todo], keep_failed=True)
            d[todo] = res.d_mm
            todo = todo[~np.asarray(res.converged)]
            if todo.size == 0:
                break
        return d

    def predict(self, z):
        """Modelled measured points (N, 2), mm (NaN where the distortion cannot be inverted)."""
        from psdcal.model.readout import gain_map

        vals = self.values(z)
        intr, coef, gains, rvec, t = self.parts(vals)
        x, v = self.ideal(vals)
        bad = v[:, 2] <= 0
        d = self._distort(x, coef, intr.c)
        d[bad] = np.nan
        if self.spec.fit_gains or not np.allclose(gains, 1.0):
            d = gain_map(d, gains, *self.sensor_mm)
        return d

    def residuals(self, z):
        r = (self.predict(z) - self.meas).ravel()
        return np.where(np.isfinite(r), r, 1e3)

    def jacobian(self, z):
        """(2N, n) analytic Jacobian (chain rule; the distortion's by the implicit function theorem)."""
        from psdcal.calibration._refine import rodrigues_batch
        from psdcal.model.distortion import distort_jacobians
        from psdcal.model.readout import gain_map

        vals = self.values(z)
        intr, coef, gains, rvec, t = self.parts(vals)
        R, dR = rodrigues_batch(rvec[None])
        R, dR = R[0], dR[0]
        s = self.source(t)
        v = s @ R.T
        N = v.shape[0]
        xn, yn = v[:, 0] / v[:, 2], v[:, 1] / v[:, 2]
        f, fy, sk = intr.f_mm, intr.fy, intr.skew
        x = np.stack([f * xn + sk * yn + intr.cx_mm, fy * yn + intr.cy_mm], axis=1)
        d = self._distort(x, coef, intr.c)
        self._anchor = np.where(np.isfinite(d), d, self.meas)
        dd_dx, dd_dc, dd_dcoef = distort_jacobians(np.nan_to_num(d), coef, intr.c)
        zero, one = np.zeros(N), np.ones(N)
        sep = self.spec.aspect
        dx_dintr = np.stack([np.stack([xn, zero if sep else yn], 1), np.stack([one, zero], 1), np.stack([zero, one], 1),
                             np.stack([yn, zero], 1), np.stack([zero, yn if sep else zero], 1)], axis=-1)  # Eq 4
        dd_dintr = dd_dx @ dx_dintr
        dd_dintr[:, :, 1:3] += dd_dc
        iz = 1.0 / v[:, 2]
        dx_dv = np.zeros((N, 2, 3))
        dx_dv[:, 0, 0] = f * iz
        dx_dv[:, 0, 1] = sk * iz
        dx_dv[:, 0, 2] = -(f * xn + sk * yn) * iz
        dx_dv[:, 1, 1] = fy * iz
        dx_dv[:, 1, 2] = -fy * yn * iz
        dd_dv = dd_dx @ dx_dv
        dv_dr = np.einsum("kij,nj->nik", dR, s)  # (N, 3, 3): column k = dR_k s
        dd_dr = dd_dv @ dv_dr
        dd_dt = dd_dv @ (-R)[None]
        if self.spec.fit_gains or not np.allclose(gains, 1.0):
            _, dy_dd, dy_dg = gain_map(np.nan_to_num(d), gains, *self.sensor_mm, jacobians=True)
        else:
            dy_dd, dy_dg = None, np.zeros((N, 2, 4))
        cols = []
        for n in self.names:
            if n in _INTR:
                c = dd_dintr[:, :, _INTR.index(n)]
            elif n in DISTORTION_NAMES:
                c = dd_dcoef[:, :, DISTORTION_NAMES.index(n)]
            elif n in STAGE_NAMES:
                c = dd_dr[:, :, STAGE_NAMES.index(n)]
            elif n in OFFSET_NAMES:
                c = dd_dt[:, :, OFFSET_NAMES.index(n)]
            else:
                cols.append(dy_dg[:, :, 1 + _GAINS.index(n)])
                continue
            cols.append(c if dy_dd is None else np.einsum("nij,nj->ni", dy_dd, c))
        J = np.stack(cols, axis=-1).reshape(2 * N, -1)
        bad = ~np.isfinite(d).all(axis=1) | (v[:, 2] <= 0)
        if np.any(bad):
            J = J.reshape(N, 2, -1)
            J[bad] = 0.0
            J = J.reshape(2 * N, -1)
        return np.nan_to_num(J)


# -- linear start ----------------------------------------------------------------------------
def linear_start(u, points_mm, *, skew: bool = False, aspect: bool = False):
    """Intrinsics and stage rotation from the homography between directions and points (no distortion).

    The directions are first turned so that their mean is the z axis and
    projected on the plane z = 1 there; the homography ``H ~ A R_s Q^T``
    between those plane points and the measured points is RQ-decomposed.

    Returns
    -------
    (Intrinsics, rvec (3,))
    """
    from scipy.linalg import rq

    from psdcal.calibration._homography import homography

    u = np.asarray(u, dtype=float)
    mean = u.mean(axis=0)
    mean /= np.linalg.norm(mean)
    axis = np.cross(mean, [0.0, 0.0, 1.0])
    sa = np.linalg.norm(axis)
    if sa < 1e-12:
        Q = np.eye(3) if mean[2] > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        from psdcal.calibration._refine import rodrigues_batch

        ang = math.atan2(sa, mean[2])
        Q = rodrigues_batch((axis / sa * ang)[None], derivatives=False)[0][0]
    w = u @ Q.T
    if np.any(w[:, 2] < 0.1):
        raise DegenerateViewsError("the directions span more than about 170 degrees; split the sweep")
    P = w[:, :2] / w[:, 2:3]
    sv = np.linalg.svd(P - P.mean(0), compute_uv=False)
    if sv[1] < 1e-6 * max(sv[0], 1e-300):
        raise DegenerateViewsError("the directions lie on one great circle (one axis swept): sweep both az and el")
    H = homography(P, np.asarray(points_mm, dtype=float), normalize=True, label="directions")
    K, Rm = rq(H)
    S = np.diag(np.sign(np.diag(K)))
    K, Rm = K @ S, S @ Rm
    if np.linalg.det(Rm) < 0:
        K, Rm = -K, -Rm
        S = np.diag(np.sign(np.diag(K)))
        K, Rm = K @ S, S @ Rm
    K = K / K[2, 2]
    f = float(np.sqrt(abs(K[0, 0] * K[1, 1]))) if not aspect else float(K[0, 0])
    intr = Intrinsics(f_mm=f, cx_mm=float(K[0, 2]), cy_mm=float(K[1, 2]), skew=float(K[0, 1]) if skew else 0.0,
                      fy_mm=float(K[1, 1]) if aspect else None)
    R = Rm @ Q
    return intr, r_from_R(R)


# -- the front door -------------------------------------------------------------------------------
def calibrate_directions(
    az_deg,
    el_deg,
    points_mm,
    *,
    radial: int = 2,
    tangential: bool = True,
    psd_radial: int = 0,
    skew: bool = False,
    aspect: bool = False,
    fit_gains: bool = False,
    gains=None,
    distance_mm: float | None = None,
    fix: dict | None = None,
    priors=None,
    sensor_mm: tuple[float, float] = (LX_MM, LY_MM),
    solver=None,
    point_ids=None,
    noise_mm: float | None = None,
    verdict: bool = True,
):
    """Calibrate a PSD + lens sensor from spots at known directions (a rotation stage sweep).

    Parameters
    ----------
    az_deg, el_deg : (N,) array_like
        Known azimuth and elevation of the source in the stage frame, degrees
        (convention in the module docstring).
    points_mm : (N, 2) array_like
        Measured impact points on the sensor, mm (the raw readout when ``fit_gains``).
    radial, tangential, psd_radial, skew, aspect, fit_gains, gains :
        The model switches of :func:`psdcal.calibrate`.
    distance_mm : float, optional
        Distance of the source from the stage's axes, mm; fits the offsets
        of the projection centre from the axes (``offset_x_mm`` ...). None:
        a source at infinity (collimated), no offsets.
    fix, priors :
        As in :func:`psdcal.calibrate`; ``fix`` may also hold the stage
        rotation (``stage_rx`` ...) and offsets.
    sensor_mm : (Lx, Ly), mm
    solver : SolverOptions
    point_ids : (N,) identifiers of the rows (default 0..N-1)
    noise_mm : float, optional
        Known noise per coordinate of the points, mm, for the verdict's ``noise`` check.
    verdict : bool
        Attach the statistical verdict (:func:`psdcal.calibration.verdict.assess_fit`: noise, residual
        structure over the sensor, plausibility) as ``result.verdict``.

    Returns
    -------
    CalibrationResult
        One "image" (``"stage"``) whose pose is the stage-to-sensor rotation
        (``rvec``) and the offsets (``tvec_mm``); the problem record has
        ``kind = "directions"`` and the stage fit (values, std, full covariance).

    Raises
    ------
    InputError, DegenerateViewsError, ConvergenceError
    """
    from psdcal.calibration._refine import SolverOptions, _single_threaded_blas
    from psdcal.calibration.priors import PARAMETER_NAMES, as_priors, map_fit, prior_rows, split_priors

    solver = solver or SolverOptions()
    az = np.asarray(az_deg, dtype=float).ravel()
    el = np.asarray(el_deg, dtype=float).ravel()
    X = np.asarray(points_mm, dtype=float)
    if X.ndim != 2 or X.shape[1] != 2 or az.shape != el.shape or az.size != X.shape[0]:
        raise InputError(f"az_deg {az.shape}, el_deg {el.shape} and points_mm {X.shape} must be (N,), (N,), (N, 2)")
    if not (np.all(np.isfinite(az)) and np.all(np.isfinite(el)) and np.all(np.isfinite(X))):
        raise InputError("directions and points must be finite")
    if distance_mm is not None and not (np.isfinite(distance_mm) and distance_mm > 0):
        raise InputError(f"distance_mm must be positive, got {distance_mm}", field="distance_mm")
    spec = ModelSpec(radial=radial, tangential=tangential, psd_radial=psd_radial, skew=skew, aspect=aspect, fit_gains=fit_gains)
    fix = {str(k): float(v) for k, v in (fix or {}).items()}
    allowed = PARAMETER_NAMES + STAGE_NAMES + OFFSET_NAMES
    for n, v in fix.items():
        if n not in allowed or not math.isfinite(v):
            raise InputError(f"fix: {n}={v} (NAME one of {', '.join(allowed)}, finite value)", field="fix")
    pri, fix = split_priors(as_priors(priors), fix)
    if "skew" in fix:
        spec = replace(spec, skew=True)
    if "fy_mm" in fix:
        spec = replace(spec, aspect=True)
    if any(n in fix for n in _GAINS) and not fit_gains:
        g = np.ones(4) if gains is None else np.asarray(gains, dtype=float) / float(np.asarray(gains)[0])
        for i, n in enumerate(_GAINS, start=1):
            if n in fix:
                g[i] = fix.pop(n)
        gains = g
    u = stage_directions(az, el)
    ids = tuple(range(az.size)) if point_ids is None else tuple(point_ids)
    g0 = np.ones(4) if gains is None else np.asarray(gains, dtype=float) / float(np.asarray(gains)[0])
    if not fit_gains and not np.allclose(g0, 1.0):
        from psdcal.calibration.gains import correct_points

        Xfit = correct_points(X, g0, *sensor_mm)
    else:
        Xfit = X
    n_min = 6 if not (skew or aspect or fit_gains) else 8
    if az.size < n_min:
        raise DegenerateViewsError(f"{az.size} directions; this model needs at least {n_min}")
    with _single_threaded_blas():
        intr0, rvec0 = linear_start(u, Xfit, skew=skew, aspect=aspect)
        base = {"f_mm": intr0.f_mm, "cx_mm": intr0.cx_mm, "cy_mm": intr0.cy_mm, "skew": intr0.skew,
                "fy_mm": intr0.fy if aspect else intr0.f_mm, **{n: 0.0 for n in DISTORTION_NAMES},
                "g_x2": 1.0, "g_y1": 1.0, "g_y2": 1.0, **dict(zip(STAGE_NAMES, rvec0)),
                **dict(zip(OFFSET_NAMES, (0.0, 0.0, 0.0)))}
        if fit_gains:
            base.update({"g_x2": g0[1], "g_y1": g0[2], "g_y2": g0[3]})
        base.update(fix)
        linear = {**intr0.to_dict(), "rvec": [float(v) for v in rvec0]}
        # stage 1: the core model (f, C, lens radial, rotation) without the terms it may trade against
        core = ModelSpec(radial=min(radial, 2), tangential=False, psd_radial=0, skew=False, aspect=False, fit_gains=False)
        m1 = DirectionsModel(u, Xfit, core, base, fixed=tuple(fix), distance_mm=None, sensor_mm=sensor_mm)
        try:
            fit1 = map_fit(m1.residuals, m1.jacobian, m1.pack(base), np.zeros((0, len(m1.names))), np.zeros(0), solver)
            if fit1.lm.status > 0 and np.all(np.isfinite(fit1.x)):
                base.update(m1.values(fit1.x))
                if aspect and "fy_mm" not in fix:
                    base["fy_mm"] = base["f_mm"]
                base.update(fix)
        except np.linalg.LinAlgError:
            pass
        model = DirectionsModel(u, Xfit, spec, base, fixed=tuple(fix), distance_mm=distance_mm, sensor_mm=sensor_mm)
        W, b = _prior_rows_full(pri, model, prior_rows)
        fit = map_fit(model.residuals, model.jacobian, model.pack(base), W, b, solver)
    res = _result(model, fit, az, el, X, ids, spec, g0, gains, fit_gains, fix, pri, distance_mm, sensor_mm, solver, linear)
    if verdict and np.all(np.isfinite(fit.x)):
        from psdcal.calibration.verdict import assess_fit

        v = assess_fit(res, model.jacobian(fit.x), model.residuals(fit.x), model.predict(fit.x), noise_mm=noise_mm)
        res = replace(res, verdict=v.to_dict())
    return res


def _prior_rows_full(priors, model, prior_rows):
    """Whitened prior rows over the whole state (global parameters, stage rotation, offsets)."""
    return prior_rows(priors, list(model.names))


def _result(model, fit, az, el, X, ids, spec, g0, gains_arg, fit_gains, fix, priors, distance_mm, sensor_mm, solver, linear):
    from psdcal.calibration.core import CalibrationResult, _jsonable

    vals = model.values(fit.x)
    intr, coef, gains, rvec, t = model.parts(vals)
    dist = Distortion.from_array(coef)
    pred = model.predict(fit.x)
    if not fit_gains and not np.allclose(g0, 1.0):
        from psdcal.model.readout import gain_map

        pred = gain_map(pred, g0, *sensor_mm)
        gains = g0
    res = X - pred
    sq = np.sum(res**2, axis=1)
    rms = float(np.sqrt(np.mean(sq)))
    ng = len(model.global_names)
    cov = fit.covariance
    std_all = np.sqrt(np.clip(np.diag(cov), 0, None))
    std = {n: None for n in ("f_mm", "cx_mm", "cy_mm", "skew", *DISTORTION_NAMES)}
    if spec.aspect:
        std["fy_mm"] = None
    for k, n in enumerate(model.global_names):
        std[n] = float(std_all[k])
    stage_std = {n: (float(std_all[model.names.index(n)]) if n in model.names else None)
                 for n in STAGE_NAMES + (OFFSET_NAMES if distance_mm is not None else ())}
    pose_std = np.array([[stage_std.get(n) if stage_std.get(n) is not None else (0.0 if n in OFFSET_NAMES else np.nan)
                          for n in STAGE_NAMES + OFFSET_NAMES]], dtype=float)
    converged = bool(fit.lm.status > 0) and bool(np.all(np.isfinite(fit.x)))
    problem = {
        "kind": "directions",
        "directions": {"az_deg": az.tolist(), "el_deg": el.tolist(), "point_ids": list(ids)},
        "points": {"image_ids": ["stage"], "xy_mm": _jsonable(X[None])},
        "options": {
            "radial": spec.radial, "tangential": spec.tangential, "psd_radial": spec.psd_radial, "skew": spec.skew,
            "aspect": spec.aspect, "fit_gains": spec.fit_gains,
            "gains": None if gains_arg is None else [float(v) for v in np.asarray(gains_arg, dtype=float)],
            "distance_mm": distance_mm, "sensor_mm": list(sensor_mm),
            "solver": {"ftol": solver.ftol, "xtol": solver.xtol, "gtol": solver.gtol, "max_iterations": solver.max_iterations},
            "fix": {n: float(v) for n, v in fix.items()}, "priors": [p.to_dict() for p in priors],
        },
        "stage": {
            "convention": CONVENTION,
            "rvec": [float(v) for v in rvec],
            "offset_mm": [float(v) for v in t] if distance_mm is not None else None,
            "distance_mm": distance_mm,
            "std": stage_std,
        },
        "fit": {"names": list(model.names), "values": [float(v) for v in fit.x], "covariance": cov.tolist(),
                "sigma2": fit.sigma2, "dof": fit.dof, "prior_dof": fit.prior_dof},
    }
    return CalibrationResult(
        intrinsics=intr,
        distortion=dist,
        gains=np.asarray(gains, dtype=float),
        model=spec,
        cost="image",
        param_names=tuple(model.global_names),
        covariance=cov[:ng, :ng],
        std=std,
        image_ids=("stage",),
        point_ids=tuple(ids),
        rvecs=rvec[None],
        tvecs_mm=(t if distance_mm is not None else np.zeros(3))[None],
        pose_std=pose_std,
        residuals_mm=res[None],
        rms_mm=rms,
        per_image_rms_mm=np.array([rms]),
        cost_rms=float(np.sqrt(np.mean(fit.residuals**2)) * np.sqrt(2.0)),
        sigma_mm=float(np.sqrt(fit.sigma2)),
        iterations=int(fit.lm.njev),
        converged=converged,
        message=str(fit.lm.message),
        stages={"linear": linear},
        problem=problem,
        sensor_mm=tuple(sensor_mm),
        created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    )


def check_result(result):
    """Raise ConvergenceError when a direction calibration did not converge or is not a camera."""
    intr = result.intrinsics
    if not result.converged:
        raise ConvergenceError(f"the direction calibration did not converge ({result.message}); check the directions' "
                               "convention (az about the vertical axis, then el) and signs, or use fewer distortion terms",
                               result=result)
    if not (np.isfinite(intr.f_mm) and intr.f_mm > 0 and intr.fy > 0):
        raise ConvergenceError(f"the direction calibration stopped at f = {intr.f_mm:.3g} mm, not a camera", result=result)
    res = np.asarray(result.residuals_mm, dtype=float)
    if not np.isfinite(result.rms_mm) or (res.size and not np.any(np.isfinite(res))):
        raise ConvergenceError("the direction calibration stopped where its model cannot reach the measured points "
                               "(no finite residual): check the directions' convention (az about the vertical axis, "
                               "then el: are az_deg and el_deg swapped?) and signs", result=result)
    return result


#: Two fitted parameters whose correlation exceeds this are reported as (nearly) not separable
#: by :func:`direction_warnings`.
DEGENERATE_CORRELATION = 0.999


def direction_warnings(result) -> list[str]:
    """What a direction calibration cannot separate, and the misfit check of the template calibration.

    A correlation above :data:`DEGENERATE_CORRELATION` between two fitted
    parameters (e.g. the offset along the boresight and f with a near
    source, or C and the stage rotation on a narrow sweep) means the sweep
    determines only their combination: both standard errors are large and
    honest, but a user reading one of them alone is misled. The fix is to
    measure one and ``--fix`` it (or give it a ``--prior``), or sweep wider.
    """
    out = list(result.warnings())
    fit = result.problem.get("fit") if result.problem else None
    if not fit:
        return out
    names = fit["names"]
    C = np.asarray(fit["covariance"], dtype=float)
    s = np.sqrt(np.clip(np.diag(C), 1e-300, None))
    rho = C / np.outer(s, s)
    np.fill_diagonal(rho, 0.0)
    done = set()
    for i, j in zip(*np.nonzero(np.abs(rho) > DEGENERATE_CORRELATION)):
        if i < j and i not in done and j not in done:
            done.update((i, j))
            out.append(f"{names[i]} and {names[j]} are not separable by this sweep (correlation {rho[i, j]:+.4f}): "
                       f"measure one and --fix it (or give it a --prior), or sweep wider")
    return out


def recalibrate_directions(d: dict):
    """Re-run a direction calibration from the problem record inside its JSON dict."""
    from psdcal.calibration._refine import SolverOptions
    from psdcal.calibration.priors import GaussianPrior

    p = d["problem"]
    o = p["options"]
    X = np.array([[np.nan if v is None else v for v in pt] for pt in p["points"]["xy_mm"][0]], dtype=float)
    return calibrate_directions(
        p["directions"]["az_deg"], p["directions"]["el_deg"], X, radial=o["radial"], tangential=o["tangential"],
        psd_radial=o["psd_radial"], skew=o["skew"], aspect=o["aspect"], fit_gains=o["fit_gains"], gains=o.get("gains"),
        distance_mm=o.get("distance_mm"), fix=o.get("fix") or None,
        priors=[GaussianPrior.from_dict(q) for q in o.get("priors") or []] or None,
        sensor_mm=tuple(o.get("sensor_mm", (LX_MM, LY_MM))), solver=SolverOptions(**o.get("solver", {})),
        point_ids=p["directions"].get("point_ids"),
    )


# -- using a direction calibration ------------------------------------------------------------
def _stage_of(result):
    st = result.problem.get("stage") if result.problem else None
    if st is None:
        raise InputError("not a direction calibration (no 'stage' record in its problem)")
    rvec = np.asarray(st["rvec"], dtype=float)
    t = np.zeros(3) if st.get("offset_mm") is None else np.asarray(st["offset_mm"], dtype=float)
    return rvec, t, st.get("distance_mm")


def _angles(vals, d_mm, spec_aspect, distance_mm, sensor_mm, gains_fitted):
    from psdcal.calibration._refine import rodrigues_batch
    from psdcal.calibration.gains import correct_points
    from psdcal.model.distortion import undistort

    coef = np.array([vals[n] for n in DISTORTION_NAMES])
    g = np.array([1.0, vals["g_x2"], vals["g_y1"], vals["g_y2"]])
    d = correct_points(d_mm, g, *sensor_mm) if not np.allclose(g, 1.0) else d_mm
    c = np.array([vals["cx_mm"], vals["cy_mm"]])
    x = undistort(d, coef, c)
    fy = vals["fy_mm"] if spec_aspect else vals["f_mm"]
    yn = (x[:, 1] - vals["cy_mm"]) / fy
    xn = (x[:, 0] - vals["cx_mm"] - vals["skew"] * yn) / vals["f_mm"]
    v = np.stack([xn, yn, np.ones_like(xn)], axis=1)
    R = rodrigues_batch(np.array([[vals[n] for n in STAGE_NAMES]]), derivatives=False)[0][0]
    w = v @ R  # R^T v
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    if distance_mm is not None:
        t = np.array([vals[n] for n in OFFSET_NAMES])
        tw = w @ t
        lam = -tw + np.sqrt(np.maximum(tw**2 - t @ t + distance_mm**2, 0.0))
        w = (t + lam[:, None] * w) / distance_mm
    return np.stack(angles_from_directions(w), axis=-1)


def predict_directions(result, points_mm, *, include_noise: bool = True):
    """Stage-frame (az, el) of measured spots with a direction calibration, and their covariance.

    Parameters
    ----------
    result : CalibrationResult of :func:`calibrate_directions` (or its JSON dict)
    points_mm : (N, 2) measured impact points (raw readout if the gains were fitted)
    include_noise : add the measurement noise (``sigma_mm`` per coordinate) to the parameters' uncertainty

    Returns
    -------
    angles_deg : (N, 2) azimuth, elevation in degrees
    cov_deg2 : (N, 2, 2) their covariance, deg^2 (first order, parameters' covariance + noise)
    """
    from psdcal.calibration.core import CalibrationResult

    if isinstance(result, dict):
        result = CalibrationResult.from_dict(result)
    fitrec = result.problem.get("fit") if result.problem else None
    if fitrec is None or result.problem.get("kind") != "directions":
        raise InputError("not a direction calibration (problem.kind != 'directions')")
    names = list(fitrec["names"])
    z = np.asarray(fitrec["values"], dtype=float)
    C = np.asarray(fitrec["covariance"], dtype=float)
    o = result.problem["options"]
    distance = o.get("distance_mm")
    d = np.asarray(points_mm, dtype=float).reshape(-1, 2)
    base = {"skew": result.intrinsics.skew, "fy_mm": result.intrinsics.fy, **result.intrinsics.to_dict(),
            **result.distortion.to_dict(), "g_x2": result.gains[1], "g_y1": result.gains[2], "g_y2": result.gains[3]}
    rvec, t, _ = _stage_of(result)
    base.update(zip(STAGE_NAMES, rvec))
    base.update(zip(OFFSET_NAMES, t))
    base = {k: float(v) for k, v in base.items() if v is not None}
    base.update(zip(names, z))
    aspect, sensor = result.model.aspect, result.sensor_mm

    def ang(vals, dd):
        return _angles(vals, dd, aspect, distance, sensor, result.model.fit_gains)

    a0 = ang(base, d)
    N = d.shape[0]
    Jp = np.zeros((N, 2, len(names)))
    for k, n in enumerate(names):
        h = 1e-6 * max(abs(base[n]), math.sqrt(max(C[k, k], 0.0)), 1e-9)
        vp, vm = dict(base), dict(base)
        vp[n] += h
        vm[n] -= h
        Jp[:, :, k] = (ang(vp, d) - ang(vm, d)) / (2 * h)
    cov = np.einsum("nik,kl,njl->nij", Jp, C, Jp)
    if include_noise:
        h = 1e-6
        Jd = np.zeros((N, 2, 2))
        for k in range(2):
            e = np.zeros(2)
            e[k] = h
            Jd[:, :, k] = (ang(base, d + e) - ang(base, d - e)) / (2 * h)
        cov = cov + result.sigma_mm**2 * np.einsum("nik,njk->nij", Jd, Jd)
    return a0, cov


def simulate_sweep(intrinsics: Intrinsics, distortion: Distortion, rvec, az_deg, el_deg, *, noise_mm: float = 0.0,
                   gains=None, distance_mm=None, offset_mm=(0.0, 0.0, 0.0), sensor_mm=(LX_MM, LY_MM), rng=None):
    """Measured points (N, 2) of a stage sweep with known truth (the forward model of this module)."""
    from psdcal.calibration._refine import rodrigues_batch
    from psdcal.model.distortion import distort
    from psdcal.model.readout import gain_map

    u = stage_directions(np.asarray(az_deg, float).ravel(), np.asarray(el_deg, float).ravel())
    s = u if distance_mm is None else distance_mm * u - np.asarray(offset_mm, dtype=float)
    R = rodrigues_batch(np.asarray(rvec, dtype=float)[None], derivatives=False)[0][0]
    v = s @ R.T
    xn, yn = v[:, 0] / v[:, 2], v[:, 1] / v[:, 2]
    x = np.stack([intrinsics.f_mm * xn + intrinsics.skew * yn + intrinsics.cx_mm, intrinsics.fy * yn + intrinsics.cy_mm], 1)
    d = distort(x, distortion, intrinsics.c).d_mm
    if gains is not None:
        d = gain_map(d, np.asarray(gains, dtype=float), *sensor_mm)
    if noise_mm > 0:
        rng = np.random.default_rng(rng)
        d = d + rng.normal(0.0, noise_mm, d.shape)
    return d


def sweep_grid(az_max_deg: float = 20.0, el_max_deg: float = 20.0, n_az: int = 9, n_el: int = 9):
    """A raster of stage directions (az, el) in degrees, (n_az * n_el,) each."""
    A, E = np.meshgrid(np.linspace(-az_max_deg, az_max_deg, n_az), np.linspace(-el_max_deg, el_max_deg, n_el))
    return A.ravel(), E.ravel()


def write_directions(path, az_deg, el_deg, points_mm) -> None:
    """Write a directions CSV ``az_deg,el_deg,x_mm,y_mm``."""
    from psdcal._atomic import write_text_atomic

    lines = [",".join(DIRECTIONS_HEADER)]
    for a, e, (x, y) in zip(np.ravel(az_deg), np.ravel(el_deg), np.asarray(points_mm, dtype=float)):
        lines.append(f"{a:.10g},{e:.10g},{x:.12g},{y:.12g}")
    write_text_atomic(Path(path), "\n".join(lines) + "\n")
