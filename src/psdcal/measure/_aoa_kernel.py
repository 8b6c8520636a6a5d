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


@njit
def angles_kernel(d, intr, separate_fy, coef, codes, B, lower, cov_d, dd_dg):
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

    Returns
    -------
    x (N, 2), n (N, 2), alpha (N, 2), cov_calib (N, 2, 2), cov_noise (N, 2, 2),
    dn_dp (N, 2, P), dn_dd (N, 2, 2)
    """
    N = d.shape[0]
    P = codes.shape[0]
    f, cx, cy, s = intr[0], intr[1], intr[2], intr[3]
    fy = intr[4] if separate_fy else f
    a00, a01, a11 = 1.0 / f, -s / (f * fy), 1.0 / fy  # dn/dx (a10 = 0)
    x = np.empty((N, 2))
    n = np.empty((N, 2))
    alpha = np.empty((N, 2))
    covc = np.empty((N, 2, 2))
    covn = np.zeros((N, 2, 2))
    dn_dp = np.empty((N, 2, P))
    dn_dd = np.empty((N, 2, 2))
    has_noise = cov_d.shape[0] == N
    has_gain = dd_dg.shape[0] == N
    A0 = np.empty(15)
    A1 = np.empty(15)
    U0 = np.empty(7)
    U1 = np.empty(7)
    V0 = np.empty(P)
    V1 = np.empty(P)
    for i in range(N):
        d0, d1 = d[i, 0], d[i, 1]
        x0, x1, h2, ex, ey, r2, G00, G01, G10, G11, U00, U01, U11 = _model_terms(d0, d1, coef, cx, cy)
        yn = (x1 - cy) / fy
        xn = (x0 - cx - s * yn) / f
        x[i, 0], x[i, 1] = x0, x1
        n[i, 0], n[i, 1] = xn, yn
        alpha[i, 0], alpha[i, 1] = math.atan(xn), math.atan(yn)  # Eq 39
        # dx/dd = (I + G) U
        X00 = (1 + G00) * U00 + G01 * U01
        X01 = (1 + G00) * U01 + G01 * U11
        X10 = G10 * U00 + (1 + G11) * U01
        X11 = G10 * U01 + (1 + G11) * U11
        D00 = a00 * X00 + a01 * X10
        D01 = a00 * X01 + a01 * X11
        D10 = a11 * X10
        D11 = a11 * X11
        dn_dd[i, 0, 0], dn_dd[i, 0, 1], dn_dd[i, 1, 0], dn_dd[i, 1, 1] = D00, D01, D10, D11
        r4 = r2 * r2
        # every derivative column, branch-free, in PARAM_CODES order; then gathered by ``codes``
        if separate_fy:
            A0[0], A1[0] = -xn / f, 0.0
        else:
            A0[0], A1[0] = -xn / f + s * yn / (f * f), -yn / f
        A0[1], A1[1] = a00 * -G00 + a01 * -G10 - 1.0 / f, a11 * -G10  # cx: dx/dc = -G
        A0[2], A1[2] = a00 * -G01 + a01 * -G11 + s / (f * fy), a11 * -G11 - 1.0 / fy  # cy
        A0[3], A1[3] = -yn / f, 0.0  # skew
        dyn = -yn / fy
        A0[4], A1[4] = -s * dyn / f, dyn  # fy
        U0[0], U1[0] = ex * r2, ey * r2
        U0[1], U1[1] = ex * r4, ey * r4
        U0[2], U1[2] = ex * r4 * r2, ey * r4 * r2
        U0[3], U1[3] = r2 + 2 * ex * ex, 2 * ex * ey
        U0[4], U1[4] = 2 * ex * ey, r2 + 2 * ey * ey
        for j in range(2):  # PSD terms act through u = d s: dx/dl = (I + G) d h2^(j+1)
            hp = h2 if j == 0 else h2 * h2
            U0[5 + j] = (1 + G00) * d0 * hp + G01 * d1 * hp
            U1[5 + j] = G10 * d0 * hp + (1 + G11) * d1 * hp
        for j in range(7):
            A0[5 + j], A1[5 + j] = a00 * U0[j] + a01 * U1[j], a11 * U1[j]
        for j in range(3):
            if has_gain:
                g0, g1 = dd_dg[i, 0, j], dd_dg[i, 1, j]
                A0[12 + j], A1[12 + j] = D00 * g0 + D01 * g1, D10 * g0 + D11 * g1
            else:
                A0[12 + j], A1[12 + j] = 0.0, 0.0
        for k in range(P):
            V0[k] = A0[codes[k]]
            V1[k] = A1[codes[k]]
            dn_dp[i, 0, k] = V0[k]
            dn_dp[i, 1, k] = V1[k]
        # cov_calib = dn_dp C dn_dp^T = |B^T v|^2 with C = B B^T (B lower triangular: half the products)
        c00 = c01 = c11 = 0.0
        for j in range(P):
            w0 = 0.0
            w1 = 0.0
            for k in range(j if lower else 0, P):
                bkj = B[k, j]
                w0 += V0[k] * bkj
                w1 += V1[k] * bkj
            c00 += w0 * w0
            c01 += w0 * w1
            c11 += w1 * w1
        covc[i, 0, 0], covc[i, 0, 1], covc[i, 1, 0], covc[i, 1, 1] = c00, c01, c01, c11
        if has_noise:
            s00, s01, s10, s11 = cov_d[i, 0, 0], cov_d[i, 0, 1], cov_d[i, 1, 0], cov_d[i, 1, 1]
            m00, m01 = D00 * s00 + D01 * s10, D00 * s01 + D01 * s11
            m10, m11 = D10 * s00 + D11 * s10, D10 * s01 + D11 * s11
            covn[i, 0, 0] = m00 * D00 + m01 * D01
            covn[i, 0, 1] = m00 * D10 + m01 * D11
            covn[i, 1, 0] = m10 * D00 + m11 * D01
            covn[i, 1, 1] = m10 * D10 + m11 * D11
    return x, n, alpha, covc, covn, dn_dp, dn_dd
