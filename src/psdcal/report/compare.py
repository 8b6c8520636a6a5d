"""Angle of arrival over the field of view: its uncertainty, and two calibrations compared.

For a point ``d`` on the sensor (a measured impact point, after any gain
correction) a calibration gives the angle of arrival (docs/model.md#angle-of-arrival-and-position)::

    x = undistort(d),  (xn, yn, 1) = A^-1 (x, y, 1),  alpha = (atan xn, atan yn)

and, from the covariance ``Sigma`` of its global parameters (poses
marginalised), the covariance of ``alpha`` to first order,
``J Sigma J^T`` with ``J = d alpha / d p`` (analytic, through
:func:`psdcal.measure.aoa.angles_from_points`).  This part of the error is
*systematic*: the same for every measurement the sensor makes.

Two calibrations A and B of one sensor read the same ``d`` as two directions.
Their difference is reported as the angle between the two rays (degrees) and
in units of the combined uncertainty: the Mahalanobis length
``m = sqrt(D^T (Sigma_A + Sigma_B)^-1 D)`` of ``D = alpha_A - alpha_B``, which
for two independent calibrations of an unchanged sensor is about 1 (the
length of a 2D standard normal vector: RMS sqrt 2, 99 % below 3.03).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psdcal.errors import InputError
from psdcal.model.readout import sensor_grid_mm

#: Above this maximum Mahalanobis length (over the field of view) two calibrations differ visibly.
VISIBLE_SIGMA = 4.0



def sensor_model(result):
    """The :class:`psdcal.measure.sensor_model.SensorModel` of a calibration (parameters and covariance).

    A calibration without a covariance matrix (a file with only ``std``) gets
    the diagonal covariance of its standard errors, as
    :meth:`psdcal.measure.sensor_model.SensorModel.from_dict` does.
    """
    from psdcal.measure.sensor_model import PARAMETER_NAMES, SensorModel

    names = tuple(result.param_names)
    cov = np.asarray(result.covariance, dtype=float)
    if not names or cov.size == 0:
        std = {n: v for n, v in (result.std or {}).items() if n in PARAMETER_NAMES and v is not None}
        names = tuple(n for n in PARAMETER_NAMES if n in std)
        cov = np.diag([float(std[n]) ** 2 for n in names]) if names else np.zeros((0, 0))
    return SensorModel(
        intrinsics=result.intrinsics,
        distortion=result.distortion,
        names=names,
        covariance=cov,
        gains=np.asarray(result.gains, dtype=float),
        lx_mm=float(result.sensor_mm[0]),
        ly_mm=float(result.sensor_mm[1]),
    )


@dataclass(frozen=True)
class AoAField:
    """Angles of arrival and their calibration uncertainty at points of the sensor.

    Attributes
    ----------
    d_mm : (..., 2) ndarray, the sensor points, mm.
    alpha_rad : (..., 2) ndarray, ``(alpha_x, alpha_y)``, rad.
    cov_alpha_rad2 : (..., 2, 2) ndarray, covariance of ``alpha`` from the calibration, rad^2.
    ray : (..., 3) ndarray, unit ray directions in the camera frame.
    """

    d_mm: np.ndarray
    alpha_rad: np.ndarray
    cov_alpha_rad2: np.ndarray
    ray: np.ndarray

    @property
    def alpha_deg(self) -> np.ndarray:
        """``alpha`` in degrees (..., 2)."""
        return np.degrees(self.alpha_rad)

    @property
    def sigma_alpha_deg(self) -> np.ndarray:
        """1-sigma of ``(alpha_x, alpha_y)`` (..., 2), degrees."""
        return np.degrees(np.sqrt(np.clip(np.diagonal(self.cov_alpha_rad2, axis1=-2, axis2=-1), 0.0, None)))

    @property
    def sigma_total_deg(self) -> np.ndarray:
        """``sqrt(var alpha_x + var alpha_y)`` (...), degrees: the size of the direction error."""
        return np.degrees(np.sqrt(np.clip(np.trace(self.cov_alpha_rad2, axis1=-2, axis2=-1), 0.0, None)))


def aoa_field(result, d_mm) -> AoAField:
    """Angles of arrival of sensor points ``d_mm`` with their calibration covariance.

    Parameters
    ----------
    result : CalibrationResult
    d_mm : (..., 2) array_like
        Points on the sensor (impact points after gain correction), mm.

    Returns
    -------
    AoAField
    """
    from psdcal.measure.aoa import angles_from_points

    a = angles_from_points(np.asarray(d_mm, dtype=float), sensor_model(result), derivatives=False)
    g = 1.0 / (1.0 + a.n * a.n)  # d atan(n) / dn
    cov = a.cov_n_calib * g[..., :, None] * g[..., None, :]
    return AoAField(np.asarray(d_mm, dtype=float), a.alpha_rad, cov, a.ray)


def fov_uncertainty(result, n: int = 41, *, margin_mm: float = 0.0) -> AoAField:
    """AoA and its calibration uncertainty over the whole sensor (the field of view).

    Parameters
    ----------
    result : CalibrationResult
    n : int, grid points per side.
    margin_mm : float, distance kept from the sensor's edges.

    Returns
    -------
    AoAField over an (n, n) grid (:func:`sensor_grid_mm`).
    """
    return aoa_field(result, sensor_grid_mm(result.sensor_mm, n, margin_mm=margin_mm))


@dataclass(frozen=True)
class Comparison:
    """Two calibrations of one sensor compared over the field of view.

    Attributes
    ----------
    a, b : AoAField
        Each calibration's angles at the same sensor points.
    delta_deg : (n, n) ndarray
        Angle between the two rays at each sensor point, degrees.
    dalpha_deg : (n, n, 2) ndarray
        ``alpha_A - alpha_B`` per axis, degrees.
    sigma_combined_deg : (n, n) ndarray
        ``sqrt(trace(Sigma_A + Sigma_B))`` in degrees.
    n_sigma : (n, n) ndarray
        Mahalanobis length of the difference in the combined covariance
        (NaN where the combined covariance is singular and the difference is not zero).
    distance_mm : float or None
        Distance of the plane (parallel to the sensor) for ``position_mm``.
    position_mm : (n, n) ndarray or None
        Distance between the two positions the calibrations give on that plane, mm.
    names : (label_a, label_b)
    """

    a: AoAField
    b: AoAField
    delta_deg: np.ndarray
    dalpha_deg: np.ndarray
    sigma_combined_deg: np.ndarray
    n_sigma: np.ndarray
    distance_mm: float | None = None
    position_mm: np.ndarray | None = None
    names: tuple = ("A", "B")

    @property
    def d_mm(self) -> np.ndarray:
        return self.a.d_mm

    @property
    def max_deg(self) -> float:
        """Largest ray difference over the field of view, degrees."""
        return float(np.nanmax(self.delta_deg))

    @property
    def rms_deg(self) -> float:
        """RMS ray difference over the field of view, degrees."""
        return float(np.sqrt(np.nanmean(self.delta_deg**2)))

    @property
    def max_sigma(self) -> float:
        """Largest difference in units of the combined uncertainty."""
        return float(np.nanmax(self.n_sigma)) if np.any(np.isfinite(self.n_sigma)) else float("nan")

    @property
    def rms_sigma(self) -> float:
        """RMS difference in units of the combined uncertainty."""
        return float(np.sqrt(np.nanmean(self.n_sigma**2))) if np.any(np.isfinite(self.n_sigma)) else float("nan")

    @property
    def visible(self) -> bool:
        """True when the difference exceeds the combined uncertainty (max > :data:`VISIBLE_SIGMA`)."""
        m = self.max_sigma
        return bool(not np.isfinite(m) and self.max_deg > 0) or bool(m > VISIBLE_SIGMA)

    def summary(self) -> dict:
        """The numbers of the comparison as a JSON-able dict."""
        out = {
            "max_deg": self.max_deg,
            "rms_deg": self.rms_deg,
            "max_sigma": self.max_sigma,
            "rms_sigma": self.rms_sigma,
            "combined_sigma_deg_median": float(np.nanmedian(self.sigma_combined_deg)),
            "visible": self.visible,
            "threshold_sigma": VISIBLE_SIGMA,
            "grid_points": int(np.isfinite(self.delta_deg).sum()),
        }
        if self.position_mm is not None:
            out.update(
                distance_mm=self.distance_mm,
                position_max_mm=float(np.nanmax(self.position_mm)),
                position_rms_mm=float(np.sqrt(np.nanmean(self.position_mm**2))),
            )
        return out

    def verdict(self) -> str:
        """One sentence a user can act on."""
        s = self.summary()
        if s["max_deg"] == 0.0:
            return "identical: the two calibrations give the same angle everywhere"
        if not np.isfinite(s["max_sigma"]):
            return (f"undecided: the rays differ by up to {s['max_deg']:.3g} deg but the combined uncertainty is "
                    "unknown (a calibration without covariance, or a singular one); compare the angles themselves")
        if self.visible:
            return (f"different: up to {s['max_sigma']:.1f} combined standard deviations apart "
                    f"(threshold {VISIBLE_SIGMA:g}); the sensor or its lens changed, or one calibration is wrong")
        return (f"consistent: within {s['max_sigma']:.2g} combined standard deviations everywhere "
                f"(threshold {VISIBLE_SIGMA:g}); no re-calibration needed on this evidence")


def _mahalanobis(dalpha, cov):
    """sqrt(D^T C^-1 D) for (..., 2) D and (..., 2, 2) C; 0 where D = 0, NaN where C is singular."""
    a, b, c = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    det = a * c - b * b
    dx, dy = dalpha[..., 0], dalpha[..., 1]
    scale = np.maximum(np.abs(a) + np.abs(c), 1e-300)
    ok = det > 1e-12 * scale * scale
    with np.errstate(invalid="ignore", divide="ignore"):
        q = (c * dx * dx - 2 * b * dx * dy + a * dy * dy) / det
    m = np.sqrt(np.clip(q, 0.0, None))
    zero = (dx == 0) & (dy == 0)
    return np.where(zero, 0.0, np.where(ok, m, np.nan))


def compare(a, b, *, n: int = 41, margin_mm: float = 0.0, distance_mm: float | None = None,
            names=("A", "B")) -> Comparison:
    """How much two calibrations of one sensor differ in angle of arrival.

    Both are evaluated at the same grid of sensor points (the sensor of
    ``a``); the two calibrations are taken as independent, so their
    covariances add.

    Parameters
    ----------
    a, b : CalibrationResult
    n : int
        Grid points per side over the sensor.
    margin_mm : float
        Distance kept from the sensor's edges, mm.
    distance_mm : float, optional
        Also report the position difference on a plane at this distance
        from the sensor, parallel to it (docs/model.md#angle-of-arrival-and-position: ``X = S xn``), mm.
    names : (str, str)
        Labels of ``a`` and ``b`` for tables and figures.

    Returns
    -------
    Comparison

    Examples
    --------
    >>> from psdcal.study.simulate import simulate_set
    >>> from psdcal import calibrate
    >>> s = simulate_set("lens2", n_images=9, noise_mm=0.003, seed=1)
    >>> r = calibrate(s.template_mm, s.points_mm)
    >>> compare(r, r).max_deg
    0.0
    """
    if distance_mm is not None and not (np.isfinite(distance_mm) and distance_mm > 0):
        raise InputError(f"distance must be a positive number of mm, got {distance_mm!r}", field="distance_mm")
    sa, sb = (tuple(float(v) for v in r.sensor_mm) for r in (a, b))
    if not np.allclose(sa, sb, rtol=1e-9, atol=0.0):
        # one impact point is not the same place on two sensors of different sizes (Eq 1-2 scale by L / 2)
        raise InputError(f"the calibrations are of sensors of different sizes ({names[0]}: {sa[0]:g} x {sa[1]:g} mm, "
                         f"{names[1]}: {sb[0]:g} x {sb[1]:g} mm): not two calibrations of one sensor",
                         path=getattr(b, "source", None), field="sensor")
    d = sensor_grid_mm(a.sensor_mm, n, margin_mm=margin_mm)
    fa, fb = aoa_field(a, d), aoa_field(b, d)
    cross = np.linalg.norm(np.cross(fa.ray, fb.ray), axis=-1)
    dot = np.sum(fa.ray * fb.ray, axis=-1)
    delta = np.degrees(np.arctan2(cross, dot))
    dalpha = fa.alpha_rad - fb.alpha_rad
    cov = fa.cov_alpha_rad2 + fb.cov_alpha_rad2
    sig = np.degrees(np.sqrt(np.clip(np.trace(cov, axis1=-2, axis2=-1), 0.0, None)))
    pos = None
    if distance_mm is not None:
        pa = distance_mm * np.tan(fa.alpha_rad)
        pb = distance_mm * np.tan(fb.alpha_rad)
        pos = np.linalg.norm(pa - pb, axis=-1)
    return Comparison(fa, fb, delta, np.degrees(dalpha), sig, _mahalanobis(dalpha, cov),
                      None if distance_mm is None else float(distance_mm), pos, tuple(names))


__all__ = ["AoAField", "Comparison", "VISIBLE_SIGMA", "aoa_field", "compare", "fov_uncertainty", "sensor_grid_mm",
           "sensor_model"]
