"""Compiled impact points with their noise covariance and gain derivatives, one pass over the rows.

The same mathematics as :func:`psdcal.measure.aoa.impact_from_amplitudes` (the
numpy reference, tested against): the channels divided by the gains,
``d = L/2 (N . v) / sum(v)`` (Eq 1-2), ``dd/dv``, the covariance
``dd/da diag(var a) dd/da^T`` and ``dd/dg``; a row whose gain-corrected sum is
not positive (or not finite) gives NaN.  ``psdcal locate`` turns its batches of
rows into impact points with it: numpy's version is some thirty array
operations on (n, 2, 4) temporaries.  The sums are in another order than
numpy's matrix products: equal to rounding (the tests bound it).
"""
from __future__ import annotations

import numpy as np

from psdcal._jit import njit


@njit
def impact_rows(a, g, var_a, lx, ly, d, cov, dd_dg, bad):  # pragma: no cover - compiled
    """Rows ``a`` (n, 4), gains ``g`` (4,), variances ``var_a`` (n, 4) -> ``d`` (n, 2), ``cov`` (n, 2, 2),
    ``dd_dg`` (n, 2, 3) (by ``g_x2, g_y1, g_y2``) and ``bad`` (n,) (NaN rows)."""
    n = a.shape[0]
    hx = 0.5 * lx
    hy = 0.5 * ly
    for r in range(n):
        v0 = a[r, 0] / g[0]
        v1 = a[r, 1] / g[1]
        v2 = a[r, 2] / g[2]
        v3 = a[r, 3] / g[3]
        s = ((v0 + v1) + v2) + v3
        mx = max(max(abs(v0), abs(v1)), max(abs(v2), abs(v3)))
        fin = (v0 - v0 == 0.0) and (v1 - v1 == 0.0) and (v2 - v2 == 0.0) and (v3 - v3 == 0.0)
        if not (s > 1e-12 * mx) or not fin:
            bad[r] = True
            d[r, 0] = d[r, 1] = np.nan
            for i in range(2):
                for j in range(2):
                    cov[r, i, j] = np.nan
                for j in range(3):
                    dd_dg[r, i, j] = np.nan
            continue
        bad[r] = False
        nx = ((-v0 + v1) + v2) - v3
        ny = ((-v0 + v1) - v2) + v3
        ux = nx / s
        uy = ny / s
        d[r, 0] = hx * nx / s
        d[r, 1] = hy * ny / s
        # dd/dv = L/2 (N - (N . v)/s) / s
        x0 = hx * (-1.0 - ux) / s
        x1 = hx * (1.0 - ux) / s
        x2 = hx * (1.0 - ux) / s
        x3 = hx * (-1.0 - ux) / s
        y0 = hy * (-1.0 - uy) / s
        y1 = hy * (1.0 - uy) / s
        y2 = hy * (-1.0 - uy) / s
        y3 = hy * (1.0 - uy) / s
        # dd/dg_i = dd/dv_i (-v_i / g_i), i = 1, 2, 3
        w1 = -v1 / g[1]
        w2 = -v2 / g[2]
        w3 = -v3 / g[3]
        dd_dg[r, 0, 0] = x1 * w1
        dd_dg[r, 0, 1] = x2 * w2
        dd_dg[r, 0, 2] = x3 * w3
        dd_dg[r, 1, 0] = y1 * w1
        dd_dg[r, 1, 1] = y2 * w2
        dd_dg[r, 1, 2] = y3 * w3
        # cov = dd/da diag(var) dd/da^T, dd/da = dd/dv / g
        ax0, ax1, ax2, ax3 = x0 / g[0], x1 / g[1], x2 / g[2], x3 / g[3]
        ay0, ay1, ay2, ay3 = y0 / g[0], y1 / g[1], y2 / g[2], y3 / g[3]
        s0, s1, s2, s3 = var_a[r, 0], var_a[r, 1], var_a[r, 2], var_a[r, 3]
        cxx = ax0 * s0 * ax0 + ax1 * s1 * ax1 + ax2 * s2 * ax2 + ax3 * s3 * ax3
        cxy = ax0 * s0 * ay0 + ax1 * s1 * ay1 + ax2 * s2 * ay2 + ax3 * s3 * ay3
        cyy = ay0 * s0 * ay0 + ay1 * s1 * ay1 + ay2 * s2 * ay2 + ay3 * s3 * ay3
        cov[r, 0, 0] = cxx
        cov[r, 0, 1] = cxy
        cov[r, 1, 0] = cxy
        cov[r, 1, 1] = cyy


def impact_compiled(a: np.ndarray, gains: np.ndarray, var_a: np.ndarray, lx_mm: float, ly_mm: float):
    """``(d, cov, dd_dg, bad)`` of rows ``a`` (n, 4) by :func:`impact_rows`."""
    n = a.shape[0]
    d = np.empty((n, 2))
    cov = np.empty((n, 2, 2))
    dd_dg = np.empty((n, 2, 3))
    bad = np.empty(n, dtype=np.bool_)
    impact_rows(np.ascontiguousarray(a, dtype=float), np.ascontiguousarray(gains, dtype=float),
                np.ascontiguousarray(var_a, dtype=float), float(lx_mm), float(ly_mm), d, cov, dd_dg, bad)
    return d, cov, dd_dg, bad


@njit
def channel_sum_rows(a, var_a, g, acc):  # pragma: no cover - compiled
    """The sums of :meth:`psdcal.measure.channel_order.SumCheck.add` over rows ``a``, ``var_a`` (n, 4).

    ``acc`` (16,) receives: [0] the rows used, [1] sum D^2 / var D, [2:5] sum J^T D / var D,
    [5:14] sum J^T J / var D (3 x 3, row-major), [14] sum D^2, [15] max |D| (the numpy code of
    ``SumCheck.add`` is the reference).
    """
    n = a.shape[0]
    acc[:] = 0.0
    for r in range(n):
        v0 = a[r, 0] / g[0]
        v1 = a[r, 1] / g[1]
        v2 = a[r, 2] / g[2]
        v3 = a[r, 3] / g[3]
        w0 = var_a[r, 0] / g[0] ** 2
        w1 = var_a[r, 1] / g[1] ** 2
        w2 = var_a[r, 2] / g[2] ** 2
        w3 = var_a[r, 3] / g[3] ** 2
        sx = v0 + v1
        sy = v2 + v3
        s = sx + sy
        d = (sx - sy) / s
        var_d = 4.0 * (sy ** 2 * (w0 + w1) + sx ** 2 * (w2 + w3)) / s ** 4
        s2 = s ** 2
        j1 = (2 * sy / s2) * (-v1 / g[1])
        j2 = (-2 * sx / s2) * (-v2 / g[2])
        j3 = (-2 * sx / s2) * (-v3 / g[3])
        if not (d - d == 0.0 and var_d - var_d == 0.0 and var_d > 0 and s > 0 and j1 - j1 == 0.0
                and j2 - j2 == 0.0 and j3 - j3 == 0.0):
            continue
        acc[0] += 1.0
        acc[1] += d * d / var_d
        q = d / var_d
        acc[2] += j1 * q
        acc[3] += j2 * q
        acc[4] += j3 * q
        k1 = j1 / var_d
        k2 = j2 / var_d
        k3 = j3 / var_d
        acc[5] += k1 * j1
        acc[6] += k1 * j2
        acc[7] += k1 * j3
        acc[8] += k2 * j1
        acc[9] += k2 * j2
        acc[10] += k2 * j3
        acc[11] += k3 * j1
        acc[12] += k3 * j2
        acc[13] += k3 * j3
        acc[14] += d * d
        ad = abs(d)
        if ad > acc[15]:
            acc[15] = ad
