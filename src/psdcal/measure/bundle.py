"""Several sensors calibrated together: poses and emitter positions in one bundle adjustment.

Sensors ``j`` (pose ``R_j``, centre ``c_j``) see points ``i`` (emitters at
unknown positions ``X_i`` -- fixed ones, or the positions of a wand moved
through the room -- and a few at known positions): observation ``(i, j)`` is

    n_ij = pi(R_j (X_i - c_j)) + e_ij,   e_ij ~ N(0, C_ij).

Maximum likelihood over all poses and unknown points by Levenberg-Marquardt
on the normal equations, block-sparse: each observation touches one pose
(6 parameters: a small rotation ``omega`` in the camera frame and the centre)
and one point (3), so

    [U   W ] [dp]   [g_p]
    [W^T V ] [dx] = [g_x],   V block diagonal (3 x 3 per point),

is solved by the Schur complement on the points, ``(U - W V^-1 W^T) dp =
g_p - W V^-1 g_x``, then ``dx = V^-1 (g_x - W^T dp)``.  The known points fix
the world frame (at least three, not collinear).  The pose covariance is the
inverse of the Schur complement (exactly the pose block of the full inverse);
a point's is ``V^-1 + V^-1 W^T S^-1 W V^-1`` (its block).  The solution does
not depend on the order of the sensors or points.

The observation covariances ``C_ij`` are the angle noise; a sensor's
calibration error, common to all its observations, is propagated through the
solution separately (``calib``) rather than treated as independent noise
(which would let it average away over many observations).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from psdcal._consistency import Check, chi2_check
from psdcal.measure._geometry import skews
from psdcal.errors import ConvergenceError, DegenerateViewsError, InputError
from psdcal.model.projection import R_from_r, r_from_R, skew3


@dataclass(frozen=True)
class BundleResult:
    """Poses and points of a bundle adjustment.

    Attributes
    ----------
    sensors : list of str
    rvecs : (S, 3) ndarray
        World -> camera rotations.
    centers_mm : (S, 3) ndarray
        Projection centres in the world, mm.
    cov_poses : (S, 6, 6) ndarray
        Covariance of each pose over ``(omega_rad, c_mm)`` (``R = exp([omega]) R_hat``).
    points : list of str
    points_mm : (M, 3) ndarray
        All points (known ones as given).
    cov_points : (M, 3, 3) ndarray
        Their covariances (zero for known points).
    known : (M,) bool ndarray
    chi2 : float
    dof : int
    iterations : int
    check : Check or None
        The chi-squared test of the observations against their stated noise
        (:func:`psdcal._consistency.chi2_check`, false-alarm rate 1e-3).
        When it fails, ``cov_poses`` and ``cov_points`` are multiplied by
        ``check.inflation = chi2 / dof`` (the ratio rule: every stated ray
        variance was too small by that factor) and the message says so.
    cov_poses_stated, cov_points_stated : ndarrays or None
        The covariances before that inflation.
    """

    sensors: list
    rvecs: np.ndarray
    centers_mm: np.ndarray
    cov_poses: np.ndarray
    points: list
    points_mm: np.ndarray
    cov_points: np.ndarray
    known: np.ndarray
    chi2: float
    dof: int
    iterations: int
    check: Check | None = None
    cov_poses_stated: np.ndarray | None = field(default=None, repr=False)
    cov_points_stated: np.ndarray | None = field(default=None, repr=False)

    @property
    def tvecs_mm(self) -> np.ndarray:
        """``t = -R c`` (S, 3)."""
        return np.stack([-R_from_r(r) @ c for r, c in zip(self.rvecs, self.centers_mm)])

    def cov_omega_t(self, j: int) -> np.ndarray:
        """Covariance (6, 6) of sensor ``j``'s pose over ``(omega_rad, t_mm)`` (the sensors file's)."""
        R = R_from_r(self.rvecs[j])
        T = np.zeros((6, 6))
        T[:3, :3] = np.eye(3)
        T[3:, :3] = skew3(R @ self.centers_mm[j])
        T[3:, 3:] = -R
        return T @ self.cov_poses[j] @ T.T

    def pose_error(self, j: int, rvec_true, center_true_mm) -> np.ndarray:
        """Error (6,) of sensor ``j``'s pose against the truth in the covariance's coordinates."""
        om = r_from_R(R_from_r(np.asarray(rvec_true, float)) @ R_from_r(self.rvecs[j]).T)
        return -np.concatenate([om, np.asarray(center_true_mm, float) - self.centers_mm[j]])


def bundle_adjust(sensors, points, obs_sensor, obs_point, n, cov_n, known_mm: dict, *, init_rvecs, init_centers_mm,
                  init_points_mm=None, iterations: int = 100, tol: float = 1e-10, calib=None) -> BundleResult:
    """Bundle adjustment of sensor poses and point positions.

    Parameters
    ----------
    sensors : list of str
        Sensor names (S).
    points : list of str
        Point names (M), known and unknown.
    obs_sensor, obs_point : (N,) int arrays
        Sensor and point index of each observation.
    n : (N, 2) array_like
        Observed normalised coordinates.
    cov_n : (N, 2, 2) array_like
        Their covariances.
    known_mm : dict
        ``{point name: (3,) world position}`` of the known points (>= 3, not collinear).
    init_rvecs, init_centers_mm : (S, 3) array_like
        Starting poses (e.g. from :func:`psdcal.measure.pose.estimate_pose`).
    init_points_mm : (M, 3) array_like, optional
        Starting points (default: triangulated from the starting poses).
    calib : tuple, optional
        ``(dn_dcalib (N, 2, m), cov_calib (S, m, m))``: each observation's
        derivative by its sensor's calibration parameters (zero-padded to
        ``m``) and each sensor's calibration covariance.  The calibration
        error is common to all of a sensor's observations: it is propagated
        through the solution (``H^-1 J^T W D_j``) and added to the pose and
        point covariances; ``cov_n`` is then the angle noise alone.

    Returns
    -------
    BundleResult

    Raises
    ------
    DegenerateViewsError
        Fewer than three known points, collinear ones, a point seen by fewer
        than two sensors (unknown) or a singular system.
    ConvergenceError
        No convergence within ``iterations``.
    """
    S, M = len(sensors), len(points)
    js = np.asarray(obs_sensor, dtype=int)
    ii = np.asarray(obs_point, dtype=int)
    n = np.asarray(n, dtype=float)
    N = len(js)
    if n.shape != (N, 2) or np.shape(cov_n) != (N, 2, 2) or ii.shape != (N,):
        raise InputError("observation arrays of different lengths")
    known = np.array([p in known_mm for p in points])
    kp = np.array([known_mm[p] for p in points if p in known_mm], dtype=float).reshape(-1, 3)
    if len(kp) < 3 or np.linalg.svd(kp - kp.mean(0), compute_uv=False)[1] <= 1e-3 * np.ptp(kp, 0).max():
        raise DegenerateViewsError("the world frame needs at least three known points, not collinear")
    W = np.linalg.inv(np.asarray(cov_n, dtype=float))
    np.linalg.cholesky(W)  # refuses a measurement covariance that is not positive definite (LinAlgError)
    Rs = np.stack([R_from_r(r) for r in np.asarray(init_rvecs, dtype=float)])
    cs = np.asarray(init_centers_mm, dtype=float).copy()
    seen = np.zeros((M, S), bool)
    seen[ii, js] = True
    if np.any((seen.sum(1) < 2) & ~known):
        bad = [points[k] for k in np.flatnonzero((seen.sum(1) < 2) & ~known)][:5]
        raise DegenerateViewsError(f"unknown point(s) {bad} seen by fewer than two sensors")
    if init_points_mm is None:
        X = _triangulate_points(Rs, cs, js, ii, n, W, M)
    else:
        X = np.asarray(init_points_mm, dtype=float).copy()
    for k, p in enumerate(points):
        if known[k]:
            X[k] = known_mm[p]
    unk = np.flatnonzero(~known)
    uidx = -np.ones(M, int)
    uidx[unk] = np.arange(len(unk))
    Mu = len(unk)

    def evaluate(Rs, cs, X):
        pc = np.einsum("nij,nj->ni", Rs[js], X[ii] - cs[js])
        z = pc[:, 2]
        if np.any(z <= 0):
            return math.inf, None, None, None
        pred = pc[:, :2] / z[:, None]
        r = n - pred
        chi2 = float(np.einsum("ni,nij,nj->", r, W, r))
        dpi = np.zeros((N, 2, 3))
        dpi[:, 0, 0] = dpi[:, 1, 1] = 1 / z
        dpi[:, 0, 2] = -pred[:, 0] / z
        dpi[:, 1, 2] = -pred[:, 1] / z
        Jp = np.concatenate([-dpi @ skews(pc), -dpi @ Rs[js]], -1)  # (N, 2, 6)
        Jx = dpi @ Rs[js]  # (N, 2, 3)
        return chi2, r, Jp, Jx

    def normal(r, Jp, Jx):
        JpW = np.swapaxes(Jp, 1, 2) @ W
        JxW = np.swapaxes(Jx, 1, 2) @ W
        U = np.zeros((S, 6, 6))
        np.add.at(U, js, JpW @ Jp)
        gp = np.zeros((S, 6))
        np.add.at(gp, js, np.einsum("nij,nj->ni", JpW, r))
        V = np.zeros((M, 3, 3))
        np.add.at(V, ii, JxW @ Jx)
        gx = np.zeros((M, 3))
        np.add.at(gx, ii, np.einsum("nij,nj->ni", JxW, r))
        Wb = JpW @ Jx  # (N, 6, 3): block (sensor j, point i)
        return U, gp, V[unk], gx[unk], Wb

    def schur(U, V, Wb, lam):
        """Reduced pose system (6S, 6S) and the pieces for back-substitution."""
        Ud = U + lam * np.einsum("sii->si", U)[:, :, None] * np.eye(6)
        Vd = V + lam * np.einsum("mii->mi", V)[:, :, None] * np.eye(3)
        Vinv = np.linalg.inv(Vd)
        A = np.zeros((6 * S, 6 * S))
        for j in range(S):
            A[6 * j : 6 * j + 6, 6 * j : 6 * j + 6] = Ud[j]
        # W V^-1 W^T summed over the unknown points, sensor pairs (j, k)
        sel = ~known[ii]
        WV = np.einsum("nab,nbc->nac", Wb[sel], Vinv[uidx[ii[sel]]])  # (n_u, 6, 3)
        obs_u = np.flatnonzero(sel)
        by_point: dict = {}
        for q, o in enumerate(obs_u):
            by_point.setdefault(ii[o], []).append(q)
        for qs in by_point.values():
            for a in qs:
                ja = js[obs_u[a]]
                for b in qs:
                    jb = js[obs_u[b]]
                    A[6 * ja : 6 * ja + 6, 6 * jb : 6 * jb + 6] -= WV[a] @ Wb[obs_u[b]].T
        return A, Vinv, WV, obs_u

    def solve(U, gp, V, gx, Wb, lam):
        return back_substitute(schur(U, V, Wb, lam), gp, gx, Wb)

    def back_substitute(pre, gp, gx, Wb):
        A, Vinv, WV, obs_u = pre
        rhs = gp.reshape(-1).copy()
        for q, o in enumerate(obs_u):
            rhs[6 * js[o] : 6 * js[o] + 6] -= WV[q] @ gx[uidx[ii[o]]]
        try:
            dp = np.linalg.solve(A, rhs).reshape(S, 6)
        except np.linalg.LinAlgError:
            raise DegenerateViewsError("the bundle's normal equations are singular (too few views)") from None
        t = gx.copy()
        for q, o in enumerate(obs_u):
            t[uidx[ii[o]]] -= Wb[o].T @ dp[js[o]]
        dx = np.einsum("mij,mj->mi", Vinv, t)
        return dp, dx

    f, r, Jp, Jx = evaluate(Rs, cs, X)
    if not np.isfinite(f):
        raise DegenerateViewsError("a point is behind a sensor at the start: check the starting poses")
    lam = 1e-3
    it = 0
    converged = False
    for it in range(1, iterations + 1):
        U, gp, V, gx, Wb = normal(r, Jp, Jx)
        while True:
            dp, dx = solve(U, gp, V, gx, Wb, lam)
            Rs2 = np.stack([R_from_r(dp[j, :3]) @ Rs[j] for j in range(S)])
            cs2 = cs + dp[:, 3:]
            X2 = X.copy()
            X2[unk] += dx
            f2, r2, Jp2, Jx2 = evaluate(Rs2, cs2, X2)
            if f2 <= f:
                break
            lam *= 10
            if lam > 1e12:
                break
        if not f2 <= f:
            converged = True  # no further decrease possible
            break
        small = f - f2 <= tol * max(f, 1e-300) + 1e-14
        Rs, cs, X, f, r, Jp, Jx = Rs2, cs2, X2, f2, r2, Jp2, Jx2
        lam = max(lam / 10, 1e-12)
        if small:
            converged = True
            break
    if not converged:
        raise ConvergenceError(f"the bundle adjustment did not converge in {iterations} iterations")
    # covariance at the solution (no damping)
    U, gp, V, gx, Wb = normal(r, Jp, Jx)
    A, Vinv, WV, obs_u = schur(U, V, Wb, 0.0)
    try:
        Sinv = np.linalg.inv(A)
    except np.linalg.LinAlgError:
        raise DegenerateViewsError("the poses are not determined (singular Schur complement)") from None
    cov_poses = np.stack([Sinv[6 * j : 6 * j + 6, 6 * j : 6 * j + 6] for j in range(S)])
    cov_points = np.zeros((M, 3, 3))
    # point blocks: V^-1 + V^-1 W_i^T S^-1 W_i V^-1 with W_i the (6S, 3) column of point i
    Wcol = np.zeros((Mu, 6 * S, 3))
    for q, o in enumerate(obs_u):
        Wcol[uidx[ii[o]], 6 * js[o] : 6 * js[o] + 6] += Wb[o]
    for m in range(Mu):
        B = Wcol[m] @ Vinv[m]
        cov_points[unk[m]] = Vinv[m] + B.T @ Sinv @ B
    if calib is not None:
        # the calibration error of sensor j moves all its rays together: d(params) = H^-1 J^T W D_j d theta_j
        D = np.asarray(calib[0], dtype=float)
        Sc = np.asarray(calib[1], dtype=float)
        pre = (A, Vinv, WV, obs_u)
        JpW = np.swapaxes(Jp, 1, 2) @ W
        JxW = np.swapaxes(Jx, 1, 2) @ W
        for j in range(S):
            mine = js == j
            cols_p, cols_x = [], []
            for c in range(D.shape[-1]):
                dn = np.where(mine[:, None], D[:, :, c], 0.0)
                gp_c = np.zeros((S, 6))
                np.add.at(gp_c, js, np.einsum("nij,nj->ni", JpW, dn))
                gx_c = np.zeros((M, 3))
                np.add.at(gx_c, ii, np.einsum("nij,nj->ni", JxW, dn))
                dp_c, dx_c = back_substitute(pre, gp_c, gx_c[unk], Wb)
                cols_p.append(dp_c)
                cols_x.append(dx_c)
            Pp = np.stack(cols_p, -1)  # (S, 6, m)
            Px = np.stack(cols_x, -1)  # (Mu, 3, m)
            cov_poses = cov_poses + Pp @ Sc[j] @ np.swapaxes(Pp, 1, 2)
            cov_points[unk] += Px @ Sc[j] @ np.swapaxes(Px, 1, 2)
    dof = 2 * N - 6 * S - 3 * Mu
    check = chi2_check(float(f), dof, name="bundle_chi2", what=f"the {N} observations of {S} sensors",
                       advice=BUNDLE_ADVICE)
    infl = 1.0 if check.inflation is None else float(check.inflation)
    return BundleResult(list(sensors), np.stack([r_from_R(R) for R in Rs]), cs, infl * cov_poses, list(points), X,
                        infl * cov_points, known, float(f), int(dof), it, check=check, cov_poses_stated=cov_poses,
                        cov_points_stated=cov_points)


#: The likely causes of a bundle adjustment that does not fit its stated noise.
BUNDLE_ADVICE = ("a wrong known position, a wand window seen differently by the sensors, an underestimated angle "
                 "noise, or a wrong start (3 known emitters can give a mirrored pose: use 4 or more)")


def _triangulate_points(Rs, cs, js, ii, n, W, M):
    """Starting points: the unweighted midpoint of the rays of each point (NaN for points seen once)."""
    X = np.full((M, 3), np.nan)
    u = np.concatenate([n, np.ones((len(n), 1))], 1)
    u = np.einsum("nji,nj->ni", Rs[js], u)  # R^T ray
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    A = np.zeros((M, 3, 3))
    b = np.zeros((M, 3))
    P = np.eye(3) - u[:, :, None] * u[:, None, :]
    np.add.at(A, ii, P)
    np.add.at(b, ii, np.einsum("nij,nj->ni", P, cs[js]))
    ok = np.linalg.matrix_rank(A) == 3
    X[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return X


def write_points_csv(path, br: "BundleResult") -> None:
    """Write the bundle's points as ``emitter,X_m,Y_m,Z_m,sigma_X_mm,sigma_Y_mm,sigma_Z_mm`` (atomically)."""
    from psdcal._atomic import write_text_atomic

    lines = ["emitter,X_m,Y_m,Z_m,sigma_X_mm,sigma_Y_mm,sigma_Z_mm"]
    for k, p in enumerate(br.points):
        s = np.sqrt(np.clip(np.diag(br.cov_points[k]), 0, None))
        X = br.points_mm[k] / 1000.0
        lines.append(f"{p},{X[0]:.9g},{X[1]:.9g},{X[2]:.9g},{s[0]:.6g},{s[1]:.6g},{s[2]:.6g}")
    write_text_atomic(path, "\n".join(lines) + "\n")
