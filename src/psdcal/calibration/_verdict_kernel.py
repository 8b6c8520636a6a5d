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
:func:`normal_transforms` is the small-matrix part of the projector from each
view's Gram matrix (:func:`psdcal.calibration._verdict_blocks.normal_transforms`
its reference) and :func:`group_f` the per-view and per-LED F statistics
(:func:`psdcal.calibration._verdict_linear.group_f`, equal to the last bit). The
kernels are plain loops (the small symmetric eigenproblems by cyclic Jacobi
rotations, no LAPACK or BLAS call): they compile in seconds and load in a
fraction of one, where numba's wrappers of ``np.linalg`` cost tens of seconds
to compile and a second to load in each fresh process.
"""
from __future__ import annotations

import numpy as np

from psdcal._jit import njit
from psdcal.calibration._schur_kernel import _cholesky


@njit
def _gram(A, r0, nr):
    """``A_s^T A_s`` of the rows ``r0 .. r0 + nr`` of the (m, k) ``A``."""
    k = A.shape[1]
    K = np.zeros((k, k))
    for i in range(r0, r0 + nr):
        for a in range(k):
            x = A[i, a]
            for b in range(a, k):
                K[a, b] += x * A[i, b]
    for a in range(k):
        for b in range(a):
            K[a, b] = K[b, a]
    return K


@njit
def _times_small(A, r0, nr, M, out):
    """``out[r0 .. r0 + nr] = A[r0 .. r0 + nr] @ M`` for a small (k, k) ``M`` (``out`` may be ``A``)."""
    k = A.shape[1]
    row = np.empty(k)
    for i in range(r0, r0 + nr):
        for a in range(k):
            row[a] = A[i, a]
        for b in range(k):
            t = 0.0
            for a in range(k):
                t += row[a] * M[a, b]
            out[i, b] = t


@njit
def _eigh_jacobi(K):
    """Eigenvalues (ascending) and eigenvectors (columns) of the small symmetric matrix ``K`` by cyclic Jacobi
    rotations (to the precision of the arithmetic: an off-diagonal entry below 1e-300 or 1e-17 of the geometric
    mean of its diagonal pair counts as zero)."""
    n = K.shape[0]
    A = K.copy()
    V = np.eye(n)
    for _sweep in range(100):
        rotated = False
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = A[p, q]
                if abs(apq) <= 1e-300 or abs(apq) <= 1e-17 * np.sqrt(abs(A[p, p] * A[q, q])):
                    A[p, q] = 0.0
                    A[q, p] = 0.0
                    continue
                rotated = True
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):  # A <- A J (columns p, q)
                    akp = A[k, p]
                    akq = A[k, q]
                    A[k, p] = c * akp - s * akq
                    A[k, q] = s * akp + c * akq
                for k in range(n):  # A <- J^T A (rows p, q)
                    apk = A[p, k]
                    aqk = A[q, k]
                    A[p, k] = c * apk - s * aqk
                    A[q, k] = s * apk + c * aqk
                for k in range(n):
                    vkp = V[k, p]
                    vkq = V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
        if not rotated:
            break
    lam = np.empty(n)
    for i in range(n):
        lam[i] = A[i, i]
    sort_eigenpairs(lam, V)
    return lam, V


@njit
def sort_eigenpairs(lam, V):
    """In place: the eigenvalues ``lam`` (n,) in ascending order, the columns of ``V`` (m, n) (the eigenvectors)
    with them (an insertion sort: exact swaps, equal values keep their order)."""
    for i in range(1, lam.shape[0]):
        j = i
        while j > 0 and lam[j - 1] > lam[j]:
            t = lam[j - 1]
            lam[j - 1] = lam[j]
            lam[j] = t
            for r in range(V.shape[0]):
                t = V[r, j - 1]
                V[r, j - 1] = V[r, j]
                V[r, j] = t
            j -= 1


@njit
def _conditioned_eigh(K, max_cond):
    """(ok, eigenvalues ascending, eigenvectors) of the small symmetric ``K`` (:func:`_eigh_jacobi`); ok: every
    eigenvalue finite and the smallest above the largest over ``max_cond ** 2`` (K, a Gram matrix of unit columns,
    conditioned better than ``max_cond ** 2``: its columns better than ``max_cond``)."""
    lam, V = _eigh_jacobi(K)
    n = lam.size
    for a in range(n):
        if not np.isfinite(lam[a]):
            return False, lam, V
    return lam[0] > lam[n - 1] / max_cond ** 2, lam, V


@njit
def pinv_sym(N, out, max_cond):
    """:func:`psdcal.calibration._verdict_linear._pinv_sym` (its numpy reference) into ``out`` (n, n), the
    eigenproblem by Jacobi rotations: the pseudo-inverse of the symmetric positive semi-definite ``N`` (n >= 1)
    scaled by its diagonal, eigenvalues below 1e-12 of the largest in magnitude dropped. False (``out``
    meaningless) when N is not finite or its scaled form is conditioned worse than ``max_cond`` (an eigenvalue
    at most the largest over it: the two eigenproblems' results then differ by more than rounding, ``eps cond``,
    and the caller takes the numpy code)."""
    n = N.shape[0]
    d = np.empty(n)
    Ns = np.empty((n, n))
    for a in range(n):
        d[a] = np.sqrt(max(N[a, a], 1e-300))
        for b in range(n):
            if not np.isfinite(N[a, b]):
                return False
    for a in range(n):
        for b in range(n):
            Ns[a, b] = N[a, b] / (d[a] * d[b])
    lam, U = _eigh_jacobi(Ns)
    big = 0.0
    for a in range(n):
        big = max(big, abs(lam[a]))
    for a in range(n):
        if not lam[a] > big / max_cond:
            return False
    inv = np.zeros(n)
    for a in range(n):
        if abs(lam[a]) > 1e-12 * big:
            inv[a] = 1.0 / lam[a]
    for a in range(n):
        for b in range(n):
            t = 0.0
            for c in range(n):
                t += U[a, c] * inv[c] * U[b, c]
            out[a, b] = t / (d[a] * d[b])
    return True


@njit
def _orthonormalise(A, r0, nr, unit_columns, max_cond, one_pass_cond, out):
    """The first Cholesky-QR pass of ``_cholqr2`` on the rows ``r0 .. r0 + nr`` of ``A``, written to the same rows
    of ``out``: 0 when the block's columns are conditioned worse than ``max_cond`` (or one has zero norm), 1 when one
    pass is orthonormal enough, 2 when a second pass (:func:`_second_pass`) is needed."""
    k = A.shape[1]
    K = _gram(A, r0, nr)
    d = np.empty(k)
    for a in range(k):
        d[a] = np.sqrt(K[a, a])
        if not (d[a] > 0.0 and np.isfinite(d[a])):
            return 0
    if not unit_columns:
        d[:] = 1.0
    Kn = np.empty((k, k))
    for a in range(k):
        for b in range(k):
            Kn[a, b] = K[a, b] / (d[a] * d[b])
    ok, lam, V = _conditioned_eigh(Kn, max_cond)
    if not ok:
        return 0
    M = np.empty((k, k))
    for a in range(k):
        for b in range(k):
            M[a, b] = V[a, b] / d[a] / np.sqrt(lam[b])
    _times_small(A, r0, nr, M, out)
    return 1 if lam[0] > lam[k - 1] / one_pass_cond ** 2 else 2


@njit
def _second_pass(Q, r0, nr):
    """In place on the rows ``r0 .. r0 + nr`` of ``Q``: ``Q L^-T`` with ``L L^T = Q^T Q`` (the second Cholesky-QR
    pass; False when not positive definite)."""
    K = _gram(Q, r0, nr)
    k = K.shape[0]
    L = np.zeros((k, k))
    if not _cholesky(K, L):
        return False
    LinvT = np.zeros((k, k))  # (L^-1)^T by forward substitution
    for j in range(k):
        LinvT[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, k):
            t = 0.0
            for m in range(j, i):
                t -= L[i, m] * LinvT[j, m]
            LinvT[j, i] = t / L[i, i]
    _times_small(Q, r0, nr, LinvT, Q)
    return True


@njit
def _coords(Q, r0, nr, B, c):
    """``c = Q_s^T B_s`` (a, k) over the rows ``r0 .. r0 + nr`` of ``Q`` (m, a) and ``B`` (m, k)."""
    c[:] = 0.0
    for row in range(r0, r0 + nr):
        for a in range(Q.shape[1]):
            q = Q[row, a]
            for j in range(B.shape[1]):
                c[a, j] += q * B[row, j]


@njit
def _less_span(Q, r0, nr, c, out):
    """``out_s -= Q_s c`` over the rows ``r0 .. r0 + nr``: the rows less their part on ``Q``'s columns."""
    for row in range(r0, r0 + nr):
        for a in range(Q.shape[1]):
            q = Q[row, a]
            for j in range(out.shape[1]):
                out[row, j] -= q * c[a, j]


@njit
def _less_gram(c, out):
    """``out -= c^T c``."""
    k = c.shape[1]
    for a in range(c.shape[0]):
        for j in range(k):
            for l in range(k):
                out[j, l] -= c[a, j] * c[a, l]


@njit
def perp_pose(Qb, nr, B):
    """``B`` (m, k) less its projection on each view's pose basis: ``Qb`` (m, 6), the rows of each view (``nr``
    each, view by view) orthonormal columns."""
    m, s = Qb.shape
    out = B.copy()
    c = np.empty((s, B.shape[1]))
    for r0 in range(0, m, nr):
        _coords(Qb, r0, nr, B, c)
        _less_span(Qb, r0, nr, c, out)
    return out


@njit
def perp(Qb, nr, Qg, B):
    """``(I - P) B``: ``B`` (m, k) off the pose bases ``Qb`` and the global basis ``Qg`` (m, g)."""
    out = perp_pose(Qb, nr, B)
    m, k = out.shape
    c = np.empty((Qg.shape[1], k))
    _coords(Qg, 0, m, out, c)
    _less_span(Qg, 0, m, c, out)
    return out


@njit
def pgram(Qb, nr, Qg, B, btb):
    """``((I - P) B)^T (I - P) B`` as ``btb - Cb^T Cb - Cg^T Cg`` (B's coordinates on the pose bases and on Qg,
    as the numpy reference)."""
    m, s = Qb.shape
    k = B.shape[1]
    out = btb.copy()
    c = np.empty((s, k))
    for r0 in range(0, m, nr):
        _coords(Qb, r0, nr, B, c)
        _less_gram(c, out)
    cg = np.empty((Qg.shape[1], k))
    _coords(Qg, 0, m, B, cg)
    _less_gram(cg, out)
    return out


@njit
def bases(Jpose, nr, G, max_cond, one_pass_cond):
    """The projector's bases: (ok, Qb (m, 6), Qg (m, g), leverages h (m,)).

    ``Jpose`` (m, 6): each row's own view's pose columns, the views' rows
    consecutive, ``nr`` each; ``G`` (m, g) the global columns (natural units).
    As the numpy reference: each view's block by a two-pass Cholesky QR of its
    unit-norm columns (the second pass for every block when one needs it); the
    global columns scaled to norm 1, projected off the poses, and their basis
    by a Cholesky QR of the columns as they are then (a column mostly absorbed
    by the poses counts as ill conditioned). ok False: a conditioning test
    failed (take the numpy path).
    """
    m, s = Jpose.shape
    g = G.shape[1]
    Qb = np.empty((m, s))
    Qg = np.zeros((m, g))
    h = np.zeros(m)
    second = False
    for r0 in range(0, m, nr):
        st = _orthonormalise(Jpose, r0, nr, True, max_cond, one_pass_cond, Qb)
        if st == 0:
            return False, Qb, Qg, h
        if st == 2:
            second = True
    if second:
        for r0 in range(0, m, nr):
            if not _second_pass(Qb, r0, nr):
                return False, Qb, Qg, h
    if g:
        Gn = np.empty((m, g))
        for a in range(g):
            t = 0.0
            for r in range(m):
                t += G[r, a] * G[r, a]
            nrm = max(np.sqrt(max(t, 0.0)), 1e-300)
            for r in range(m):
                Gn[r, a] = G[r, a] / nrm
        Gp = perp_pose(Qb, nr, Gn)
        st = _orthonormalise(Gp, 0, m, False, max_cond, one_pass_cond, Qg)
        if st == 0:
            return False, Qb, Qg, h
        if st == 2 and not _second_pass(Qg, 0, m):
            return False, Qb, Qg, h
    for r in range(m):
        t = 0.0
        for a in range(s):
            t += Qb[r, a] * Qb[r, a]
        for a in range(g):
            t += Qg[r, a] * Qg[r, a]
        h[r] = t
    return True, Qb, Qg, h


@njit
def normal_transforms(K, g, one_pass_cond):
    """:func:`psdcal.calibration._verdict_blocks.normal_transforms` (its numpy reference: the same arguments and
    returns, ``(ok, T, Rg, gtg_view)``) in loops, the small eigenproblems by Jacobi rotations.

    ``K`` (v, k, k): each view's Gram matrix of its pose columns (6), then the ``g`` global ones, then any others.
    """
    v = K.shape[0]
    s = 6
    n = s + g
    T = np.zeros((v, n, n))
    Rg = np.zeros((g, g))
    gtg_view = np.zeros((v, g, g))
    Kn = np.empty((s, s))
    d = np.empty(s)
    cb = np.empty((s, g))
    C = np.empty((v, s, g))
    for i in range(v):
        for a in range(s):
            d[a] = np.sqrt(K[i, a, a])
            if not (d[a] > 0.0 and np.isfinite(d[a])):
                return False, T, Rg, gtg_view
        for a in range(s):
            for b in range(s):
                Kn[a, b] = K[i, a, b] / (d[a] * d[b])
        ok, lam, V = _conditioned_eigh(Kn, one_pass_cond)
        if not ok:
            return False, T, Rg, gtg_view
        for a in range(s):  # Mb = V / d / sqrt(lam)
            for b in range(s):
                T[i, a, b] = V[a, b] / d[a] / np.sqrt(lam[b])
        for b in range(s):  # cb = Mb^T K_ag (Qb_v^T G_v)
            for j in range(g):
                t = 0.0
                for a in range(s):
                    t += T[i, a, b] * K[i, a, s + j]
                cb[b, j] = t
        for j in range(g):  # the Schur complement K_gg - cb^T cb
            for l in range(g):
                t = K[i, s + j, s + l]
                for b in range(s):
                    t -= cb[b, j] * cb[b, l]
                gtg_view[i, j, l] = t
        for a in range(s):  # C = Mb cb: G_v's part on the poses is A_v C
            for j in range(g):
                t = 0.0
                for b in range(s):
                    t += T[i, a, b] * cb[b, j]
                C[i, a, j] = t
    if g == 0:
        return True, T, Rg, gtg_view
    nrm = np.empty(g)
    for j in range(g):
        t = 0.0
        for i in range(v):
            t += K[i, s + j, s + j]
        nrm[j] = max(np.sqrt(max(t, 0.0)), 1e-300)
    Kp = np.zeros((g, g))
    for i in range(v):
        for j in range(g):
            for l in range(g):
                Kp[j, l] += gtg_view[i, j, l]
    for j in range(g):
        for l in range(g):
            Kp[j, l] /= nrm[j] * nrm[l]
    for j in range(g):
        dp = np.sqrt(Kp[j, j])
        if not (dp > 0.0 and np.isfinite(dp)):
            return False, T, Rg, gtg_view
    ok, lg, Vg = _conditioned_eigh(Kp, one_pass_cond)
    if not ok:
        return False, T, Rg, gtg_view
    Mg = np.empty((g, g))
    for j in range(g):
        for l in range(g):
            Mg[j, l] = Vg[j, l] / nrm[j] / np.sqrt(lg[l])
            Rg[l, j] = np.sqrt(lg[l]) * Vg[j, l] * nrm[j]
    for i in range(v):
        for a in range(s):  # -C Mg
            for l in range(g):
                t = 0.0
                for j in range(g):
                    t += C[i, a, j] * Mg[j, l]
                T[i, a, s + l] = -t
        for j in range(g):
            for l in range(g):
                T[i, s + j, s + l] = Mg[j, l]
    return True, T, Rg, gtg_view


@njit
def group_f(groups, h, e, n_groups, ssr, dof):
    """:func:`psdcal.calibration._verdict_linear.group_f`'s statistics in one loop (the same operations in the same
    order: equal to the last bit): (F, d_g, d_r, usable, worst) per group of the points ``groups`` (N,), from the
    leverages ``h`` and residuals ``e`` (2N,), rows (x0, y0, x1, ...)."""
    lev = np.zeros(n_groups)
    sq = np.zeros(n_groups)
    for i in range(groups.size):
        g = groups[i]
        lev[g] += (1.0 - h[2 * i]) + (1.0 - h[2 * i + 1])
        sq[g] += e[2 * i] * e[2 * i] + e[2 * i + 1] * e[2 * i + 1]
    F = np.empty(n_groups)
    d_g = np.ones(n_groups)
    d_r = np.ones(n_groups)
    usable = np.zeros(n_groups, dtype=np.bool_)
    worst = 0
    best = -np.inf
    for g in range(n_groups):
        usable[g] = lev[g] >= 0.5 and dof - lev[g] >= 0.5
        if usable[g]:
            d_g[g] = lev[g]
            d_r[g] = dof - lev[g]
            F[g] = (sq[g] / d_g[g]) / (max(ssr - sq[g], 1e-300) / d_r[g])
        else:
            F[g] = np.nan
        if np.isfinite(F[g]) and F[g] > best:
            best = F[g]
            worst = g
    return F, d_g, d_r, usable, worst

