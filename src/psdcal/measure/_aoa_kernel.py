"""Compiled angles of arrival with their covariance, in blocks of points.

The same mathematics as the numpy reference
:func:`psdcal.measure.aoa.angles_from_points` (which stays the tested
reference): ``x = undistort(d)`` (Eq 7-16, explicit, no iteration),
``yn = (y - cy) / fy``, ``xn = (x - cx - s yn) / f`` (inverse of Eq 4),
``alpha = atan(n)`` (Eq 39), with the analytic derivatives of ``n`` by the
calibration parameters and by ``d``, and both covariances
``dn/dp C dn/dp^T`` (as ``|B^T dn/dp^T|^2`` with a Cholesky factor ``B`` of
``C``) and ``dn/dd Sigma_d dn/dd^T`` (no (N, 2, n_params) temporaries).

The points go in blocks of :data:`BLOCK`: a block's model terms and
derivative columns are written point-contiguous into one small scratch
array (in cache), so that each step is a loop over the points of the block,
which the compiler vectorises (SIMD) without fastmath: the same operations
in the same order as per point, only several points at a time; the
angles use the kernel's own arctangent :func:`_atan` (plain arithmetic,
within 6e-16 of ``numpy.arctan``) instead of a libm call per value. The
derivatives ``dn/dp`` are copied out only when asked for.
"""
from __future__ import annotations

import math

import numpy as np

from psdcal._jit import njit
from psdcal.model._point_kernel import _model_terms

#: parameter codes of :func:`angles_kernel` (index into this tuple)
PARAM_CODES = ("f_mm", "cx_mm", "cy_mm", "skew", "fy_mm", "k1", "k2", "k3", "p1", "p2", "l1", "l2",
               "g_x2", "g_y1", "g_y2")


def covariance_factor(C):
    """``(B, lower)`` with ``C = B B^T``: the Cholesky factor of a positive-definite covariance (lower
    triangular), else ``Q sqrt(max(lambda, 0))`` from its eigen-decomposition (a semi-definite one)."""
    C = np.asarray(C, dtype=float)
    if C.size == 0:
        return np.zeros((0, 0)), True
    try:
        return np.linalg.cholesky(C), True
    except np.linalg.LinAlgError:
        lam, Q = np.linalg.eigh(0.5 * (C + C.T))
        return np.ascontiguousarray(Q * np.sqrt(np.clip(lam, 0.0, None))), False


#: terms of the arctangent series in :func:`_atan`: with |y| <= tan(pi/8) the first left-out term is
#: below 4e-16 of the result
_ATAN_TERMS = 18
#: its coefficients (-1)^k / (2k + 1)
_ATAN_SERIES = tuple((-1.0) ** k / (2 * k + 1) for k in range(_ATAN_TERMS))
_TAN_PI_8 = math.sqrt(2.0) - 1.0


@njit
def _atan(x):
    """``atan(x)`` (Eq 39) as plain arithmetic, so that a loop over points vectorises (libm's atan is a call
    per value): ``atan(x) = pi/2 - atan(1/x)`` brings |x| into [0, 1], ``atan(z) = pi/4 +
    atan((z - 1)/(z + 1))`` into |y| <= tan(pi/8), then the series ``y sum (-y^2)^k / (2k + 1)``.
    Within 6e-16 (relative) of ``numpy.arctan`` (tests/test_aoa_kernel.py); NaN stays NaN, +-inf gives
    +-pi/2."""
    a = abs(x)
    big = a > 1.0
    z = 1.0 / a if big else a
    mid = z > _TAN_PI_8
    y = (z - 1.0) / (z + 1.0) if mid else z
    u = y * y
    p = _ATAN_SERIES[_ATAN_TERMS - 1]
    for k in range(_ATAN_TERMS - 2, -1, -1):
        p = _ATAN_SERIES[k] + u * p
    r = y * p
    r = r + 0.25 * math.pi if mid else r
    r = 0.5 * math.pi - r if big else r
    return math.copysign(r, x)


#: points per block: the block's scratch (42 rows of BLOCK numbers, 43 kB) stays in cache, point-contiguous,
#: so that every step is a loop over the points of a block (SIMD, no fastmath needed); 128 measured
#: faster than 64 (docs/guide/performance.md)
BLOCK = 128


@njit
def angles_kernel(d, intr, separate_fy, coef, codes, B, lower, cov_d, dd_dg, derivatives, out_buf):
    """Angles, normalised coordinates and covariances of impact points.

    Parameters
    ----------
    d : (N, 2) measured impact points, mm
    intr : (5,) f, cx, cy, skew, fy (mm; fy used when ``separate_fy``)
    coef : (7,) k1, k2, k3, p1, p2, l1, l2
    codes : (P,) int, :data:`PARAM_CODES` index of each calibration parameter (covariance order)
    B : (P, P) a factor of the calibration covariance, C = B B^T (:func:`covariance_factor`)
    lower : bool, B is lower triangular (a Cholesky factor)
    cov_d : (N, 2, 2) impact-point noise covariance, or (0, 2, 2) for none
    dd_dg : (N, 2, 3) derivative of d by (g_x2, g_y1, g_y2), or (0, 2, 3) for none
    derivatives : bool, also return dn/dp (else an empty (0, 2, P) array: the covariances do not need it)
    out_buf : (18 N + 2 N P,) or (18 N,) without derivatives: the outputs' memory, allocated by the caller
        (numpy asks the kernel for huge pages on large arrays, numba's allocator does not: a million points in
        one call spent more time in first-touch page faults than computing), or any other size to allocate here

    Returns
    -------
    x (N, 2), n (N, 2), alpha (N, 2), cov_calib (N, 2, 2), cov_noise (N, 2, 2),
    dn_dp (N, 2, P) or (0, 2, P), dn_dd (N, 2, 2)
    """
    N = d.shape[0]
    P = codes.shape[0]
    f, cx, cy, s = intr[0], intr[1], intr[2], intr[3]
    fy = intr[4] if separate_fy else f
    a00, a01, a11 = 1.0 / f, -s / (f * fy), 1.0 / fy  # dn/dx (a10 = 0)
    # all outputs are (C-contiguous) parts of one allocation: with several large ones, the C allocator
    # gives their memory back to the system after a call and page-faults it in again at the next one
    # (streaming calls of 65536 points spent more time in those faults than computing)
    nd = N * 2 * P if derivatives else 0
    buf = out_buf if out_buf.shape[0] == 18 * N + nd else np.empty(18 * N + nd)
    x = buf[:2 * N].reshape((N, 2))
    n = buf[2 * N:4 * N].reshape((N, 2))
    alpha = buf[4 * N:6 * N].reshape((N, 2))
    covc = buf[6 * N:10 * N].reshape((N, 2, 2))
    covn = buf[10 * N:14 * N].reshape((N, 2, 2))
    dn_dd = buf[14 * N:18 * N].reshape((N, 2, 2))
    dn_dp = buf[18 * N:].reshape((N if derivatives else 0, 2, P))
    has_noise = cov_d.shape[0] == N
    if not has_noise:
        covn[:] = 0.0
    has_gain = dd_dg.shape[0] == N
    # One scratch block W[row, point] (point-contiguous, a single array so that the compiler sees that
    # its rows do not overlap and vectorises the loops over the points): rows 0-1 x, 2-3 n,
    # 4-7 dn/dd, then the 15 derivative columns in PARAM_CODES order, row 8 + 2 code + (0 for xn, 1 for yn),
    # rows 38-39 the points d of the block (copied first: reading d itself kept the main loop scalar),
    # rows 40-41 the angles
    W = np.zeros((8 + 2 * 15 + 4, BLOCK))
    w0 = np.empty(BLOCK)
    w1 = np.empty(BLOCK)
    c00 = np.empty(BLOCK)
    c01 = np.empty(BLOCK)
    c11 = np.empty(BLOCK)
    for i0 in range(0, N, BLOCK):
        m = min(BLOCK, N - i0)
        for t in range(m):
            W[38, t] = d[i0 + t, 0]
            W[39, t] = d[i0 + t, 1]
        for t in range(m):
            d0, d1 = W[38, t], W[39, t]
            # the undistortion model at d (Eq 7-16)
            x0, x1, h2, ex, ey, r2, G00, G01, G10, G11, U00, U01, U11 = _model_terms(d0, d1, coef, cx, cy)
            yn = (x1 - cy) / fy
            xn = (x0 - cx - s * yn) / f
            W[0, t], W[1, t], W[2, t], W[3, t] = x0, x1, xn, yn
            # dx/dd = (I + G) U
            X00 = (1 + G00) * U00 + G01 * U01
            X01 = (1 + G00) * U01 + G01 * U11
            X10 = G10 * U00 + (1 + G11) * U01
            X11 = G10 * U01 + (1 + G11) * U11
            W[4, t] = a00 * X00 + a01 * X10
            W[5, t] = a00 * X01 + a01 * X11
            W[6, t] = a11 * X10
            W[7, t] = a11 * X11
            r4 = r2 * r2
            # every derivative column, branch-free, in PARAM_CODES order
            if separate_fy:
                W[8, t], W[9, t] = -xn / f, 0.0
            else:
                W[8, t], W[9, t] = -xn / f + s * yn / (f * f), -yn / f
            W[10, t], W[11, t] = a00 * -G00 + a01 * -G10 - 1.0 / f, a11 * -G10  # cx: dx/dc = -G
            W[12, t], W[13, t] = a00 * -G01 + a01 * -G11 + s / (f * fy), a11 * -G11 - 1.0 / fy  # cy
            W[14, t], W[15, t] = -yn / f, 0.0  # skew
            dyn = -yn / fy
            W[16, t], W[17, t] = -s * dyn / f, dyn  # fy
            # distortion coefficients: n moves by A^-1 dx/dcoef
            u0, u1 = ex * r2, ey * r2  # k1
            W[18, t], W[19, t] = a00 * u0 + a01 * u1, a11 * u1
            u0, u1 = ex * r4, ey * r4  # k2
            W[20, t], W[21, t] = a00 * u0 + a01 * u1, a11 * u1
            u0, u1 = ex * r4 * r2, ey * r4 * r2  # k3
            W[22, t], W[23, t] = a00 * u0 + a01 * u1, a11 * u1
            u0, u1 = r2 + 2 * ex * ex, 2 * ex * ey  # p1
            W[24, t], W[25, t] = a00 * u0 + a01 * u1, a11 * u1
            u0, u1 = 2 * ex * ey, r2 + 2 * ey * ey  # p2
            W[26, t], W[27, t] = a00 * u0 + a01 * u1, a11 * u1
            # PSD terms act through u = d s: dx/dl = (I + G) d h2^(j+1)
            u0, u1 = (1 + G00) * d0 * h2 + G01 * d1 * h2, G10 * d0 * h2 + (1 + G11) * d1 * h2  # l1
            W[28, t], W[29, t] = a00 * u0 + a01 * u1, a11 * u1
            hp = h2 * h2
            u0, u1 = (1 + G00) * d0 * hp + G01 * d1 * hp, G10 * d0 * hp + (1 + G11) * d1 * hp  # l2
            W[30, t], W[31, t] = a00 * u0 + a01 * u1, a11 * u1
        if has_gain:  # gains act through d: dn/dg = dn/dd dd/dg
            gb = dd_dg[i0:i0 + m]
            for j in range(3):
                for t in range(m):
                    g0, g1 = gb[t, 0, j], gb[t, 1, j]
                    W[32 + 2 * j, t] = W[4, t] * g0 + W[5, t] * g1
                    W[33 + 2 * j, t] = W[6, t] * g0 + W[7, t] * g1
        for t in range(m):
            i = i0 + t
            x[i, 0], x[i, 1] = W[0, t], W[1, t]
            n[i, 0], n[i, 1] = W[2, t], W[3, t]
            dn_dd[i, 0, 0], dn_dd[i, 0, 1], dn_dd[i, 1, 0], dn_dd[i, 1, 1] = W[4, t], W[5, t], W[6, t], W[7, t]
        for t in range(m):
            W[40, t] = _atan(W[2, t])  # Eq 39
            W[41, t] = _atan(W[3, t])
        for t in range(m):
            i = i0 + t
            alpha[i, 0], alpha[i, 1] = W[40, t], W[41, t]
        # cov_calib = dn_dp C dn_dp^T = |B^T v|^2 with C = B B^T (B lower triangular: half the products),
        # over the points of the block
        for t in range(m):
            c00[t] = 0.0
            c01[t] = 0.0
            c11[t] = 0.0
        for j in range(P):
            k = j if lower else 0
            bk = B[k, j]
            r = 8 + 2 * codes[k]
            for t in range(m):
                w0[t] = W[r, t] * bk
                w1[t] = W[r + 1, t] * bk
            k += 1
            while k + 2 < P:  # three rows at a time (the same sums in the same order, fewer passes)
                ba, bb, bc = B[k, j], B[k + 1, j], B[k + 2, j]
                ra, rb, rc = 8 + 2 * codes[k], 8 + 2 * codes[k + 1], 8 + 2 * codes[k + 2]
                for t in range(m):
                    w0[t] = ((w0[t] + W[ra, t] * ba) + W[rb, t] * bb) + W[rc, t] * bc
                    w1[t] = ((w1[t] + W[ra + 1, t] * ba) + W[rb + 1, t] * bb) + W[rc + 1, t] * bc
                k += 3
            while k < P:
                bk = B[k, j]
                r = 8 + 2 * codes[k]
                for t in range(m):
                    w0[t] += W[r, t] * bk
                    w1[t] += W[r + 1, t] * bk
                k += 1
            for t in range(m):
                c00[t] += w0[t] * w0[t]
                c01[t] += w0[t] * w1[t]
                c11[t] += w1[t] * w1[t]
        for t in range(m):
            i = i0 + t
            covc[i, 0, 0], covc[i, 0, 1], covc[i, 1, 0], covc[i, 1, 1] = c00[t], c01[t], c01[t], c11[t]
        if has_noise:
            for t in range(m):
                i = i0 + t
                D00, D01, D10, D11 = W[4, t], W[5, t], W[6, t], W[7, t]
                s00, s01, s10, s11 = cov_d[i, 0, 0], cov_d[i, 0, 1], cov_d[i, 1, 0], cov_d[i, 1, 1]
                m00, m01 = D00 * s00 + D01 * s10, D00 * s01 + D01 * s11
                m10, m11 = D10 * s00 + D11 * s10, D10 * s01 + D11 * s11
                covn[i, 0, 0] = m00 * D00 + m01 * D01
                covn[i, 0, 1] = m00 * D10 + m01 * D11
                covn[i, 1, 0] = m10 * D00 + m11 * D01
                covn[i, 1, 1] = m10 * D10 + m11 * D11
        if derivatives:
            for k in range(P):
                r = 8 + 2 * codes[k]
                for t in range(m):
                    dn_dp[i0 + t, 0, k] = W[r, t]
                    dn_dp[i0 + t, 1, k] = W[r + 1, t]
    return x, n, alpha, covc, covn, dn_dp, dn_dd
