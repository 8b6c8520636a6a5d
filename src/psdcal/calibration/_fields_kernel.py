"""The verdict's field tests compiled: the small symmetric eigenproblems of the F-test and of the restricted refit.

:func:`psdcal.calibration._verdict_fields._basis` (the residuals' coordinates on
the fields the parameters do not absorb, the nested F-test's explained sum of
squares) and :func:`psdcal.calibration._verdict_fields.field_shift` (the
linearised refit with the fields whose visible part is large enough) end in a
few operations on (k, k) matrices, k the number of fields (22 for the
structure check, a handful for the terms the model leaves out): scalings, an
eigenproblem or two, a Cholesky factor and its inverse. In numpy each of
those is a call whose overhead, not its arithmetic, dominates at these
sizes. The kernels below do the same steps in loops (the numpy functions are the
reference; the tests compare the two): the eigenproblems by a Householder
reduction to tridiagonal form and implicit QR steps with Wilkinson's shift
(:func:`eigh`), which for these sizes costs a fraction of the cyclic Jacobi
rotations of :mod:`psdcal.calibration._verdict_kernel`. The eigenvalues agree
with LAPACK's to rounding; eigenvectors of (nearly) equal eigenvalues may
differ by a rotation within their eigenspace, which none of the results
depends on (they are sums over the kept directions). A kernel returns
``ok = False`` (the caller then runs the numpy code) on non-finite input or
when the QR iteration does not converge.

:func:`angle_shifts` is the arithmetic of :func:`psdcal.calibration._verdict_linear.effect`
(its reference :func:`psdcal.calibration._verdict_linear._angle_shifts`) and
:func:`field_parts_ext` the fields' parts with the side-by-side array their
products use (:class:`psdcal.calibration._verdict_blocks.FieldParts`).
"""
from __future__ import annotations

import math

import numpy as np

from psdcal._jit import njit
from psdcal.calibration._schur_kernel import _cholesky
from psdcal.calibration._verdict_kernel import sort_eigenpairs
from psdcal.calibration._rules_kernel import field_parts

#: Relative size of an off-diagonal entry of the tridiagonal matrix below which it counts as zero (the unit
#: roundoff of double precision times two).
_EPS = 2.220446049250313e-16


@njit
def _givens(a, b):
    """(c, s) with ``s a + c b = 0`` and ``c^2 + s^2 = 1`` (the rotation ``[[c, s], [-s, c]]`` whose transpose
    takes ``(a, b)`` to ``(r, 0)``)."""
    if b == 0.0:
        return 1.0, 0.0
    if abs(b) > abs(a):
        tau = -a / b
        s = 1.0 / math.sqrt(1.0 + tau * tau)
        return s * tau, s
    tau = -b / a
    c = 1.0 / math.sqrt(1.0 + tau * tau)
    return c, c * tau


@njit
def _negligible(d, e, i):
    """Whether the subdiagonal entry ``e[i]`` of the tridiagonal matrix (diagonal ``d``) counts as zero."""
    x = abs(e[i])
    return x <= _EPS * (abs(d[i]) + abs(d[i + 1])) or x < 1e-300


@njit
def _eigh_apply(K, Zt):
    """(ok, eigenvalues ascending (n,)) of the symmetric ``K`` (its lower triangle read, as ``np.linalg.eigh``
    does), and ``Zt`` (n, r) replaced by ``V^T Zt`` (V the eigenvectors as columns, in the eigenvalues' order):
    the identity gives ``V^T``, a column a vector's coordinates on the eigenvectors. ok False on non-finite input
    or no convergence."""
    n = K.shape[0]
    A = np.empty((n, n))
    for i in range(n):
        for j in range(i + 1):
            x = K[i, j]
            if not math.isfinite(x):
                return False, np.zeros(n)
            A[i, j] = x
            A[j, i] = x
    nc = Zt.shape[1]
    u = np.zeros(n)
    p = np.zeros(max(n, nc))
    # Householder reflections H = I - u u^T (|u|^2 = 2) zero column k below its subdiagonal: A <- H A H, Zt <- H Zt
    for k in range(n - 2):
        sigma = 0.0
        for i in range(k + 2, n):
            sigma += A[i, k] * A[i, k]
        if sigma == 0.0:
            continue
        x0 = A[k + 1, k]
        alpha = math.sqrt(x0 * x0 + sigma)
        if x0 > 0.0:
            alpha = -alpha
        v0 = x0 - alpha
        f = math.sqrt(2.0 / (v0 * v0 + sigma))
        u[k + 1] = v0 * f
        for i in range(k + 2, n):
            u[i] = A[i, k] * f
        # H A22 H = A22 - u q^T - q u^T with p = A22 u, q = p - (u^T p / 2) u
        up = 0.0
        for i in range(k + 1, n):
            t = 0.0
            for j in range(k + 1, n):
                t += A[i, j] * u[j]
            p[i] = t
            up += u[i] * t
        h = 0.5 * up
        for i in range(k + 1, n):
            p[i] -= h * u[i]
        for i in range(k + 1, n):
            for j in range(k + 1, n):
                A[i, j] -= u[i] * p[j] + p[i] * u[j]
        A[k + 1, k] = alpha
        A[k, k + 1] = alpha
        for i in range(k + 2, n):
            A[i, k] = 0.0
            A[k, i] = 0.0
        for r in range(nc):  # Zt <- H Zt (its rows updated: contiguous)
            p[r] = 0.0
        for j in range(k + 1, n):
            uj = u[j]
            for r in range(nc):
                p[r] += uj * Zt[j, r]
        for j in range(k + 1, n):
            uj = u[j]
            for r in range(nc):
                Zt[j, r] -= uj * p[r]
    # the tridiagonal matrix: diagonal d, subdiagonal e
    d = np.empty(n)
    e = np.zeros(max(n - 1, 0))
    for i in range(n):
        d[i] = A[i, i]
        if i + 1 < n:
            e[i] = A[i + 1, i]
    # implicit symmetric QR steps with Wilkinson's shift on the unreduced trailing block [lo, hi]: Givens rotations G
    # chase the bulge down (T <- G^T T G, Zt <- G^T Zt)
    hi = n - 1
    steps = 0
    while hi > 0:
        if _negligible(d, e, hi - 1):
            e[hi - 1] = 0.0
            hi -= 1
            continue
        lo = hi - 1
        while lo > 0 and not _negligible(d, e, lo - 1):
            lo -= 1
        if lo > 0:
            e[lo - 1] = 0.0
        steps += 1
        if steps > 30 * n:
            return False, np.zeros(n)
        b = e[hi - 1]
        dd = 0.5 * (d[hi - 1] - d[hi])
        r = math.hypot(dd, b)
        mu = d[hi] - b * b / (dd + (r if dd >= 0.0 else -r))
        x = d[lo] - mu
        z = e[lo]
        for k in range(lo, hi):
            c, s = _givens(x, z)
            if k > lo:
                e[k - 1] = c * x - s * z  # (x, z) = (e[k - 1], the bulge): the bulge becomes 0
            a0 = d[k]
            b0 = e[k]
            d0 = d[k + 1]
            cs = c * s
            cc = c * c
            sn = s * s
            d[k] = cc * a0 - 2.0 * cs * b0 + sn * d0
            d[k + 1] = sn * a0 + 2.0 * cs * b0 + cc * d0
            e[k] = cs * (a0 - d0) + (cc - sn) * b0
            if k < hi - 1:
                z = -s * e[k + 1]  # the new bulge at (k, k + 2)
                e[k + 1] = c * e[k + 1]
                x = e[k]
            for j in range(nc):  # Zt <- G^T Zt
                t1 = Zt[k, j]
                t2 = Zt[k + 1, j]
                Zt[k, j] = c * t1 - s * t2
                Zt[k + 1, j] = s * t1 + c * t2
    lam = d
    sort_eigenpairs(lam, Zt.T)  # ascending, with the eigenvectors (the rows of Zt)
    return True, lam


@njit
def eigh(K):
    """(ok, eigenvalues ascending (n,), eigenvectors as columns (n, n)) of the symmetric ``K`` (its lower triangle
    read, as ``np.linalg.eigh`` does); ok False on non-finite input or no convergence."""
    Zt = np.eye(K.shape[0])
    ok, lam = _eigh_apply(K, Zt)
    return ok, lam, Zt.T


@njit
def _eig_desc(K):
    """:func:`psdcal.calibration._verdict_fields._sym_eig_desc`: (ok, eigenvalues descending and clipped at 0,
    eigenvectors)."""
    ok, lam, V = eigh(K)
    n = lam.shape[0]
    ld = np.empty(n)
    Vd = np.empty((n, n))
    for j in range(n):
        ld[j] = max(lam[n - 1 - j], 0.0)
        for i in range(n):
            Vd[i, j] = V[i, n - 1 - j]
    return ok, ld, Vd


@njit
def _scales(btb):
    """The columns' norms from their Gram matrix (at least 1e-300)."""
    k = btb.shape[0]
    scale = np.empty(k)
    for i in range(k):
        scale[i] = max(math.sqrt(max(btb[i, i], 0.0)), 1e-300)
    return scale


@njit
def _finite(x):
    for v in x.ravel():
        if not math.isfinite(v):
            return False
    return True


@njit
def field_coords(btb, K, bte, weights):
    """:func:`psdcal.calibration._verdict_fields._basis` from B's Gram matrix ``btb`` (k, k), that of ``(I - P) B``
    ``K`` (k, k) and ``B^T e`` ``bte`` (k,): (ok, ``ute`` (r,), ``W`` (k, r), (k, 0) without ``weights``) with the
    same steps (the columns scaled to norm 1, those the parameters absorb to 1e-4 left out, the directions whose
    singular value is below 1e-2 of the largest dropped). Without ``weights`` the eigenvectors are not formed: the
    rotations are applied to ``bte`` alone."""
    k = btb.shape[0]
    if not (_finite(btb) and _finite(K) and _finite(bte)):
        return False, np.zeros(0), np.zeros((k, 0))
    scale = _scales(btb)
    idx = np.empty(k, dtype=np.intp)
    nu = 0
    for i in range(k):
        if math.sqrt(max(K[i, i] / (scale[i] * scale[i]), 0.0)) > 1e-4:
            idx[nu] = i
            nu += 1
    if nu == 0:
        return True, np.zeros(0), np.zeros((k, 0))
    Ku = np.empty((nu, nu))
    for a in range(nu):
        for b in range(nu):
            Ku[a, b] = K[idx[a], idx[b]] / (scale[idx[a]] * scale[idx[b]])
    y = np.empty((nu, 1))
    for a in range(nu):
        y[a, 0] = bte[idx[a]] / scale[idx[a]]
    if weights:
        ok, lam, V = _eig_desc(Ku)
    else:  # the coordinates V^T y only, eigenvalues ascending, then in _eig_desc's order
        ok, lam_a = _eigh_apply(Ku, y)
        lam = np.empty(nu)
        z = np.empty(nu)
        for j in range(nu):
            lam[j] = max(lam_a[nu - 1 - j], 0.0)
            z[j] = y[nu - 1 - j, 0]
        V = np.zeros((nu, 0))
    if not ok:
        return False, np.zeros(0), np.zeros((k, 0))
    s0 = math.sqrt(lam[0])
    r = 0
    while r < nu and math.sqrt(lam[r]) > 1e-2 * s0:
        r += 1
    ute = np.empty(r)
    W = np.zeros((k, r if weights else 0))
    for j in range(r):
        s = math.sqrt(lam[j])
        if not weights:
            ute[j] = z[j] / s
            continue
        t = 0.0
        for a in range(nu):
            t += V[a, j] * y[a, 0]
        ute[j] = t / s
        for a in range(nu):
            W[idx[a], j] = (V[a, j] / s) / scale[idx[a]]
    return True, ute, W


@njit
def _span_basis(Kn):
    """:func:`psdcal.calibration._verdict_fields._span_basis`: (ok, M (k, r))."""
    k = Kn.shape[0]
    L = np.zeros((k, k))
    if _cholesky(Kn, L):
        Li = np.zeros((k, k))  # L^-1 by forward substitution, column by column
        for j in range(k):
            Li[j, j] = 1.0 / L[j, j]
            for i in range(j + 1, k):
                t = 0.0
                for q in range(j, i):
                    t += L[i, q] * Li[q, j]
                Li[i, j] = -t / L[i, i]
        ss = 0.0
        tr = 0.0
        for i in range(k):
            tr += Kn[i, i]
            for j in range(i + 1):
                ss += Li[i, j] * Li[i, j]
        if math.isfinite(ss) and 1.0 / ss > 1e-12 * tr:
            return True, Li.T.copy()
    ok, lam, V = _eig_desc(Kn)
    if not ok:
        return False, np.zeros((k, 0))
    r = 0
    lim = 1e-12 * max(lam[0], 1e-300) if k else 0.0
    while r < k and lam[r] > lim:
        r += 1
    M = np.empty((k, r))
    for j in range(r):
        s = math.sqrt(lam[j])
        for i in range(k):
            M[i, j] = V[i, j] / s
    return True, M


@njit
def visible_fit(btb, K, bte, min_visible):
    """The coefficients ``c`` (k,) of :func:`psdcal.calibration._verdict_fields.field_shift`'s refit restricted to
    the combinations of B's columns whose visible fraction exceeds ``min_visible``, from ``btb``, ``K``, ``bte``
    as in :func:`field_coords`: (ok, c), the same steps as the numpy code."""
    k = btb.shape[0]
    c = np.zeros(k)
    if not (_finite(btb) and _finite(K) and _finite(bte)):
        return False, c
    scale = _scales(btb)
    Kb = np.empty((k, k))
    Kp = np.empty((k, k))
    for i in range(k):
        for j in range(k):
            ss = scale[i] * scale[j]
            Kb[i, j] = btb[i, j] / ss
            Kp[i, j] = K[i, j] / ss
    ok, M = _span_basis(Kb)
    if not ok:
        return False, c
    r = M.shape[1]
    KM = np.zeros((k, r))  # Kp M, then M^T Kp M
    for i in range(k):
        for q in range(k):
            x = Kp[i, q]
            for j in range(r):
                KM[i, j] += x * M[q, j]
    Kv = np.zeros((r, r))
    for i in range(r):
        for j in range(r):
            t = 0.0
            for q in range(k):
                t += M[q, i] * KM[q, j]
            Kv[i, j] = t
    ok, lam, V = _eig_desc(Kv)
    if not ok:
        return False, c
    nu = 0
    while nu < r and math.sqrt(min(lam[nu], 1.0)) > min_visible:
        nu += 1
    if nu == 0:
        return True, c
    y = np.zeros(r)  # M^T Bn^T e
    for q in range(k):
        bq = bte[q] / scale[q]
        for j in range(r):
            y[j] += M[q, j] * bq
    w = np.zeros(r)  # V[:, use] (ute / s)
    for j in range(nu):
        s = math.sqrt(min(lam[j], 1.0))
        t = 0.0
        for i in range(r):
            t += V[i, j] * y[i]
        t = (t / s) / s
        for i in range(r):
            w[i] += V[i, j] * t
    for q in range(k):
        t = 0.0
        for j in range(r):
            t += M[q, j] * w[j]
        c[q] = t / scale[q]
    return True, c


@njit
def field_parts_ext(pts, c, half, degree):
    """:func:`psdcal.calibration._rules_kernel.field_parts`'s ``(mono (N, p), R (2N, 2))`` and the two side by side,
    ``ext`` (N, p + 4): each point's monomials, then its rows of R (x r^4, x r^6, y r^4, y r^6)."""
    mono, R = field_parts(pts, c, half, degree)
    n, p = mono.shape
    ext = np.empty((n, p + 4))
    for i in range(n):
        for a in range(p):
            ext[i, a] = mono[i, a]
        ext[i, p] = R[2 * i, 0]
        ext[i, p + 1] = R[2 * i, 1]
        ext[i, p + 2] = R[2 * i + 1, 0]
        ext[i, p + 3] = R[2 * i + 1, 1]
    return mono, R, ext


@njit
def angle_shifts(A, full, D, f, sd, cov):
    """:func:`psdcal.calibration._verdict_linear.effect`'s sums: the angles' shifts ``da = A full`` (2K,) less the
    field ``f`` (K, 2) through ``D`` (K, 2, 2) (no field: ``f`` of zero rows), then (the largest ``|da| / sd`` over
    the rows with ``sd > 0``, 0 without any; the largest ``|da|``, 0 without rows; the parameters' standard errors
    ``sqrt(max(diag(cov), 0))``). A NaN shift makes the maxima it enters NaN, as numpy's maximum does."""
    m, n = A.shape
    sig = 0.0
    rad = 0.0
    nan_sig = False
    nan_rad = False
    for r in range(m):
        t = 0.0
        for j in range(n):
            t += A[r, j] * full[j]
        if f.shape[0]:
            i = r // 2
            a = r - 2 * i
            t = t - (D[i, a, 0] * f[i, 0] + D[i, a, 1] * f[i, 1])
        x = abs(t)
        if x != x:
            nan_rad = True
            if sd[r] > 0.0:
                nan_sig = True
        if x > rad:
            rad = x
        if sd[r] > 0.0 and x / sd[r] > sig:
            sig = x / sd[r]
    if nan_sig:
        sig = np.nan
    if nan_rad:
        rad = np.nan
    k = cov.shape[0]
    sdp = np.empty(k)
    for i in range(k):
        sdp[i] = math.sqrt(max(cov[i, i], 0.0))
    return sig, rad, sdp
