"""The verdict's distortion evaluations compiled: the angles' sensitivities and the one-to-one test.

Two numpy functions of the verdict spend their time in numpy's per-call cost
(some forty array operations on 49 or 960 points):
:func:`psdcal.calibration._verdict_linear.angle_jacobians` (the forward
distortion :func:`psdcal.model.distortion.undistort` with its Jacobians on
the angle grid) and :func:`psdcal.calibration._verdict_rules._monotonic`
(the undistorted radius along rays from C). The kernels below are the same
arithmetic in scalar loops (Eq 7-16, docs/model.md#distortion: the one-to-one
test evaluates the model's compiled point, :mod:`psdcal.model._point_kernel`;
the Jacobians keep the numpy code's order of operations, to the bit for the
points); the numpy functions stay the reference, and the tests
compare the two (the points and Jacobians to rounding, the test's answer
exactly). They are used where the calibration's compiled kernels are
(:func:`psdcal._jit.use_compiled`): the command line's small problems never
load them.
"""
from __future__ import annotations

import numpy as np

from psdcal._jit import njit
from psdcal.model._point_kernel import _model_terms


@njit
def undistort_jacobians(d, coeffs, c):
    """:func:`~psdcal.model.distortion.undistort` with ``jacobians=True`` of the points ``d`` (K, 2) mm under the
    seven coefficients ``coeffs`` (k1, k2, k3, p1, p2, l1, l2) about the centre ``c`` (2,) mm: ``x`` (K, 2),
    ``dx_dd`` (K, 2, 2), ``dx_dc`` (K, 2, 2), ``dx_dcoef`` (K, 2, 7)."""
    k1, k2, k3, p1, p2, l1, l2 = coeffs[0], coeffs[1], coeffs[2], coeffs[3], coeffs[4], coeffs[5], coeffs[6]
    n = d.shape[0]
    x = np.empty((n, 2))
    dx_dd = np.empty((n, 2, 2))
    dx_dc = np.empty((n, 2, 2))
    dx_dcoef = np.zeros((n, 2, 7))
    for i in range(n):
        d0 = d[i, 0]
        d1 = d[i, 1]
        h2 = d0 * d0 + d1 * d1
        s = 1.0 + l1 * h2 + l2 * h2 * h2
        u0 = d0 * s
        u1 = d1 * s
        ex = u0 - c[0]
        ey = u1 - c[1]
        r2 = ex * ex + ey * ey
        rad = r2 * (k1 + r2 * (k2 + r2 * k3))
        tx = p1 * (r2 + 2 * ex * ex) + 2 * p2 * ex * ey
        ty = p2 * (r2 + 2 * ey * ey) + 2 * p1 * ex * ey
        x[i, 0] = u0 + ex * rad + tx
        x[i, 1] = u1 + ey * rad + ty
        g = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))
        G00 = rad + g * (ex * ex) + (6 * p1 * ex + 2 * p2 * ey)
        G01 = g * (ex * ey) + (2 * p1 * ey + 2 * p2 * ex)
        G10 = g * (ey * ex) + (2 * p2 * ex + 2 * p1 * ey)
        G11 = rad + g * (ey * ey) + (6 * p2 * ey + 2 * p1 * ex)
        a00 = 1.0 + G00
        a11 = 1.0 + G11
        gs = 2 * (l1 + 2 * l2 * h2)
        b00 = s + gs * (d0 * d0)
        b01 = gs * (d0 * d1)
        b10 = gs * (d1 * d0)
        b11 = s + gs * (d1 * d1)
        dx_dd[i, 0, 0] = a00 * b00 + G01 * b10
        dx_dd[i, 0, 1] = a00 * b01 + G01 * b11
        dx_dd[i, 1, 0] = G10 * b00 + a11 * b10
        dx_dd[i, 1, 1] = G10 * b01 + a11 * b11
        dx_dc[i, 0, 0] = -G00
        dx_dc[i, 0, 1] = -G01
        dx_dc[i, 1, 0] = -G10
        dx_dc[i, 1, 1] = -G11
        r4 = r2 * r2
        r6 = r2 * r2 * r2
        dx_dcoef[i, 0, 0] = ex * r2
        dx_dcoef[i, 1, 0] = ey * r2
        dx_dcoef[i, 0, 1] = ex * r4
        dx_dcoef[i, 1, 1] = ey * r4
        dx_dcoef[i, 0, 2] = ex * r6
        dx_dcoef[i, 1, 2] = ey * r6
        dx_dcoef[i, 0, 3] = r2 + 2 * ex * ex
        dx_dcoef[i, 1, 3] = 2 * ex * ey
        dx_dcoef[i, 0, 4] = 2 * ex * ey
        dx_dcoef[i, 1, 4] = r2 + 2 * ey * ey
        q0 = d0 * h2
        q1 = d1 * h2
        dx_dcoef[i, 0, 5] = a00 * q0 + G01 * q1
        dx_dcoef[i, 1, 5] = G10 * q0 + a11 * q1
        h4 = h2 * h2
        q0 = d0 * h4
        q1 = d1 * h4
        dx_dcoef[i, 0, 6] = a00 * q0 + G01 * q1
        dx_dcoef[i, 1, 6] = G10 * q0 + a11 * q1
    return x, dx_dd, dx_dc, dx_dcoef


@njit
def monotonic(coeffs, c, lim, rad, dirs):
    """Whether the undistorted radius grows along each ray ``c + rad[j] dirs[i]`` (``rad`` (n_r,) mm increasing,
    ``dirs`` (n_dir, 2) unit) between consecutive points inside the sensor (``|d_k| <= lim[k]``), and is finite
    at every point inside: :func:`~psdcal.calibration._verdict_rules._monotonic`'s test."""
    for i in range(dirs.shape[0]):
        prev_in = False
        prev = 0.0
        for j in range(rad.shape[0]):
            d0 = c[0] + rad[j] * dirs[i, 0]
            d1 = c[1] + rad[j] * dirs[i, 1]
            inside = abs(d0) <= lim[0] and abs(d1) <= lim[1]
            if not inside:
                prev_in = False
                continue
            x0, x1, _, _, _, _, _, _, _, _, _, _, _ = _model_terms(d0, d1, coeffs, c[0], c[1])  # the model's point
            proj = (x0 - c[0]) * dirs[i, 0] + (x1 - c[1]) * dirs[i, 1]
            if not np.isfinite(proj):
                return False
            if prev_in and not (proj - prev > 0):
                return False
            prev_in = True
            prev = proj
    return True


@njit
def field_parts(pts, c, half, degree):
    """:func:`psdcal.calibration._verdict_linear.field_parts`'s arrays: the monomials ``u^i v^j`` (i + j <=
    ``degree``, in the order i, then j) of ``u = pts / half`` (N, n_mono), and the radial fields ``d r^4``,
    ``d r^6`` of ``d = (pts - c) / half`` (2N, 2), rows (x0, y0, x1, ...)."""
    n = pts.shape[0]
    n_mono = (degree + 1) * (degree + 2) // 2
    mono = np.empty((n, n_mono))
    R = np.empty((2 * n, 2))
    pu = np.empty(degree + 1)
    pv = np.empty(degree + 1)
    for k in range(n):
        u0 = pts[k, 0] / half[0]
        u1 = pts[k, 1] / half[1]
        pu[0] = 1.0
        pv[0] = 1.0
        for q in range(1, degree + 1):
            pu[q] = pu[q - 1] * u0
            pv[q] = pv[q - 1] * u1
        col = 0
        for i in range(degree + 1):
            for j in range(degree + 1 - i):
                mono[k, col] = pu[i] * pv[j]
                col += 1
        d0 = (pts[k, 0] - c[0]) / half[0]
        d1 = (pts[k, 1] - c[1]) / half[1]
        r2 = d0 * d0 + d1 * d1
        r4 = r2 * r2
        r6 = r2 * r2 * r2
        R[2 * k, 0] = d0 * r4
        R[2 * k + 1, 0] = d1 * r4
        R[2 * k, 1] = d0 * r6
        R[2 * k + 1, 1] = d1 * r6
    return mono, R


@njit
def _angle_chain(x, dx_dd, dx_dc, dx_dcoef, c, f, fy, sk, src, col, dc, dsk, df, dfy):
    """The chain rule of :func:`psdcal.calibration._verdict_linear.angle_jacobians` (the same operations in the
    same order): parameter k moves x by nothing (``src[k]`` 0), by ``dx_dc[:, :, col[k]]`` (1) or by
    ``dx_dcoef[:, :, col[k]]`` (2), and C by ``dc[k]`` (2,), skew by ``dsk[k]``, f by ``df[k]``, fy by ``dfy[k]``."""
    K = x.shape[0]
    n = src.shape[0]
    A = np.empty((2 * K, n))
    D = np.empty((K, 2, 2))
    for i in range(K):
        ty = (x[i, 1] - c[1]) / fy
        tx = (x[i, 0] - c[0] - sk * ty) / f
        wx = 1.0 / (1.0 + tx * tx)
        wy = 1.0 / (1.0 + ty * ty)
        for k in range(n):
            dx0 = 0.0
            dx1 = 0.0
            if src[k] == 1:
                dx0 = dx_dc[i, 0, col[k]]
                dx1 = dx_dc[i, 1, col[k]]
            elif src[k] == 2:
                dx0 = dx_dcoef[i, 0, col[k]]
                dx1 = dx_dcoef[i, 1, col[k]]
            dty = (dx1 - dc[k, 1] - ty * dfy[k]) / fy
            A[2 * i, k] = wx * ((dx0 - dc[k, 0] - dsk[k] * ty - sk * dty - tx * df[k]) / f)
            A[2 * i + 1, k] = wy * dty
        for j in range(2):
            dty = dx_dd[i, 1, j] / fy
            D[i, 0, j] = wx * ((dx_dd[i, 0, j] - sk * dty) / f)
            D[i, 1, j] = wy * dty
    return A, D


def angle_jacobians(result, d_mm, names):
    """:func:`psdcal.calibration._verdict_linear.angle_jacobians` (the same arguments and returns) from the kernels
    above."""
    from psdcal.model.params import DISTORTION_NAMES

    intr = result.intrinsics
    c = np.array([intr.cx_mm, intr.cy_mm], dtype=float)
    x, dx_dd, dx_dc, dx_dcoef = undistort_jacobians(d_mm, result.distortion.as_array(), c)
    n = len(names)
    src = np.zeros(n, dtype=np.int64)
    col = np.zeros(n, dtype=np.int64)
    dc = np.zeros((n, 2))
    dsk, df, dfy = np.zeros(n), np.zeros(n), np.zeros(n)
    for k, nm in enumerate(names):
        if nm == "f_mm":
            df[k] = 1.0
            dfy[k] = 1.0 if intr.fy_mm is None else 0.0
        elif nm == "fy_mm":
            dfy[k] = 1.0
        elif nm in ("cx_mm", "cy_mm"):
            j = 0 if nm == "cx_mm" else 1
            src[k], col[k], dc[k, j] = 1, j, 1.0
        elif nm == "skew":
            dsk[k] = 1.0
        elif nm in DISTORTION_NAMES:
            src[k], col[k] = 2, DISTORTION_NAMES.index(nm)
    return _angle_chain(x, dx_dd, dx_dc, dx_dcoef, c, float(intr.f_mm), float(intr.fy), float(intr.skew), src, col,
                        dc, dsk, df, dfy)
