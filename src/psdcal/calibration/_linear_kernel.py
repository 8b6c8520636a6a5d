"""Compiled linear stage: homographies, closed-form intrinsics, poses, per-view focal lengths.

The same mathematics as the numpy reference in
:mod:`psdcal.calibration._homography` (:func:`~psdcal.calibration._homography.homographies`,
Eq 17-18 and 36-38), :mod:`psdcal.calibration._closed_form`
(:func:`~psdcal.calibration._closed_form.intrinsics_from_homographies`, Eq 19-25;
:func:`~psdcal.calibration._closed_form.poses_from_homographies`, Eq 26-28) and
:func:`psdcal.calibration.core.focal_from_homographies`, written as scalar loops for
numba (:mod:`psdcal._jit`) so that each step of a small calibration is ONE call
instead of some tens of numpy calls on arrays of a few elements.

The singular value decompositions are the one-sided (Hestenes) Jacobi method
on the triangular factor of a Householder QR: ``A = Q R``, then plane rotations
``R V = W`` until the columns of ``W`` are orthogonal to working precision;
the singular values are the norms of ``W``'s columns, the right singular
vectors ``V``'s columns. Jacobi is at least as accurate as LAPACK's bidiagonal
SVD (J. Demmel, K. Veselic, "Jacobi's method is more accurate than QR", SIAM
J. Matrix Anal. Appl. 13(4), 1992), so the null vectors agree with numpy's to
round-off times the conditioning of the problem (they are unique up to sign,
fixed as the reference fixes it).

Every kernel reports a failure as an integer code (and the view it concerns);
the Python wrappers raise the reference's exception with its message.
"""
from __future__ import annotations

import math

import numpy as np

from psdcal._jit import njit, njit_inline

#: codes returned by :func:`homographies_kernel`
H_OK, H_FEW_POINTS, H_COLLINEAR, H_RANK_DEFICIENT, H_USE_REFERENCE = 0, 1, 2, 3, 4
#: codes returned by :func:`intrinsics_kernel`
I_OK, I_UNDETERMINED, I_NOT_POSITIVE_DEFINITE, I_NEGATIVE_FOCAL, I_USE_REFERENCE = 0, 1, 2, 3, 4

_JACOBI_TOL = 2e-15  # columns p, q count as orthogonal when |w_p . w_q| <= tol |w_p| |w_q| (about 9 eps)
_JACOBI_MAX_SWEEPS = 60


@njit_inline
def _householder_r(A, m, k):
    """Upper triangular factor R (k, k) of the first ``m`` rows of A (m >= k), in place in A's first k rows.

    Rows below k are overwritten with the Householder vectors' tails (scratch).
    """
    for j in range(k):
        norm2 = 0.0
        for i in range(j, m):
            norm2 += A[i, j] * A[i, j]
        if norm2 == 0.0:
            continue
        alpha = math.sqrt(norm2)
        if A[j, j] > 0:
            alpha = -alpha
        # v = a - alpha e_j; H = I - 2 v v^T / (v^T v), v^T v = 2 (norm2 - alpha a_jj)
        v0 = A[j, j] - alpha
        vtv = norm2 - alpha * A[j, j]  # half of v^T v
        A[j, j] = v0
        for c in range(j + 1, k):
            s = 0.0
            for i in range(j, m):
                s += A[i, j] * A[i, c]
            s /= vtv
            for i in range(j, m):
                A[i, c] -= s * A[i, j]
        A[j, j] = alpha
        for i in range(j + 1, m):
            A[i, j] = 0.0
    for i in range(k):
        for j in range(i):
            A[i, j] = 0.0


@njit_inline
def _jacobi_svd(W, V, k):
    """One-sided Jacobi on the (k, k) W in place: afterwards W = W_in V with orthogonal columns.

    V (k, k) is set to the accumulated rotations (orthogonal, det +1). The
    singular values are the column norms of the result. Returns whether it
    converged (a sweep without rotation; False for non-finite input).
    """
    for i in range(k):
        for j in range(k):
            V[i, j] = 1.0 if i == j else 0.0
    n = W.shape[0]
    nrm2 = np.empty(k)  # squared column norms: exact at each sweep's start, updated by each rotation
    for _sweep in range(_JACOBI_MAX_SWEEPS):
        for j in range(k):
            acc = 0.0
            for i in range(n):
                acc += W[i, j] * W[i, j]
            nrm2[j] = acc
        rotated = False
        for p in range(k - 1):
            for q in range(p + 1, k):
                a = nrm2[p]
                b = nrm2[q]
                g = 0.0
                for i in range(n):
                    g += W[i, p] * W[i, q]
                if g == 0.0 or abs(g) <= _JACOBI_TOL * math.sqrt(a) * math.sqrt(b):
                    continue
                rotated = True
                zeta = (b - a) / (2.0 * g)
                t = 1.0 / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
                if zeta < 0:
                    t = -t
                c = 1.0 / math.sqrt(1.0 + t * t)
                s = c * t
                # the rotated columns' squared norms: a - t g and b + t g (t solves t^2 + 2 zeta t = 1)
                nrm2[p] = max(a - t * g, 0.0)  # (round-off can take a null column's below 0)
                nrm2[q] = max(b + t * g, 0.0)
                for i in range(n):
                    wp = W[i, p]
                    wq = W[i, q]
                    W[i, p] = c * wp - s * wq
                    W[i, q] = s * wp + c * wq
                for i in range(k):
                    vp = V[i, p]
                    vq = V[i, q]
                    V[i, p] = c * vp - s * vq
                    V[i, q] = s * vp + c * vq
        if not rotated:
            return True
    return False


@njit_inline
def _column_norms(W, k, out):
    for j in range(k):
        s = 0.0
        for i in range(W.shape[0]):
            s += W[i, j] * W[i, j]
        out[j] = math.sqrt(s)


@njit_inline
def _valid_sums(P, valid, row):
    """Count and coordinate sums of the valid points of P (M, 2) (valid[row] (M,)): ``(cnt, sx, sy)``."""
    cnt = 0
    sx = 0.0
    sy = 0.0
    for m in range(P.shape[0]):
        if valid[row, m]:
            cnt += 1
            sx += P[m, 0]
            sy += P[m, 1]
    return cnt, sx, sy


@njit_inline
def _collinearity(P, valid, row):
    """:func:`~psdcal.calibration._homography.collinearity_batch` of one set: P (M, 2), valid[row] (M,)."""
    M = P.shape[0]
    cnt, mx, my = _valid_sums(P, valid, row)
    cnt = max(cnt, 1)
    mx /= cnt
    my /= cnt
    a = 0.0
    b = 0.0
    c = 0.0
    for m in range(M):
        if valid[row, m]:
            dx = P[m, 0] - mx
            dy = P[m, 1] - my
            a += dx * dx
            b += dx * dy
            c += dy * dy
    theta = 0.5 * math.atan2(2.0 * b, a - c)
    ct = math.cos(theta)
    st = math.sin(theta)
    lam_min = 0.0
    for m in range(M):
        if valid[row, m]:
            across = (P[m, 1] - my) * ct - (P[m, 0] - mx) * st
            lam_min += across * across
    lam_max = a + c - lam_min
    if lam_max > 0:
        return math.sqrt(lam_min / lam_max)
    return 0.0


@njit_inline
def _similarity(P, valid, row):
    """Hartley's normalisation of the valid points of P (M, 2): scale s, mean (mx, my)."""
    M = P.shape[0]
    cnt, mx, my = _valid_sums(P, valid, row)
    mx /= cnt
    my /= cnt
    dist = 0.0
    for m in range(M):
        if valid[row, m]:
            dist += math.hypot(P[m, 0] - mx, P[m, 1] - my)
    dist /= cnt
    return math.sqrt(2.0) / dist, mx, my


@njit
def homographies_kernel(src, dst, normalize):
    """The checks and DLT of :func:`~psdcal.calibration._homography.homographies`, all views.

    Parameters
    ----------
    src : (M, 2) float64, template points, mm.
    dst : (n, M, 2) float64, image points, mm; a point with a non-finite coordinate is missing.
    normalize : bool, Hartley normalisation (Eq 36-38).

    Returns
    -------
    H : (n, 3, 3) unit Frobenius norm, ``H[2, 2] >= 0`` (valid when code == 0).
    code : :data:`H_OK`, :data:`H_FEW_POINTS`, :data:`H_COLLINEAR`, :data:`H_RANK_DEFICIENT`,
        or :data:`H_USE_REFERENCE` when the SVD of a view did not converge (non-finite
        arithmetic): the caller runs the numpy reference, which decides.
    view : the first view that fails (the checks of all views come before any DLT).
    count : its number of valid points.
    """
    n = dst.shape[0]
    M = dst.shape[1]
    H = np.zeros((n, 3, 3))
    valid = np.empty((n, M), dtype=np.bool_)
    for v in range(n):
        for m in range(M):
            valid[v, m] = math.isfinite(dst[v, m, 0]) and math.isfinite(dst[v, m, 1])
    # the checks of every view first: the first view failing either names the error
    for v in range(n):
        cnt = 0
        for m in range(M):
            if valid[v, m]:
                cnt += 1
        if cnt < 4:
            return H, H_FEW_POINTS, v, cnt
        flat = min(_collinearity(src, valid, v), _collinearity(dst[v], valid, v))
        if flat < 1e-6:
            return H, H_COLLINEAR, v, cnt
    A = np.zeros((max(2 * M, 9), 9))  # at least 9 rows: 4 points give 8 rows, the ninth is zero
    Wm = np.zeros((9, 9))
    Vm = np.zeros((9, 9))
    sv = np.zeros(9)
    for v in range(n):
        if normalize:
            sp, mpx, mpy = _similarity(src, valid, v)
            sq, mqx, mqy = _similarity(dst[v], valid, v)
        else:
            sp, mpx, mpy = 1.0, 0.0, 0.0
            sq, mqx, mqy = 1.0, 0.0, 0.0
        # rows (X, Y, 1, 0, 0, 0, -xX, -xY, -x) and (0, 0, 0, X, Y, 1, -yX, -yY, -y) of the valid points (Eq 18)
        r = 0
        for m in range(M):
            if not valid[v, m]:
                continue
            if normalize:
                X = sp * src[m, 0] + (-sp * mpx)
                Y = sp * src[m, 1] + (-sp * mpy)
                x = sq * dst[v, m, 0] + (-sq * mqx)
                y = sq * dst[v, m, 1] + (-sq * mqy)
            else:
                X = src[m, 0]
                Y = src[m, 1]
                x = dst[v, m, 0]
                y = dst[v, m, 1]
            A[r, 0] = X
            A[r, 1] = Y
            A[r, 2] = 1.0
            A[r, 3] = 0.0
            A[r, 4] = 0.0
            A[r, 5] = 0.0
            A[r, 6] = -x * X
            A[r, 7] = -x * Y
            A[r, 8] = -x
            A[r + 1, 0] = 0.0
            A[r + 1, 1] = 0.0
            A[r + 1, 2] = 0.0
            A[r + 1, 3] = X
            A[r + 1, 4] = Y
            A[r + 1, 5] = 1.0
            A[r + 1, 6] = -y * X
            A[r + 1, 7] = -y * Y
            A[r + 1, 8] = -y
            r += 2
        rows = max(r, 9)
        for i in range(r, rows):
            for j in range(9):
                A[i, j] = 0.0
        # singular values and right vectors of A from those of its (9, 9) triangular factor
        _householder_r(A, rows, 9)
        for i in range(9):
            for j in range(9):
                Wm[i, j] = A[i, j]
        if not _jacobi_svd(Wm, Vm, 9):  # non-finite or unconverged: the reference decides
            return H, H_USE_REFERENCE, v, r // 2
        _column_norms(Wm, 9, sv)
        # the largest, the smallest and the second smallest singular values (numpy's s[0], s[8], s[7])
        i_max = 0
        i_min = 0
        for j in range(1, 9):
            if sv[j] > sv[i_max]:
                i_max = j
            if sv[j] < sv[i_min]:
                i_min = j
        s7 = np.inf
        for j in range(9):
            if j != i_min and sv[j] < s7:
                s7 = sv[j]
        if s7 <= 1e-12 * sv[i_max]:
            return H, H_RANK_DEFICIENT, v, r // 2
        h00, h01, h02 = Vm[0, i_min], Vm[1, i_min], Vm[2, i_min]
        h10, h11, h12 = Vm[3, i_min], Vm[4, i_min], Vm[5, i_min]
        h20, h21, h22 = Vm[6, i_min], Vm[7, i_min], Vm[8, i_min]
        if normalize:
            # Eq 38: H = T_Q^-1 H^o T_P, T = [[s, 0, -s mx], [0, s, -s my], [0, 0, 1]]
            tx = -sp * mpx
            ty = -sp * mpy
            g00 = h00 * sp
            g01 = h01 * sp
            g02 = h00 * tx + h01 * ty + h02
            g10 = h10 * sp
            g11 = h11 * sp
            g12 = h10 * tx + h11 * ty + h12
            g20 = h20 * sp
            g21 = h21 * sp
            g22 = h20 * tx + h21 * ty + h22
            iq = 1.0 / sq
            h00 = g00 * iq + mqx * g20
            h01 = g01 * iq + mqx * g21
            h02 = g02 * iq + mqx * g22
            h10 = g10 * iq + mqy * g20
            h11 = g11 * iq + mqy * g21
            h12 = g12 * iq + mqy * g22
            h20 = g20
            h21 = g21
            h22 = g22
        nrm = math.sqrt(h00 * h00 + h01 * h01 + h02 * h02 + h10 * h10 + h11 * h11 + h12 * h12
                        + h20 * h20 + h21 * h21 + h22 * h22)
        if h22 < 0:
            nrm = -nrm
        H[v, 0, 0] = h00 / nrm
        H[v, 0, 1] = h01 / nrm
        H[v, 0, 2] = h02 / nrm
        H[v, 1, 0] = h10 / nrm
        H[v, 1, 1] = h11 / nrm
        H[v, 1, 2] = h12 / nrm
        H[v, 2, 0] = h20 / nrm
        H[v, 2, 1] = h21 / nrm
        H[v, 2, 2] = h22 / nrm
    return H, H_OK, -1, 0


@njit_inline
def _null_vector_small(G, m, k, Wm, Vm, sv, z):
    """The right singular vector z (k,) of G's smallest singular value (G (m, k), m >= k; G overwritten).

    Returns the largest and the second smallest singular values (numpy's s[0], s[k-2])
    and whether the SVD converged.
    """
    _householder_r(G, m, k)
    for i in range(k):
        for j in range(k):
            Wm[i, j] = G[i, j]
    converged = _jacobi_svd(Wm[:k, :k], Vm[:k, :k], k)
    _column_norms(Wm[:k, :k], k, sv)
    i_max = 0
    i_min = 0
    for j in range(1, k):
        if sv[j] > sv[i_max]:
            i_max = j
        if sv[j] < sv[i_min]:
            i_min = j
    s_second = np.inf
    for j in range(k):
        if j != i_min and sv[j] < s_second:
            s_second = sv[j]
    for i in range(k):
        z[i] = Vm[i, i_min]
    return sv[i_max], s_second, converged


@njit
def intrinsics_kernel(Hs, skew, aspect):
    """The closed form of :func:`~psdcal.calibration._closed_form.intrinsics_from_homographies` (Eq 19-25).

    Parameters
    ----------
    Hs : (n, 3, 3) float64 homographies, n >= 2 (>= 3 with ``skew`` or ``aspect``; checked by the caller).
    skew, aspect : bool, the skew / a separate vertical focal length free.

    Returns
    -------
    out : (5,) ``alpha, u0, v0, gamma, beta`` (mm; valid when code == 0); the
        one-focal-length model's ``f`` is ``sqrt(alpha beta)``, computed by the caller.
    code : :data:`I_OK`, :data:`I_UNDETERMINED`, :data:`I_NOT_POSITIVE_DEFINITE`,
        :data:`I_NEGATIVE_FOCAL`, or :data:`I_USE_REFERENCE` for a non-finite entry or a
        zero homography (the caller then runs the reference, which decides).
    """
    n = Hs.shape[0]
    out = np.zeros(5)
    for v in range(n):
        nz = False
        for i in range(3):
            for j in range(3):
                if not math.isfinite(Hs[v, i, j]):
                    return out, I_USE_REFERENCE
                nz = nz or Hs[v, i, j] != 0.0
        if not nz:
            return out, I_USE_REFERENCE
    # the reduced unknown's columns: [b11 (+ b22)], [b12], [b22], b13, b23, b33
    k = 4 + (1 if skew else 0) + (1 if aspect else 0)
    G = np.zeros((2 * n, 6))
    for v in range(n):
        nrm = 0.0
        for i in range(3):
            for j in range(3):
                nrm += Hs[v, i, j] * Hs[v, i, j]
        nrm = math.sqrt(nrm)
        a0, a1, a2 = Hs[v, 0, 0] / nrm, Hs[v, 1, 0] / nrm, Hs[v, 2, 0] / nrm  # h1
        c0, c1, c2 = Hs[v, 0, 1] / nrm, Hs[v, 1, 1] / nrm, Hs[v, 2, 1] / nrm  # h2
        # Zhang's v_12 and v_11 - v_22 over b = [b11, b12, b22, b13, b23, b33] (Eq 22)
        v12 = (a0 * c0, a0 * c1 + a1 * c0, a1 * c1, a2 * c0 + a0 * c2, a2 * c1 + a1 * c2, a2 * c2)
        v11 = (a0 * a0, a0 * a1 + a1 * a0, a1 * a1, a2 * a0 + a0 * a2, a2 * a1 + a1 * a2, a2 * a2)
        v22 = (c0 * c0, c0 * c1 + c1 * c0, c1 * c1, c2 * c0 + c0 * c2, c2 * c1 + c1 * c2, c2 * c2)
        for row in range(2):
            r = 2 * v + row
            if row == 0:
                e = v12
            else:
                e = (v11[0] - v22[0], v11[1] - v22[1], v11[2] - v22[2], v11[3] - v22[3], v11[4] - v22[4], v11[5] - v22[5])
            col = 0
            G[r, col] = e[0] if aspect else e[0] + e[2]
            col += 1
            if skew:
                G[r, col] = e[1]
                col += 1
            if aspect:
                G[r, col] = e[2]
                col += 1
            G[r, col] = e[3]
            G[r, col + 1] = e[4]
            G[r, col + 2] = e[5]
    # column scaling for conditioning
    sc = np.zeros(6)
    for j in range(k):
        s = 0.0
        for i in range(2 * n):
            s += G[i, j] * G[i, j]
        sc[j] = math.sqrt(s) if s > 0 else 1.0
        for i in range(2 * n):
            G[i, j] /= sc[j]
    Wm = np.zeros((6, 6))
    Vm = np.zeros((6, 6))
    sv = np.zeros(6)
    z = np.zeros(6)
    s_max, s_second, converged = _null_vector_small(G, 2 * n, k, Wm, Vm, sv, z)
    if not converged:
        return out, I_USE_REFERENCE
    if not (s_second > 1e-12 * s_max):
        return out, I_UNDETERMINED
    for j in range(k):
        z[j] /= sc[j]
    if z[0] < 0:
        for j in range(k):
            z[j] = -z[j]
    b11 = z[0]
    col = 1
    b12 = 0.0
    if skew:
        b12 = z[col]
        col += 1
    b22 = b11
    if aspect:
        b22 = z[col]
        col += 1
    b13, b23, b33 = z[col], z[col + 1], z[col + 2]
    den = b11 * b22 - b12 * b12
    if not (b11 > 0 and den > 0):
        return out, I_NOT_POSITIVE_DEFINITE
    v0 = (b12 * b13 - b11 * b23) / den
    lam = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11
    if not lam / b11 > 0:
        return out, I_NEGATIVE_FOCAL
    alpha = math.sqrt(lam / b11)
    beta = math.sqrt(lam * b11 / den)
    gamma = -b12 * alpha * alpha * beta / lam
    u0 = gamma * v0 / beta - b13 * alpha * alpha / lam
    out[0] = alpha
    out[1] = u0
    out[2] = v0
    out[3] = gamma
    out[4] = beta
    return out, I_OK


@njit_inline
def _rotation_vector(R):
    """:func:`~psdcal.model.projection.r_from_R_batch` of R (3, 3) (the same formulas), as a tuple."""
    w0 = R[2, 1] - R[1, 2]
    w1 = R[0, 2] - R[2, 0]
    w2 = R[1, 0] - R[0, 1]
    s = 0.5 * math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)  # sin(theta)
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)  # cos(theta)
    theta = math.atan2(s, c)
    if theta < 1e-8:
        return 0.5 * w0, 0.5 * w1, 0.5 * w2
    if not c < -0.5:
        f = theta / (2.0 * s)
        return w0 * f, w1 * f, w2 * f
    # beyond 120 degrees: the axis is the largest column of (R + R^T) / 2 - c I = (1 - c) u u^T, signed like w
    kk = 0
    best = R[0, 0] - c
    for j in range(1, 3):
        if R[j, j] - c > best:
            best = R[j, j] - c
            kk = j
    a0 = 0.5 * (R[0, kk] + R[kk, 0]) - (c if kk == 0 else 0.0)
    a1 = 0.5 * (R[1, kk] + R[kk, 1]) - (c if kk == 1 else 0.0)
    a2 = 0.5 * (R[2, kk] + R[kk, 2]) - (c if kk == 2 else 0.0)
    nrm = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    if a0 * w0 + a1 * w1 + a2 * w2 < 0:
        nrm = -nrm
    return a0 / nrm * theta, a1 / nrm * theta, a2 / nrm * theta


@njit_inline
def _nearest_rotation(Mx, W, V, R):
    """:func:`~psdcal.model.projection.nearest_rotation` of Mx (3, 3) into R: ``U diag(1, 1, d) V^T``.

    ``Mx V = W`` with orthogonal columns (Jacobi, det V = +1); the columns of U
    are W's normalised, except the one of the smallest singular value, which
    is the cross product of the other two (so det U = +1, and U V^T is the
    rotation nearest to Mx whatever the sign of det Mx). False (R not set) when Mx
    has rank <= 1 (no unique nearest rotation) or the SVD did not converge.
    """
    for i in range(3):
        for j in range(3):
            W[i, j] = Mx[i, j]
    if not _jacobi_svd(W, V, 3):
        return False
    n0 = math.sqrt(W[0, 0] * W[0, 0] + W[1, 0] * W[1, 0] + W[2, 0] * W[2, 0])
    n1 = math.sqrt(W[0, 1] * W[0, 1] + W[1, 1] * W[1, 1] + W[2, 1] * W[2, 1])
    n2 = math.sqrt(W[0, 2] * W[0, 2] + W[1, 2] * W[1, 2] + W[2, 2] * W[2, 2])
    kmin = 0
    if n1 < n0:
        kmin = 1
    if n2 < min(n0, n1):
        kmin = 2
    ka = (kmin + 1) % 3
    kb = (kmin + 2) % 3
    na = n0 if ka == 0 else (n1 if ka == 1 else n2)
    nb = n0 if kb == 0 else (n1 if kb == 1 else n2)
    if not (na > 0 and nb > 0):
        return False
    for i in range(3):
        W[i, ka] /= na
        W[i, kb] /= nb
    # u_kmin = u_ka x u_kb (cyclic order: det U = +1)
    W[0, kmin] = W[1, ka] * W[2, kb] - W[2, ka] * W[1, kb]
    W[1, kmin] = W[2, ka] * W[0, kb] - W[0, ka] * W[2, kb]
    W[2, kmin] = W[0, ka] * W[1, kb] - W[1, ka] * W[0, kb]
    for i in range(3):
        for j in range(3):
            R[i, j] = W[i, 0] * V[j, 0] + W[i, 1] * V[j, 1] + W[i, 2] * V[j, 2]
    return True


@njit
def poses_kernel(Hs, f, skew, cx, fy, cy):
    """:func:`~psdcal.calibration._closed_form.poses_from_homographies` of Hs (n, 3, 3) (Eq 26-28).

    ``A = [[f, skew, cx], [0, fy, cy], [0, 0, 1]]`` (mm). Returns rvecs (n, 3)
    rad, tvecs (n, 3) mm and whether the input was usable (finite, ``f fy != 0``);
    when not, the caller runs the reference, which decides.
    """
    n = Hs.shape[0]
    rv = np.zeros((n, 3))
    tv = np.zeros((n, 3))
    if not (math.isfinite(f) and math.isfinite(skew) and math.isfinite(cx) and math.isfinite(fy)
            and math.isfinite(cy) and f != 0.0 and fy != 0.0):
        return rv, tv, False
    for v in range(n):
        for i in range(3):
            for j in range(3):
                if not math.isfinite(Hs[v, i, j]):
                    return rv, tv, False
    # A^-1 of the upper triangular A
    i00 = 1.0 / f
    i11 = 1.0 / fy
    i01 = -skew * i00 * i11
    i02 = -(cx * i00 + cy * i01)
    i12 = -cy * i11
    Mx = np.zeros((3, 3))
    W = np.zeros((3, 3))
    V = np.zeros((3, 3))
    R = np.zeros((3, 3))
    a = np.zeros((3, 3))  # a[:, j] = A^-1 h_j
    for v in range(n):
        for j in range(3):
            h0 = Hs[v, 0, j]
            h1 = Hs[v, 1, j]
            h2 = Hs[v, 2, j]
            a[0, j] = i00 * h0 + i01 * h1 + i02 * h2
            a[1, j] = i11 * h1 + i12 * h2
            a[2, j] = h2
        norm1 = math.sqrt(a[0, 0] * a[0, 0] + a[1, 0] * a[1, 0] + a[2, 0] * a[2, 0])
        norm2 = math.sqrt(a[0, 1] * a[0, 1] + a[1, 1] * a[1, 1] + a[2, 1] * a[2, 1])
        if not norm1 + norm2 > 0:  # a zero homography: the reference's SVD raises
            return rv, tv, False
        lam = 2.0 / (norm1 + norm2)
        if a[2, 2] * lam < 0:  # template in front: t_z > 0
            lam = -lam
        for i in range(3):
            Mx[i, 0] = lam * a[i, 0]
            Mx[i, 1] = lam * a[i, 1]
            tv[v, i] = lam * a[i, 2]
        Mx[0, 2] = Mx[1, 0] * Mx[2, 1] - Mx[2, 0] * Mx[1, 1]
        Mx[1, 2] = Mx[2, 0] * Mx[0, 1] - Mx[0, 0] * Mx[2, 1]
        Mx[2, 2] = Mx[0, 0] * Mx[1, 1] - Mx[1, 0] * Mx[0, 1]
        for i in range(3):
            for j in range(3):
                if not math.isfinite(Mx[i, j]):  # a zero homography: the reference's SVD raises
                    return rv, tv, False
        if not _nearest_rotation(Mx, W, V, R):  # rank <= 1 (no unique nearest rotation) or unconverged: the reference decides
            return rv, tv, False
        r0, r1, r2 = _rotation_vector(R)
        rv[v, 0] = r0
        rv[v, 1] = r1
        rv[v, 2] = r2
    return rv, tv, True


@njit
def focal_from_homographies_kernel(Hs, cx, cy):
    """:func:`psdcal.calibration.core.focal_from_homographies` of Hs (n, 3, 3) with C = (cx, cy) mm.

    Returns f (n,) mm, NaN where a view does not fix it.
    """
    n = Hs.shape[0]
    out = np.empty(n)
    for v in range(n):
        # G = T(-C) H, scaled by the norm of its first two columns
        g00 = Hs[v, 0, 0] - cx * Hs[v, 2, 0]
        g10 = Hs[v, 1, 0] - cy * Hs[v, 2, 0]
        g20 = Hs[v, 2, 0]
        g01 = Hs[v, 0, 1] - cx * Hs[v, 2, 1]
        g11 = Hs[v, 1, 1] - cy * Hs[v, 2, 1]
        g21 = Hs[v, 2, 1]
        nrm = math.sqrt(g00 * g00 + g01 * g01 + g10 * g10 + g11 * g11 + g20 * g20 + g21 * g21)
        out[v] = np.nan
        if not nrm > 0:
            continue
        g00 /= nrm
        g10 /= nrm
        g20 /= nrm
        g01 /= nrm
        g11 /= nrm
        g21 /= nrm
        a0 = g00 * g01 + g10 * g11
        a1 = g00 * g00 + g10 * g10 - g01 * g01 - g11 * g11
        b0 = g20 * g21
        b1 = g20 * g20 - g21 * g21
        den = a0 * a0 + a1 * a1
        if den > 0:
            w = -(a0 * b0 + a1 * b1) / den  # 1/f^2: a w + b = 0
            if math.isfinite(w) and w > 0:
                out[v] = 1.0 / math.sqrt(w)
    return out
