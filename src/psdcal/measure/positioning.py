"""Positions from angles of arrival (docs/model.md#angle-of-arrival-and-position; the paper's Section 3.4 and Introduction).

* One sensor and a known plane: a transmitter moving on a plane parallel to
  the sensor at distance ``S`` sits at ``X = S xn``, ``Y = S yn`` in the
  camera frame (docs/model.md#angle-of-arrival-and-position; ``X = S ex / f`` without skew and distortion).
* Two or more sensors with known poses: the 3D point is the weighted
  least-squares intersection of their rays (AoA positioning needs two
  receivers, the paper's Introduction).

Pose convention (the same as the calibration's extrinsics): a sensor's pose
``(rvec, tvec_mm)`` maps **world** points into its camera frame,
``Pc = R(rvec) Pw + tvec``; hence ``Pw = R^T (Pc - tvec)`` and the sensor's
projection centre is at ``-R^T tvec`` in the world frame.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from psdcal._consistency import ALPHA, Check, chi2_check, extra_variance
from psdcal.measure.aoa import AoAResult, angles_from_points
from psdcal.errors import DegenerateViewsError, InputError
from psdcal.model.projection import R_from_r
from psdcal.measure.sensor_model import SensorModel


# --------------------------------------------------------------------------- plane
@dataclass(frozen=True)
class PlanePosition:
    """Position on a plane parallel to the sensor (docs/model.md#angle-of-arrival-and-position).

    Attributes
    ----------
    xy_mm : (..., 2) ndarray
        ``(X, Y)`` in the camera frame, mm, at ``Z = distance_mm``.
    cov_xy_mm2 : (..., 2, 2) ndarray
        Covariance (calibration + noise), mm^2.
    distance_mm : float
    """

    xy_mm: np.ndarray
    cov_xy_mm2: np.ndarray
    distance_mm: float

    @property
    def sigma_xy_mm(self) -> np.ndarray:
        """1-sigma of ``(X, Y)`` (..., 2), mm."""
        return np.sqrt(np.clip(np.diagonal(self.cov_xy_mm2, axis1=-2, axis2=-1), 0.0, None))


def plane_position(aoa: AoAResult, distance_mm: float) -> PlanePosition:
    """Transmitter position on the plane ``Zc = distance_mm`` (docs/model.md#angle-of-arrival-and-position).

    ``X = S xn``, ``Y = S yn`` (the paper's ``X = S ex / f``); the covariance is
    ``S^2 cov(n)``.  ``S`` is taken as exact.
    """
    s = float(distance_mm)
    if not np.isfinite(s) or s <= 0:
        raise InputError(f"the plane distance must be a positive number of mm, got {distance_mm}", field="distance_mm")
    return PlanePosition(xy_mm=s * aoa.n, cov_xy_mm2=(s * s) * aoa.cov_n, distance_mm=s)


# --------------------------------------------------------------------------- several sensors
@dataclass(frozen=True)
class SensorPose:
    """A calibrated sensor placed in the world frame: ``Pc = R(rvec) Pw + tvec_mm``."""

    name: str
    model: SensorModel
    rvec: np.ndarray
    tvec_mm: np.ndarray
    recording: str | None = None
    #: Covariance (6, 6) of the pose over ``(omega_rad, t_mm)``, ``R = exp([omega]) R_hat``
    #: (the sensors file's optional ``pose_covariance``, from ``psdcal pose``); None: exact pose.
    cov_pose: np.ndarray | None = None
    #: The pose's dependence on the sensor's calibration (the sensors file's optional
    #: ``pose_calibration``): ``(jacobian (6, m) over (omega, t) by the model's parameters,
    #: noise-only pose covariance (6, 6))``.  With it, a ray's calibration error and the pose's
    #: (which partly compensate each other) are propagated together.
    pose_calib: tuple | None = None

    @property
    def R(self) -> np.ndarray:
        """Rotation world -> camera (3, 3)."""
        return R_from_r(self.rvec)

    @property
    def center_w_mm(self) -> np.ndarray:
        """Projection centre of the sensor in the world frame (3,), mm."""
        return -self.R.T @ np.asarray(self.tvec_mm, dtype=float)


def pose_vectors(item: dict, path, where: str) -> dict:
    """``{"rvec": (3,), "tvec_mm": (3,)}`` of one sensors-file entry; InputError naming the field otherwise."""
    out = {}
    for key in ("rvec", "tvec_mm"):
        try:
            vec = np.asarray(item.get(key), dtype=float)
        except (TypeError, ValueError):
            vec = np.zeros(0)
        if vec.shape != (3,) or not np.all(np.isfinite(vec)):
            raise InputError(f"'{key}' must be 3 finite numbers, got {item.get(key)!r}", path=path,
                             field=f"{where}.{key}")
        out[key] = vec
    return out


def load_sensors(path) -> list[SensorPose]:
    """Read SENSORS.json: a list of ``{name, calib, rvec, tvec_mm[, recording]}``.

    ``calib`` and ``recording`` are paths relative to the JSON file.  Also
    accepted: ``{"sensors": [...]}``.

    Raises
    ------
    InputError
        Naming the file and the key (``sensors[i].key``).
    """
    from psdcal.io import read_json

    path = Path(path)
    data = read_json(path, "sensors file")
    if isinstance(data, dict):
        data = data.get("sensors")
    if not isinstance(data, list) or len(data) < 2:
        raise InputError("expected a list of at least two sensors", path=path, field="sensors")
    out = []
    names = set()
    for i, item in enumerate(data):
        where = f"sensors[{i}]"
        if not isinstance(item, dict):
            raise InputError("each sensor must be an object", path=path, field=where)
        for key in ("calib", "rvec", "tvec_mm"):
            if key not in item:
                raise InputError(f"missing key '{key}'", path=path, field=f"{where}.{key}")
        name = str(item.get("name", f"s{i + 1}"))
        if name in names:
            raise InputError(f"repeated sensor name {name!r}", path=path, field=f"{where}.name")
        names.add(name)
        vecs = pose_vectors(item, path, where)
        calib = path.parent / str(item["calib"])
        model = SensorModel.load(calib)
        rec = item.get("recording")
        out.append(
            SensorPose(
                name=name,
                model=model,
                rvec=vecs["rvec"],
                tvec_mm=vecs["tvec_mm"],
                recording=None if rec is None else str(path.parent / str(rec)),
                cov_pose=_pose_covariance(item.get("pose_covariance"), path, f"{where}.pose_covariance"),
                pose_calib=_pose_calibration(item.get("pose_calibration"), model, path, f"{where}.pose_calibration"),
            )
        )
    centres = [-R_from_r(sp.rvec).T @ sp.tvec_mm for sp in out]
    for i in range(len(out)):
        for j in range(i):
            if np.linalg.norm(centres[i] - centres[j]) < 1e-6 * max(1.0, np.linalg.norm(centres[i])):
                raise InputError(f"sensors {out[j].name!r} and {out[i].name!r} are at the same position: "
                                 "triangulation needs a baseline between sensors", path=path, field=f"sensors[{i}].tvec_mm")
    return out


def _pose_covariance(obj, path, where):
    """The optional ``pose_covariance`` of a sensors-file entry: (6, 6) over (omega_rad, t_mm), or None."""
    if obj is None:
        return None
    from psdcal.measure.pose import POSE_COV_NAMES

    if not isinstance(obj, dict) or list(obj.get("names", [])) != list(POSE_COV_NAMES):
        raise InputError(f"'pose_covariance' must be an object with names {list(POSE_COV_NAMES)} and a matrix",
                         path=path, field=where)
    try:
        c = np.asarray(obj.get("matrix"), dtype=float)
    except (TypeError, ValueError):
        c = np.zeros(0)
    if c.shape != (6, 6) or not np.all(np.isfinite(c)) or not np.allclose(c, c.T, rtol=1e-6, atol=1e-300) \
            or np.any(np.diag(c) < 0):
        raise InputError("'pose_covariance.matrix' must be a symmetric 6x6 matrix with a non-negative diagonal",
                         path=path, field=f"{where}.matrix")
    return 0.5 * (c + c.T)


def _pose_calibration(obj, model, path, where):
    """The optional ``pose_calibration`` of a sensors-file entry -> (jacobian (6, m), noise covariance (6, 6))."""
    if obj is None:
        return None
    if not isinstance(obj, dict):
        raise InputError("'pose_calibration' must be an object", path=path, field=where)
    names = obj.get("names")
    if list(names or []) != list(model.names):
        raise InputError(f"'pose_calibration.names' {names} are not the calibration's parameters "
                         f"{list(model.names)}: the pose was estimated with another calibration", path=path,
                         field=f"{where}.names")
    try:
        J = np.asarray(obj.get("jacobian"), dtype=float).reshape(6, len(model.names))
        C = np.asarray(obj.get("noise_covariance"), dtype=float).reshape(6, 6)
    except (TypeError, ValueError):
        raise InputError("'pose_calibration' needs a 6 x m 'jacobian' and a 6 x 6 'noise_covariance'", path=path,
                         field=where) from None
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(C))):
        raise InputError("'pose_calibration' has non-finite entries", path=path, field=where)
    return J, 0.5 * (C + C.T)


@dataclass(frozen=True)
class Triangulation:
    """Least-squares intersection of rays from several sensors.

    Attributes
    ----------
    p_w_mm : (..., 3) ndarray
        Point in the world frame, mm (NaN where fewer than two rays were valid).
    cov_p_mm2 : (..., 3, 3) ndarray
        Its covariance, mm^2 (inverse of the Gauss-Newton information matrix).
    chi2 : (...) ndarray
        Weighted sum of squared ray residuals at the solution (about
        ``2 n_sensors - 3`` for consistent rays).
    n_sensors : (...) int ndarray
        Number of rays used.
    dof : (...) int ndarray or None
        Degrees of freedom of each point's ``chi2``: ``2 n_sensors - 3``.
    flagged : (...) bool ndarray or None
        Points whose own chi-squared test fails at the false-alarm rate
        ``check.false_alarm`` (``chi2`` beyond the ``1 - alpha`` quantile of
        ``chi2(dof)``): rays that disagree with the stated noise at that point.
    check : Check or None
        The chi-squared test of all the points together (``sum chi2`` against
        ``sum dof``, :func:`psdcal._consistency.chi2_check`).  When it fails,
        every ray's covariance gains an extra isotropic noise ``extra_var_n``
        (the ``"extra"`` rule of :mod:`psdcal._consistency`, estimated from all
        the points' residuals) and ``cov_p_mm2`` is inflated accordingly.
    extra_var_n : float
        That extra variance of the normalised coordinates (rad^2 near the
        axis); 0 when the test passed or was not run.
    cov_p_stated_mm2 : (..., 3, 3) ndarray or None
        The covariance from the stated noise alone (before inflation), mm^2.
    dcov_dextra_mm2 : (..., 3, 3) ndarray or None
        ``d cov_p / d extra_var_n``: the covariance with an extra ray variance
        ``s2`` is ``cov_p_stated_mm2 + s2 * dcov_dextra_mm2`` (the sandwich
        covariance of the point computed with the stated weights).
    residual_n : (k, ..., 2) ndarray or None
        The rays' residuals ``n_i - pi(R_i P + t_i)`` at the solution (NaN for unused rays).
    ray_cov_n : (k, ..., 2, 2) ndarray or None
        The rays' total stated covariances (noise, pose and calibration parts) at the solution.
    """

    p_w_mm: np.ndarray
    cov_p_mm2: np.ndarray
    chi2: np.ndarray
    n_sensors: np.ndarray
    dof: np.ndarray | None = None
    flagged: np.ndarray | None = None
    check: Check | None = None
    extra_var_n: float = 0.0
    cov_p_stated_mm2: np.ndarray | None = field(default=None, repr=False)
    dcov_dextra_mm2: np.ndarray | None = field(default=None, repr=False)
    residual_n: np.ndarray | None = field(default=None, repr=False)
    ray_cov_n: np.ndarray | None = field(default=None, repr=False)

    @property
    def sigma_p_mm(self) -> np.ndarray:
        """1-sigma of ``(X, Y, Z)`` (..., 3), mm."""
        return np.sqrt(np.clip(np.diagonal(self.cov_p_mm2, axis1=-2, axis2=-1), 0.0, None))


def triangulate(n, cov_n, R, t_mm, *, iterations: int = 8, cov_pose=None, calib=None, inflate: bool = True,
                alpha: float = ALPHA) -> Triangulation:
    """3D point from the normalised image coordinates seen by several sensors.

    Minimises ``sum_i r_i^T W_i r_i`` with ``r_i = n_i - pi(R_i P + t_i)``,
    ``pi(X, Y, Z) = (X/Z, Y/Z)`` and ``W_i = cov_n_i^-1`` (maximum likelihood
    for Gaussian ray errors) by Gauss-Newton, started from the unweighted
    midpoint (the point closest to all rays).  The covariance of the point is
    ``(sum_i J_i^T W_i J_i)^-1`` at the solution.

    Parameters
    ----------
    n : (k, ..., 2) array_like
        Normalised coordinates ``(xn, yn)`` of each of ``k`` sensors; NaN marks
        a sensor that did not see the point.
    cov_n : (k, ..., 2, 2) array_like
        Their covariances.
    R : (k, 3, 3) array_like
        Rotations world -> camera.
    t_mm : (k, 3) array_like
        Translations, ``Pc = R Pw + t``.
    cov_pose : (k, 6, 6) array_like or None, optional
        Covariance of each sensor's pose over ``(omega_rad, t_mm)`` with
        ``R = exp([omega]) R_hat`` (NaN or zeros for an exact pose).  Each
        ray's covariance then gains ``J_pose C_pose J_pose^T`` evaluated at the
        current point, ``J_pose = d pi / d Pc [-[R P]_x, I]``, so the point's
        covariance includes the poses' uncertainty.
    calib : tuple or None, optional
        ``(dn_dcalib (k, ..., 2, m), cov_calib (k, m, m), pose_dcalib (k, 6, m))``:
        the rays' and the poses' common dependence on each sensor's
        calibration.  The calibration error ``d theta`` then moves a ray's
        residual by ``(dn_dcalib - J_pose pose_dcalib) d theta`` (a pose fitted
        with the same calibration partly compensates it); ``cov_n`` and
        ``cov_pose`` must then be their noise parts only.
    inflate : bool
        Check the points against the stated noise and inflate the covariance
        when they disagree (below).  False: only the per-point ``flagged``
        and the stated covariance (a caller that pools several calls, as
        ``locate`` over a file, applies the rule itself with
        :func:`extra_ray_sums` and :func:`apply_extra_variance`).
    alpha : float
        False-alarm rate of the per-point flags and of the pooled test.

    Returns
    -------
    Triangulation

    Notes
    -----
    The consistency rule (docs/guide/positioning.md#sigmas-that-cover-the-error):
    each point's ``chi2`` is tested against ``chi2(2 k - 3)`` at ``alpha``
    (``flagged``); all the points of the call are tested together
    (``check``: ``sum chi2`` against ``sum dof``).  When that pooled test
    fails, an extra noise of variance ``s2`` on every ray's normalised
    coordinates (isotropic, the same for all rays) is estimated from all the
    residuals, ``sum r^T (C + s2 I)^-1 r = sum dof``, and each point's
    covariance becomes the sandwich covariance of the same estimate under that
    noise; ``check.message`` gives its size.  One noisy point does not
    inflate the others unless the whole call disagrees with the noise.
    """
    n = np.asarray(n, dtype=float)
    cov_n = np.asarray(cov_n, dtype=float)
    R = np.asarray(R, dtype=float)
    t = np.asarray(t_mm, dtype=float)
    batch = n.shape[1:-1]
    ok = np.all(np.isfinite(n), axis=-1) & np.all(np.isfinite(cov_n), axis=(-1, -2))  # (k, ...)
    n0 = np.where(ok[..., None], n, 0.0)
    # weights: inverse covariances with a floor so a perfectly known ray stays finite
    cov = np.where(ok[..., None, None], cov_n, np.eye(2))
    scale = np.maximum(np.trace(cov, axis1=-2, axis2=-1) / 2, 1e-30)
    cov = cov + (1e-12 * scale)[..., None, None] * np.eye(2)
    W = np.linalg.inv(cov) * ok[..., None, None]
    expand = (slice(None),) + (None,) * len(batch)
    Rb = R[expand]  # (k, 1.., 3, 3)
    tb = t[expand]  # (k, 1.., 3)
    # start: midpoint of the rays in the world frame
    ray_c = np.concatenate([n0, np.ones(n0.shape[:-1] + (1,))], axis=-1)
    u = np.einsum("k...ji,k...j->k...i", Rb, ray_c)  # R^T ray
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    o = -np.einsum("k...ji,k...j->k...i", Rb, tb)  # centres
    proj = (np.eye(3) - u[..., :, None] * u[..., None, :]) * ok[..., None, None]
    A = proj.sum(0)
    b = np.einsum("k...ij,k...j->...i", proj, o)
    n_used = ok.sum(0)
    good = n_used >= 2
    A_safe = np.where(good[..., None, None], A, np.eye(3))
    p = np.linalg.solve(A_safe, b[..., None])[..., 0]
    info = np.broadcast_to(np.eye(3), batch + (3, 3))
    chi2 = np.zeros(batch)
    cp = None
    if cov_pose is not None:
        cp = np.nan_to_num(np.asarray(cov_pose, dtype=float))[expand]  # (k, 1.., 6, 6)
    if calib is not None:
        D = np.nan_to_num(np.asarray(calib[0], dtype=float))
        Sc = np.asarray(calib[1], dtype=float)[expand]
        Ap = np.asarray(calib[2], dtype=float)[expand]
        calib = (D, Sc, Ap)
        if cp is None:
            cp = np.zeros((len(R),) + (1,) * len(batch) + (6, 6))
    for it in range(iterations + 1):
        pc = np.einsum("k...ij,...j->k...i", Rb, p) + tb
        z = pc[..., 2]
        z = np.where(np.abs(z) > 1e-9, z, 1e-9)
        pred = pc[..., :2] / z[..., None]
        r = n0 - pred
        # d pred / d pc (k, ..., 2, 3), then d pred / d p = that @ R
        zero = np.zeros_like(z)
        dpred_dpc = np.stack(
            [
                np.stack([1 / z, zero, -pred[..., 0] / z], axis=-1),
                np.stack([zero, 1 / z, -pred[..., 1] / z], axis=-1),
            ],
            axis=-2,
        )
        J = dpred_dpc @ Rb
        if cp is not None:
            W, ray_cov = _pose_weights(cov, cp, pc - tb, dpred_dpc, ok, calib, with_total=True)
        else:
            ray_cov = cov
        JtW = np.swapaxes(J, -1, -2) @ W
        info = (JtW @ J).sum(0)
        grad = np.einsum("k...ij,k...j->...i", JtW, r)  # sums over the sensors k
        chi2 = np.einsum("k...i,k...ij,k...j->...", r, W, r)
        if it == iterations:
            break
        info_safe = np.where(good[..., None, None], info, np.eye(3))
        p = p + np.linalg.solve(info_safe, grad[..., None])[..., 0]
    info_safe = np.where(good[..., None, None], info, np.eye(3))
    try:
        cov_p = np.linalg.inv(info_safe)
    except np.linalg.LinAlgError:
        raise DegenerateViewsError("the rays are parallel: the point cannot be triangulated") from None
    # the sandwich increment: cov(s2) = H^-1 sum J^T W (C + s2 I) W J H^-1 = cov_p + s2 B
    B = cov_p @ (JtW @ np.swapaxes(JtW, -1, -2)).sum(0) @ cov_p
    p = np.where(good[..., None], p, np.nan)
    cov_p = np.where(good[..., None, None], cov_p, np.nan)
    B = np.where(good[..., None, None], 0.5 * (B + np.swapaxes(B, -1, -2)), np.nan)
    chi2 = np.where(good, chi2, np.nan)
    dof = np.where(good, 2 * n_used - 3, 0)
    use = ok & good[None]
    residual = np.where(use[..., None], r, np.nan)
    ray_cov = np.where(use[..., None, None], ray_cov, np.nan)
    flagged = row_flags(chi2, dof, alpha)
    tri = Triangulation(p_w_mm=p, cov_p_mm2=cov_p, chi2=chi2, n_sensors=n_used, dof=dof, flagged=flagged,
                        cov_p_stated_mm2=cov_p, dcov_dextra_mm2=B, residual_n=residual, ray_cov_n=ray_cov)
    if not inflate:
        return tri
    check = pooled_check(float(np.nansum(chi2)), int(dof.sum()), int(good.sum()), alpha)
    return apply_extra_variance(tri, check, extra_ray_variance(tri, int(dof.sum())) if check.passed is False else 0.0)


#: The likely causes of rays that disagree with their stated noise.
TRIANGULATION_ADVICE = ("the angle noise is larger than stated, a sensor's pose (or calibration) is off, or the "
                        "emitter moved between the sensors' measurements")


def pooled_check(chi2_sum: float, dof_sum: float, n_points: int, alpha: float = ALPHA) -> Check:
    """The chi-squared test of ``n_points`` triangulated points together (no inflation applied yet)."""
    what = "the rays of the point" if n_points == 1 else f"the rays of {n_points} points"
    return chi2_check(chi2_sum, dof_sum, name="triangulation_chi2", what=what, alpha=alpha, inflate=False,
                      advice=TRIANGULATION_ADVICE)


def row_flags(chi2, dof, alpha: float = ALPHA) -> np.ndarray:
    """Points whose ``chi2`` exceeds the ``1 - alpha`` quantile of ``chi2(dof)`` (False where ``dof <= 0``)."""
    from psdcal._stats import chi2_isf

    chi2 = np.asarray(chi2, dtype=float)
    dof = np.asarray(dof)
    out = np.zeros(chi2.shape, dtype=bool)
    for d in np.unique(dof):
        if d > 0:
            m = dof == d
            out[m] = chi2[m] > chi2_isf(alpha, float(d))
    return out


def _whitened(tri: Triangulation):
    """Residual components along the eigenvectors of each ray's covariance, and those eigenvalues (flat)."""
    r = tri.residual_n
    C = tri.ray_cov_n
    use = np.all(np.isfinite(r), -1) & np.all(np.isfinite(C), (-1, -2))
    lam, V = np.linalg.eigh(C[use])
    rw = np.einsum("nji,nj->ni", V, r[use])
    return rw.ravel(), np.maximum(lam, 1e-300).ravel()


def extra_ray_variance(tri: Triangulation, dof: float) -> float:
    """The extra isotropic variance ``s2`` of the rays' normalised coordinates with ``sum r^T (C + s2 I)^-1 r = dof``.

    ``dof``: the degrees of freedom of the residuals pooled (``tri.dof.sum()``
    for one call).  0 when the stated noise already explains them.
    """
    rw, lam = _whitened(tri)
    return extra_variance(rw, lam, dof)


def extra_ray_sums(tri: Triangulation, grid) -> np.ndarray:
    """``sum r^T (C + s2 I)^-1 r`` over all the call's rays for each ``s2`` of ``grid`` (to pool several calls)."""
    rw, lam = _whitened(tri)
    grid = np.asarray(grid, dtype=float)
    out = np.zeros(grid.shape)
    for i in range(0, len(rw), 8192):
        out += ((rw[i:i + 8192, None] ** 2) / (lam[i:i + 8192, None] + grid[None, :])).sum(0)
    return out


def apply_extra_variance(tri: Triangulation, check: Check, s2: float) -> Triangulation:
    """The triangulation with every ray's covariance grown by ``s2 I`` (the check records the size).

    ``cov_p_mm2 = cov_p_stated_mm2 + s2 * dcov_dextra_mm2``; the check's
    ``inflation`` is the median growth of the points' covariance traces and
    its message names the extra noise (in urad near the sensors' axes).
    """
    s2 = float(s2)
    if not s2 > 0:
        return replace(tri, check=check, extra_var_n=0.0)
    cov = tri.cov_p_stated_mm2 + s2 * tri.dcov_dextra_mm2
    check = extra_noise_check(check, s2, np.trace(tri.cov_p_stated_mm2, axis1=-2, axis2=-1),
                              np.trace(cov, axis1=-2, axis2=-1))
    return replace(tri, cov_p_mm2=cov, check=check, extra_var_n=s2)


def extra_noise_check(check: Check, s2: float, trace_before, trace_after) -> Check:
    """``check`` with the size of an extra ray noise ``s2`` and the sigma growth it causes in its message."""
    tr0 = np.asarray(trace_before, dtype=float).ravel()
    tr1 = np.asarray(trace_after, dtype=float).ravel()
    ratio = tr1 / np.where(tr0 > 0, tr0, np.nan)
    ratio = ratio[np.isfinite(ratio)]
    infl = float(np.median(ratio)) if ratio.size else 1.0
    lo, hi = (float(np.sqrt(ratio.min())), float(np.sqrt(ratio.max()))) if ratio.size else (1.0, 1.0)
    grow = f"x{lo:.3g}" if hi - lo < 1e-3 * lo else f"x{lo:.3g} to x{hi:.3g}"
    msg = (check.message + f"; an extra ray noise of {1e6 * math.sqrt(s2):.4g} urad (in normalised coordinates) "
           f"added to every ray explains them: position sigmas grown {grow}")
    return replace(check, message=msg, inflation=infl, effect_sigma=math.sqrt(infl) - 1.0)


def _pose_weights(cov, cov_pose, rp, dpred_dpc, ok, calib=None, with_total=False):
    """Inverse of the ray covariance ``cov`` plus the pose part ``Jp Cp Jp^T``, ``Jp = dpi/dPc [-[R P]_x, I]``,
    plus, with ``calib = (D, Sigma, A)``, the common calibration part ``(D - Jp A) Sigma (D - Jp A)^T``."""
    x, y, zz = rp[..., 0], rp[..., 1], rp[..., 2]
    zero = np.zeros_like(x)
    # -[v]_x for v = R P
    neg_skew = np.stack([np.stack([zero, zz, -y], -1), np.stack([-zz, zero, x], -1), np.stack([y, -x, zero], -1)], -2)
    Jp = np.concatenate([dpred_dpc @ neg_skew, dpred_dpc], axis=-1)  # (k, ..., 2, 6)
    total = cov + Jp @ cov_pose @ np.swapaxes(Jp, -1, -2)
    if calib is not None:
        D, Sc, Ap = calib
        E = D - Jp @ Ap  # (k, ..., 2, m)
        total = total + E @ Sc @ np.swapaxes(E, -1, -2)
    W = np.linalg.inv(total) * ok[..., None, None]
    return (W, total) if with_total else W


def triangulate_aoa(results, sensors) -> Triangulation:
    """Triangulate from one :class:`AoAResult` per sensor (same leading shape).

    Parameters
    ----------
    results : sequence of AoAResult
    sensors : sequence of SensorPose
    """
    if len(results) != len(sensors) or len(sensors) < 2:
        raise InputError("triangulation needs one AoA result per sensor and at least two sensors")
    n = np.stack([r.n for r in results])
    cov = np.stack([r.cov_n for r in results])
    R = np.stack([s.R for s in sensors])
    t = np.stack([np.asarray(s.tvec_mm, dtype=float) for s in sensors])
    n, cov, kw = ray_inputs(results, sensors)
    return triangulate(n, cov, R, t, **kw)


def ray_inputs(results, sensors, seen=None):
    """Rays, their covariances and the keyword arguments of :func:`triangulate` for these sensors.

    Without pose uncertainty: ``n`` and the total ``cov_n`` of each
    :class:`AoAResult`.  With ``pose_covariance`` only: plus ``cov_pose``.
    When every sensor's pose carries ``pose_calibration`` (from ``psdcal
    pose``): the noise parts of the rays and poses, and ``calib`` with the
    common calibration dependence (the two partly compensate).

    Parameters
    ----------
    results : sequence of AoAResult (same leading shape)
    sensors : sequence of SensorPose
    seen : sequence of bool arrays, optional
        Rows where each sensor saw the emitter (others become NaN).

    Returns
    -------
    n : (k, ..., 2), cov : (k, ..., 2, 2), kwargs : dict
    """
    if seen is None:
        seen = [np.ones(np.shape(r.n)[:-1], bool) for r in results]
    joint = all(getattr(s, "pose_calib", None) is not None for s in sensors)
    n = np.stack([np.where(sn[..., None], r.n, np.nan) for r, sn in zip(results, seen)])
    if not joint:
        cov = np.stack([np.where(sn[..., None, None], r.cov_n, np.nan) for r, sn in zip(results, seen)])
        return n, cov, {"cov_pose": pose_covariances(sensors)}
    cov = np.stack([np.where(sn[..., None, None], r.cov_n_noise, np.nan) for r, sn in zip(results, seen)])
    m = max(len(s.model.names) for s in sensors)
    batch = np.shape(results[0].n)[:-1]
    D = np.zeros((len(sensors),) + batch + (2, m))
    Sc = np.zeros((len(sensors), m, m))
    Ap = np.zeros((len(sensors), 6, m))
    for j, (r, s) in enumerate(zip(results, sensors)):
        q = len(s.model.names)
        D[j, ..., :q] = r.dn_dp
        Sc[j, :q, :q] = s.model.covariance
        Ap[j, :, :q] = s.pose_calib[0]
    cov_pose = np.stack([s.pose_calib[1] for s in sensors])
    return n, cov, {"cov_pose": cov_pose, "calib": (D, Sc, Ap)}


def pose_covariances(sensors):
    """Stacked pose covariances (k, 6, 6) of sensors (zeros for exact poses), or None when all are exact."""
    if all(getattr(s, "cov_pose", None) is None for s in sensors):
        return None
    return np.stack([np.zeros((6, 6)) if s.cov_pose is None else np.asarray(s.cov_pose, float) for s in sensors])


# --------------------------------------------------------------------------- error maps
@dataclass(frozen=True)
class ErrorMap:
    """AoA and position error over the sensor (the paper's Figure 9).

    Attributes
    ----------
    d_x_mm, d_y_mm : (nx,), (ny,) ndarrays
        Grid of impact points on the sensor, mm.
    aoa_error_deg : (ny, nx) ndarray
        Norm of the angle error ``|(d alpha_x, d alpha_y)|``, degrees.
    position_error_mm : (ny, nx) ndarray
        Norm of the position error on the plane, mm.
    distance_mm : float
    mode : str
        ``"sigma"`` (1-sigma from the covariance) or ``"mean+2std"``.
    """

    d_x_mm: np.ndarray
    d_y_mm: np.ndarray
    aoa_error_deg: np.ndarray
    position_error_mm: np.ndarray
    distance_mm: float
    mode: str


def error_map(model: SensorModel, distance_mm: float, *, mode: str = "sigma", grid: int = 61,
              sigma_d_mm: float = 0.0, extent: float = 0.98) -> ErrorMap:
    """AoA and position error over the field of view at distance ``S``.

    Parameters
    ----------
    model : SensorModel
    distance_mm : float
        Plane distance ``S``, mm (the paper: 5000).
    mode : {"sigma", "mean+2std"}
        ``"sigma"``: the 1-sigma norm ``sqrt(var_x + var_y)`` propagated from
        the calibration covariance (and ``sigma_d_mm``).  ``"mean+2std"``:
        as the paper's Figure 9, the difference between the angles computed
        with every free parameter moved by ``+2`` standard errors and with the
        calibrated values.
    grid : int
        Points per axis over the active area.
    sigma_d_mm : float
        Impact-point noise (isotropic, 1-sigma, mm) added in ``"sigma"`` mode.
    extent : float
        Fraction of the half-size of the active area covered.

    Returns
    -------
    ErrorMap
    """
    if mode not in ("sigma", "mean+2std"):
        raise InputError(f"unknown error-map mode {mode!r}; use 'sigma' or 'mean+2std'", field="mode")
    s = float(distance_mm)
    if not np.isfinite(s) or s <= 0:
        raise InputError(f"the plane distance must be a positive number of mm, got {distance_mm}", field="distance_mm")
    gx = np.linspace(-extent * model.lx_mm / 2, extent * model.lx_mm / 2, int(grid))
    gy = np.linspace(-extent * model.ly_mm / 2, extent * model.ly_mm / 2, int(grid))
    d = np.stack(np.meshgrid(gx, gy), axis=-1)  # (ny, nx, 2)
    if mode == "sigma":
        cov_d = np.broadcast_to(sigma_d_mm**2 * np.eye(2), d.shape + (2,))
        res = angles_from_points(d, model, cov_d)
        sig_a = res.sigma_alpha_rad
        aoa_err = np.degrees(np.hypot(sig_a[..., 0], sig_a[..., 1]))
        cov_xy = plane_position(res, s).cov_xy_mm2
        pos_err = np.sqrt(np.clip(np.trace(cov_xy, axis1=-2, axis2=-1), 0.0, None))
    else:
        res = angles_from_points(d, model)
        shifted = model.with_values({nm: model.value(nm) + 2 * sd for nm, sd in zip(model.names, model.std())})
        # the shifted gains act on the signals: re-read the same signals through them
        res2 = angles_from_points(_regain(d, model, shifted), shifted)
        da = res2.alpha_rad - res.alpha_rad
        aoa_err = np.degrees(np.hypot(da[..., 0], da[..., 1]))
        dn = (res2.n - res.n) * s
        pos_err = np.hypot(dn[..., 0], dn[..., 1])
    return ErrorMap(d_x_mm=gx, d_y_mm=gy, aoa_error_deg=aoa_err, position_error_mm=pos_err, distance_mm=s, mode=mode)


def _regain(d_mm, model: SensorModel, shifted: SensorModel):
    """Impact points read through ``shifted``'s gains from the signals that give ``d_mm`` under ``model``."""
    if np.array_equal(model.gains, shifted.gains):
        return d_mm
    from psdcal.measure.aoa import impact_from_amplitudes
    from psdcal.model.readout import photocurrents

    v = photocurrents(d_mm, 1.0, model.lx_mm, model.ly_mm) * model.gains
    return impact_from_amplitudes(v, shifted).d_mm


def plot_error_map(emap: ErrorMap, path, *, title: str | None = None) -> None:
    """Draw an :class:`ErrorMap` as two colour maps in one PNG (written atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from psdcal._atomic import atomic_path

    what = "1-sigma" if emap.mode == "sigma" else "parameters at mean + 2 std"
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), constrained_layout=True)
    for ax, z, label in (
        (axes[0], emap.aoa_error_deg, "AoA error (deg)"),
        (axes[1], emap.position_error_mm, f"position error at S = {emap.distance_mm:g} mm (mm)"),
    ):
        im = ax.pcolormesh(emap.d_x_mm, emap.d_y_mm, z, shading="auto", cmap="viridis")
        cs = ax.contour(emap.d_x_mm, emap.d_y_mm, z, colors="w", linewidths=0.6)
        ax.clabel(cs, fontsize=7, fmt="%.3g")
        ax.set_aspect("equal")
        ax.set_xlabel("impact point x (mm)")
        ax.set_ylabel("impact point y (mm)")
        ax.set_title(label)
        fig.colorbar(im, ax=ax, shrink=0.85)
    fig.suptitle(title or f"AoA and position error over the field of view ({what})")
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)


def write_error_map_csv(emap: ErrorMap, path) -> None:
    """Write an :class:`ErrorMap` as CSV ``d_x_mm,d_y_mm,aoa_error_deg,position_error_mm`` (atomically)."""
    from psdcal._atomic import write_text_atomic

    xx, yy = np.meshgrid(emap.d_x_mm, emap.d_y_mm)
    lines = ["d_x_mm,d_y_mm,aoa_error_deg,position_error_mm"]
    for x, y, a, p in zip(xx.ravel(), yy.ravel(), emap.aoa_error_deg.ravel(), emap.position_error_mm.ravel()):
        lines.append(f"{x:.6g},{y:.6g},{a:.6g},{p:.6g}")
    write_text_atomic(path, "\n".join(lines) + "\n")
