"""Compiled angles of arrival with their covariance, one pass over the points.

The same mathematics as the numpy reference
:func:`psdcal.measure.aoa.angles_from_points` (which stays the tested
reference): ``x = undistort(d)`` (Eq 7-16, explicit, no iteration),
``yn = (y - cy) / fy``, ``xn = (x - cx - s yn) / f`` (inverse of Eq 4),
``alpha = atan(n)`` (Eq 39), with the analytic derivatives of ``n`` by the
calibration parameters and by ``d``, and both covariances
``dn/dp C dn/dp^T`` and ``dn/dd Sigma_d dn/dd^T`` formed per point from
scalars (no (N, 2, n_params) temporaries).
"""
from __future__ import annotations

import math

import numpy as np

from psdcal._jit import njit
from psdcal.calibration._image_kernel import _model_terms

#: parameter codes of :func:`angles_kernel` (index into this tuple)
PARAM_CODES = ("f_mm", "cx_mm", "cy_mm", "skew", "fy_mm", "k1", "k2", "k3", "p1", "p2", "l1", "l2",
               "g_x2", "g_y1", "g_y2")


@njit
def angles_kernel(d, intr, separate_fy, coef, codes, C, cov_d, dd_dg):
    """Angles, normalised coordinates and covariances of impact points.

    Parameters
    ----------
    d : (N, 2) measured impact points, mm
    intr : (5,) f, cx, cy, skew, fy (mm; fy used when ``separate_fy``)
    coef : (7,) k1, k2, k3, p1, p2, l1, l2
    codes : (P,) int, :data:`PARAM_CODES` index of each calibration parameter (covariance order)
    C : (P, P) calibration covariance
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
    T0 = np.empty(P)
    T1 = np.empty(P)
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
        for k in range(P):
            c = codes[k]
            if c == 0:  # f
                if separate_fy:
                    v0, v1 = -xn / f, 0.0
                else:
                    v0, v1 = -xn / f + s * yn / (f * f), -yn / f
            elif c == 4:  # fy
                dyn = -yn / fy
                v0, v1 = -s * dyn / f, dyn
            elif c == 3:  # skew
                v0, v1 = -yn / f, 0.0
            elif c == 1:  # cx: dx/dc = -G
                v0, v1 = a00 * -G00 + a01 * -G10 - 1.0 / f, a11 * -G10
            elif c == 2:  # cy
                v0, v1 = a00 * -G01 + a01 * -G11 + s / (f * fy), a11 * -G11 - 1.0 / fy
            elif c <= 11:  # distortion coefficient
                j = c - 5
                if j == 0:
                    u0, u1 = ex * r2, ey * r2
                elif j == 1:
                    u0, u1 = ex * r4, ey * r4
                elif j == 2:
                    u0, u1 = ex * r4 * r2, ey * r4 * r2
                elif j == 3:
                    u0, u1 = r2 + 2 * ex * ex, 2 * ex * ey
                elif j == 4:
                    u0, u1 = 2 * ex * ey, r2 + 2 * ey * ey
                else:  # PSD terms act through u = d s: dx/dl = (I + G) d h2^(j-4)
                    hp = h2 if j == 5 else h2 * h2
                    u0 = (1 + G00) * d0 * hp + G01 * d1 * hp
                    u1 = G10 * d0 * hp + (1 + G11) * d1 * hp
                v0, v1 = a00 * u0 + a01 * u1, a11 * u1
            else:  # gain ratio
                if has_gain:
                    g0, g1 = dd_dg[i, 0, c - 12], dd_dg[i, 1, c - 12]
                    v0, v1 = D00 * g0 + D01 * g1, D10 * g0 + D11 * g1
                else:
                    v0, v1 = 0.0, 0.0
            dn_dp[i, 0, k] = v0
            dn_dp[i, 1, k] = v1
        # cov_calib = dn_dp C dn_dp^T
        for k in range(P):
            t0 = 0.0
            t1 = 0.0
            for m in range(P):
                ckm = C[k, m]
                t0 += dn_dp[i, 0, m] * ckm
                t1 += dn_dp[i, 1, m] * ckm
            T0[k], T1[k] = t0, t1
        c00 = c01 = c11 = 0.0
        for k in range(P):
            c00 += T0[k] * dn_dp[i, 0, k]
            c01 += T0[k] * dn_dp[i, 1, k]
            c11 += T1[k] * dn_dp[i, 1, k]
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
