"""The verdict's projector compiled: the orthonormal bases of the Jacobian's columns and the products with them.

:func:`psdcal.calibration._verdict_linear.projector` (the numpy reference)
builds the projector off the fit's Jacobian from its block structure (each
view's six pose columns, then the global columns projected off them) and
returns functions that apply it. In numpy that is some hundred small array
operations per verdict (a batched eigenproblem, batched products of
(rows x 6) blocks, ...), whose per-call cost, not the arithmetic, dominates
on a few thousand rows. The kernels below do the same arithmetic in scalar
loops: the same two-pass Cholesky QR with the same conditioning tests
(:data:`~psdcal.calibration._verdict_linear.CHOLQR_MAX_COND`,
:data:`~psdcal.calibration._verdict_linear.CHOLQR_ONE_PASS_COND`), so that the
bases span the same spaces and the projections agree to rounding; where a
test fails (a view whose pose columns are ill conditioned or rank deficient,
global columns that need the Householder QR's rank test) :func:`bases`
reports it and the caller takes the numpy path.

Only views of equal row counts in view order (the "dense" layout) are
handled; the tests compare every function with the numpy reference.
"""
from __future__ import annotations

import numpy as np

from psdcal._jit import njit


@njit
def _chol_lower(K):
    """Lower Cholesky factor of the small symmetric matrix ``K`` (ok False when not positive definite)."""
    n = K.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        s = K[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False, L
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            t = K[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / L[j, j]
    return True, L


@njit
def _gram(A):
    """``A^T A`` of a tall (r, k) matrix."""
    return A.T @ A


@njit
def _first_pass(A, unit_columns, max_cond, one_pass_cond):
    """The first Cholesky-QR pass of ``_cholqr2`` on one (r, k) block: (status, Q) with status 0 when the block's
    columns are conditioned worse than ``max_cond`` (or one has zero norm), 1 when one pass is orthonormal enough,
    2 when a second pass is needed."""
    r, k = A.shape
    K = _gram(A)
    d = np.empty(k)
    for a in range(k):
        d[a] = np.sqrt(K[a, a])
        if not (d[a] > 0.0 and np.isfinite(d[a])):
            return 0, np.empty((r, k))
    if not unit_columns:
        d[:] = 1.0
    Kn = np.empty((k, k))
    for a in range(k):
        for b in range(k):
            Kn[a, b] = K[a, b] / (d[a] * d[b])
    lam, V = np.linalg.eigh(Kn)
    for a in range(k):
        if not np.isfinite(lam[a]):
            return 0, np.empty((r, k))
    if not lam[0] > lam[k - 1] / max_cond ** 2:
        return 0, np.empty((r, k))
    M = np.empty((k, k))
    for a in range(k):
        for b in range(k):
            M[a, b] = V[a, b] / d[a] / np.sqrt(lam[b])
    Q = A @ M
    return (1 if lam[0] > lam[k - 1] / one_pass_cond ** 2 else 2), Q


@njit
def _second_pass(Q):
    """``Q L^-T`` with ``L L^T = Q^T Q`` (the second Cholesky-QR pass)."""
    ok, L = _chol_lower(_gram(Q))
    k = L.shape[0]
    Linv = np.linalg.inv(L)
    return ok, Q @ np.ascontiguousarray(Linv.T)


@njit
def _block_bases(Jb, max_cond, one_pass_cond):
    """Orthonormal bases (v, nr, 6) of each view's pose columns ``Jb`` (v, nr, 6); ok False when a block fails the
    conditioning test."""
    v, nr, k = Jb.shape
    Qb = np.empty((v, nr, k))
    second = False
    for i in range(v):
        st, Q = _first_pass(np.ascontiguousarray(Jb[i]), True, max_cond, one_pass_cond)
        if st == 0:
            return False, Qb
        if st == 2:
            second = True
        Qb[i] = Q
    if second:  # as the numpy reference: the second pass for every block when one needs it
        for i in range(v):
            ok, Q = _second_pass(np.ascontiguousarray(Qb[i]))
            if not ok:
                return False, Qb
            Qb[i] = Q
    return True, Qb


@njit
def perp_pose(Qb, B):
    """``B`` (m, k) less its projection on each view's pose basis ``Qb`` (v, nr, 6), rows view by view."""
    v, nr, s = Qb.shape
    out = B.copy()
    for i in range(v):
        q = Qb[i]
        rows = out[i * nr:(i + 1) * nr]
        rows -= q @ (q.T @ B[i * nr:(i + 1) * nr])
    return out


@njit
def perp(Qb, Qg, B):
    """``(I - P) B``: ``B`` (m, k) off the pose bases ``Qb`` and the global basis ``Qg`` (m, g)."""
    out = perp_pose(Qb, B)
    if Qg.shape[1]:
        out -= Qg @ (Qg.T @ out)
    return out


@njit
def pgram(Qb, Qg, B, btb):
    """``((I - P) B)^T (I - P) B`` as ``btb - Cb^T Cb - Cg^T Cg`` (B's coordinates on the pose bases and on Qg,
    as the numpy reference)."""
    v, nr, s = Qb.shape
    out = btb.copy()
    for i in range(v):
        c = Qb[i].T @ B[i * nr:(i + 1) * nr]
        out -= c.T @ c
    if Qg.shape[1]:
        cg = Qg.T @ B
        out -= cg.T @ cg
    return out


@njit
def bases(Jb, G, max_cond, one_pass_cond):
    """The projector's bases: (ok, Qb (v, nr, 6), Qg (m, g), leverages h (m,)).

    ``Jb`` (v, nr, 6): each view's pose columns; ``G`` (m, g) the global
    columns (natural units). As the numpy reference: each view's block by a
    two-pass Cholesky QR of its unit-norm columns; the global columns scaled
    to norm 1, projected off the poses, and their basis by a Cholesky QR of the
    columns as they are then (a column mostly absorbed by the poses counts as
    ill conditioned). ok False: a conditioning test failed (take the numpy path).
    """
    v, nr, s = Jb.shape
    m, g = G.shape
    ok, Qb = _block_bases(Jb, max_cond, one_pass_cond)
    Qg = np.zeros((m, g))
    h = np.zeros(m)
    if not ok:
        return False, Qb, Qg, h
    Gn = np.empty((m, g))
    for a in range(g):
        t = 0.0
        for r in range(m):
            t += G[r, a] * G[r, a]
        nrm = max(np.sqrt(max(t, 0.0)), 1e-300)
        for r in range(m):
            Gn[r, a] = G[r, a] / nrm
    if g:
        Gp = perp_pose(Qb, Gn)
        st, Q = _first_pass(Gp, False, max_cond, one_pass_cond)
        if st == 0:
            return False, Qb, Qg, h
        if st == 2:
            ok2, Q = _second_pass(Q)
            if not ok2:
                return False, Qb, Qg, h
        Qg = Q
    for i in range(v):
        for r in range(nr):
            t = 0.0
            for a in range(s):
                t += Qb[i, r, a] * Qb[i, r, a]
            h[i * nr + r] = t
    for r in range(m):
        t = 0.0
        for a in range(g):
            t += Qg[r, a] * Qg[r, a]
        h[r] += t
    return True, Qb, Qg, h

