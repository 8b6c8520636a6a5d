"""Compiled line-straightness step: grouping, cost, Jacobian and solver in one call.

The same mathematics as the numpy reference in
:mod:`psdcal.calibration._straightness` (:func:`~psdcal.calibration._straightness._line_residuals`
of :func:`~psdcal.model.distortion.undistort`, driven by
:func:`psdcal.calibration._lm.levenberg_marquardt`), written as scalar
loops for numba (:mod:`psdcal._jit`), so that a whole estimate is one call:

- every (view, line) pair of valid points is a group, kept when it has >= 3
  points (the measured points are undistorted by the radial terms only, Eq
  11-16 with ``k1..k3``: ``x = d + e (k1 r^2 + k2 r^4 + k3 r^6)``, ``e = d - c``);
- the residual of a point is its signed distance to the total-least-squares
  line of its group, divided by the group's RMS spread along the line;
- Levenberg-Marquardt on the normal equations over the 1-3 scaled unknowns
  ``z_j = k_j rmax^(2j)``, step for step the algorithm of
  ``levenberg_marquardt`` (Marquardt's scaling ``D`` = running maximum of
  ``diag(J^T J)``, Nielsen's damping, MINPACK's gradient, step and
  cost-reduction tests, the same status codes).

Results equal the reference's to round-off: the sums run in point order as
``np.bincount`` adds them; the products ``J^T J``, ``J^T r``, ``r . r``
(BLAS there) and the small Cholesky solve differ in the last bits only, and
so does each line's normal (``(-sin t, cos t)``, ``t = atan2(2b, a - c) / 2``
there, the same vector from half-angle formulas here, which spares three
transcendental functions per line and evaluation).
"""
from __future__ import annotations

import math

import numpy as np

from psdcal._jit import njit
from psdcal.calibration._lm_rules import negligible_decrement, next_damping, trial_verdict

#: status of :func:`solve_radial` when a line index is outside the template (the caller
#: then takes the numpy path, which raises numpy's IndexError)
BAD_INDEX = -1


@njit
def group_lines(pts_mm, members, line_len):
    """The points of every (view, line) pair with >= 3 valid points, grouped (compiled).

    Parameters
    ----------
    pts_mm : (n_images, M, 2) float64, measured points, mm, NaN where missing
    members : (L,) int64, the lines' template indices one after the other (numpy's
        negative indices allowed)
    line_len : (n_lines,) int64, points of each line

    Returns
    -------
    flat_mm : (N, 2), the grouped points: view by view, line by line, in the lines' order
    start : (n_groups + 1,) int64, group g is ``flat_mm[start[g]:start[g + 1]]``
    n_groups : int, or :data:`BAD_INDEX` when an index is outside ``[-M, M)``
    """
    n_img = pts_mm.shape[0]
    M = pts_mm.shape[1]
    L = members.shape[0]
    idx = np.empty(L, dtype=np.int64)
    for i in range(L):
        m = members[i]
        if m < 0:
            m += M
        if m < 0 or m >= M:
            return np.empty((0, 2)), np.zeros(1, dtype=np.int64), BAD_INDEX
        idx[i] = m
    flat = np.empty((n_img * L, 2))
    start = np.zeros(n_img * line_len.shape[0] + 1, dtype=np.int64)
    n = 0
    n_groups = 0
    for v in range(n_img):
        first = 0
        for ln in range(line_len.shape[0]):
            stop = first + line_len[ln]
            cnt = 0
            for i in range(first, stop):
                x = pts_mm[v, idx[i], 0]
                y = pts_mm[v, idx[i], 1]
                if math.isfinite(x) and math.isfinite(y):
                    cnt += 1
            if cnt >= 3:
                for i in range(first, stop):
                    x = pts_mm[v, idx[i], 0]
                    y = pts_mm[v, idx[i], 1]
                    if math.isfinite(x) and math.isfinite(y):
                        flat[n, 0] = x
                        flat[n, 1] = y
                        n += 1
                n_groups += 1
                start[n_groups] = n
            first = stop
    return flat[:n], start[: n_groups + 1], n_groups


@njit
def prepare(d_mm, start, c_mm, z_scale):
    """What the cost needs that does not depend on k (compiled): offsets, radii, point derivatives.

    The undistorted points are linear in k, so their derivatives by the
    unknowns ``z_j = k_j z_scale[j]``, ``e r^(2j) / z_scale[j]``, and those
    minus their group's mean are fixed.

    Parameters
    ----------
    d_mm : (N, 2) measured points, mm, grouped: group g is ``start[g] .. start[g+1] - 1``
    start : (n_groups + 1,) int64
    c_mm : (2,) centre of distortion, mm
    z_scale : (n,) scale of the unknowns (mm^2, mm^4, mm^6)

    Returns
    -------
    e_mm : (N, 2), ``d - c``; r2_mm2 : (N,), ``|e|^2``
    dq : (n, 2, N), derivatives of the undistorted points, centred in each group, by ``z_j``
    """
    N = d_mm.shape[0]
    nk = z_scale.shape[0]
    e = np.empty((N, 2))
    r2 = np.empty(N)
    dq = np.empty((nk, 2, N))
    for i in range(N):
        e[i, 0] = d_mm[i, 0] - c_mm[0]
        e[i, 1] = d_mm[i, 1] - c_mm[1]
        r2[i] = e[i, 0] * e[i, 0] + e[i, 1] * e[i, 1]
    for g in range(start.shape[0] - 1):
        s, t = start[g], start[g + 1]
        for j in range(nk):
            mx = 0.0
            my = 0.0
            for i in range(s, t):
                rp = r2[i]
                for _ in range(j):
                    rp = rp * r2[i]
                dq[j, 0, i] = e[i, 0] * rp / z_scale[j]
                dq[j, 1, i] = e[i, 1] * rp / z_scale[j]
                mx += dq[j, 0, i]
                my += dq[j, 1, i]
            mx = mx / (t - s)
            my = my / (t - s)
            for i in range(s, t):
                dq[j, 0, i] = dq[j, 0, i] - mx
                dq[j, 1, i] = dq[j, 1, i] - my
    return e, r2, dq


@njit
def line_residuals(d_mm, e_mm, r2_mm2, start, k, q_mm, abc, nrm, spread, res):
    """Residuals at ``k`` of the grouped points (compiled; fills the buffers).

    Undistorts by the radial terms (``x = d + e (k1 r^2 + k2 r^4 + k3 r^6)``,
    n = ``k.size`` <= 3), centres each group, fits its line and divides each
    point's signed distance to it by the group's RMS spread along it. Sums run
    in point order, as ``np.bincount`` adds them.

    Parameters
    ----------
    d_mm, e_mm, r2_mm2, start : as :func:`prepare` takes and gives them
    k : (n,) k1 [mm^-2], k2 [mm^-4], k3 [mm^-6]
    q_mm : (N, 2) out: undistorted points minus their group's centroid, mm
    abc : (3, n_groups) out: each group's scatter ``[[a, b], [b, c]]`` as rows a, b, c, mm^2
    nrm : (2, n_groups) out: each line's unit normal ``(-sin t, cos t)``, ``t = atan2(2b, a - c) / 2``
        (the major axis of the scatter), from ``cos 2t = (a - c) / (2 rad)``, ``sin 2t = b / rad``,
        ``rad = sqrt(((a - c) / 2)^2 + b^2)``: ``cos t = sqrt((1 + cos 2t) / 2)``, ``sin t = sin 2t / (2 cos t)``
        when ``a >= c``, else ``sin t = sign(b) sqrt((1 - cos 2t) / 2)``, ``cos t = sin 2t / (2 sin t)``
        (no cancellation either way; ``atan2`` itself when ``rad`` is 0 or not finite)
    spread : (n_groups,) out: RMS spread along the line, mm
    res : (N,) out: residuals (dimensionless)
    """
    nk = k.shape[0]
    k1 = k[0] if nk > 0 else 0.0
    k2 = k[1] if nk > 1 else 0.0
    k3 = k[2] if nk > 2 else 0.0
    n_groups = start.shape[0] - 1
    # one pass over the groups per stage: the groups' short dependency chains then overlap
    for g in range(n_groups):  # undistorted points and their centroid (in nrm until the normals)
        s, t = start[g], start[g + 1]
        sx = 0.0
        sy = 0.0
        for i in range(s, t):
            r2 = r2_mm2[i]
            fac = r2 * (k1 + r2 * (k2 + r2 * k3))
            x = d_mm[i, 0] + e_mm[i, 0] * fac
            y = d_mm[i, 1] + e_mm[i, 1] * fac
            q_mm[i, 0] = x
            q_mm[i, 1] = y
            sx += x
            sy += y
        n = float(t - s)
        nrm[0, g] = sx / n
        nrm[1, g] = sy / n
    for g in range(n_groups):  # centred points and scatter
        s, t = start[g], start[g + 1]
        mx = nrm[0, g]
        my = nrm[1, g]
        a = 0.0
        b = 0.0
        c = 0.0
        for i in range(s, t):
            qx = q_mm[i, 0] - mx
            qy = q_mm[i, 1] - my
            q_mm[i, 0] = qx
            q_mm[i, 1] = qy
            a += qx * qx
            b += qx * qy
            c += qy * qy
        abc[0, g] = a
        abc[1, g] = b
        abc[2, g] = c
    for g in range(n_groups):  # line normal and spread
        a, b, c = abc[0, g], abc[1, g], abc[2, g]
        h = 0.5 * (a - c)
        rad = math.sqrt(h * h + b * b)
        if rad > 0.0 and rad < math.inf:
            # t = atan2(2b, a - c) / 2 by half angles: cos 2t = h / rad, sin 2t = b / rad
            if h >= 0.0:
                ny = math.sqrt((rad + h) / (2.0 * rad))
                nx = -b / (2.0 * rad * ny)
            else:
                st = math.copysign(math.sqrt((rad - h) / (2.0 * rad)), b)
                nx = -st
                ny = b / (2.0 * rad * st)
        else:
            theta = 0.5 * math.atan2(2.0 * b, a - c)
            nx = -math.sin(theta)
            ny = math.cos(theta)
        nrm[0, g] = nx
        nrm[1, g] = ny
        lmax = 0.5 * (a + c) + rad
        spread[g] = math.sqrt(lmax / float(start[g + 1] - start[g]))
    for g in range(n_groups):  # residuals
        wx = nrm[0, g] / spread[g]
        wy = nrm[1, g] / spread[g]
        for i in range(start[g], start[g + 1]):
            res[i] = q_mm[i, 0] * wx + q_mm[i, 1] * wy


@njit
def line_jacobian(dq, start, q_mm, abc, nrm, spread, res, jac):
    """Jacobian (N, n) of :func:`line_residuals` by the unknowns ``z_j`` (compiled; fills ``jac``).

    From :func:`prepare`'s ``dq`` and the state :func:`line_residuals` left;
    includes the rotation of each line and the change of its spread (as
    :func:`psdcal.calibration._straightness._line_residuals`).
    """
    nk = dq.shape[0]
    for g in range(start.shape[0] - 1):
        s, t = start[g], start[g + 1]
        a, b, c = abc[0, g], abc[1, g], abc[2, g]
        nx, ny, sp = nrm[0, g], nrm[1, g], spread[g]
        wx = nx / sp
        wy = ny / sp
        rad = math.sqrt((0.5 * (a - c)) ** 2 + b * b)
        lmax = 0.5 * (a + c) + rad
        den = (a - c) * (a - c) + 4.0 * b * b
        if not den > 0.0:
            den = 1.0
        rad_safe = rad if rad > 0.0 else 1.0
        for j in range(nk):
            # derivatives of the scatter (halves of d(a), d(c))
            da = 0.0
            db = 0.0
            dc = 0.0
            for i in range(s, t):
                da += q_mm[i, 0] * dq[j, 0, i]
                dc += q_mm[i, 1] * dq[j, 1, i]
                db += q_mm[i, 0] * dq[j, 1, i] + q_mm[i, 1] * dq[j, 0, i]
            da = 2.0 * da
            dc = 2.0 * dc
            # rotation of the line and change of its spread
            dtheta = ((a - c) * db - b * (da - dc)) / den
            dlmax = 0.5 * (da + dc) + (0.25 * (a - c) * (da - dc) + b * db) / rad_safe
            dlog_spread = 0.5 * dlmax / lmax
            # n = (-sin t, cos t): dn = (-ny, nx) dt
            dnx = -ny * dtheta
            dny = nx * dtheta
            for i in range(s, t):
                jac[i, j] = (
                    dq[j, 0, i] * wx + dq[j, 1, i] * wy
                    + (q_mm[i, 0] * dnx + q_mm[i, 1] * dny) / sp
                    - res[i] * dlog_spread
                )


@njit
def radial_residuals(d_mm, group, n_groups, k, c_mm, z_scale, want_jac):
    """Residuals (N,) and, with ``want_jac``, Jacobian (N, n) (else (0, n)) of the straightness cost at ``k``.

    Equal to :func:`~psdcal.calibration._straightness._line_residuals` of
    ``undistort(d_mm, k, c_mm)`` with ``dpts`` the derivatives by the unknowns
    ``z_j = k_j z_scale[j]``. ``group`` (N,) in [0, n_groups) in any order
    (the points are sorted by group, stably, and the results put back).
    """
    N = d_mm.shape[0]
    nk = z_scale.shape[0]
    order = np.argsort(group, kind="mergesort")
    start = np.zeros(n_groups + 1, dtype=np.int64)
    for i in range(N):
        start[group[i] + 1] += 1
    for g in range(n_groups):
        start[g + 1] += start[g]
    d = np.empty((N, 2))
    for i in range(N):
        d[i, 0] = d_mm[order[i], 0]
        d[i, 1] = d_mm[order[i], 1]
    e, r2, dq = prepare(d, start, c_mm, z_scale)
    q = np.empty((N, 2))
    abc = np.empty((3, n_groups))
    nrm = np.empty((2, n_groups))
    spread = np.empty(n_groups)
    rs = np.empty(N)
    line_residuals(d, e, r2, start, k, q, abc, nrm, spread, rs)
    res = np.empty(N)
    for i in range(N):
        res[order[i]] = rs[i]
    if not want_jac:
        return res, np.empty((0, nk))
    js = np.empty((N, nk))
    line_jacobian(dq, start, q, abc, nrm, spread, rs, js)
    jac = np.empty((N, nk))
    for i in range(N):
        jac[order[i]] = js[i]
    return res, jac


@njit
def _normal(jac, res, A, g):
    """``A = J^T J``, ``g = J^T r`` (sums in row order)."""
    n = A.shape[0]
    for a in range(n):
        s = 0.0
        for i in range(res.shape[0]):
            s += jac[i, a] * res[i]
        g[a] = s
        for b in range(a + 1):
            s = 0.0
            for i in range(res.shape[0]):
                s += jac[i, a] * jac[i, b]
            A[a, b] = s
            A[b, a] = s


@njit
def _damped_solve(A, damp, g, h):
    """``h = (A + diag(damp))^-1 g`` by Cholesky; False (h undefined) when not positive definite.

    The test of numpy's Cholesky (OpenBLAS's ``potrf``): a pivot <= 0 fails; a NaN one
    does not (the step is then NaN, and the solver rejects it).
    """
    n = A.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        s = A[j, j] + damp[j]
        for p in range(j):
            s -= L[j, p] * L[j, p]
        if s <= 0.0:
            return False
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            t = A[i, j]
            for p in range(j):
                t -= L[i, p] * L[j, p]
            L[i, j] = t / L[j, j]
    for i in range(n):  # L y = g
        t = g[i]
        for p in range(i):
            t -= L[i, p] * h[p]
        h[i] = t / L[i, i]
    for i in range(n - 1, -1, -1):  # L^T h = y
        t = h[i]
        for p in range(i + 1, n):
            t -= L[p, i] * h[p]
        h[i] = t / L[i, i]
    return True


@njit
def _half_sq(r):
    s = 0.0
    for i in range(r.shape[0]):
        s += r[i] * r[i]
    return 0.5 * s


@njit
def solve_radial(pts_mm, members, line_len, c_mm, n_terms, ftol, xtol, gtol, max_iterations):
    """The whole straightness estimate (compiled): grouping, then Levenberg-Marquardt from k = 0.

    Parameters
    ----------
    pts_mm : (n_images, M, 2) float64, measured points, mm, NaN where missing
    members, line_len : the lines, as :func:`group_lines` takes them
    c_mm : (2,) float64, centre of distortion, mm
    n_terms : int, 1 .. 3, unknowns k1 .. k_n
    ftol, xtol, gtol, max_iterations : the solver's settings
        (:class:`psdcal.calibration._refine.SolverOptions`)

    Returns
    -------
    k : (n_terms,) k1 [mm^-2], k2 [mm^-4], k3 [mm^-6] (zeros without a group)
    cost : float, half the sum of the squared residuals at k
    status : int, as ``levenberg_marquardt``'s (0 iteration limit, 1 gtol, 2 xtol or
        damping overflow, 3 ftol, 4 zero residual), or :data:`BAD_INDEX`
    damping_overflow : bool, status 2 came from the damping's overflow
    n_groups, n_points : int, groups and grouped points
    njev, nfev : int, Jacobian and residual evaluations
    """
    nk = n_terms
    k = np.zeros(nk)
    flat, start, n_groups = group_lines(pts_mm, members, line_len)
    if n_groups <= 0:
        return k, math.nan, (BAD_INDEX if n_groups < 0 else 0), False, max(n_groups, 0), 0, 0, 0
    N = flat.shape[0]
    rmax2 = 0.0
    for i in range(N):
        ex = flat[i, 0] - c_mm[0]
        ey = flat[i, 1] - c_mm[1]
        s = ex * ex + ey * ey
        if s > rmax2 or i == 0:
            rmax2 = s
    # unknowns scaled so that k_i * rmax^(2i) is O(1)
    scale = np.empty(nk)
    for j in range(nk):
        scale[j] = math.pow(rmax2, j + 1.0)
    e, r2, dq = prepare(flat, start, c_mm, scale)
    q = np.empty((N, 2))
    abc = np.empty((3, n_groups))
    nrm = np.empty((2, n_groups))
    spread = np.empty(n_groups)
    res = np.empty(N)
    jac = np.empty((N, nk))
    A = np.empty((nk, nk))
    g = np.empty(nk)
    diagA = np.empty(nk)
    D = np.empty(nk)
    sD = np.empty(nk)
    x = np.zeros(nk)
    x_new = np.empty(nk)
    kk = np.empty(nk)
    h = np.empty(nk)
    damp = np.empty(nk)

    # residuals and Jacobian at the start (the state buffers always hold the last point evaluated)
    for j in range(nk):
        kk[j] = x[j] / scale[j]
    line_residuals(flat, e, r2, start, kk, q, abc, nrm, spread, res)
    line_jacobian(dq, start, q, abc, nrm, spread, res, jac)
    nfev = 1
    njev = 1
    F = _half_sq(res)
    _normal(jac, res, A, g)
    for j in range(nk):
        diagA[j] = A[j, j]
        D[j] = max(diagA[j], 1e-300) if not math.isnan(diagA[j]) else diagA[j]
    mu = 1e-8
    nu = 2.0
    status = 0
    overflow = False
    max_nfev = 4 * max_iterations + 10
    fresh = True
    x_scale = 0.0
    while njev <= max_iterations and nfev < max_nfev:
        if F == 0.0:
            status = 4
            break
        if fresh:
            # MINPACK's gradient test (a NaN fails it, as np.max propagates NaN)
            gmax = -math.inf
            for j in range(nk):
                cn = math.sqrt(max(diagA[j], 1e-300) if not math.isnan(diagA[j]) else diagA[j])
                t = abs(g[j]) / cn
                if math.isnan(t) or math.isnan(gmax):
                    gmax = math.nan
                elif t > gmax:
                    gmax = t
            if gmax <= gtol * math.sqrt(2 * F):
                status = 1
                break
            s = 0.0
            for j in range(nk):
                sD[j] = math.sqrt(D[j])
                s += (sD[j] * x[j]) * (sD[j] * x[j])
            x_scale = math.sqrt(s)
            fresh = False
            # the undamped Gauss-Newton step's predicted reduction: at most ftol of the cost, stop here
            for j in range(nk):
                damp[j] = 0.0
            if _damped_solve(A, damp, g, h):
                s = 0.0
                for j in range(nk):
                    s += g[j] * h[j]
                if negligible_decrement(0.5 * s, F, ftol):
                    status = 3
                    break
        for j in range(nk):
            damp[j] = mu * D[j]
        if not _damped_solve(A, damp, g, h):  # not positive definite at this damping
            mu *= nu
            nu *= 2.0
            if not math.isfinite(mu) or mu > 1e200:  # (a system with NaN in it fails at every damping)
                status = 2
                overflow = True
                break
            continue
        s = 0.0
        for j in range(nk):
            h[j] = -h[j]
            s += (sD[j] * h[j]) * (sD[j] * h[j])
        if math.sqrt(s) <= xtol * (x_scale + xtol):
            status = 2
            break
        for j in range(nk):
            x_new[j] = x[j] + h[j]
        for j in range(nk):
            kk[j] = x_new[j] / scale[j]
        line_residuals(flat, e, r2, start, kk, q, abc, nrm, spread, res)
        nfev += 1
        F_new = _half_sq(res)
        s = 0.0
        for j in range(nk):
            s += h[j] * (mu * D[j] * h[j] - g[j])
        pred = 0.5 * s
        accept, small, rho = trial_verdict(F, F_new, pred, nu, ftol)
        mu, nu = next_damping(mu, nu, rho, accept)
        if accept:
            for j in range(nk):
                x[j] = x_new[j]
            F = F_new
            line_jacobian(dq, start, q, abc, nrm, spread, res, jac)
            njev += 1
            _normal(jac, res, A, g)
            for j in range(nk):
                diagA[j] = A[j, j]
                if math.isnan(D[j]) or math.isnan(diagA[j]):
                    D[j] = math.nan
                elif diagA[j] > D[j]:
                    D[j] = diagA[j]
            fresh = True
            if small:
                status = 3
                break
        elif not math.isfinite(mu) or mu > 1e200:
            status = 2
            overflow = True
            break
    for j in range(nk):
        k[j] = x[j] / scale[j]
    return k, F, status, overflow, n_groups, N, njev, nfev
