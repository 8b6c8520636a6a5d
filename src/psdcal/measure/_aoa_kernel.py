"""Compiled angles of arrival with their covariance, one pass over the points.

The same mathematics as the numpy reference
:func:`psdcal.measure.aoa.angles_from_points` (which stays the tested
reference): ``x = undistort(d)`` (Eq 7-16, explicit, no iteration),
``yn = (y - cy) / fy``, ``xn = (x - cx - s yn) / f`` (inverse of Eq 4),
``alpha = atan(n)`` (Eq 39), with the analytic derivatives of ``n`` by the
calibration parameters and by ``d``, and both covariances
``dn/dp C dn/dp^T`` (as ``|B^T dn/dp^T|^2`` with a Cholesky factor ``B`` of
``C``) and ``dn/dd Sigma_d dn/dd^T`` formed per point from scalars (no
(N, 2, n_params) temporaries).
"""
from __future__ import annotations

import math

import numpy as np

from psdcal._jit import njit
from psdcal.calibration._image_kernel import _model_terms

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


#: points per block: the derivative columns of a block stay in L1 cache, point-contiguous, so that the
#: quadratic form and the covariance loops run over the points of a block (SIMD, no fastmath needed)
BLOCK = 64


@njit
def angles_kernel(d, intr, separate_fy, coef, codes, B, lower, cov_d, dd_dg, derivatives):
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
    buf = np.empty(18 * N + nd)
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
    # the 15 derivative columns of a block in PARAM_CODES order, point-contiguous: S[code, row, point]
    S = np.zeros((15, 2, BLOCK))
    D = np.empty((4, BLOCK))
    w0 = np.empty(BLOCK)
    w1 = np.empty(BLOCK)
    c00 = np.empty(BLOCK)
    c01 = np.empty(BLOCK)
    c11 = np.empty(BLOCK)
    for i0 in range(0, N, BLOCK):
        m = min(BLOCK, N - i0)
        for t in range(m):
            i = i0 + t
            d0, d1 = d[i, 0], d[i, 1]
            x0, x1, h2, ex, ey, r2, G00, G01, G10, G11, U00, U01, U11 = _model_terms(d0, d1, coef, cx, cy)
            yn = (x1 - cy) / fy
            xn = (x0 - cx - s * yn) / f
            x[i, 0], x[i, 1] = x0, x1
            n[i, 0], n[i, 1] = xn, yn
            # dx/dd = (I + G) U
            X00 = (1 + G00) * U00 + G01 * U01
            X01 = (1 + G00) * U01 + G01 * U11
            X10 = G10 * U00 + (1 + G11) * U01
            X11 = G10 * U01 + (1 + G11) * U11
            D00 = a00 * X00 + a01 * X10
            D01 = a00 * X01 + a01 * X11
            D10 = a11 * X10
            D11 = a11 * X11
            D[0, t], D[1, t], D[2, t], D[3, t] = D00, D01, D10, D11
            r4 = r2 * r2
            # every derivative column, branch-free, in PARAM_CODES order
            if separate_fy:
                S[0, 0, t], S[0, 1, t] = -xn / f, 0.0
            else:
                S[0, 0, t], S[0, 1, t] = -xn / f + s * yn / (f * f), -yn / f
            S[1, 0, t], S[1, 1, t] = a00 * -G00 + a01 * -G10 - 1.0 / f, a11 * -G10  # cx: dx/dc = -G
            S[2, 0, t], S[2, 1, t] = a00 * -G01 + a01 * -G11 + s / (f * fy), a11 * -G11 - 1.0 / fy  # cy
            S[3, 0, t], S[3, 1, t] = -yn / f, 0.0  # skew
            dyn = -yn / fy
            S[4, 0, t], S[4, 1, t] = -s * dyn / f, dyn  # fy
            # distortion coefficients: n moves by A^-1 dx/dcoef
            u0, u1 = ex * r2, ey * r2  # k1
            S[5, 0, t], S[5, 1, t] = a00 * u0 + a01 * u1, a11 * u1
            u0, u1 = ex * r4, ey * r4  # k2
            S[6, 0, t], S[6, 1, t] = a00 * u0 + a01 * u1, a11 * u1
            u0, u1 = ex * r4 * r2, ey * r4 * r2  # k3
            S[7, 0, t], S[7, 1, t] = a00 * u0 + a01 * u1, a11 * u1
            u0, u1 = r2 + 2 * ex * ex, 2 * ex * ey  # p1
            S[8, 0, t], S[8, 1, t] = a00 * u0 + a01 * u1, a11 * u1
            u0, u1 = 2 * ex * ey, r2 + 2 * ey * ey  # p2
            S[9, 0, t], S[9, 1, t] = a00 * u0 + a01 * u1, a11 * u1
            # PSD terms act through u = d s: dx/dl = (I + G) d h2^(j+1)
            u0, u1 = (1 + G00) * d0 * h2 + G01 * d1 * h2, G10 * d0 * h2 + (1 + G11) * d1 * h2  # l1
            S[10, 0, t], S[10, 1, t] = a00 * u0 + a01 * u1, a11 * u1
            hp = h2 * h2
            u0, u1 = (1 + G00) * d0 * hp + G01 * d1 * hp, G10 * d0 * hp + (1 + G11) * d1 * hp  # l2
            S[11, 0, t], S[11, 1, t] = a00 * u0 + a01 * u1, a11 * u1
            if has_gain:  # gains act through d
                for j in range(3):
                    g0, g1 = dd_dg[i, 0, j], dd_dg[i, 1, j]
                    S[12 + j, 0, t], S[12 + j, 1, t] = D00 * g0 + D01 * g1, D10 * g0 + D11 * g1
        for t in range(m):
            i = i0 + t
            alpha[i, 0], alpha[i, 1] = math.atan(n[i, 0]), math.atan(n[i, 1])  # Eq 39
            dn_dd[i, 0, 0], dn_dd[i, 0, 1], dn_dd[i, 1, 0], dn_dd[i, 1, 1] = D[0, t], D[1, t], D[2, t], D[3, t]
        # cov_calib = dn_dp C dn_dp^T = |B^T v|^2 with C = B B^T (B lower triangular: half the products),
        # over the points of the block
        for t in range(m):
            c00[t] = 0.0
            c01[t] = 0.0
            c11[t] = 0.0
        for j in range(P):
            for t in range(m):
                w0[t] = 0.0
                w1[t] = 0.0
            for k in range(j if lower else 0, P):
                bkj = B[k, j]
                r = codes[k]
                for t in range(m):
                    w0[t] += S[r, 0, t] * bkj
                    w1[t] += S[r, 1, t] * bkj
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
                D00, D01, D10, D11 = D[0, t], D[1, t], D[2, t], D[3, t]
                s00, s01, s10, s11 = cov_d[i, 0, 0], cov_d[i, 0, 1], cov_d[i, 1, 0], cov_d[i, 1, 1]
                m00, m01 = D00 * s00 + D01 * s10, D00 * s01 + D01 * s11
                m10, m11 = D10 * s00 + D11 * s10, D10 * s01 + D11 * s11
                covn[i, 0, 0] = m00 * D00 + m01 * D01
                covn[i, 0, 1] = m00 * D10 + m01 * D11
                covn[i, 1, 0] = m10 * D00 + m11 * D01
                covn[i, 1, 1] = m10 * D10 + m11 * D11
        if derivatives:
            for t in range(m):
                i = i0 + t
                for k in range(P):
                    dn_dp[i, 0, k] = S[codes[k], 0, t]
                    dn_dp[i, 1, k] = S[codes[k], 1, t]
    return x, n, alpha, covc, covn, dn_dp, dn_dd
