"""Preliminary distortion estimate by line straightness (the paper's Section 3.2).

Template points that are collinear stay collinear under perspective, so after
a correct undistortion their measured points are collinear again. The paper's
slope form (Eq 30-35) has misprinted derivatives; as docs/model.md#line-straightness says, we
minimise instead the squared distance of each undistorted point to the
total-least-squares line of its group, divided by the group's spread along
the line (which makes the cost invariant to a common scaling and rules out the
trivial "shrink everything" solution).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from psdcal import _jit
from psdcal._jit import lazy_njit
from psdcal.model.distortion import undistort


def find_lines(template_mm, *, min_points: int = 3, tol_rel: float = 1e-6, max_lines: int | None = None) -> list[np.ndarray]:
    """All maximal sets of >= ``min_points`` collinear template points.

    The lines depend on the template only, which a calibration (and every
    Monte-Carlo trial) reuses: results are memoised per template (its bytes
    and shape) and options; each call returns fresh copies.
    :func:`find_lines_reference` is the uncached search.

    For each point ``i``, the directions to all other points are sorted by
    angle and split where consecutive angles differ by more than the
    tolerance; a group is a line through ``i``, recorded only when ``i`` is
    its smallest index, so every maximal line appears exactly once.
    O(M^2 log M).

    Parameters
    ----------
    template_mm : (M, 2) array_like
    min_points : int
    tol_rel : float
        Collinearity tolerance as a fraction of the template's extent.
    max_lines : int, optional
        Keep only this many lines, the ones with the most points (ties: the
        order found).

    Returns
    -------
    list of int arrays (sorted indices), one per line.
    """
    P = np.ascontiguousarray(template_mm, dtype=float)
    if P.ndim != 2:
        return find_lines_reference(P, min_points=min_points, tol_rel=tol_rel, max_lines=max_lines)
    cached = _find_lines_cached(P.tobytes(), P.shape, int(min_points), float(tol_rel), max_lines)
    return [ln.copy() for ln in cached]


@functools.lru_cache(maxsize=64)
def _find_lines_cached(template_bytes: bytes, shape: tuple, min_points: int, tol_rel: float, max_lines):
    """Memoised :func:`find_lines_reference` on a template given as its bytes (float64) and shape."""
    P = np.frombuffer(template_bytes, dtype=float).reshape(shape)
    lines = find_lines_reference(P, min_points=min_points, tol_rel=tol_rel, max_lines=max_lines)
    for ln in lines:
        ln.setflags(write=False)
    return tuple(lines)


def find_lines_reference(template_mm, *, min_points: int = 3, tol_rel: float = 1e-6, max_lines: int | None = None) -> list[np.ndarray]:
    """The search of :func:`find_lines` itself, without memoisation (same parameters and result)."""
    P = np.asarray(template_mm, dtype=float)
    M = P.shape[0]
    if M < min_points:
        return []
    extent = float(np.ptp(P, axis=0).max())
    tol = tol_rel * max(extent, 1e-300)
    lines = []
    idx_all = np.arange(M)
    for i in range(M - min_points + 1):
        v = P - P[i]
        dist = np.hypot(v[:, 0], v[:, 1])
        keep = dist > tol
        keep[i] = False
        js = idx_all[keep]
        if js.size < min_points - 1:
            continue
        ang = np.mod(np.arctan2(v[keep, 1], v[keep, 0]), np.pi)
        order = np.argsort(ang)
        a = ang[order]
        angtol = tol / dist[keep][order]
        gid = np.concatenate([[0], np.cumsum(np.diff(a) > np.maximum(angtol[1:], angtol[:-1]))])
        # angles near pi and near 0 are the same direction
        if gid[-1] > 0 and (np.pi - a[-1]) + a[0] <= max(angtol[0], angtol[-1]):
            gid[gid == gid[-1]] = 0
        counts = np.bincount(gid)
        for g in np.flatnonzero(counts >= min_points - 1):
            members = js[order[gid == g]]
            if members.min() > i:
                lines.append(np.concatenate([[i], np.sort(members)]))
    if max_lines is not None and len(lines) > max_lines:
        order = sorted(range(len(lines)), key=lambda k: -len(lines[k]))[:max_lines]
        lines = [lines[k] for k in sorted(order)]
    return lines


@dataclass(frozen=True)
class StraightnessResult:
    """Preliminary radial distortion (k1 [mm^-2], k2 [mm^-4]) about ``c_mm``."""

    k: np.ndarray
    c_mm: np.ndarray
    n_lines: int
    rms_rel: float
    success: bool



def _line_residuals(pts, group, n_groups, dpts=None):
    """Signed distance of each point to its group's total-least-squares line.

    Distances are divided by the group's RMS spread along the line, which
    makes the cost scale-free.  The line's direction is the major axis of
    the group's 2x2 scatter ``[[a, b], [b, c]]``, angle ``atan2(2b, a-c)/2``.

    With ``dpts`` (N, 2, k), the derivatives of the points with respect to k
    unknowns, also returns the exact Jacobian (N, k), including the rotation
    of each line and the change of its spread.
    """
    cnt = np.bincount(group, minlength=n_groups)
    mx = np.bincount(group, pts[:, 0], n_groups) / cnt
    my = np.bincount(group, pts[:, 1], n_groups) / cnt
    qx = pts[:, 0] - mx[group]
    qy = pts[:, 1] - my[group]
    a = np.bincount(group, qx * qx, n_groups)
    b = np.bincount(group, qx * qy, n_groups)
    c = np.bincount(group, qy * qy, n_groups)
    theta = 0.5 * np.arctan2(2 * b, a - c)
    nx, ny = -np.sin(theta), np.cos(theta)
    rad = np.sqrt((0.5 * (a - c)) ** 2 + b * b)
    lmax = 0.5 * (a + c) + rad
    spread = np.sqrt(lmax / cnt)
    w_x = (nx / spread)[group]
    w_y = (ny / spread)[group]
    res = qx * w_x + qy * w_y
    if dpts is None:
        return res
    k = dpts.shape[2]
    jac = np.empty((pts.shape[0], k))
    den = (a - c) ** 2 + 4 * b * b
    den = np.where(den > 0, den, 1.0)
    rad_safe = np.where(rad > 0, rad, 1.0)
    for j in range(k):
        dx = dpts[:, 0, j] - (np.bincount(group, dpts[:, 0, j], n_groups) / cnt)[group]
        dy = dpts[:, 1, j] - (np.bincount(group, dpts[:, 1, j], n_groups) / cnt)[group]
        da = 2 * np.bincount(group, qx * dx, n_groups)
        dc = 2 * np.bincount(group, qy * dy, n_groups)
        db = np.bincount(group, qx * dy + qy * dx, n_groups)
        dtheta = ((a - c) * db - b * (da - dc)) / den
        dlmax = 0.5 * (da + dc) + (0.25 * (a - c) * (da - dc) + b * db) / rad_safe
        dlog_spread = 0.5 * dlmax / lmax
        # n = (-sin t, cos t): dn = -(cos t, sin t) dt = (-ny, nx) dt
        dnx, dny = (-ny * dtheta)[group], (nx * dtheta)[group]
        jac[:, j] = dx * w_x + dy * w_y + (qx * dnx + qy * dny) / spread[group] - res * dlog_spread[group]
    return res, jac


@lazy_njit
def _radial_scatter_kernel(d_mm, group, n_groups, k, c_mm):
    """Undistort by radial terms and form each group's centred points and scatter (compiled).

    The undistortion is Eq 11-16 with only ``k1..k_n`` (n = ``k.size`` <= 3)
    non-zero: ``x = d + e (k1 r^2 + k2 r^4 + k3 r^6)``, ``e = d - c``.
    The sums run in point order, as ``np.bincount`` adds them in
    :func:`_line_residuals`, so the results equal the numpy reference's.

    Parameters
    ----------
    d_mm : (N, 2) float64, measured points, mm
    group : (N,) int64 in [0, n_groups)
    n_groups : int
    k : (n,) float64, radial coefficients k1 [mm^-2], k2 [mm^-4], k3 [mm^-6]
    c_mm : (2,) float64, centre of distortion, mm

    Returns
    -------
    q_mm : (N, 2), undistorted points minus their group's centroid, mm
    cnt : (n_groups,) float64, points per group
    abc_mm2 : (3, n_groups), the scatter ``[[a, b], [b, c]]`` of each group as rows a, b, c, mm^2
    """
    N = d_mm.shape[0]
    nk = k.shape[0]
    k1 = k[0] if nk > 0 else 0.0
    k2 = k[1] if nk > 1 else 0.0
    k3 = k[2] if nk > 2 else 0.0
    x = np.empty((N, 2))
    cnt = np.zeros(n_groups)
    mean = np.zeros((n_groups, 2))
    for i in range(N):
        ex = d_mm[i, 0] - c_mm[0]
        ey = d_mm[i, 1] - c_mm[1]
        r2 = ex * ex + ey * ey
        rad = r2 * (k1 + r2 * (k2 + r2 * k3))
        x[i, 0] = d_mm[i, 0] + ex * rad
        x[i, 1] = d_mm[i, 1] + ey * rad
        g = group[i]
        cnt[g] += 1.0
        mean[g, 0] += x[i, 0]
        mean[g, 1] += x[i, 1]
    for g in range(n_groups):
        mean[g, 0] = mean[g, 0] / cnt[g]
        mean[g, 1] = mean[g, 1] / cnt[g]
    q = np.empty((N, 2))
    abc = np.zeros((3, n_groups))
    for i in range(N):
        g = group[i]
        qx = x[i, 0] - mean[g, 0]
        qy = x[i, 1] - mean[g, 1]
        q[i, 0] = qx
        q[i, 1] = qy
        abc[0, g] += qx * qx
        abc[1, g] += qx * qy
        abc[2, g] += qy * qy
    return q, cnt, abc


@lazy_njit
def _radial_line_residuals_kernel(d_mm, q_mm, group, cnt, abc, nx, ny, c_mm, z_scale, want_jac):
    """Compiled :func:`_line_residuals` (and its Jacobian) from :func:`_radial_scatter_kernel`'s output.

    ``(nx, ny)`` is each line's unit normal ``(-sin t, cos t)``,
    ``t = atan2(2b, a - c) / 2``, computed by the caller with numpy (whose
    ``arctan2`` need not agree to the last bit with the C library's; using
    the same one keeps the result equal to the reference's). The
    derivatives of the undistorted points by ``k_j`` are ``e r^(2j)``;
    divided by ``z_scale[j]`` (the solver's unknown is ``z_j = k_j z_scale[j]``)
    they are the ``dpts`` of :func:`_line_residuals`.

    Parameters
    ----------
    d_mm : (N, 2) float64, measured points, mm
    q_mm, group, cnt, abc : as :func:`_radial_scatter_kernel` gives them
    nx, ny : (n_groups,) float64, line normals
    c_mm : (2,) float64, centre of distortion, mm
    z_scale : (n,) float64, scale of the unknowns (mm^2, mm^4, mm^6)
    want_jac : bool

    Returns
    -------
    res : (N,) residuals (dimensionless); jac : (N, n), or (0, n) without ``want_jac``
    """
    N = d_mm.shape[0]
    n_groups = cnt.shape[0]
    nk = z_scale.shape[0]
    # spread of each group along its line, sqrt(lmax / cnt), and the residual weights n / spread
    radg = np.empty(n_groups)
    lmax = np.empty(n_groups)
    spread = np.empty(n_groups)
    wx = np.empty(n_groups)
    wy = np.empty(n_groups)
    for g in range(n_groups):
        h = 0.5 * (abc[0, g] - abc[2, g])
        radg[g] = math.sqrt(h * h + abc[1, g] * abc[1, g])
        lmax[g] = 0.5 * (abc[0, g] + abc[2, g]) + radg[g]
        spread[g] = math.sqrt(lmax[g] / cnt[g])
        wx[g] = nx[g] / spread[g]
        wy[g] = ny[g] / spread[g]
    res = np.empty(N)
    for i in range(N):
        g = group[i]
        res[i] = q_mm[i, 0] * wx[g] + q_mm[i, 1] * wy[g]
    if not want_jac:
        return res, np.empty((0, nk))
    # derivatives of the undistorted points by the unknowns
    dx = np.empty((N, nk))
    dy = np.empty((N, nk))
    for i in range(N):
        ex = d_mm[i, 0] - c_mm[0]
        ey = d_mm[i, 1] - c_mm[1]
        r2 = ex * ex + ey * ey
        rp = r2
        for j in range(nk):
            dx[i, j] = ex * rp / z_scale[j]
            dy[i, j] = ey * rp / z_scale[j]
            rp = rp * r2
    jac = np.empty((N, nk))
    mdx = np.empty(n_groups)
    mdy = np.empty(n_groups)
    da = np.empty(n_groups)
    db = np.empty(n_groups)
    dc = np.empty(n_groups)
    dnx = np.empty(n_groups)
    dny = np.empty(n_groups)
    dlog_spread = np.empty(n_groups)
    ddx = np.empty(N)
    ddy = np.empty(N)
    for j in range(nk):
        mdx[:] = 0.0
        mdy[:] = 0.0
        da[:] = 0.0
        db[:] = 0.0
        dc[:] = 0.0
        for i in range(N):
            g = group[i]
            mdx[g] += dx[i, j]
            mdy[g] += dy[i, j]
        for g in range(n_groups):
            mdx[g] = mdx[g] / cnt[g]
            mdy[g] = mdy[g] / cnt[g]
        # derivatives of the centred points and of the scatter (da, db, dc: halves of d(a), d(c))
        for i in range(N):
            g = group[i]
            qx = q_mm[i, 0]
            qy = q_mm[i, 1]
            ddx[i] = dx[i, j] - mdx[g]
            ddy[i] = dy[i, j] - mdy[g]
            da[g] += qx * ddx[i]
            dc[g] += qy * ddy[i]
            db[g] += qx * ddy[i] + qy * ddx[i]
        for g in range(n_groups):
            a, b, c = abc[0, g], abc[1, g], abc[2, g]
            den = (a - c) * (a - c) + 4.0 * b * b
            if not den > 0.0:
                den = 1.0
            rad_safe = radg[g] if radg[g] > 0.0 else 1.0
            dag = 2.0 * da[g]
            dcg = 2.0 * dc[g]
            # rotation of the line and change of its spread
            dtheta = ((a - c) * db[g] - b * (dag - dcg)) / den
            dlmax = 0.5 * (dag + dcg) + (0.25 * (a - c) * (dag - dcg) + b * db[g]) / rad_safe
            dlog_spread[g] = 0.5 * dlmax / lmax[g]
            # n = (-sin t, cos t): dn = (-ny, nx) dt
            dnx[g] = -ny[g] * dtheta
            dny[g] = nx[g] * dtheta
        for i in range(N):
            g = group[i]
            jac[i, j] = (
                ddx[i] * wx[g]
                + ddy[i] * wy[g]
                + (q_mm[i, 0] * dnx[g] + q_mm[i, 1] * dny[g]) / spread[g]
                - res[i] * dlog_spread[g]
            )
    return res, jac


def _radial_line_state(d_mm, group, n_groups, k, c_mm):
    """Centred undistorted points, group sizes, scatters and line normals at ``k`` (compiled + numpy).

    Returns the arguments ``q_mm, cnt, abc, nx, ny`` of
    :func:`_radial_line_residuals_kernel`; the normal's angle is numpy's
    (as in :func:`_line_residuals`).
    """
    q, cnt, abc = _radial_scatter_kernel(d_mm, group, n_groups, k, c_mm)
    theta = 0.5 * np.arctan2(2 * abc[1], abc[0] - abc[2])
    return q, cnt, abc, -np.sin(theta), np.cos(theta)


def _radial_line_residuals_jit(d_mm, group, n_groups, k, c_mm, z_scale, want_jac):
    """Residuals (N,) and, with ``want_jac``, Jacobian (N, n) of the straightness cost, compiled.

    Equal to :func:`_line_residuals` of ``undistort(d_mm, k, c_mm)`` with
    ``dpts`` the derivatives by ``k / z_scale``'s unknowns.
    """
    q, cnt, abc, nx, ny = _radial_line_state(d_mm, group, n_groups, k, c_mm)
    return _radial_line_residuals_kernel(d_mm, q, group, cnt, abc, nx, ny, c_mm, z_scale, want_jac)


def estimate_radial(points_mm, lines, *, c_mm=(0.0, 0.0), n_terms: int = 2) -> StraightnessResult:
    """Estimate k1 (and k2) that make the measured lines straight (Section 3.2).

    Parameters
    ----------
    points_mm : (n_images, M, 2) array_like
        Measured impact points, NaN where missing.
    lines : list of index arrays from :func:`find_lines`
    c_mm : (2,) centre of distortion (the electrical centre by default).
    n_terms : 1 or 2 (3 also works: k3)

    Returns
    -------
    StraightnessResult (k has ``n_terms`` entries; zeros when there is no line).

    With :func:`psdcal._jit.enabled`, the cost and its Jacobian come from
    compiled kernels that reproduce :func:`_line_residuals` of
    :func:`~psdcal.model.distortion.undistort` (the reference, used otherwise).
    """
    pts = np.asarray(points_mm, dtype=float)
    c = np.asarray(c_mm, dtype=float)
    n_groups = 0
    if lines and n_terms >= 1:
        # every (image, line) pair is a group of its valid points; keep those with >= 3
        members = np.concatenate(lines)
        line_of = np.repeat(np.arange(len(lines)), [len(ln) for ln in lines])
        P = pts[:, members]  # (n_images, L_tot, 2)
        ok = np.all(np.isfinite(P), axis=-1)
        gid = (np.arange(pts.shape[0])[:, None] * len(lines) + line_of[None, :])[ok]
        counts = np.bincount(gid, minlength=pts.shape[0] * len(lines))
        keep = counts[gid] >= 3
        flat = P[ok][keep]
        _, group = np.unique(gid[keep], return_inverse=True)
        n_groups = int(group.max()) + 1 if group.size else 0
    if n_groups == 0:
        return StraightnessResult(np.zeros(max(n_terms, 0)), c, 0, float("nan"), False)
    rmax2 = float(np.max(np.sum((flat - c) ** 2, axis=1)))
    # unknowns scaled so that k_i * rmax^(2i) is O(1)
    scale = np.array([rmax2 ** (i + 1) for i in range(n_terms)])

    if _jit.use_compiled(flat.shape[0]) and n_terms <= 3:
        # the compiled kernel: same residuals and Jacobian as the numpy reference below
        d_c = np.ascontiguousarray(flat)
        g_c = np.ascontiguousarray(group, dtype=np.int64)
        c_c = np.ascontiguousarray(np.broadcast_to(c, (2,)), dtype=float)
        last = {}  # the solver asks for the Jacobian where it has just evaluated the residuals

        def state(z):
            key = z.tobytes()
            if last.get("key") != key:
                last["key"], last["state"] = key, _radial_line_state(d_c, g_c, n_groups, z / scale, c_c)
            return last["state"]

        def fun(z):
            # the Jacobian comes with the residuals (one pass): LM asks for it at the accepted points,
            # which are most of the points it evaluates
            q, cnt, abc, nx, ny = state(z)
            res, jz = _radial_line_residuals_kernel(d_c, q, g_c, cnt, abc, nx, ny, c_c, scale, True)
            last["jac"] = (z.tobytes(), jz)
            return res

        def jac(z):
            hit = last.get("jac")
            if hit is not None and hit[0] == z.tobytes():
                return hit[1]
            q, cnt, abc, nx, ny = state(z)
            return _radial_line_residuals_kernel(d_c, q, g_c, cnt, abc, nx, ny, c_c, scale, True)[1]

    else:

        def fun(z):
            coef = np.zeros(7)
            coef[:n_terms] = z / scale
            return _line_residuals(undistort(flat, coef, c), group, n_groups)

        def jac(z):
            coef = np.zeros(7)
            coef[:n_terms] = z / scale
            u, _, _, du_dk = undistort(flat, coef, c, jacobians=True)
            return _line_residuals(u, group, n_groups, du_dk[:, :, :n_terms] / scale)[1]

    from psdcal.calibration._refine import SolverOptions, levenberg_marquardt

    # A starting value: 1e-9 relative is far below what the refinement needs
    # (noiseless data still converge to round-off, the residual reaching 0).
    sol = levenberg_marquardt(fun, jac, np.zeros(n_terms), SolverOptions(ftol=1e-9, xtol=1e-9, gtol=1e-10, max_iterations=50))
    k = sol.x / scale
    return StraightnessResult(k, c, n_groups, float(np.sqrt(2 * sol.cost / max(len(flat), 1))), bool(sol.status > 0))
