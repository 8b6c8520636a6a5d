"""The numerical core of :mod:`psdcal.measure.pose`: model, starts and refinement of a proper rotation.

Every rotation built here is a proper rotation (determinant +1): the starts
(plane homography, DLT, closed-form P3P on triplets, distances along the rays)
go through :func:`_kabsch` or :func:`_orthonormal`, which never return a
reflection, and the refinement multiplies by ``exp([omega])``.
:func:`search` asserts it (a determinant -1 is a bug, never a result).

Conventions as in :mod:`psdcal.measure.pose`: ``n = pi(R (P - c))`` with
``pi(X, Y, Z) = (X / Z, Y / Z)``; ``R`` world -> camera, ``c`` the projection
centre in the world (mm); the parameters are ``(omega, c)`` with
``R = exp([omega]) R_hat``.
"""
from __future__ import annotations

import math

import numpy as np



def skew_batch(v):
    """``[v]_x`` of each row of ``v`` (k, 3) -> (k, 3, 3)."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def exp_rotation(w):
    """``exp([w]_x)`` (3, 3) of a rotation vector ``w`` (3,) (Rodrigues' formula, a proper rotation)."""
    th2 = float(w @ w)
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th2 < 1e-24:
        return np.eye(3) + K
    th = math.sqrt(th2)
    return np.eye(3) + (math.sin(th) / th) * K + ((1.0 - math.cos(th)) / th2) * (K @ K)


def predict(R, c, P):
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
    J = np.concatenate([-dpi @ skew_batch(pc), -dpi @ R], axis=-1)
    return n, pc, J


def _kabsch(Q, P):
    """R (proper), c with Q ~ R (P - c), least squares (Q camera points, P world points, (k, 3))."""
    qm, pm = Q.mean(0), P.mean(0)
    H = (P - pm).T @ (Q - qm)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    c = pm - R.T @ qm
    return R, c


def _orthonormal(M):
    """The proper rotation nearest to ``M`` (3, 3)."""
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return R


def rays(n):
    """Unit rays (k, 3) of normalised coordinates (k, 2)."""
    u = np.concatenate([n, np.ones((len(n), 1))], axis=1)
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def p3p(u, X):
    """Closed-form poses from three rays ``u`` (3, 3) (unit) and their world points ``X`` (3, 3).

    The distances ``s_i`` along the rays satisfy the three laws of cosines
    ``s_i^2 + s_j^2 - 2 s_i s_j cos(u_i, u_j) = |X_i - X_j|^2``; with
    ``s_1 = x s_0``, ``s_2 = y s_0`` their differences give ``x = N(y) / D(y)``
    (``N`` quadratic, ``D`` linear) and a quartic in ``y``. Each positive real
    root gives the camera points ``s_i u_i`` and a pose by :func:`_kabsch`.

    Returns
    -------
    list of (R, c)
        Up to four poses (proper rotations).
    """
    d01 = float(np.sum((X[0] - X[1]) ** 2))
    d02 = float(np.sum((X[0] - X[2]) ** 2))
    d12 = float(np.sum((X[1] - X[2]) ** 2))
    c01, c02, c12 = float(u[0] @ u[1]), float(u[0] @ u[2]), float(u[1] @ u[2])
    if min(d01, d02, d12) <= 0:
        return []
    conv = np.convolve
    Q = np.array([1.0, -2.0 * c02, 1.0])  # 1 + y^2 - 2 y c02 (ascending powers)
    N = (d12 - d01) * Q - d02 * np.array([-1.0, 0.0, 1.0])
    D = 2.0 * d02 * np.array([c01, -c12])
    DD = conv(D, D)
    quartic = d02 * (np.concatenate([DD, [0.0, 0.0]]) + conv(N, N) - 2.0 * c01 * np.concatenate([conv(N, D), [0.0]]))
    quartic = quartic - d01 * conv(Q, DD)
    if not np.all(np.isfinite(quartic)) or np.max(np.abs(quartic)) == 0:
        return []
    out = []
    for y in np.roots(np.trim_zeros(quartic, "b")[::-1]):
        if abs(y.imag) > 0.05 * max(1.0, abs(y.real)):
            continue  # a pair of roots made complex by the noise near a double root is kept (its real part)
        y = float(y.real)
        den = D[0] + D[1] * y
        q = 1.0 + y * y - 2.0 * c02 * y
        if y <= 0 or abs(den) < 1e-12 * d02 or q <= 0:
            continue
        x = (N[0] + N[1] * y + N[2] * y * y) / den
        if x <= 0:
            continue
        s0 = math.sqrt(d02 / q)
        s = np.array([s0, x * s0, y * s0])
        cam = s[:, None] * u
        # the three laws of cosines hold (a spurious root of the elimination does not; a root made complex
        # by the noise holds them nearly)
        err = [abs(np.sum((cam[i] - cam[j]) ** 2) - d) for (i, j, d) in ((0, 1, d01), (0, 2, d02), (1, 2, d12))]
        if max(err) > 0.1 * max(d01, d02, d12):
            continue
        out.append(_kabsch(cam, X))
    return out


def linear_starts(n, P):
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
        s_uv = float(np.sqrt(np.mean(np.sum(uv**2, axis=1)))) or 1.0
        uv = uv / s_uv  # Hartley's normalisation: the linear system well conditioned
        A = np.zeros((2 * k, 9))
        A[0::2, 0:2], A[0::2, 2] = uv, 1.0
        A[1::2, 3:5], A[1::2, 5] = uv, 1.0
        A[0::2, 6:8], A[0::2, 8] = -n[:, :1] * uv, -n[:, 0]
        A[1::2, 6:8], A[1::2, 8] = -n[:, 1:] * uv, -n[:, 1]
        H = np.linalg.svd(A)[2][-1].reshape(3, 3) @ np.diag([1.0 / s_uv, 1.0 / s_uv, 1.0])
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
        A = np.zeros((2 * k, 12))
        A[0::2, 0:4], A[0::2, 8:12] = X, -n[:, :1] * X
        A[1::2, 4:8], A[1::2, 8:12] = X, -n[:, 1:] * X
        Pm = np.linalg.svd(A)[2][-1].reshape(3, 4)
        scale = 1.0 / np.cbrt(abs(np.linalg.det(Pm[:, :3])) or 1.0)
        if (Pm[2] @ X[0]) * scale < 0:
            scale = -scale
        R = _orthonormal(scale * Pm[:, :3])
        t = scale * Pm[:, 3]
        out.append((R, m - R.T @ t))
    return out


def _triplets(P, most: int):
    """Up to ``most`` triplets of emitter indices, the widest triangles first."""
    k = len(P)
    tri = np.array([(i, j, l) for i in range(k) for j in range(i + 1, k) for l in range(j + 1, k)])
    area = np.linalg.norm(np.cross(P[tri[:, 1]] - P[tri[:, 0]], P[tri[:, 2]] - P[tri[:, 0]]), axis=1)
    return [tuple(tri[q]) for q in np.argsort(area)[::-1][:most]]


def _ray_distance_starts(u, P, idx, starts, rng):
    """Poses from the distances along the rays fitted to every pair's distance (least squares), then Kabsch."""
    from scipy.optimize import least_squares

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
        yield _kabsch(sol.x[:, None] * u[idx], P[idx])


def candidate_starts(n, P, *, triplets: int = 4, fallback: bool = True, seed: int = 0):
    """Candidate poses (R, c), cheapest and likeliest first, for :func:`search` to refine until one fits.

    1. linear estimates (:func:`linear_starts`);
    2. the closed-form P3P solutions (:func:`p3p`, up to four each) of the
       ``triplets`` widest triangles of emitters, in order of their fit to all
       emitters;
    3. with ``fallback``, the distances along the rays fitted to every pair of
       emitters (one common distance, then 3 random starts).
    """
    u = rays(n)
    yield from linear_starts(n, P)
    cands = []
    for t in _triplets(P, triplets):
        idx = np.array(t)
        cands += p3p(u[idx], P[idx])
    if cands:
        def misfit(Rc):
            pc = (P - Rc[1]) @ Rc[0].T
            if np.any(pc[:, 2] <= 0):
                return math.inf
            return float(np.sum((pc[:, :2] / pc[:, 2:] - n) ** 2))

        cost = [misfit(rc) for rc in cands]
        for q in np.argsort(cost):
            if np.isfinite(cost[q]):
                yield cands[q]
    if fallback:
        yield from fallback_starts(n, P, seed=seed)


def fallback_starts(n, P, *, seed: int = 0):
    """The distances along the rays fitted to every pair of emitters' distance (one common start, 3 random)."""
    yield from _ray_distance_starts(rays(n), P, np.arange(len(P)), 4, np.random.default_rng(seed))


def refine(R, c, n, P, W, free, iterations):
    """Gauss-Newton with step halving on ``r^T W r`` over the free parameters of ``(omega, c)``."""
    k = len(P)

    def evaluate(R, c):
        pred, pc, J = predict(R, c, P)
        if np.any(pc[:, 2] <= 0):
            return math.inf, None, None
        r = (n - pred).ravel()
        return float(r @ W @ r), r, J.reshape(2 * k, 6)[:, free]

    f, r, J = evaluate(R, c)
    if not np.isfinite(f):
        return R, c, math.inf
    for _ in range(iterations):
        JW = J.T @ W
        H = JW @ J
        g = JW @ r
        try:
            step = np.linalg.solve(H + 1e-12 * np.trace(H) * np.eye(len(H)), g)
        except np.linalg.LinAlgError:
            break
        full = np.zeros(6)
        full[free] = step
        lam = 1.0
        improved = False
        for _ in range(20):
            R2 = exp_rotation(lam * full[:3]) @ R
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


def _same_pose(a, b, dist_mm):
    """Whether two poses (R, c) are within 1 deg and 1 % of the distance of each other (one basin)."""
    cosang = (np.trace(a[0] @ b[0].T) - 1.0) / 2.0
    return cosang > math.cos(math.radians(1.0)) and np.linalg.norm(a[1] - b[1]) < 0.01 * dist_mm


def search(starts, n, P, W, free, iterations, accept, *, known_height_mm=None, max_refine: int = 60,
           skip_above: float = math.inf, after_accept: int = 0, minima: list | None = None):
    """Refine the candidate starts in turn; stop at the first minimum with ``chi2 <= accept``.

    Starts with an emitter behind the sensor, in the basin of a minimum
    already found, or whose chi2 before refinement exceeds ``skip_above`` or
    1000 times the best minimum's (plus 1000 ``accept``), are skipped; at most
    ``max_refine`` are refined. With ``after_accept``, up to that many more
    starts are refined after the first fitting minimum (those whose chi2
    before refinement is below ``100 accept``), to find a second minimum
    that fits too (the two-fold ambiguity of a plane seen from afar).
    ``minima`` (a list) receives every distinct minimum ``(R, c, chi2)``.

    Returns
    -------
    (R, c, chi2) of the best minimum found (chi2 inf when none), every rotation proper.
    """
    best = None
    found: list = []
    tried = 0
    extra = None
    for R, c in starts:
        if known_height_mm is not None:
            c = np.array([c[0], c[1], known_height_mm])
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(c))) or np.any((P - c) @ R[2] <= 0):
            continue
        dist = float(np.mean(np.linalg.norm(P - c, axis=1)))
        if any(_same_pose((R, c), f, dist) for f in found):
            continue
        limit = min(skip_above, math.inf if best is None else 1e3 * best[2] + 1e3 * accept)
        if extra is not None:
            limit = min(limit, 100.0 * accept)
        if limit < math.inf:
            # a start far worse than the best minimum found (or than skip_above) is in another, worse basin
            r = (n - (P - c) @ R[:2].T / ((P - c) @ R[2])[:, None]).ravel()
            if float(r @ W @ r) > limit:
                continue
        R, c, chi2 = refine(R, c, n, P, W, free, iterations)
        tried += 1
        if not np.isfinite(chi2):
            continue
        if np.linalg.det(R) < 0.5:  # pragma: no cover - a reflection is a bug, never a result
            raise AssertionError(f"pose solver produced a rotation of determinant {np.linalg.det(R):.3g}")
        dist = float(np.mean(np.linalg.norm(P - c, axis=1)))
        if not any(_same_pose((R, c), f, dist) for f in found):
            found.append((R, c))
            if minima is not None:
                minima.append((R, c, chi2))
        if best is None or chi2 < best[2] - 1e-9:
            best = (R, c, chi2)
        if extra is not None:
            extra -= 1
            if extra <= 0:
                break
        elif chi2 <= accept:
            if after_accept <= 0:
                break
            extra = after_accept
        if tried >= max_refine:
            break
    return best if best is not None else (None, None, math.inf)
