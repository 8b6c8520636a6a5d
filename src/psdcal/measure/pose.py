"""A calibrated sensor's pose in the room from emitters at known positions (PnP).

The sensor sees ``k`` emitters at known world positions ``P_k`` (mm) in the
directions ``n_k = (X/Z, Y/Z)`` (normalised coordinates, from
:mod:`psdcal.measure.aoa`).  Its pose ``(R, c)`` (rotation world -> camera,
projection centre ``c`` in the world) satisfies

    n_k = pi(R (P_k - c)),     pi(X, Y, Z) = (X / Z, Y / Z)

(the calibration's convention ``Pc = R Pw + t`` with ``t = -R c``).

Steps
-----
1. A start that needs no guess: the distances ``lambda_k`` from the centre to
   the emitters along their rays from the triangle constraints
   ``|lambda_i u_i - lambda_j u_j| = |P_i - P_j|`` (a few starts), then the
   rotation and centre by orthogonal Procrustes (Kabsch) between the camera
   points ``lambda_k u_k`` and ``P_k``.  With a known orientation the centre is
   the least-squares intersection of the world rays through the emitters (a
   known height fixes ``c_z``; one emitter then suffices).
2. Maximum likelihood: Gauss-Newton on ``sum r^T W r`` over all emitters with
   ``r = n - pi(R (P - c))`` and ``W^-1 = Sigma_noise + D Sigma_theta D^T``,
   the angle noise (block diagonal) plus the calibration's covariance
   ``Sigma_theta`` carried through ``D = dn / d theta`` (the same calibration
   error moves every ray: it is correlated between emitters).
3. Covariance ``(J^T W J)^-1`` over ``(omega, c)`` with ``R = exp([omega]) R_hat``
   (a small rotation in the camera frame, rad) and the centre ``c`` (mm);
   its noise and calibration parts are reported separately.

Checks: fewer emitters than the unknowns need, collinear emitters, or an
information matrix that cannot be inverted raise
:class:`psdcal.errors.DegenerateViewsError`; the fit's ``chi2`` against its
``2k - p`` degrees of freedom (false-alarm rate 0.1 %) and a pose uncertainty
above the thresholds give warnings.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from psdcal._consistency import Check, chi2_check
from psdcal._stats import chi2_isf
from psdcal.errors import DegenerateViewsError, InputError
from psdcal.measure._pose_solve import candidate_starts, fallback_starts, predict, refine, search
from psdcal.model.projection import R_from_r, r_from_R, skew3

#: Names of the pose covariance in the sensors file, over ``(omega, t)``: ``R = exp([omega]) R_hat``, ``Pc = R Pw + t``.
POSE_COV_NAMES = ("omega_x_rad", "omega_y_rad", "omega_z_rad", "tx_mm", "ty_mm", "tz_mm")

#: chi2 false-alarm probability of the consistency check.
CHI2_ALARM = 1e-3
#: A horizontal layout of emitters at least this high above ``z = 0`` (mm) is taken as a ceiling (sensor below).
CEILING_MM = 1500.0
#: A plane that passes closer than this to the origin (mm) leaves its side to the sign of its normal.
ORIGIN_TIE_MM = 500.0
#: Largest plausible extent of the emitters (mm): beyond, the coordinates are taken as a unit error.
MAX_EXTENT_MM = 100_000.0


@dataclass(frozen=True)
class PoseResult:
    """A sensor pose with its covariance.

    Attributes
    ----------
    rvec : (3,) ndarray
        Rotation vector world -> camera.
    tvec_mm : (3,) ndarray
        ``Pc = R Pw + t``.
    center_w_mm : (3,) ndarray
        Projection centre in the world, mm.
    cov : (6, 6) ndarray
        Covariance of ``(omega_rad, c_mm)`` (camera-frame small rotation, then
        the centre); zero rows/columns for fixed parameters.
    cov_noise, cov_calib : (6, 6) ndarrays
        Its parts from the angle noise and from the calibration covariance.
    chi2 : float
        Weighted squared residual at the solution.
    dof : int
        ``2 k - (free parameters)``.
    n_emitters : int
    free : (6,) bool ndarray
    residual_n : (k, 2) ndarray
        Residuals in normalised coordinates.
    warnings : tuple of str
    checks : tuple of psdcal._consistency.Check
        ``pose_chi2``, ``unique``, ``handedness``, and when they fail ``units`` and ``layout``.
    usable : bool
        False when a severe check failed (a mirrored survey, the sensor on
        the unexpected side of a coplanar layout, a unit error).
    mirror_chi2 : float or None
        The chi2 of the best pose fitting the mirror image of the survey.
    inflation : float
        The factor applied to the covariance by the ``pose_chi2`` check (1: none).
    """

    rvec: np.ndarray
    tvec_mm: np.ndarray
    center_w_mm: np.ndarray
    cov: np.ndarray
    cov_noise: np.ndarray
    cov_calib: np.ndarray
    chi2: float
    dof: int
    n_emitters: int
    free: np.ndarray
    residual_n: np.ndarray = field(repr=False)
    warnings: tuple = ()
    #: Derivative (6, m) of ``(omega, c)`` by the calibration parameters (None without them).
    dpose_dcalib: np.ndarray | None = field(default=None, repr=False)
    checks: tuple = ()
    usable: bool = True
    mirror_chi2: float | None = None
    inflation: float = 1.0

    @property
    def R(self) -> np.ndarray:
        return R_from_r(self.rvec)

    @property
    def sigma_rotation_deg(self) -> np.ndarray:
        """1-sigma of the small rotation about the camera's x, y, z axes, degrees (3,)."""
        return np.degrees(np.sqrt(np.clip(np.diag(self.cov)[:3], 0.0, None)))

    @property
    def sigma_center_mm(self) -> np.ndarray:
        """1-sigma of the centre's world coordinates, mm (3,)."""
        return np.sqrt(np.clip(np.diag(self.cov)[3:], 0.0, None))

    @property
    def chi2_p(self) -> float:
        """Probability of a chi2 at least this large for a correct model (NaN without dof)."""
        if self.dof <= 0:
            return math.nan
        from psdcal._stats import chi2_sf  # scipy.stats would cost a fresh `psdcal pose` some 0.5 s to import

        return float(chi2_sf(self.chi2, self.dof))

    def _to_omega_t(self) -> np.ndarray:
        """``d(omega, t) / d(omega, c)`` (6, 6): ``t = -exp([omega]) R c``, ``dt/domega = [R c]_x``, ``dt/dc = -R``."""
        T = np.zeros((6, 6))
        T[:3, :3] = np.eye(3)
        T[3:, :3] = skew3(self.R @ self.center_w_mm)
        T[3:, 3:] = -self.R
        return T

    def cov_omega_t(self, part: str = "total") -> np.ndarray:
        """Covariance (6, 6) of ``(omega_rad, t_mm)`` (the sensors file's ``pose_covariance``).

        ``part``: ``"total"``, ``"noise"`` or ``"calib"``.
        """
        C = {"total": self.cov, "noise": self.cov_noise, "calib": self.cov_calib}[part]
        T = self._to_omega_t()
        return T @ C @ T.T

    def error(self, rvec_true, center_true_mm) -> np.ndarray:
        """The error ``(omega, c)`` (6,) of this estimate against a true pose, in the covariance's coordinates."""
        R_true = R_from_r(np.asarray(rvec_true, dtype=float))
        omega_true = r_from_R(R_true @ self.R.T)  # R_true = exp(omega) R_hat
        return -np.concatenate([omega_true, np.asarray(center_true_mm, dtype=float) - self.center_w_mm])

    def nees(self, rvec_true, center_true_mm) -> float:
        """Normalised estimation error squared of the free parameters against the truth."""
        e = self.error(rvec_true, center_true_mm)[self.free]
        C = self.cov[np.ix_(self.free, self.free)]
        return float(e @ np.linalg.solve(C, e))

    def sensors_entry(self, name: str, calib: str, recording: str | None = None, calib_names=None) -> dict:
        """The entry of a sensors file (``locate --sensors``) with the pose's covariance and checks.

        With ``calib_names`` (the calibration's covariance names) and a known
        ``dpose_dcalib``, also ``pose_calibration``: the pose's derivative by
        the calibration parameters over ``(omega, t)`` and its noise-only
        covariance, so that triangulation can propagate the calibration error
        of the rays and of the pose together (they partly compensate).
        """
        d = {"name": name, "calib": calib, "rvec": self.rvec.tolist(), "tvec_mm": self.tvec_mm.tolist()}
        if recording is not None:
            d["recording"] = recording
        d["pose_covariance"] = {"names": list(POSE_COV_NAMES), "matrix": self.cov_omega_t().tolist()}
        if calib_names is not None and self.dpose_dcalib is not None:
            d["pose_calibration"] = {"names": list(calib_names),
                                     "jacobian": (self._to_omega_t() @ self.dpose_dcalib).tolist(),
                                     "noise_covariance": self.cov_omega_t("noise").tolist()}
        d["pose"] = {
            "center_w_mm": self.center_w_mm.tolist(),
            "sigma_center_mm": self.sigma_center_mm.tolist(),
            "sigma_rotation_deg": self.sigma_rotation_deg.tolist(),
            "n_emitters": self.n_emitters,
            "chi2": self.chi2,
            "dof": self.dof,
            "chi2_p": None if self.dof <= 0 else self.chi2_p,
            "free": [nm for nm, f in zip(("omega_x", "omega_y", "omega_z", "cx", "cy", "cz"), self.free) if f],
            "warnings": list(self.warnings),
            "usable": bool(self.usable),
            "inflation": float(self.inflation),
            "mirror_chi2": None if self.mirror_chi2 is None else float(self.mirror_chi2),
            "checks": [c.to_dict() for c in self.checks],
        }
        return d


# --------------------------------------------------------------------------- starts
def _start_known_rotation(n, P, R, height_mm=None):
    """Centre from the world rays through the emitters (a known rotation); ``c_z = height`` when given."""
    u = np.concatenate([n, np.ones((len(n), 1))], axis=1) @ R  # R^T (n, 1): world directions
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for uk, pk in zip(u, P):
        Q = np.eye(3) - np.outer(uk, uk)
        A += Q
        b += Q @ pk
    if height_mm is None:
        return np.linalg.lstsq(A, b, rcond=None)[0]
    # c = (x, y, h): minimise over x, y
    Axy = A[:, :2]
    bxy = b - A[:, 2] * height_mm
    xy = np.linalg.lstsq(Axy, bxy, rcond=None)[0]
    return np.array([xy[0], xy[1], height_mm])


# --------------------------------------------------------------------------- front door
def estimate_pose(n, cov_n_noise, points_w_mm, *, dn_dp=None, cov_params=None, known_rvec=None,
                  known_height_mm=None, iterations: int = 30, warn_rotation_deg: float = 0.5,
                  warn_center_frac: float = 0.01, side_point_mm=None, check_mirror: bool = True,
                  max_extent_mm: float | None = MAX_EXTENT_MM) -> PoseResult:
    """A sensor's pose from the directions of emitters at known positions.

    Parameters
    ----------
    n : (k, 2) array_like
        Normalised coordinates of the emitters seen by the sensor.
    cov_n_noise : (k, 2, 2) array_like
        Their noise covariance (independent between emitters).
    points_w_mm : (k, 3) array_like
        The emitters' world positions, mm.
    dn_dp : (k, 2, m) array_like, optional
        Derivatives of ``n`` with respect to the calibration parameters.
    cov_params : (m, m) array_like, optional
        The calibration covariance (with ``dn_dp``).
    known_rvec : (3,) array_like, optional
        A known rotation (world -> camera): only the centre is estimated.
    known_height_mm : float, optional
        A known height ``c_z`` of the projection centre.
    warn_rotation_deg, warn_center_frac : float
        A pose whose rotation 1-sigma (any axis) exceeds ``warn_rotation_deg``
        or whose centre 1-sigma exceeds ``warn_center_frac`` of the mean
        distance to the emitters gets a warning (poor layout).
    side_point_mm : (3,) array_like, optional
        A point on the sensor's side of the emitters' plane (mm), for
        (nearly) coplanar layouts where the data cannot tell a survey from its
        mirror image; default: the rule of :func:`expected_side`.
    check_mirror : bool
        Fit the mirror image of the survey too (the ``handedness`` check).
    max_extent_mm : float, optional
        Largest plausible extent of the emitters (default
        :data:`MAX_EXTENT_MM`, 100 m): beyond, the ``units`` check fails.

    Returns
    -------
    PoseResult
        ``checks`` holds ``pose_chi2`` (the chi2 against its ``2 k - p``
        degrees of freedom: when it fails, the covariance is multiplied by
        ``chi2 / dof``, see :mod:`psdcal._consistency`), ``handedness`` (the
        mirror image of the survey fitted too: a mirrored survey, or a sensor
        on the unexpected side of a coplanar layout, fails it), ``unique`` (a
        second minimum that fits outside the stated uncertainty fails it), and
        only when they fail ``units`` and ``layout`` (the poor-layout warning). ``usable`` is False when a severe check failed
        (a mirrored survey, a sensor on the wrong side, a unit error): the
        pose is then not to be used, and ``warnings`` says why.

    Raises
    ------
    DegenerateViewsError
        Too few emitters, collinear emitters, emitters behind the sensor, or a
        layout that leaves the pose undetermined.
    """
    n = np.asarray(n, dtype=float)
    P = np.asarray(points_w_mm, dtype=float)
    cov_noise = np.asarray(cov_n_noise, dtype=float)
    k = len(P)
    if n.shape != (k, 2) or P.shape != (k, 3) or cov_noise.shape != (k, 2, 2):
        raise InputError(f"shapes n {n.shape}, points {P.shape}, covariances {cov_noise.shape} do not match")
    if not (np.all(np.isfinite(n)) and np.all(np.isfinite(P)) and np.all(np.isfinite(cov_noise))):
        raise InputError("non-finite angle, position or covariance")
    free = np.ones(6, dtype=bool)
    if known_rvec is not None:
        free[:3] = False
    if known_height_mm is not None:
        free[5] = False
    p = int(free.sum())
    need = math.ceil(p / 2)
    if known_rvec is None:
        need = max(need, 3)
    if k < need:
        raise DegenerateViewsError(
            f"{k} emitter(s) cannot fix {p} pose parameters: at least {need} are needed"
            + ("" if known_rvec is not None else " (or give a known orientation / height)"))
    if known_rvec is None:
        sv = np.linalg.svd(P - P.mean(0), compute_uv=False)
        if sv[1] <= 1e-3 * sv[0]:
            raise DegenerateViewsError("the emitters are collinear: the rotation about their line is undetermined")
    # weights: angle noise + calibration (correlated between emitters)
    C = np.zeros((2 * k, 2 * k))
    for i in range(k):
        C[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = cov_noise[i]
    C_cal = np.zeros_like(C)
    if dn_dp is not None and cov_params is not None and np.size(cov_params):
        D = np.asarray(dn_dp, dtype=float).reshape(2 * k, -1)
        C_cal = D @ np.asarray(cov_params, dtype=float) @ D.T
    Ctot = C + C_cal
    floor = 1e-12 * max(float(np.trace(Ctot)) / (2 * k), 1e-30)
    Ctot = Ctot + floor * np.eye(2 * k)
    try:
        W = np.linalg.inv(Ctot)
    except np.linalg.LinAlgError:
        raise InputError("the angle covariance is singular") from None

    dof = 2 * k - p
    accept = chi2_isf(CHI2_ALARM, dof) if dof > 0 else 1e-9
    if known_rvec is not None:
        R0 = R_from_r(np.asarray(known_rvec, dtype=float))
        R, c, chi2 = refine(R0, _start_known_rotation(n, P, R0, known_height_mm), n, P, W, free, iterations)
    else:
        minima: list = []
        R, c, chi2 = search(candidate_starts(n, P, fallback=False), n, P, W, free, iterations, accept,
                            known_height_mm=known_height_mm, after_accept=6, minima=minima)
        if R is None:  # no closed-form start led anywhere: the distances along the rays, fitted
            R, c, chi2 = search(fallback_starts(n, P), n, P, W, free, iterations, accept,
                                known_height_mm=known_height_mm)
    if R is None or not np.isfinite(chi2):
        raise DegenerateViewsError("no pose puts every emitter in front of the sensor")
    if abs(np.linalg.det(R) - 1.0) > 1e-6:  # pragma: no cover - the solver builds proper rotations only
        raise AssertionError(f"pose solver returned a rotation of determinant {np.linalg.det(R):.6g}")
    checks = []
    mirror_chi2 = None
    if known_rvec is None and check_mirror:
        hand, mirror_chi2 = _handedness_check(R, c, chi2, n, P, W, free, iterations, accept, dof,
                                              known_height_mm, side_point_mm)
        checks.append(hand)
    units = _units_check(P, max_extent_mm)
    if units is not None:
        checks.append(units)
    pred, pc, J = predict(R, c, P)
    Jf = J.reshape(2 * k, 6)[:, free]
    H = Jf.T @ W @ Jf
    try:
        # the condition of the information scaled to unit diagonal (radians and millimetres mixed otherwise)
        dsc = 1.0 / np.sqrt(np.diag(H))
        Hs = H * dsc[:, None] * dsc[None, :]
        if not np.all(np.isfinite(Hs)) or np.linalg.cond(Hs) > 1e12:
            raise np.linalg.LinAlgError
        Hinv = np.linalg.inv(Hs) * dsc[:, None] * dsc[None, :]
    except (np.linalg.LinAlgError, FloatingPointError):
        raise DegenerateViewsError("the emitters' layout leaves the pose undetermined (singular information)") from None
    G = Hinv @ Jf.T @ W  # d pose / d n
    cov = np.zeros((6, 6))
    cov_n = np.zeros((6, 6))
    cov_c = np.zeros((6, 6))
    ix = np.ix_(free, free)
    cov[ix] = 0.5 * (Hinv + Hinv.T)
    cov_n[ix] = G @ C @ G.T
    cov_c[ix] = G @ C_cal @ G.T
    dpose_dcalib = None
    if dn_dp is not None and cov_params is not None and np.size(cov_params):
        dpose_dcalib = np.zeros((6, D.shape[1]))
        dpose_dcalib[free] = G @ D
    warnings = []
    fit = chi2_check(chi2, dof, name="pose_chi2", what=f"the angles of {k} emitters", advice=_CHI2_ADVICE)
    checks.insert(0, fit)
    if dof > 0:
        if fit.passed is False:
            # the documented rule (ratio): every sigma grows by sqrt(chi2 / dof); the extra error is counted
            # as noise (independent of the calibration), so cov = cov_noise + cov_calib still holds
            f = float(fit.inflation)
            cov_n = cov_n + (f - 1.0) * cov
            cov = f * cov
            warnings.append(f"the angles do not fit the emitter positions: {fit.message} ({fit.advice})")
    else:
        warnings.append(f"{k} emitters fix the pose exactly (no redundancy): the fit cannot be checked"
                        + ("; 3 emitters can also fit up to 4 poses" if k == 3 and known_rvec is None else ""))
    if known_rvec is None:
        checks.insert(1, _uniqueness_check(R, c, chi2, cov, free, minima, accept, dof))
    for chk in checks[1:]:
        if chk.passed is False:
            warnings.append(chk.message)
    sig_rot = np.degrees(np.sqrt(np.clip(np.diag(cov)[:3], 0, None)))
    sig_c = np.sqrt(np.clip(np.diag(cov)[3:], 0, None))
    dist = float(np.mean(np.linalg.norm(P - c, axis=1)))
    if sig_rot.max() > warn_rotation_deg or sig_c.max() > warn_center_frac * dist:
        msg = (f"poor emitter layout: pose 1-sigma {sig_rot.max():.3g} deg, centre {sig_c.max():.3g} mm at "
               f"{dist / 1000:.3g} m (spread the emitters wider, in depth too, or add more)")
        warnings.append(msg)
        checks.append(Check("layout", float(sig_rot.max()), float(warn_rotation_deg), None, 0.0, False,
                            msg + "; so far from a quadratic bowl, the sigmas and even the minimum found (another "
                                  "may fit as well) are not to be relied on",
                            advice="spread the emitters wider, in depth too, or add more"))
    rvec = r_from_R(R)
    R = R_from_r(rvec)  # what is written (rvec, tvec) is exactly the pose whose centre is reported
    usable = not any(chk.passed is False and chk.severe for chk in checks)
    return PoseResult(rvec=rvec, tvec_mm=-R @ c, center_w_mm=c, cov=cov, cov_noise=cov_n, cov_calib=cov_c,
                      chi2=float(chi2), dof=int(dof), n_emitters=k, free=free, residual_n=n - pred,
                      warnings=tuple(warnings), dpose_dcalib=dpose_dcalib, checks=tuple(checks), usable=usable,
                      mirror_chi2=mirror_chi2, inflation=float(fit.inflation or 1.0))


_CHI2_ADVICE = "a wrong emitter coordinate, an emitter that moved, a reflection, or an underestimated angle noise"



def expected_side(P, side_point_mm=None):
    """The side of the emitters' plane where the sensor is expected (the rule for coplanar layouts).

    The room frame is right-handed with ``z`` up. For emitters whose mirror
    image fits the angles as well (a (nearly) coplanar layout), the data
    cannot tell a correct survey from a mirrored one: the sensor then lands
    on one side of the emitters' best-fit plane or the other. It is expected

    - on the side of ``side_point_mm`` when given (any point on the sensor's
      side: a point in the room);
    - for a horizontal layout (normal within 45 deg of ``z``): above the
      emitters when their centroid is less than :data:`CEILING_MM` above
      ``z = 0`` (floor, table), below them otherwise (ceiling);
    - for any other layout (a wall): on the side facing the room frame's
      origin, or, when the plane passes within :data:`ORIGIN_TIE_MM` of the
      origin, on the side its normal's largest component points to positive
      coordinates (into the room when the room lies at positive coordinates).

    Parameters
    ----------
    P : (k, 3) array_like
        The emitters, mm.
    side_point_mm : (3,) array_like, optional

    Returns
    -------
    (normal, words) : the unit normal (3,) of the plane pointing to the expected side, and the rule in words.
    """
    P = np.asarray(P, dtype=float)
    m = P.mean(0)
    e3 = np.linalg.svd(P - m)[2][2]
    if side_point_mm is not None:
        d = float((np.asarray(side_point_mm, dtype=float) - m) @ e3)
        if abs(d) < 1e-6 * (1.0 + float(np.linalg.norm(P - m, axis=1).max())):
            raise InputError("the side point lies in the emitters' plane: give a point on the sensor's side",
                             field="side_point")
        return e3 * np.sign(d), "on the side of the given side point"
    if abs(e3[2]) >= math.sqrt(0.5):
        up = e3 * np.sign(e3[2])
        if m[2] < CEILING_MM:
            return up, f"above the emitters (a horizontal layout less than {CEILING_MM / 1000:g} m above z = 0)"
        return -up, f"below the emitters (a horizontal layout {CEILING_MM / 1000:g} m or more above z = 0: a ceiling)"
    d0 = float(-m @ e3)
    if abs(d0) >= ORIGIN_TIE_MM:
        return e3 * np.sign(d0), "on the side of the emitters' plane that faces the room frame's origin"
    j = int(np.argmax(np.abs(e3)))
    return e3 * np.sign(e3[j]), "on the side of the emitters' plane toward positive coordinates (it passes by the origin)"


def _handedness_check(R, c, chi2, n, P, W, free, iterations, accept, dof, known_height_mm, side_point_mm):
    """Fit the mirror image of the survey; name a mirrored survey, or apply the side rule when both fit.

    The survey is reflected in the plane ``x = mean x`` (any reflection gives the same test: a proper rotation
    fitting a reflected survey is a reflection fitting the survey). The first start is the current pose
    mirrored through the emitters' best-fit plane, which fits a coplanar layout exactly.

    Returns
    -------
    (Check, chi2 of the mirror's best fit)
    """
    m = P.mean(0)
    e3 = np.linalg.svd(P - m)[2][2]
    S = np.diag([-1.0, 1.0, 1.0])
    M = np.eye(3) - 2.0 * np.outer(e3, e3)
    P2 = m + (P - m) @ S
    first = [(R @ M @ S, m + S @ M @ (c - m))]
    scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
    # a quick search (the mirror of a fitting survey is found from its first, exact starts in a few steps),
    # then a full refinement when the best of it comes near fitting
    # emitters spread in depth (6 or more): the DLT of the mirror image is its exact start when it fits
    sv = np.linalg.svd(P - m, compute_uv=False)
    tri = 0 if len(P) >= 6 and sv[2] > 0.1 * sv[0] else 4
    Rm, cm, chi2_m = search(itertools.chain(first, candidate_starts(n, P2, fallback=False, triplets=tri)), n, P2, W, free,
                            min(iterations, 8), accept * scale, known_height_mm=known_height_mm, max_refine=6,
                            skip_above=1e4 * accept * scale)
    if Rm is not None and accept * scale < chi2_m < 100.0 * accept * scale:
        chi2_m = min(chi2_m, refine(Rm, cm, n, P2, W, free, iterations)[2])
    # each fit judged against the noise the better of the two shows (the stated one, or more)
    if dof > 0:
        scale = max(1.0, min(chi2, chi2_m) / dof)
    fits, fits_m = chi2 <= accept * scale, chi2_m <= accept * scale
    stat = f"chi2 {chi2:.4g}, mirror image {chi2_m:.4g}, for {dof} dof"
    if fits and not fits_m:
        return Check("handedness", chi2_m, accept * scale, None, 0.0, True,
                     f"the survey's handedness is confirmed: its mirror image does not fit ({stat})", dof=dof), chi2_m
    if fits_m and not fits:
        return Check("handedness", chi2, accept * scale, None, 0.0, False,
                     f"the survey looks mirrored (x/y swapped or a left-handed frame): its mirror image fits the "
                     f"angles and it does not ({stat})",
                     advice="check the survey's axes: the room frame must be right-handed (x, y on the floor, z up)",
                     severe=True, dof=dof), chi2_m
    normal, words = expected_side(P, side_point_mm)
    h = float((c - m) @ normal)
    if h > 0:
        return Check("handedness", h, 0.0, None, 0.0, True,
                     f"the survey's mirror image fits as well ({stat}: (nearly) coplanar emitters, or angles that "
                     f"fit neither); the sensor is {words}, as the side rule expects", dof=dof), chi2_m
    if abs(normal[2]) >= math.sqrt(0.5):
        side = "below" if normal[2] > 0 else "above"
    else:
        side = "behind"
    return Check("handedness", h, 0.0, None, 0.0, False,
                 f"the sensor lands {side} the emitters' plane, {abs(h) / 1000:.3g} m on the wrong side for the rule "
                 f"(expected {words}); a mirrored survey (x/y swapped or a left-handed frame) fits as well ({stat}: "
                 f"(nearly) coplanar emitters): check the survey, or give the sensor's side "
                 f"(side_point_mm, --side-point) if it really is there",
                 advice="a coplanar layout cannot tell a survey from its mirror image: add an emitter off the plane, "
                        "or state the sensor's side", severe=True, dof=dof), chi2_m


#: Two minima whose chi2 differ by less than this are both taken as possible (a likelihood ratio of e^4.5 = 90).
AMBIGUOUS_DCHI2 = 9.0


def _uniqueness_check(R, c, chi2, cov, free, minima, accept, dof):
    """Whether another pose (a second minimum, outside the covariance) fits the angles nearly as well.

    A rival minimum that fits (``chi2 <= accept``, the noise scaled as the fit shows) and lies beyond the
    covariance's 99.9 % region, with a chi2 less than :data:`AMBIGUOUS_DCHI2` above the best, makes the pose
    ambiguous (a severe failure); a rival inside the region is covered by the stated sigmas.
    """
    scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
    idx = np.flatnonzero(free)
    Cinv = np.linalg.inv(cov[np.ix_(idx, idx)])
    m2_limit = chi2_isf(CHI2_ALARM, len(idx))

    def mahalanobis(m):
        e = np.concatenate([r_from_R(m[0] @ R.T), m[1] - c])[idx]
        return float(e @ Cinv @ e)

    rivals = [m for m in minima if m[2] <= accept * scale and mahalanobis(m) > m2_limit]
    if not rivals:
        return Check("unique", None, AMBIGUOUS_DCHI2, None, 0.0, True,
                     "no other pose found that fits the angles outside the stated uncertainty")
    R2, c2, chi2_2 = min(rivals, key=lambda m: m[2])
    ang = math.degrees(math.acos(np.clip((np.trace(R2 @ R.T) - 1.0) / 2.0, -1.0, 1.0)))
    d = float(np.linalg.norm(c2 - c))
    dchi2 = (chi2_2 - chi2) / scale
    words = (f"another pose fits the angles too (chi2 {chi2_2:.4g} against {chi2:.4g}): the centre "
             f"{d / 1000:.3g} m and the rotation {ang:.3g} deg away")
    if dchi2 >= AMBIGUOUS_DCHI2:
        return Check("unique", dchi2, AMBIGUOUS_DCHI2, None, 0.0, True,
                     words + f"; the data prefer this one by {dchi2:.3g} in chi2")
    return Check("unique", dchi2, AMBIGUOUS_DCHI2, None, 0.0, False,
                 words + f"; the data cannot tell them apart (chi2 difference {dchi2:.3g} < {AMBIGUOUS_DCHI2:g}): "
                         "the pose is ambiguous",
                 advice="a plane of emitters seen from afar: add emitters, spread them wider or in depth, or give a "
                        "known orientation or height", severe=True)


def _units_check(P, max_extent_mm):
    """A failed plausibility check when the emitters span more than ``max_extent_mm`` (a unit error), else None."""
    ext = float(np.linalg.norm(P.max(0) - P.min(0)))
    if max_extent_mm is None or ext <= max_extent_mm:
        return None
    return Check("units", ext, float(max_extent_mm), None, 0.0, False,
                 f"the emitters span {ext / 1000:.4g} m (more than {max_extent_mm / 1000:g} m): coordinates in "
                 f"centimetres or millimetres where metres (mm in the API) were expected?",
                 advice="give the coordinates in metres (X_m,Y_m,Z_m), or raise max_extent_mm for a larger site",
                 severe=True)


# --------------------------------------------------------------------------- helpers for files
def read_emitters(path, *, max_extent_m: float | None = MAX_EXTENT_MM / 1000.0
                  ) -> tuple[list[str], np.ndarray, np.ndarray | None]:
    """Read an emitters CSV ``emitter,X_m,Y_m,Z_m[,carrier_hz]``.

    ``max_extent_m``: emitters spread over more than this (the diagonal of
    their bounding box, m) raise an :class:`InputError` naming the file and
    ``X_m``: centimetres or millimetres under the metre columns (a room of
    5 m in centimetres spans 500 "m"). None: no check.

    Returns
    -------
    names : list of str
    points_w_mm : (k, 3) ndarray, mm
    carriers_hz : (k,) ndarray or None
    """
    from pathlib import Path

    path = Path(path)
    from psdcal.io import csv_rows

    rows = csv_rows(path, "emitters file")
    if not rows:
        raise InputError("empty file", path=path)
    header = [h.strip() for h in rows[0]]
    for col in ("emitter", "X_m", "Y_m", "Z_m"):
        if col not in header:
            raise InputError(f"missing column '{col}' (header must be emitter,X_m,Y_m,Z_m[,carrier_hz])",
                             path=path, line=1, field=col)
    cols = ["X_m", "Y_m", "Z_m"] + (["carrier_hz"] if "carrier_hz" in header else [])
    names, vals = [], []
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or not any(c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(f"expected {len(header)} fields, found {len(row)}", path=path, line=lineno)
        name = row[header.index("emitter")].strip()
        if not name:
            raise InputError("empty emitter name", path=path, line=lineno, field="emitter")
        if name in names:
            raise InputError(f"repeated emitter {name!r}", path=path, line=lineno, field="emitter")
        v = []
        for col in cols:
            text = row[header.index(col)]
            try:
                x = float(text)
            except ValueError:
                raise InputError(f"not a number: {text!r}", path=path, line=lineno, field=col) from None
            if not math.isfinite(x):
                raise InputError("not a finite number", path=path, line=lineno, field=col)
            v.append(x)
        names.append(name)
        vals.append(v)
    if not names:
        raise InputError("no emitters after the header", path=path)
    a = np.array(vals)
    ext = float(np.linalg.norm(a[:, :3].max(0) - a[:, :3].min(0)))
    if max_extent_m is not None and ext > max_extent_m:
        raise InputError(f"the emitters span {ext:.4g} m (more than {max_extent_m:g} m): X_m,Y_m,Z_m are metres, "
                         "not centimetres or millimetres (for a larger site, raise the limit: --max-extent-m)",
                         path=path, field="X_m")
    return names, a[:, :3] * 1000.0, (a[:, 3] if a.shape[1] == 4 else None)


@dataclass(frozen=True)
class EmitterMeans:
    """Per-emitter averaged impact points.

    Attributes
    ----------
    names : list of str
    d_mm : (k, 2) ndarray
    cov_d_mm2 : (k, 2, 2) ndarray
        Covariance of the mean.
    dd_dgains : (k, 2, 3) ndarray or None
    n_windows : (k,) int ndarray
    scatter_p : (k,) ndarray
        Probability of the scatter of the windows about the mean (a small
        value: the emitter moved, or the noise is underestimated).
    """

    names: list
    d_mm: np.ndarray
    cov_d_mm2: np.ndarray
    dd_dgains: np.ndarray | None
    n_windows: np.ndarray
    scatter_p: np.ndarray


def _grouped_means(names, values, var):
    """Inverse-variance mean of the rows of each name, in order of first appearance.

    Parameters
    ----------
    names : (N,) sequence
    values, var : (N, k) arrays, the rows and their variances

    Returns
    -------
    order (list of names), means (n, k), variance of each mean (n, k), rows per name (n,), and the
    chi-squared p-value of each name's scatter about its mean (NaN for one row)
    """
    from psdcal._stats import chi2_sf

    names = np.asarray(names, dtype=object)
    order = list(dict.fromkeys(names.tolist()))
    means, var_mean, counts, ps = [], [], [], []
    for nm in order:
        m = names == nm
        w = 1.0 / np.maximum(var[m], 1e-300)
        mu = (w * values[m]).sum(0) / w.sum(0)
        means.append(mu)
        var_mean.append(1.0 / w.sum(0))
        counts.append(int(m.sum()))
        x2 = float(((values[m] - mu) ** 2 * w).sum())
        dof = values.shape[1] * (int(m.sum()) - 1)
        ps.append(chi2_sf(x2, dof) if dof > 0 else math.nan)
    return order, np.array(means), np.array(var_mean), np.array(counts), np.array(ps)


def mean_amplitudes(names, a, var_a, model) -> EmitterMeans:
    """Average amplitude rows per emitter (inverse-variance weights), then impact points (Eq 1-2).

    Parameters
    ----------
    names : (N,) sequence of str
    a, var_a : (N, 4) arrays
    model : SensorModel
    """
    from psdcal.measure.aoa import impact_from_amplitudes

    order, means, varm, counts, ps = _grouped_means(names, np.asarray(a, dtype=float), np.asarray(var_a, dtype=float))
    imp = impact_from_amplitudes(means, model, varm)
    return EmitterMeans(order, imp.d_mm, imp.cov_d_mm2, imp.dd_dgains, counts, ps)


def mean_points(names, d_mm, sigma_d_mm) -> EmitterMeans:
    """Average impact-point rows per emitter (inverse-variance weights)."""
    order, means, varm, counts, ps = _grouped_means(names, np.asarray(d_mm, dtype=float),
                                                    np.asarray(sigma_d_mm, dtype=float) ** 2)
    covs = np.array([np.diag(v) for v in varm])
    return EmitterMeans(order, means, covs, None, counts, ps)


def pose_from_means(means: EmitterMeans, model, names_w, points_w_mm, **kw) -> PoseResult:
    """:func:`estimate_pose` for emitters averaged by :func:`mean_amplitudes` / :func:`mean_points`.

    Emitters seen but absent from ``names_w`` are ignored; ``names_w`` not seen
    are left out.
    """
    from psdcal.measure.aoa import angles_from_points

    idx = {nm: i for i, nm in enumerate(names_w)}
    use = [j for j, nm in enumerate(means.names) if nm in idx]
    if not use:
        raise InputError(f"none of the emitters seen ({means.names}) is in the emitters file ({list(names_w)})",
                         field="emitter")
    d = means.d_mm[use]
    dd = None if means.dd_dgains is None else means.dd_dgains[use]
    res = angles_from_points(d, model, means.cov_d_mm2[use], dd)
    P = np.asarray(points_w_mm, dtype=float)[[idx[means.names[j]] for j in use]]
    return estimate_pose(res.n, res.cov_n_noise, P, dn_dp=res.dn_dp, cov_params=model.covariance, **kw)


def pose_from_angles(names, alpha_deg, sigma_alpha_deg, names_w, points_w_mm, **kw) -> PoseResult:
    """:func:`estimate_pose` from rows of angles of arrival (an angles table without impact points).

    The rows of each emitter are averaged (inverse-variance weights) and
    ``n = tan(alpha)``; the sigmas are taken as the whole, independent
    uncertainty (a calibration's correlated part cannot be separated here:
    use impact points or amplitudes with the calibration for that).

    Parameters
    ----------
    names : (N,) sequence of str
    alpha_deg, sigma_alpha_deg : (N, 2) array_like
    names_w : sequence of str
        Emitters with known positions.
    points_w_mm : (k, 3) array_like
    """
    names = np.asarray(names, dtype=object)
    a = np.radians(np.asarray(alpha_deg, dtype=float))
    s = np.radians(np.asarray(sigma_alpha_deg, dtype=float))
    idx = {nm: i for i, nm in enumerate(names_w)}
    use = [nm for nm in dict.fromkeys(names.tolist()) if nm in idx]
    if not use:
        raise InputError(f"none of the emitters seen is in the emitters file ({list(names_w)})", field="emitter")
    n, cov = [], []
    for nm in use:
        m = names == nm
        w = 1.0 / np.maximum(s[m] ** 2, 1e-300)
        mu = (w * a[m]).sum(0) / w.sum(0)
        var = 1.0 / w.sum(0)
        nn = np.tan(mu)
        n.append(nn)
        cov.append(np.diag(var * (1 + nn * nn) ** 2))  # dn/dalpha = 1 + tan^2
    P = np.asarray(points_w_mm, dtype=float)[[idx[nm] for nm in use]]
    return estimate_pose(np.array(n), np.array(cov), P, **kw)
