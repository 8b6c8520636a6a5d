"""Compiled solves of block normal equations: the Schur complement of the pose blocks.

The normal equations of a compact block Jacobian
(:func:`psdcal.calibration._gram_kernel.gram_block_normal`) are kept in blocks: the global
block ``U`` (n_global^2), one 6 x 6 block ``V_v`` per view and the coupling ``W_v``
(n_global x 6). The LM step (:func:`schur_solve`) and the covariance (:func:`schur_covariance`)
eliminate the poses view by view through the Schur complement
``S = U - sum_v W_v V_v^-1 W_v^T`` (the reduced camera system, Triggs et al., *Bundle
adjustment - a modern synthesis*, 2000, Section 6.1), so their cost is linear in the number of
views. The numpy reference of these steps is :mod:`psdcal.calibration._normal`
(``schur_solve_reference``, ``schur_covariance_reference``); :func:`_cholesky` is also the
verdict kernel's (:mod:`psdcal.calibration._verdict_kernel`).
"""
from __future__ import annotations

import math

import numpy as np

from psdcal._jit import njit


@njit
def _cholesky(A, L):
    """Lower Cholesky factor of the symmetric ``A`` into ``L``; False when A is not positive definite."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 0.0):
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@njit
def _cho_solve(L, b):
    """Solve ``L L^T x = b`` in place (b (n,))."""
    n = L.shape[0]
    for i in range(n):
        t = b[i]
        for k in range(i):
            t -= L[i, k] * b[k]
        b[i] = t / L[i, i]
    for i in range(n - 1, -1, -1):
        t = b[i]
        for k in range(i + 1, n):
            t -= L[k, i] * b[k]
        b[i] = t / L[i, i]


@njit
def _reduce(U, W, V, damp_g, damp_p):
    """Schur complement of the (damped) pose blocks.

    Returns ``(ok, S, Y, Lv)``: ``S = U + diag(damp_g) - sum_v W_v Vd_v^-1 W_v^T``
    (ng, ng), ``Y[v] = Vd_v^-1 W_v^T`` (n, 6, ng) and the Cholesky factors
    ``Lv`` (n, 6, 6) of ``Vd_v = V_v + diag(damp_p[v])``; ok is False when a
    pose block is not positive definite.
    """
    n = V.shape[0]
    ng = U.shape[0]
    S = U.copy()
    for a in range(ng):
        S[a, a] += damp_g[a]
    Y = np.empty((n, 6, ng))
    Lv = np.zeros((n, 6, 6))
    Vd = np.empty((6, 6))
    col = np.empty(6)
    for v in range(n):
        for a in range(6):
            for b in range(6):
                Vd[a, b] = V[v, a, b]
            Vd[a, a] += damp_p[v, a]
        if not _cholesky(Vd, Lv[v]):
            return False, S, Y, Lv
        for c in range(ng):
            for a in range(6):
                col[a] = W[v, c, a]
            _cho_solve(Lv[v], col)
            for a in range(6):
                Y[v, a, c] = col[a]
        for a in range(ng):
            for b in range(a + 1):
                acc = 0.0
                for k in range(6):
                    acc += W[v, a, k] * Y[v, k, b]
                S[a, b] -= acc
    for a in range(ng):
        for b in range(a):
            S[b, a] = S[a, b]
    return True, S, Y, Lv


@njit
def schur_solve(U, W, V, gg, gp, damp_g, damp_p):
    """Solve ``(A + diag(damp)) h = g`` of block normal equations by eliminating the poses.

    ``A = [[U, W_1 .. W_n], [W^T, diag(V_1 .. V_n)]]``, ``g = (gg, gp)``,
    ``damp = (damp_g, damp_p)``. The global part solves the reduced system
    ``S hg = gg - sum_v W_v Vd_v^-1 gp_v``, then each view
    ``hp_v = Vd_v^-1 (gp_v - W_v^T hg)``: O(n ng^2) work, no matrix of the
    size of A.

    Returns
    -------
    ok : bool, False when a block or S is not positive definite
    hg : (ng,), hp : (n, 6)
    """
    n = V.shape[0]
    ng = U.shape[0]
    hg = np.zeros(ng)
    hp = np.zeros((n, 6))
    ok, S, Y, Lv = _reduce(U, W, V, damp_g, damp_p)
    if not ok:
        return False, hg, hp
    b = gg.copy()
    col = np.empty(6)
    for v in range(n):
        for a in range(6):
            col[a] = gp[v, a]
        _cho_solve(Lv[v], col)
        for c in range(ng):
            acc = 0.0
            for a in range(6):
                acc += W[v, c, a] * col[a]
            b[c] -= acc
    Ls = np.zeros((ng, ng))
    if not _cholesky(S, Ls):
        return False, hg, hp
    _cho_solve(Ls, b)
    for c in range(ng):
        hg[c] = b[c]
    for v in range(n):
        for a in range(6):
            acc = gp[v, a]
            for c in range(ng):
                acc -= W[v, c, a] * hg[c]
            col[a] = acc
        _cho_solve(Lv[v], col)
        for a in range(6):
            hp[v, a] = col[a]
    return True, hg, hp


@njit
def schur_covariance(U, W, V):
    """Blocks of ``A^-1`` for block normal equations (no damping), without forming A.

    Returns
    -------
    ok : bool (False when A is not positive definite)
    Cg : (ng, ng) ``S^-1``, the global block (the covariance of the intrinsics up to sigma^2)
    Cp : (n, 6, 6) ``V_v^-1 + Y_v S^-1 Y_v^T`` (``Y_v = V_v^-1 W_v^T``), the pose blocks
    Cx : (n, ng, 6) ``-S^-1 Y_v^T``, the global-pose blocks
    """
    n = V.shape[0]
    ng = U.shape[0]
    Cg = np.zeros((ng, ng))
    Cp = np.zeros((n, 6, 6))
    Cx = np.zeros((n, ng, 6))
    ok, S, Y, Lv = _reduce(U, W, V, np.zeros(ng), np.zeros((n, 6)))
    if not ok:
        return False, Cg, Cp, Cx
    Ls = np.zeros((ng, ng))
    if not _cholesky(S, Ls):
        return False, Cg, Cp, Cx
    e = np.empty(ng)
    for c in range(ng):
        for a in range(ng):
            e[a] = 0.0
        e[c] = 1.0
        _cho_solve(Ls, e)
        for a in range(ng):
            Cg[a, c] = e[a]
    col = np.empty(6)
    for v in range(n):
        for a in range(6):  # Cx = -Cg Y^T
            for c in range(ng):
                acc = 0.0
                for k in range(ng):
                    acc += Cg[c, k] * Y[v, a, k]
                Cx[v, c, a] = -acc
        for b in range(6):  # V^-1 column b
            for a in range(6):
                col[a] = 0.0
            col[b] = 1.0
            _cho_solve(Lv[v], col)
            for a in range(6):
                acc = 0.0
                for c in range(ng):
                    acc -= Y[v, a, c] * Cx[v, c, b]
                Cp[v, a, b] = col[a] + acc
    return True, Cg, Cp, Cx
