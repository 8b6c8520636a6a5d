"""Compiled image-plane cost: residuals and Jacobian in a few short passes over the points.

The same mathematics as the numpy reference in :mod:`psdcal.calibration._refine`
(``Evaluator._image``), :mod:`psdcal.model.distortion` (``undistort``, ``distort``,
``distort_jacobians``) and :func:`psdcal.calibration._refine.rodrigues_batch`, written as
scalar loops for numba (:mod:`psdcal._jit`). For each observation ``i`` of
view ``v``:

- ``Pc = R_v [X, Y, 0]^T + t_v`` (Rodrigues rotation; Eq 3 of the paper);
- ideal point ``x = (f xn + s yn + cx, fy yn + cy)``, ``xn = Pc_x / Pc_z``
  (Eq 4);
- measured point ``d`` with ``undistort(d) = x`` by Newton's method
  (Eq 7-16 inverted, docs/model.md#distortion), from a warm start, then from the measured
  point, then from a fixed-point start, the first that converges;
- the Jacobian of ``d`` with respect to (f, cx, cy, skew, fy, k1, k2, k3,
  p1, p2, l1, l2) and the view's (r, t) from the implicit function theorem,
  ``dd/dtheta = -(dx/dd)^-1 dx/dtheta``.

The Jacobian's global columns are chosen by ``gmap`` (index into the 12
derivatives above, in that order). It is returned in *compact block form*
(2N, n_global + 6): the global columns, then the six (r, t) columns of the
row's own view; in the dense Jacobian these six sit at ``n_global + 6 v`` and
all other pose entries of the row are zero (:func:`expand_compact`).

The normal equations of such a Jacobian are kept in blocks
(:func:`psdcal.calibration._gram_kernel.gram_block_normal`) and solved through the Schur
complement of the pose blocks (:mod:`psdcal.calibration._schur_kernel`).
"""
from __future__ import annotations

import math

import numpy as np

from psdcal._jit import njit, njit_inline
from psdcal.model._point_kernel import _model_terms as _model_terms_kernel

#: the model's point (psdcal.model._point_kernel._model_terms, the same function) inlined into the kernels here:
#: the per-point calls of the Newton inverse and the Jacobian cost no call and no passing of ``coef``
_model_terms = njit_inline(getattr(_model_terms_kernel, "py_func", _model_terms_kernel))

#: order of the global derivatives the kernel computes (``gmap`` indexes it)
GLOBAL_ORDER = ("f_mm", "cx_mm", "cy_mm", "skew", "fy_mm", "k1", "k2", "k3", "p1", "p2", "l1", "l2",
                "g_x1", "g_x2", "g_y1", "g_y2")


@njit
def _rotations(rv, want_d):
    """R (n, 3, 3) and dR (n, 3, 3, 3) (dR[v, k] = dR/dr_k) of rotation vectors rv (n, 3)."""
    n = rv.shape[0]
    R = np.zeros((n, 3, 3))
    dR = np.zeros((n, 3, 3, 3))
    K = np.zeros((3, 3))
    W = np.zeros((3, 3))
    for v in range(n):
        r0, r1, r2 = rv[v, 0], rv[v, 1], rv[v, 2]
        th2 = r0 * r0 + r1 * r1 + r2 * r2
        th = math.sqrt(th2)
        small = th < 1e-12
        if small:
            A, B = 1.0, 0.5
        else:
            A = math.sin(th) / th
            B = (1.0 - math.cos(th)) / th2
        K[0, 0], K[0, 1], K[0, 2] = 0.0, -r2, r1
        K[1, 0], K[1, 1], K[1, 2] = r2, 0.0, -r0
        K[2, 0], K[2, 1], K[2, 2] = -r1, r0, 0.0
        for i in range(3):
            for j in range(3):
                kk = K[i, 0] * K[0, j] + K[i, 1] * K[1, j] + K[i, 2] * K[2, j]
                R[v, i, j] = (1.0 if i == j else 0.0) + A * K[i, j] + B * kk
        if not want_d:
            continue
        for k in range(3):
            if small:
                e0 = 1.0 if k == 0 else 0.0
                e1 = 1.0 if k == 1 else 0.0
                e2 = 1.0 if k == 2 else 0.0
                dR[v, k, 0, 1], dR[v, k, 0, 2] = -e2, e1
                dR[v, k, 1, 0], dR[v, k, 1, 2] = e2, -e0
                dR[v, k, 2, 0], dR[v, k, 2, 1] = -e1, e0
                continue
            # w = r x (I - R)[:, k]
            a0 = (1.0 if k == 0 else 0.0) - R[v, 0, k]
            a1 = (1.0 if k == 1 else 0.0) - R[v, 1, k]
            a2 = (1.0 if k == 2 else 0.0) - R[v, 2, k]
            w0 = r1 * a2 - r2 * a1
            w1 = r2 * a0 - r0 * a2
            w2 = r0 * a1 - r1 * a0
            W[0, 0], W[0, 1], W[0, 2] = 0.0, -w2, w1
            W[1, 0], W[1, 1], W[1, 2] = w2, 0.0, -w0
            W[2, 0], W[2, 1], W[2, 2] = -w1, w0, 0.0
            rk = rv[v, k]
            for i in range(3):
                for j in range(3):
                    acc = 0.0
                    for m in range(3):
                        acc += (rk * K[i, m] + W[i, m]) * R[v, m, j]
                    dR[v, k, i, j] = acc / th2
    return R, dR



@njit_inline
def _undistort_point(dx, dy, coef, cx, cy):
    """x = undistort(d) and dx/dd = (I + G) U (Eq 7-16) of one point; returns (x0, x1, J00, J01, J10, J11)."""
    x0, x1, _, _, _, _, G00, G01, G10, G11, U00, U01, U11 = _model_terms(dx, dy, coef, cx, cy)
    return (x0, x1, (1 + G00) * U00 + G01 * U01, (1 + G00) * U01 + G01 * U11,
            G10 * U00 + (1 + G11) * U01, G10 * U01 + (1 + G11) * U11)


@njit_inline
def _monotone(dx, dy, coef, cx, cy):
    """Whether d lies on the branch of the model that starts at the centre (distortion._on_monotone_branch)."""
    k1, k2, k3, l1, l2 = coef[0], coef[1], coef[2], coef[5], coef[6]
    h2 = dx * dx + dy * dy
    s_psd = 1 + h2 * (l1 + l2 * h2)
    ds_psd = 1 + h2 * (3 * l1 + 5 * l2 * h2)
    ex, ey = dx * s_psd - cx, dy * s_psd - cy
    r2 = ex * ex + ey * ey
    s_lens = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    ds_lens = 1 + r2 * (3 * k1 + r2 * (5 * k2 + 7 * r2 * k3))
    return s_psd > 0 and ds_psd > 0 and s_lens > 0 and ds_lens > 0


@njit_inline
def _newton(x0, x1, sx, sy, coef, cx, cy, tol, max_iter):
    """d with undistort(d) = x from the start (sx, sy); as :func:`psdcal.model.distortion.distort`.

    Returns (d0, d1, converged).
    """
    d0, d1 = sx, sy
    prev = math.inf
    st0 = st1 = 0.0
    err = math.inf
    det = 0.0
    for it in range(max_iter + 1):
        a0, a1, J00, J01, J10, J11 = _undistort_point(d0, d1, coef, cx, cy)
        r0, r1 = a0 - x0, a1 - x1
        e = math.sqrt(r0 * r0 + r1 * r1)
        if not (e < prev) and prev < math.inf:
            # the last step made things worse: take back half of it
            st0 *= 0.5
            st1 *= 0.5
            d0 += st0
            d1 += st1
            if max(abs(st0), abs(st1)) <= 1e-16:
                prev = math.inf  # give up backtracking, accept the next point
            continue
        err = e
        det = J00 * J11 - J01 * J10
        if e <= tol or not math.isfinite(e) or it == max_iter:
            break
        st0 = (J11 * r0 - J01 * r1) / det
        st1 = (-J10 * r0 + J00 * r1) / det
        prev = e
        d0 -= st0
        d1 -= st1
        smax = max(abs(st0), abs(st1))
        if smax <= 0.3 * math.sqrt(tol):
            # quadratic convergence: the remaining error is about kappa s^2 < tol / 10
            err = smax * smax
            break
    ok = math.isfinite(err) and err <= 10 * tol and det > 0 and _monotone(d0, d1, coef, cx, cy)
    return d0, d1, ok


@njit_inline
def _fixed_point_start(x0, x1, coef, cx, cy):
    """Start of the Newton inverse: a few fixed-point steps of the lens radial part about c."""
    k1, k2, k3 = coef[0], coef[1], coef[2]
    d0, d1 = x0, x1
    e0, e1 = x0 - cx, x1 - cy
    for _ in range(3):
        f0, f1 = d0 - cx, d1 - cy
        rr = f0 * f0 + f1 * f1
        den = 1.0 + rr * (k1 + rr * (k2 + rr * k3))
        c0 = cx + e0 / den
        c1 = cy + e1 / den
        if math.isfinite(c0) and math.isfinite(c1):
            d0, d1 = c0, c1
    return d0, d1


@njit
def _newton_sweeps(X0, X1, TOL, D0, D1, coef, cx, cy, max_iter, CONV):
    """:func:`_newton` of every point at once, from the starts ``D0``, ``D1`` (N,) (overwritten by the results; ``CONV``
    (N,) bool the converged flags): one Newton iteration of every point still iterating per sweep, the same
    operations in the same order as :func:`_newton` point by point (so the same bits), but a short loop over the
    points whose independent iterations the processor overlaps."""
    N = X0.shape[0]
    PREV = np.full(N, math.inf)
    ST0 = np.zeros(N)
    ST1 = np.zeros(N)
    ERR = np.full(N, math.inf)
    DET = np.zeros(N)
    act = np.arange(N)
    nact = N
    for it in range(max_iter + 1):
        m = 0
        for q in range(nact):
            i = act[q]
            d0, d1, prev = D0[i], D1[i], PREV[i]
            x0, x1, tol = X0[i], X1[i], TOL[i]
            a0, a1, J00, J01, J10, J11 = _undistort_point(d0, d1, coef, cx, cy)
            r0, r1 = a0 - x0, a1 - x1
            e = math.sqrt(r0 * r0 + r1 * r1)
            if not (e < prev) and prev < math.inf:
                st0 = ST0[i] * 0.5
                st1 = ST1[i] * 0.5
                ST0[i], ST1[i] = st0, st1
                D0[i], D1[i] = d0 + st0, d1 + st1
                if max(abs(st0), abs(st1)) <= 1e-16:
                    PREV[i] = math.inf
                act[m] = i
                m += 1
                continue
            ERR[i] = e
            DET[i] = J00 * J11 - J01 * J10
            if e <= tol or not math.isfinite(e) or it == max_iter:
                continue
            det = DET[i]
            st0 = (J11 * r0 - J01 * r1) / det
            st1 = (-J10 * r0 + J00 * r1) / det
            ST0[i], ST1[i] = st0, st1
            PREV[i] = e
            D0[i], D1[i] = d0 - st0, d1 - st1
            smax = max(abs(st0), abs(st1))
            if smax <= 0.3 * math.sqrt(tol):
                ERR[i] = smax * smax
                continue
            act[m] = i
            m += 1
        nact = m
        if nact == 0:
            break
    for i in range(N):
        err = ERR[i]
        CONV[i] = math.isfinite(err) and err <= 10 * TOL[i] and DET[i] > 0 and _monotone(D0[i], D1[i], coef, cx, cy)


@njit
def image_model(P, img, theta, separate_fy, poses, warm, meas, gmap, want_jac, tol_mm, max_iter, gain_basis):
    """Modelled measured points of all observations, and their Jacobian.

    Parameters
    ----------
    P : (N, 2) template point of each observation, mm
    img : (N,) int, view of each observation
    theta : (16,) the global parameters in the order of :data:`GLOBAL_ORDER`:
        f, cx, cy (mm), skew, fy (mm, used only when ``separate_fy``), k1, k2, k3, p1, p2, l1, l2,
        and the four channel gains (used only with ``gain_basis``)
    poses : (n, 6) rotation vector and translation (mm) of each view
    warm : (N, 2) warm start of the Newton inverse (NaN: none), mm
    meas : (N, 2) measured points (the second start), mm
    gmap : (n_global,) int, column k of the Jacobian is derivative ``GLOBAL_ORDER[gmap[k]]``
    want_jac : bool
    tol_mm, max_iter : of the Newton inverse, as :func:`psdcal.model.distortion.distort`
    gain_basis : (4, 3, 3) or (0, 3, 3)
        With four matrices, the readout through unequal channel gains is
        modelled: ``y ~ H [d, 1]`` with ``H = sum_j g_j gain_basis[j]``
        (:func:`psdcal.model.readout.gain_homography` is linear in the gains; the
        basis is its value at the unit vectors). Empty: ``y = d``.

    Returns
    -------
    d : (N, 2) spot positions (before the gain readout), mm (the last iterate where the inverse failed)
    ok : (N,) bool, the inverse converged
    y : (N, 2) modelled measured points (``d`` itself without gains), mm
    J : (2N, n_global + 6) Jacobian of y in compact block form (rows x0, y0, x1, ...): the
        global columns, then the six (r, t) columns of the row's own view ``img[i]`` (all other
        pose columns are zero; :func:`expand_compact` gives the dense matrix); (0, 0) without ``want_jac``
    """
    N = P.shape[0]
    d = np.empty((N, 2))
    y = np.empty((N, 2)) if gain_basis.shape[0] == 4 else d
    ok = np.empty(N, dtype=np.bool_)
    J = np.empty((2 * N, gmap.shape[0] + 6)) if want_jac else np.zeros((0, 0))  # every entry is written
    image_model_into(P, img, theta, separate_fy, poses, warm, meas, gmap, want_jac, tol_mm, max_iter, gain_basis,
                     d, ok, y, J)
    return d, ok, y, J


@njit
def image_model_into(P, img, theta, separate_fy, poses, warm, meas, gmap, want_jac, tol_mm, max_iter, gain_basis,
                     d, ok, y, J):
    """:func:`image_model` into given arrays (the LM loop's buffers, reused from one evaluation to the next).

    ``d`` (N, 2), ``ok`` (N,) bool, ``y`` (N, 2) (``d`` itself without gains) and, with ``want_jac``,
    ``J`` (2N, n_global + 6) are overwritten entirely (the values of :func:`image_model`, bit for bit).
    The derivatives of the PSD terms l1, l2 (Eq 7-10) are computed only when ``gmap`` asks for one of them.

    The points go through short loops in turn, each of which the processor runs several points at a time
    (one long loop body per point would leave each point's chain of dependent operations waiting): the
    projections and first starts, the Newton inverses from those starts (:func:`_newton_sweeps`), the other
    starts of the points whose inverse failed, the undistortion Jacobians at ``d``, then the rows.
    """
    N = P.shape[0]
    ng = gmap.shape[0]
    R, dR = _rotations(poses[:, :3], want_jac)
    tv = poses[:, 3:]
    f, cx, cy, sk = theta[0], theta[1], theta[2], theta[3]
    fy = theta[4] if separate_fy else f
    coef = theta[5:12]
    gains_on = gain_basis.shape[0] == 4
    Hg = np.zeros((3, 3))
    if gains_on:
        for j in range(4):
            Hg += theta[12 + j] * gain_basis[j]
    psd_free = False
    for k in range(ng):
        if gmap[k] == 10 or gmap[k] == 11:
            psd_free = True
    D = np.zeros((2, 16))
    PRJ = np.empty((N, 3))  # xn, yn, pcz of each point
    X0 = np.empty(N)
    X1 = np.empty(N)
    TOL = np.empty(N)
    D0 = np.empty(N)
    D1 = np.empty(N)
    CONV = np.empty(N, dtype=np.bool_)
    for i in range(N):
        v = img[i]
        X, Y = P[i, 0], P[i, 1]
        pcx = R[v, 0, 0] * X + R[v, 0, 1] * Y + tv[v, 0]
        pcy = R[v, 1, 0] * X + R[v, 1, 1] * Y + tv[v, 1]
        pcz = R[v, 2, 0] * X + R[v, 2, 1] * Y + tv[v, 2]
        xn, yn = pcx / pcz, pcy / pcz
        x0 = f * xn + sk * yn + cx  # Eq 4
        x1 = fy * yn + cy
        PRJ[i, 0], PRJ[i, 1], PRJ[i, 2] = xn, yn, pcz
        X0[i], X1[i] = x0, x1
        TOL[i] = tol_mm * max(1.0, math.sqrt(x0 * x0 + x1 * x1))
        if math.isfinite(warm[i, 0]) and math.isfinite(warm[i, 1]):
            D0[i], D1[i] = warm[i, 0], warm[i, 1]
        else:
            D0[i], D1[i] = _fixed_point_start(x0, x1, coef, cx, cy)
    _newton_sweeps(X0, X1, TOL, D0, D1, coef, cx, cy, max_iter, CONV)
    for i in range(N):
        if not CONV[i]:  # the other starts, point by point
            x0, x1, tol = X0[i], X1[i], TOL[i]
            for attempt in range(1, 3):
                if attempt == 1:
                    s0, s1 = meas[i, 0], meas[i, 1]
                else:
                    s0, s1 = _fixed_point_start(x0, x1, coef, cx, cy)
                d0, d1, conv = _newton(x0, x1, s0, s1, coef, cx, cy, tol, max_iter)
                if conv:
                    break
            D0[i], D1[i], CONV[i] = d0, d1, conv
    T = np.empty((N if want_jac else 0, 12))
    for i in range(T.shape[0]):
        # -- undistortion Jacobians at d (as distortion.undistort(..., jacobians=True))
        _, _, h2, ex, ey, r2, G00, G01, G10, G11, U00, U01, U11 = _model_terms(D0[i], D1[i], coef, cx, cy)
        A00 = (1 + G00) * U00 + G01 * U01  # dx/dd = (I + G) dU/dd
        A01 = (1 + G00) * U01 + G01 * U11
        A10 = G10 * U00 + (1 + G11) * U01
        A11 = G10 * U01 + (1 + G11) * U11
        det = A00 * A11 - A01 * A10
        T[i, 0], T[i, 1], T[i, 2], T[i, 3] = A11 / det, -A01 / det, -A10 / det, A00 / det  # dd/dx
        T[i, 4], T[i, 5], T[i, 6], T[i, 7] = G00, G01, G10, G11
        T[i, 8], T[i, 9], T[i, 10], T[i, 11] = h2, ex, ey, r2
    for i in range(N):
        v = img[i]
        X, Y = P[i, 0], P[i, 1]
        xn, yn, pcz = PRJ[i, 0], PRJ[i, 1], PRJ[i, 2]
        d0, d1, conv = D0[i], D1[i], CONV[i]
        d[i, 0], d[i, 1] = d0, d1
        ok[i] = conv
        if gains_on:  # readout through unequal gains: a homography of the spot position
            h0 = Hg[0, 0] * d0 + Hg[0, 1] * d1 + Hg[0, 2]
            h1 = Hg[1, 0] * d0 + Hg[1, 1] * d1 + Hg[1, 2]
            h2g = Hg[2, 0] * d0 + Hg[2, 1] * d1 + Hg[2, 2]
            y[i, 0], y[i, 1] = h0 / h2g, h1 / h2g
        if not want_jac:
            continue
        I00, I01, I10, I11 = T[i, 0], T[i, 1], T[i, 2], T[i, 3]
        G00, G01, G10, G11 = T[i, 4], T[i, 5], T[i, 6], T[i, 7]
        h2, ex, ey, r2 = T[i, 8], T[i, 9], T[i, 10], T[i, 11]
        # dd/dtheta for the global parameters: D[:, j] = inv @ dx/dtheta_j (with sign)
        # intrinsics through x (Eq 4)
        if separate_fy:
            D[0, 0], D[1, 0] = I00 * xn, I10 * xn
            D[0, 4], D[1, 4] = I01 * yn, I11 * yn
        else:
            D[0, 0], D[1, 0] = I00 * xn + I01 * yn, I10 * xn + I11 * yn
            D[0, 4] = D[1, 4] = 0.0
        D[0, 3], D[1, 3] = I00 * yn, I10 * yn
        # cx, cy: through x (+identity) and through the model's centre (dx/dc = -G)
        D[0, 1], D[1, 1] = I00 * (1 + G00) + I01 * G10, I10 * (1 + G00) + I11 * G10
        D[0, 2], D[1, 2] = I00 * G01 + I01 * (1 + G11), I10 * G01 + I11 * (1 + G11)
        # distortion coefficients: dd/dk = -inv dx/dk
        r4 = r2 * r2
        q0 = (ex * r2, ex * r4, ex * r4 * r2, r2 + 2 * ex * ex, 2 * ex * ey)
        q1 = (ey * r2, ey * r4, ey * r4 * r2, 2 * ex * ey, r2 + 2 * ey * ey)
        for j in range(5):
            D[0, 5 + j] = -(I00 * q0[j] + I01 * q1[j])
            D[1, 5 + j] = -(I10 * q0[j] + I11 * q1[j])
        for j in range(2 if psd_free else 0):
            hp = h2 if j == 0 else h2 * h2
            u0, u1 = d0 * hp, d1 * hp
            w0 = (1 + G00) * u0 + G01 * u1
            w1 = G10 * u0 + (1 + G11) * u1
            D[0, 10 + j] = -(I00 * w0 + I01 * w1)
            D[1, 10 + j] = -(I10 * w0 + I11 * w1)
        # poses: dd/dPc = inv @ dx/dPc, dPc/dr_k = dR_k[:, :2] P, dPc/dt = I
        iz = 1.0 / pcz
        B00, B01, B02 = f * iz, sk * iz, -(f * xn + sk * yn) * iz
        B11, B12 = fy * iz, -fy * yn * iz
        E00, E01, E02 = I00 * B00, I00 * B01 + I01 * B11, I00 * B02 + I01 * B12
        E10, E11, E12 = I10 * B00, I10 * B01 + I11 * B11, I10 * B02 + I11 * B12
        if gains_on:
            # chain everything upstream of d through dy/dd = dproj(H [d, 1]) H[:, :2]
            ih = 1.0 / h2g
            P00, P02 = ih, -h0 * ih * ih
            P11, P12 = ih, -h1 * ih * ih
            Y00 = P00 * Hg[0, 0] + P02 * Hg[2, 0]
            Y01 = P00 * Hg[0, 1] + P02 * Hg[2, 1]
            Y10 = P11 * Hg[1, 0] + P12 * Hg[2, 0]
            Y11 = P11 * Hg[1, 1] + P12 * Hg[2, 1]
            for j in range(12):
                a, b = D[0, j], D[1, j]
                D[0, j] = Y00 * a + Y01 * b
                D[1, j] = Y10 * a + Y11 * b
            E00, E01, E02, E10, E11, E12 = (
                Y00 * E00 + Y01 * E10, Y00 * E01 + Y01 * E11, Y00 * E02 + Y01 * E12,
                Y10 * E00 + Y11 * E10, Y10 * E01 + Y11 * E11, Y10 * E02 + Y11 * E12,
            )
            for j in range(4):  # dy/dg_j = dproj (gain_basis[j] [d, 1])
                b0 = gain_basis[j, 0, 0] * d0 + gain_basis[j, 0, 1] * d1 + gain_basis[j, 0, 2]
                b1 = gain_basis[j, 1, 0] * d0 + gain_basis[j, 1, 1] * d1 + gain_basis[j, 1, 2]
                b2 = gain_basis[j, 2, 0] * d0 + gain_basis[j, 2, 1] * d1 + gain_basis[j, 2, 2]
                D[0, 12 + j] = P00 * b0 + P02 * b2
                D[1, 12 + j] = P11 * b1 + P12 * b2
        row = 2 * i
        for k in range(ng):
            J[row, k] = D[0, gmap[k]]
            J[row + 1, k] = D[1, gmap[k]]
        base = ng
        for k in range(3):
            g0 = dR[v, k, 0, 0] * X + dR[v, k, 0, 1] * Y
            g1 = dR[v, k, 1, 0] * X + dR[v, k, 1, 1] * Y
            g2 = dR[v, k, 2, 0] * X + dR[v, k, 2, 1] * Y
            J[row, base + k] = E00 * g0 + E01 * g1 + E02 * g2
            J[row + 1, base + k] = E10 * g0 + E11 * g1 + E12 * g2
        J[row, base + 3], J[row, base + 4], J[row, base + 5] = E00, E01, E02
        J[row + 1, base + 3], J[row + 1, base + 4], J[row + 1, base + 5] = E10, E11, E12


def global_map(names) -> np.ndarray:
    """``gmap`` of :func:`image_model` for the free global parameter names."""
    return np.array([GLOBAL_ORDER.index(n) for n in names], dtype=np.int64)


@njit
def normal_equations(J, r, img, ng):
    """``J^T J`` and ``J^T r`` of a block-sparse Jacobian from :func:`image_model`.

    Rows ``2i, 2i+1`` (observation ``i`` of view ``img[i]``) are non-zero
    only in the ``ng`` global columns and the six columns of their view, so
    each contributes a (ng+6)^2 block instead of a full outer product: the
    cost is O(N (ng+6)^2), not O(N (ng+6n)^2).

    Parameters
    ----------
    J : (2N, ng + 6 n), r : (2N,), img : (N,) int, ng : int

    Returns
    -------
    A : (ng + 6 n, ng + 6 n), g : (ng + 6 n,)
    """
    m = J.shape[1]
    A = np.zeros((m, m))
    g = np.zeros(m)
    N = img.shape[0]
    cols = np.empty(ng + 6, dtype=np.int64)
    for k in range(ng):
        cols[k] = k
    for i in range(N):
        base = ng + 6 * img[i]
        for k in range(6):
            cols[ng + k] = base + k
        for row in range(2 * i, 2 * i + 2):
            ri = r[row]
            for a in range(ng + 6):
                ca = cols[a]
                ja = J[row, ca]
                if ja == 0.0:
                    continue
                g[ca] += ja * ri
                for b in range(a + 1):
                    cb = cols[b]
                    A[ca, cb] += ja * J[row, cb]
    for a in range(m):  # mirror the lower triangle
        for b in range(a):
            A[b, a] = A[a, b]
    return A, g


@njit
def _inv3(M, out):
    """Inverse of a 3x3 matrix by cofactors into ``out``; returns the determinant."""
    a, b, c = M[0, 0], M[0, 1], M[0, 2]
    d, e, f = M[1, 0], M[1, 1], M[1, 2]
    g, h, i = M[2, 0], M[2, 1], M[2, 2]
    A, B, C = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A + b * B + c * C
    out[0, 0], out[1, 0], out[2, 0] = A / det, B / det, C / det
    out[0, 1], out[1, 1], out[2, 1] = -(b * i - c * h) / det, (a * i - c * g) / det, -(a * h - b * g) / det
    out[0, 2], out[1, 2], out[2, 2] = (b * f - c * e) / det, -(a * f - c * d) / det, (a * e - b * d) / det
    return det


@njit
def template_model(P, img, theta, separate_fy, poses, meas, gmap, want_jac):
    """Residuals of the template-plane cost (the paper's Eq 29) and their Jacobian.

    For observation ``i`` of view ``v``: ``x = undistort(d_i)`` (Eq 7-16),
    ``q = (A [r1 r2 t])^-1 [x, 1]``, residual ``q[:2] / q[2] - P_i`` in mm on
    the template plate (the numpy reference is ``Evaluator._template`` in
    :mod:`psdcal.calibration._refine`). Arguments as :func:`image_model`; ``meas`` (N, 2)
    are the measured points.

    Returns
    -------
    r : (2N,) residuals, mm on the plate (rows x0, y0, x1, ...)
    J : (2N, n_global + 6) their Jacobian in the compact block form of :func:`image_model`;
        (0, 0) without ``want_jac``
    """
    N = P.shape[0]
    n = poses.shape[0]
    ng = gmap.shape[0]
    R, dR = _rotations(poses[:, :3], want_jac)
    f, cx, cy, sk = theta[0], theta[1], theta[2], theta[3]
    fy = theta[4] if separate_fy else f
    coef = theta[5:12]
    # per view: M = [r1 r2 t], H = A M, and their inverses
    Hinv = np.empty((n, 3, 3))
    Minv = np.empty((n, 3, 3))
    Mm = np.empty((n, 3, 3))
    H = np.empty((3, 3))
    for v in range(n):
        for a in range(3):
            Mm[v, a, 0], Mm[v, a, 1], Mm[v, a, 2] = R[v, a, 0], R[v, a, 1], poses[v, 3 + a]
        for b in range(3):
            H[0, b] = f * Mm[v, 0, b] + sk * Mm[v, 1, b] + cx * Mm[v, 2, b]
            H[1, b] = fy * Mm[v, 1, b] + cy * Mm[v, 2, b]
            H[2, b] = Mm[v, 2, b]
        _inv3(H, Hinv[v])
        _inv3(Mm[v], Minv[v])
    r = np.empty(2 * N)
    if want_jac:
        J = np.zeros((2 * N, ng + 6))
    else:
        J = np.zeros((0, 0))
    D = np.zeros((2, 16))
    V = np.empty((3, 5))
    for i in range(N):
        v = img[i]
        d0, d1 = meas[i, 0], meas[i, 1]
        # x = undistort(d) (Eq 7-16); G = d(lens correction)/de, so dx/dc = -G
        x0, x1, h2, ex, ey, r2, G00, G01, G10, G11, _, _, _ = _model_terms(d0, d1, coef, cx, cy)
        q0 = Hinv[v, 0, 0] * x0 + Hinv[v, 0, 1] * x1 + Hinv[v, 0, 2]
        q1 = Hinv[v, 1, 0] * x0 + Hinv[v, 1, 1] * x1 + Hinv[v, 1, 2]
        q2 = Hinv[v, 2, 0] * x0 + Hinv[v, 2, 1] * x1 + Hinv[v, 2, 2]
        iq = 1.0 / q2
        row = 2 * i
        r[row] = q0 * iq - P[i, 0]
        r[row + 1] = q1 * iq - P[i, 1]
        if not want_jac:
            continue
        # dP/dq (2x3)
        a00, a02 = iq, -q0 * iq * iq
        a11, a12 = iq, -q1 * iq * iq
        # intrinsics: dq = Hinv (dx~ - dA M q) (Eq 29 differentiated)
        mq0 = Mm[v, 0, 0] * q0 + Mm[v, 0, 1] * q1 + Mm[v, 0, 2] * q2
        mq1 = Mm[v, 1, 0] * q0 + Mm[v, 1, 1] * q1 + Mm[v, 1, 2] * q2
        mq2 = Mm[v, 2, 0] * q0 + Mm[v, 2, 1] * q1 + Mm[v, 2, 2] * q2
        V[0, 0], V[1, 0], V[2, 0] = -mq0, (0.0 if separate_fy else -mq1), 0.0  # f
        V[0, 1], V[1, 1], V[2, 1] = -G00 - mq2, -G10, 0.0  # cx
        V[0, 2], V[1, 2], V[2, 2] = -G01, -G11 - mq2, 0.0  # cy
        V[0, 3], V[1, 3], V[2, 3] = -mq1, 0.0, 0.0  # skew
        V[0, 4], V[1, 4], V[2, 4] = 0.0, (-mq1 if separate_fy else 0.0), 0.0  # fy
        for j in range(5):
            w0 = Hinv[v, 0, 0] * V[0, j] + Hinv[v, 0, 1] * V[1, j] + Hinv[v, 0, 2] * V[2, j]
            w1 = Hinv[v, 1, 0] * V[0, j] + Hinv[v, 1, 1] * V[1, j] + Hinv[v, 1, 2] * V[2, j]
            w2 = Hinv[v, 2, 0] * V[0, j] + Hinv[v, 2, 1] * V[1, j] + Hinv[v, 2, 2] * V[2, j]
            D[0, j] = a00 * w0 + a02 * w2
            D[1, j] = a11 * w1 + a12 * w2
        # distortion coefficients: dq = Hinv [dx/dk, 0]
        r4 = r2 * r2
        c0 = (ex * r2, ex * r4, ex * r4 * r2, r2 + 2 * ex * ex, 2 * ex * ey, 0.0, 0.0)
        c1 = (ey * r2, ey * r4, ey * r4 * r2, 2 * ex * ey, r2 + 2 * ey * ey, 0.0, 0.0)
        for j in range(7):
            if j < 5:
                u0, u1 = c0[j], c1[j]
            else:  # PSD terms act through u = d s: dx/dl = (I + G) d h2^(j-4)
                hp = h2 if j == 5 else h2 * h2
                u0 = (1 + G00) * d0 * hp + G01 * d1 * hp
                u1 = G10 * d0 * hp + (1 + G11) * d1 * hp
            w0 = Hinv[v, 0, 0] * u0 + Hinv[v, 0, 1] * u1
            w1 = Hinv[v, 1, 0] * u0 + Hinv[v, 1, 1] * u1
            w2 = Hinv[v, 2, 0] * u0 + Hinv[v, 2, 1] * u1
            D[0, 5 + j] = a00 * w0 + a02 * w2
            D[1, 5 + j] = a11 * w1 + a12 * w2
        for k in range(ng):
            J[row, k] = D[0, gmap[k]]
            J[row + 1, k] = D[1, gmap[k]]
        # poses: dq = -M^-1 (dM q); dM/dr_k q = dR_k[:, :2] q[:2], dM/dt q = q2 I
        base = ng
        for k in range(6):
            if k < 3:
                m0 = dR[v, k, 0, 0] * q0 + dR[v, k, 0, 1] * q1
                m1 = dR[v, k, 1, 0] * q0 + dR[v, k, 1, 1] * q1
                m2 = dR[v, k, 2, 0] * q0 + dR[v, k, 2, 1] * q1
            else:
                m0 = q2 if k == 3 else 0.0
                m1 = q2 if k == 4 else 0.0
                m2 = q2 if k == 5 else 0.0
            w0 = -(Minv[v, 0, 0] * m0 + Minv[v, 0, 1] * m1 + Minv[v, 0, 2] * m2)
            w1 = -(Minv[v, 1, 0] * m0 + Minv[v, 1, 1] * m1 + Minv[v, 1, 2] * m2)
            w2 = -(Minv[v, 2, 0] * m0 + Minv[v, 2, 1] * m1 + Minv[v, 2, 2] * m2)
            J[row, base + k] = a00 * w0 + a02 * w2
            J[row + 1, base + k] = a11 * w1 + a12 * w2
    return r, J


def expand_compact(Jc, img, n_views):
    """Dense Jacobian (2N, ng + 6 n) of a compact block Jacobian ``Jc`` (2N, ng + 6) (numpy)."""
    ng = Jc.shape[1] - 6
    N = img.shape[0]
    J = np.zeros((2 * N, ng + 6 * n_views))
    J[:, :ng] = Jc[:, :ng]
    rows = np.arange(2 * N)
    cols = ng + 6 * np.repeat(img, 2)[:, None] + np.arange(6)[None, :]
    J[rows[:, None], cols] = Jc[:, ng:]
    return J


@njit
def undistort_points(d, coef, c):
    """:func:`psdcal.model.distortion.undistort` of (n, M, 2) points (no Jacobians), the same operations in the
    same order (so the same bits); NaN points stay NaN.

    Parameters
    ----------
    d : (n, M, 2) measured points, mm; coef : (7,) k1, k2, k3, p1, p2, l1, l2; c : (2,) optical centre, mm
    """
    k1, k2, k3, p1, p2, l1, l2 = coef[0], coef[1], coef[2], coef[3], coef[4], coef[5], coef[6]
    out = np.empty(d.shape)
    for i in range(d.shape[0]):
        for j in range(d.shape[1]):
            d0, d1 = d[i, j, 0], d[i, j, 1]
            h2 = d0 * d0 + d1 * d1
            s = 1.0 + l1 * h2 + l2 * h2 * h2  # Eq 7-10
            u0, u1 = d0 * s, d1 * s
            e0, e1 = u0 - c[0], u1 - c[1]
            r2 = e0 * e0 + e1 * e1
            rad = r2 * (k1 + r2 * (k2 + r2 * k3))  # Eq 11-16
            tx = p1 * (r2 + 2 * e0 * e0) + 2 * p2 * e0 * e1
            ty = p2 * (r2 + 2 * e1 * e1) + 2 * p1 * e0 * e1
            out[i, j, 0] = u0 + e0 * rad + tx
            out[i, j, 1] = u1 + e1 * rad + ty
    return out
