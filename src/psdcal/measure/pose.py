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

import math
from dataclasses import dataclass, field

import numpy as np

from psdcal.errors import DegenerateViewsError, InputError
from psdcal.model.projection import R_from_r, r_from_R, skew3

#: Names of the pose covariance in the sensors file, over ``(omega, t)``: ``R = exp([omega]) R_hat``, ``Pc = R Pw + t``.
POSE_COV_NAMES = ("omega_x_rad", "omega_y_rad", "omega_z_rad", "tx_mm", "ty_mm", "tz_mm")

#: chi2 false-alarm probability of the consistency check.
CHI2_ALARM = 1e-3


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
        from scipy.stats import chi2

        return float(chi2.sf(self.chi2, self.dof))

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
        }
        return d


# --------------------------------------------------------------------------- model
def _predict(R, c, P):
    """Normalised coordinates (k, 2), camera points (k, 3) and Jacobian (k, 2, 6) over (omega, c)."""
    pc = (P - c) @ R.T
    z = pc[:, 2]
    n = pc[:, :2] / z[:, None]
    dpi = np.zeros((len(P), 2, 3))
    dpi[:, 0, 0] = 1 / z
    dpi[:, 1, 1] = 1 / z
    dpi[:, 0, 2] = -n[:, 0] / z
    dpi[:, 1, 2] = -n[:, 1] / z
    # d pc / d omega = -[pc]_x ; d pc / d c = -R
    J = np.concatenate([-dpi @ np.stack([skew3(p) for p in pc]), -dpi @ R], axis=-1)
    return n, pc, J


def _kabsch(Q, P):
    """R, c with Q ~ R (P - c), least squares (Q camera points, P world points, (k, 3))."""
    qm, pm = Q.mean(0), P.mean(0)
    H = (P - pm).T @ (Q - qm)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    c = pm - R.T @ qm
    return R, c


def _start_general(n, P, *, n_starts: int = 12, seed: int = 0):
    """Candidate poses (R, c), one at a time, for the caller to refine until one fits.

    1. linear estimates (:func:`_linear_starts`);
    2. the distances ``lambda_k`` along the rays from the triangle constraints
       ``|lambda_i u_i - lambda_j u_j| = |P_i - P_j|`` over all emitters (the
       first start at one common distance, the next ones at random distances
       0.2 to 5 times that), then Kabsch;
    3. the same on triplets of emitters (the widest triangles first): each
       triplet's up to four exact solutions (P3P) are found from random
       starts, so a wrong basin of the all-emitter equations (the mirror
       ambiguity of nearly planar layouts) is left.
    """
    from scipy.optimize import least_squares

    u = np.concatenate([n, np.ones((len(n), 1))], axis=1)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    k = len(P)
    rng = np.random.default_rng(seed)
    seen: list[np.ndarray] = []

    def new(R, c, scale):
        if np.any((P - c) @ R.T[:, 2] <= 0) or any(np.linalg.norm(c - c2) < 1e-6 * scale for c2 in seen):
            return False
        seen.append(c)
        return True

    for R, c in _linear_starts(n, P):
        if new(R, c, 1.0):
            yield R, c

    def solve(idx, starts):
        ii, jj = np.triu_indices(len(idx), 1)
        ii, jj = idx[ii], idx[jj]
        dist = np.linalg.norm(P[ii] - P[jj], axis=1)
        ang = np.arccos(np.clip(np.sum(u[ii] * u[jj], axis=1), -1.0, 1.0))
        scale = float(np.median(dist / np.maximum(ang, 1e-6)))
        pos = {v: q for q, v in enumerate(idx)}
        a = np.array([pos[v] for v in ii])
        b = np.array([pos[v] for v in jj])

        def res(lam):
            return (np.linalg.norm(lam[a, None] * u[ii] - lam[b, None] * u[jj], axis=1) - dist) / scale

        for s in range(starts):
            lam0 = scale * (np.ones(len(idx)) if s == 0 else np.exp(rng.uniform(np.log(0.2), np.log(5.0), len(idx))))
            sol = least_squares(res, lam0, bounds=(1e-9 * scale, np.inf), method="trf", xtol=1e-10, ftol=1e-10)
            R, c = _kabsch(sol.x[:, None] * u[idx], P[idx])
            if new(R, c, scale):
                yield R, c

    yield from solve(np.arange(k), n_starts)
    if k > 3:
        tri = [(i, j, l) for i in range(k) for j in range(i + 1, k) for l in range(j + 1, k)]
        area = [np.linalg.norm(np.cross(P[j] - P[i], P[l] - P[i])) for i, j, l in tri]
        for q in np.argsort(area)[::-1][:4]:
            yield from solve(np.array(tri[q]), 12)


def _orthonormal(M):
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return R


def _linear_starts(n, P):
    """Linear pose estimates: the plane-to-image homography (Zhang's decomposition) for >= 4 emitters, and
    the direct linear transform of the 3 x 4 projection for >= 6 emitters spread in depth."""
    k = len(P)
    out = []
    m = P.mean(0)
    _, sv, Vt = np.linalg.svd(P - m)
    E = Vt.T  # columns: the layout's principal axes; the third is the plane's normal
    if np.linalg.det(E) < 0:  # a right-handed basis, so that R = Rp E^T is a rotation, not a reflection
        E[:, 2] = -E[:, 2]
    if k >= 4:
        uv = (P - m) @ E[:, :2]
        A = []
        for (u, v), (x, y) in zip(uv, n):
            A.append([u, v, 1, 0, 0, 0, -x * u, -x * v, -x])
            A.append([0, 0, 0, u, v, 1, -y * u, -y * v, -y])
        H = np.linalg.svd(np.array(A))[2][-1].reshape(3, 3)
        h1, h2, h3 = H[:, 0], H[:, 1], H[:, 2]
        scale = 2.0 / (np.linalg.norm(h1) + np.linalg.norm(h2))
        if h3[2] * scale < 0:
            scale = -scale
        Rp = _orthonormal(np.stack([scale * h1, scale * h2, np.cross(scale * h1, scale * h2)], 1))
        t = scale * h3
        R = Rp @ E.T
        out.append((R, m - R.T @ t))
    if k >= 6 and sv[2] > 0.05 * sv[0]:
        X = np.concatenate([P - m, np.ones((k, 1))], 1)
        A = []
        for Xk, (x, y) in zip(X, n):
            A.append(np.concatenate([Xk, np.zeros(4), -x * Xk]))
            A.append(np.concatenate([np.zeros(4), Xk, -y * Xk]))
        Pm = np.linalg.svd(np.array(A))[2][-1].reshape(3, 4)
        scale = 1.0 / np.cbrt(abs(np.linalg.det(Pm[:, :3])) or 1.0)
        if (Pm[2] @ X[0]) * scale < 0:
            scale = -scale
        R = _orthonormal(scale * Pm[:, :3])
        t = scale * Pm[:, 3]
        out.append((R, m - R.T @ t))
    return out


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
                  warn_center_frac: float = 0.01) -> PoseResult:
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

    Returns
    -------
    PoseResult

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

    def cost(R, c):
        pred, pc, _ = _predict(R, c, P)
        if np.any(pc[:, 2] <= 0):
            return math.inf
        r = (n - pred).ravel()
        return float(r @ W @ r)

    if known_rvec is not None:
        R0 = R_from_r(np.asarray(known_rvec, dtype=float))
        starts = iter([(R0, _start_known_rotation(n, P, R0, known_height_mm))])
    else:
        starts = _start_general(n, P)
        if known_height_mm is not None:
            starts = ((R, np.array([c[0], c[1], known_height_mm])) for R, c in starts)
    from scipy.stats import chi2 as chi2_dist

    dof = 2 * k - p
    accept = chi2_dist.isf(CHI2_ALARM, dof) if dof > 0 else 1e-9
    best = None
    for R, c in starts:
        R, c, chi2 = _refine(R, c, n, P, W, free, iterations)
        if best is None or chi2 < best[2] - 1e-9:
            best = (R, c, chi2)
        if chi2 <= accept:  # consistent with the noise: the global minimum (or as good as one)
            break
    if best is None:
        raise DegenerateViewsError("no pose puts every emitter in front of the sensor")
    R, c, chi2 = best
    if not np.isfinite(chi2):
        raise DegenerateViewsError("no pose puts every emitter in front of the sensor")
    pred, pc, J = _predict(R, c, P)
    Jf = J.reshape(2 * k, 6)[:, free]
    H = Jf.T @ W @ Jf
    try:
        if np.linalg.cond(H) > 1e14:
            raise np.linalg.LinAlgError
        Hinv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
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
    if dof > 0:
        pval = float(chi2_dist.sf(chi2, dof))
        if pval < CHI2_ALARM:
            warnings.append(
                f"the angles do not fit the emitter positions (chi2 {chi2:.3g} for {dof} dof, p = {pval:.2g}): "
                "a wrong emitter coordinate, a reflection, or an underestimated angle noise")
    else:
        warnings.append(f"{k} emitters fix the pose exactly (no redundancy): the fit cannot be checked"
                        + ("; 3 emitters can also fit up to 4 poses" if k == 3 and known_rvec is None else ""))
    sig_rot = np.degrees(np.sqrt(np.clip(np.diag(cov)[:3], 0, None)))
    sig_c = np.sqrt(np.clip(np.diag(cov)[3:], 0, None))
    dist = float(np.mean(np.linalg.norm(P - c, axis=1)))
    if sig_rot.max() > warn_rotation_deg or sig_c.max() > warn_center_frac * dist:
        warnings.append(
            f"poor emitter layout: pose 1-sigma {sig_rot.max():.3g} deg, centre {sig_c.max():.3g} mm at "
            f"{dist / 1000:.3g} m (spread the emitters wider, in depth too, or add more)")
    rvec = r_from_R(R)
    return PoseResult(rvec=rvec, tvec_mm=-R @ c, center_w_mm=c, cov=cov, cov_noise=cov_n, cov_calib=cov_c,
                      chi2=float(chi2), dof=int(dof), n_emitters=k, free=free, residual_n=n - pred,
                      warnings=tuple(warnings), dpose_dcalib=dpose_dcalib)


def _refine(R, c, n, P, W, free, iterations):
    """Gauss-Newton with step halving on ``r^T W r`` over the free parameters of ``(omega, c)``."""
    k = len(P)

    def evaluate(R, c):
        pred, pc, J = _predict(R, c, P)
        if np.any(pc[:, 2] <= 0):
            return math.inf, None, None
        r = (n - pred).ravel()
        return float(r @ W @ r), r, J.reshape(2 * k, 6)[:, free]

    f, r, J = evaluate(R, c)
    if not np.isfinite(f):
        return R, c, math.inf
    for _ in range(iterations):
        H = J.T @ W @ J
        g = J.T @ W @ r
        try:
            step = np.linalg.solve(H + 1e-12 * np.trace(H) * np.eye(len(H)), g)
        except np.linalg.LinAlgError:
            break
        full = np.zeros(6)
        full[free] = step
        lam = 1.0
        improved = False
        for _ in range(20):
            R2 = R_from_r(lam * full[:3]) @ R
            c2 = c + lam * full[3:]
            f2, r2, J2 = evaluate(R2, c2)
            if f2 <= f:
                improved = True
                break
            lam *= 0.5
        if not improved:
            break
        done = f - f2 <= 1e-12 * max(f, 1e-300) + 1e-15
        R, c, f, r, J = R2, c2, f2, r2, J2
        if done:
            break
    return R, c, f


# --------------------------------------------------------------------------- helpers for files
def read_emitters(path) -> tuple[list[str], np.ndarray, np.ndarray | None]:
    """Read an emitters CSV ``emitter,X_m,Y_m,Z_m[,carrier_hz]``.

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
    from scipy.stats import chi2

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
        ps.append(float(chi2.sf(x2, dof)) if dof > 0 else math.nan)
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
