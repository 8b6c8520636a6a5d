"""Vectorised kernels of a rigid tag seen by sensors (the self-calibration and the tag's pose).

Conventions (docs/guide/selfcal.md#the-model):

- sensor ``k``: ``Pc = R_k (Pw - c_k)``; a small update ``R_k <- exp([omega]) R_k`` (camera frame),
  ``c_k <- c_k + dc``;
- tag at step ``t``: ``Pw = Q_t B + p_t`` for a body point ``B``; update ``Q_t <- exp([phi]) Q_t``
  (world frame), ``p_t <- p_t + dp``;
- observation ``n = pi(Pc) = (Xc/Zc, Yc/Zc)`` with covariance ``C``; whitened residual
  ``L (n - pi(Pc))`` with ``L = chol(C)^-1``.
"""
from __future__ import annotations

import numpy as np

from psdcal.model.projection import nearest_rotation_batch


def skew_batch(v):
    """``[v]_x`` (N, 3, 3) of rows ``v`` (N, 3)."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def exp_so3(w):
    """Rotation matrices (N, 3, 3) of rotation vectors (N, 3) (Rodrigues)."""
    w = np.asarray(w, dtype=float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew_batch(w)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    return np.eye(3) + a * K + b * (K @ K)


def whiteners(cov):
    """``L`` (N, 2, 2) with ``L C L^T = I`` (the inverse of the Cholesky factor)."""
    G = np.linalg.cholesky(np.asarray(cov, dtype=float))
    return np.linalg.inv(G)


def project(R, c, X):
    """Camera points, normalised directions and ``dpi/dPc`` for world points ``X`` (N, 3) in poses ``R, c`` (N, ...)."""
    Pc = _mv(R, X - c)
    z = Pc[:, 2]
    n = Pc[:, :2] / z[:, None]
    D = np.zeros((len(z), 2, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0 / z
    D[:, 0, 2] = -Pc[:, 0] / z**2
    D[:, 1, 2] = -Pc[:, 1] / z**2
    return Pc, n, D


def _mv(M, v):
    """Batched matrix-vector product ``M (N, a, b) @ v (N, b) -> (N, a)``."""
    return (M @ v[..., None])[..., 0]


def bmm(A, B):
    """Batched product of tiny matrices ``A (N, a, b) @ B (N, b, c)``."""
    return A @ B


def sum_by(idx, X, size: int):
    """``out[j] = sum of X[i] where idx[i] == j`` (size, ...), for any ``idx`` (fast when it is sorted)."""
    idx = np.asarray(idx)
    X = np.asarray(X, dtype=float)
    out = np.zeros((size,) + X.shape[1:])
    if len(idx) == 0:
        return out
    if np.any(np.diff(idx) < 0):
        o = np.argsort(idx, kind="stable")
        idx, X = idx[o], X[o]
    starts = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
    out[idx[starts]] = np.add.reduceat(X, starts, axis=0)
    return out


def gram(J, J2=None):
    """``J^T J2`` (N, p, q) of stacked Jacobians ``J`` (N, m, p), ``J2`` (N, m, q) (default ``J``)."""
    J2 = J if J2 is None else J2
    out = J[:, 0, :, None] * J2[:, 0, None, :]
    for i in range(1, J.shape[1]):
        out += J[:, i, :, None] * J2[:, i, None, :]
    return out


def residuals_and_jacobians(Rs, cs, Q, p, B, k, t, e, n_obs, L, *, jac: bool = True):
    """Whitened residuals (N, 2) and their Jacobians by the sensor (N, 2, 6) and tag (N, 2, 6) updates.

    ``Rs, cs``: sensor poses (K, 3, 3), (K, 3); ``Q, p``: tag poses (T, 3, 3), (T, 3);
    ``B`` (E, 3) body points; ``k, t, e`` (N,) indices of each observation.
    Also returns the depth ``Zc`` (N,) (a point behind a sensor has ``Zc <= 0``).
    """
    QB = _mv(Q[t], B[e])
    X = QB + p[t]
    Rk = Rs[k]
    Pc, nh, D = project(Rk, cs[k], X)
    r = _mv(L, n_obs - nh)
    if not jac:
        return r, None, None, Pc[:, 2]
    LD = -bmm(L, D)  # d r / d Pc
    LDR = bmm(LD, Rk)
    # a^T [v]x = (a x v)^T, row by row
    Js = np.concatenate([-np.cross(LD, Pc[:, None, :]), -LDR], axis=2)
    Jt = np.concatenate([-np.cross(LDR, QB[:, None, :]), LDR], axis=2)
    return r, Js, Jt, Pc[:, 2]


def fixed_point_residuals(Rs, cs, P, k, n_obs, L, *, jac: bool = True):
    """Whitened residuals (N, 2) of known world points ``P`` (N, 3) and their Jacobians by the sensor update."""
    Rk = Rs[k]
    Pc, nh, D = project(Rk, cs[k], P)
    r = _mv(L, n_obs - nh)
    if not jac:
        return r, None, Pc[:, 2]
    LD = -bmm(L, D)
    return r, np.concatenate([-np.cross(LD, Pc[:, None, :]), -bmm(LD, Rk)], axis=2), Pc[:, 2]


def kabsch(A, B, w=None):
    """Rotation ``R`` and translation ``t`` minimising ``sum w |R A_i + t - B_i|^2`` (A, B (n, 3))."""
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    w = np.ones(len(A)) if w is None else np.asarray(w, dtype=float)
    ca = (w[:, None] * A).sum(0) / w.sum()
    cb = (w[:, None] * B).sum(0) / w.sum()
    H = ((A - ca) * w[:, None]).T @ (B - cb)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cb - R @ ca


def kabsch_batch(A, B, w):
    """:func:`kabsch` over a batch: ``A, B`` (T, m, 3), weights ``w`` (T, m) (0: point absent)."""
    ws = w.sum(1)[:, None]
    ca = np.einsum("tm,tmi->ti", w, A) / ws
    cb = np.einsum("tm,tmi->ti", w, B) / ws
    H = np.einsum("tm,tmi,tmj->tij", w, A - ca[:, None], B - cb[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    d[d == 0] = 1.0
    Dm = np.zeros((len(A), 3, 3))
    Dm[:, 0, 0] = Dm[:, 1, 1] = 1.0
    Dm[:, 2, 2] = d
    R = np.swapaxes(Vt, 1, 2) @ Dm @ np.swapaxes(U, 1, 2)
    return R, cb - np.einsum("tij,tj->ti", R, ca)


def _axis_to_z(u):
    """Rotations (T, 3, 3) taking the unit vectors ``u`` (T, 3) onto +z (the shortest turn)."""
    z = np.array([0.0, 0.0, 1.0])
    ax = np.cross(u, z)
    s = np.linalg.norm(ax, axis=1)
    ang = np.arctan2(s, u[:, 2])
    w = np.where(s[:, None] > 1e-15, ax / np.where(s > 1e-15, s, 1.0)[:, None], 0.0) * ang[:, None]
    return exp_so3(w)


def weak_perspective(n, B):
    """Starts of a rigid body's pose in one camera (:func:`_weak_perspective` in a camera turned to the body)."""
    u = np.concatenate([n, np.ones(n.shape[:-1] + (1,))], axis=-1)
    um = u / np.linalg.norm(u, axis=-1, keepdims=True)
    A = _axis_to_z(um.mean(1) / np.linalg.norm(um.mean(1), axis=-1, keepdims=True))
    v = np.einsum("tij,tmj->tmi", A, u)
    out = []
    for R, p in _weak_perspective(v[..., :2] / v[..., 2:], B):
        At = np.swapaxes(A, 1, 2)
        out.append((At @ R, np.einsum("tij,tj->ti", At, p)))
    return out


def _weak_perspective(n, B):
    """Starts of a rigid body's pose in one camera from its points' directions (scaled orthography).

    Parameters
    ----------
    n : (T, m, 2) ndarray
        Normalised directions of the same ``m >= 3`` body points at ``T`` steps.
    B : (m, 3) ndarray
        The body points, mm.

    Returns
    -------
    list of (Q (T, 3, 3), p (T, 3))
        One start for a body with points off a plane; two (the mirror tilt
        ambiguity of a plane seen from afar) for a planar body.
    """
    Bc = B - B.mean(0)
    nc = n - n.mean(1, keepdims=True)
    _, s, Vt = np.linalg.svd(Bc)
    planar = s[2] < 1e-6 * s[0]
    if not planar:
        M = np.einsum("tmi,mj->tij", nc, np.linalg.pinv(Bc).T)  # (T, 2, 3): nc = Bc M^T
        scale = 0.5 * (np.linalg.norm(M[:, 0], axis=1) + np.linalg.norm(M[:, 1], axis=1))
        r12 = M / scale[:, None, None]
        R = np.concatenate([r12, np.cross(r12[:, 0], r12[:, 1])[:, None]], axis=1)
        starts = [nearest_rotation_batch(R)]
    else:
        E = Vt[:2].T  # body in-plane basis (3, 2)
        C2 = Bc @ E  # (m, 2)
        M2 = np.einsum("tmi,mj->tij", nc, np.linalg.pinv(C2).T)  # (T, 2, 2): columns m1, m2 = s * R[:2] E
        m1, m2 = M2[:, :, 0], M2[:, :, 1]
        a1, a2, a12 = (m1 * m1).sum(1), (m2 * m2).sum(1), (m1 * m2).sum(1)
        det = np.maximum(a1 * a2 - a12**2, 1e-300)
        disc = np.sqrt(np.maximum((a1 + a2) ** 2 - 4 * det, 0.0))
        q = ((a1 + a2) - disc) / (2 * det)  # q = 1 / s^2, the root with real z components
        sq = np.sqrt(q)
        za = np.sqrt(np.clip(1 - q * a1, 0.0, 1.0))
        zb = np.sqrt(np.clip(1 - q * a2, 0.0, 1.0))
        sgn = np.where(-q * a12 >= 0, 1.0, -1.0)
        starts = []
        for flip in (1.0, -1.0):
            ca = np.concatenate([m1 * sq[:, None], (flip * za)[:, None]], axis=1)
            cb = np.concatenate([m2 * sq[:, None], (flip * sgn * zb)[:, None]], axis=1)
            RE = np.stack([ca, cb], axis=2)  # R E (T, 3, 2)
            r3 = np.cross(RE[:, :, 0], RE[:, :, 1])
            Full = np.concatenate([RE, r3[:, :, None]], axis=2)  # R [E, e3]
            e3 = np.cross(E[:, 0], E[:, 1])
            R = Full @ np.stack([E[:, 0], E[:, 1], e3], axis=0)  # R = Full [E e3]^T
            starts.append(nearest_rotation_batch(R))
        scale = 1.0 / sq
    out = []
    for R in starts:
        tz = 1.0 / scale
        nm = n.mean(1)
        RBm = np.einsum("tij,j->ti", R, B.mean(0))
        p = np.concatenate([nm * tz[:, None], tz[:, None]], axis=1) - RBm
        out.append((R, p))
    return out


def solve_blocks(H, g, damping):
    """Solve ``(H + damping diag(H)) x = -g`` for a batch of 6x6 blocks ``H`` (T, 6, 6), ``g`` (T, 6)."""
    d = np.diagonal(H, axis1=1, axis2=2)
    Hd = H + np.einsum("t,ti,ij->tij", damping, np.maximum(d, 1e-12 * d.max(1, keepdims=True) + 1e-300), np.eye(6))
    return -np.linalg.solve(Hd, g[..., None])[..., 0]


def tag_gauss_newton(Rs, cs, Q, p, B, k, t, e, n_obs, L, T, *, iterations: int = 50, tol: float = 1e-9):
    """Refine every step's tag pose with the sensors fixed (independent 6x6 Levenberg-Marquardt per step).

    A step stops when its Gauss-Newton step would lower its chi2 by less than
    ``tol (1 + chi2)``; only the steps still moving are evaluated.
    Returns ``Q, p, cost (T,), H (T, 6, 6)`` (``H = J^T J`` at the solution).
    """
    Q = np.array(Q, dtype=float)
    p = np.array(p, dtype=float)

    def accumulate(Qs, ps, steps):
        """cost, H, g of the steps ``steps`` (sorted indices) at poses ``Qs, ps`` (len(steps), ...)."""
        m = np.isin(t, steps)
        loc = np.searchsorted(steps, t[m])
        nS = len(steps)
        with np.errstate(all="ignore"):
            r, _, Jt, z = residuals_and_jacobians(Rs, cs, Qs, ps, B, k[m], loc, e[m], n_obs[m], L[m])
            cost = sum_by(loc, (r * r).sum(1), nS)
            cost[(sum_by(loc, (z <= 0).astype(float), nS) > 0) | ~np.isfinite(cost)] = np.inf
            H = sum_by(loc, gram(Jt), nS)
            g = sum_by(loc, _mv(np.swapaxes(Jt, 1, 2), r), nS)
        bad = ~np.isfinite(cost)
        H[bad] = np.eye(6)
        g[bad] = 0.0
        return cost, H, g

    allsteps = np.arange(T)
    cost, H, g = accumulate(Q, p, allsteps)
    lam = np.full(T, 1e-3)
    done = ~np.isfinite(cost)
    for _ in range(iterations):
        act = np.flatnonzero(~done)
        if len(act) == 0:
            break
        dx = solve_blocks(H[act], g[act], lam[act])
        pred = -(g[act] * dx).sum(1)  # the decrease the (damped) step expects
        fin = (pred < tol * (1.0 + cost[act])) & (lam[act] <= 1e-2)
        done[act[fin]] = True
        act, dx = act[~fin], dx[~fin]
        if len(act) == 0:
            break
        Qn = exp_so3(dx[:, :3]) @ Q[act]
        pn = p[act] + dx[:, 3:]
        cn, Hn, gn = accumulate(Qn, pn, act)
        better = cn < cost[act]
        up = act[better]
        Q[up], p[up], cost[up], H[up], g[up] = Qn[better], pn[better], cn[better], Hn[better], gn[better]
        lam[up] = np.maximum(lam[up] / 10.0, 1e-9)
        lam[act[~better]] *= 10.0
        done |= lam > 1e8
    return Q, p, cost, H
