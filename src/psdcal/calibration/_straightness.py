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
    lines = _find_lines_blocked(P, min_points=min_points, tol_rel=tol_rel, max_lines=max_lines)
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
        order = np.argsort(ang, kind="stable")
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


def _find_lines_blocked(P: np.ndarray, *, min_points: int, tol_rel: float, max_lines: int | None,
                        block: int = 128) -> list[np.ndarray]:
    """:func:`find_lines_reference`'s search for blocks of ``block`` points at once (the same lines in
    the same order; numpy over ``(block, M)`` arrays instead of a Python loop over the points)."""
    M = P.shape[0]
    if P.ndim != 2 or P.shape[1] != 2 or M < min_points:
        return find_lines_reference(P, min_points=min_points, tol_rel=tol_rel, max_lines=max_lines)
    extent = float(np.ptp(P, axis=0).max())
    tol = tol_rel * max(extent, 1e-300)
    need = min_points - 1
    lines = []
    for i0 in range(0, M - min_points + 1, block):
        rows = np.arange(i0, min(i0 + block, M - min_points + 1))
        B = rows.size
        vx = P[None, :, 0] - P[rows, 0][:, None]  # (B, M): P[j] - P[i]
        vy = P[None, :, 1] - P[rows, 1][:, None]
        dist = np.hypot(vx, vy)
        keep = dist > tol
        keep[np.arange(B), rows] = False
        with np.errstate(invalid="ignore"):
            ang = np.where(keep, np.mod(np.arctan2(vy, vx), np.pi), np.inf)  # the others sort last
        order = np.argsort(ang, axis=1, kind="stable")
        a = np.take_along_axis(ang, order, 1)
        with np.errstate(divide="ignore"):
            angtol = tol / np.take_along_axis(dist, order, 1)
        nk = keep.sum(axis=1)
        valid = np.arange(M)[None, :] < nk[:, None]  # sorted positions of kept points
        with np.errstate(invalid="ignore"):
            brk = np.diff(a, axis=1) > np.maximum(angtol[:, 1:], angtol[:, :-1])
        brk &= valid[:, 1:]
        gid = np.zeros((B, M), dtype=np.int64)
        np.cumsum(brk, axis=1, out=gid[:, 1:])
        # angles near pi and near 0 are the same direction: the last group joins the first
        last = np.maximum(nk - 1, 0)
        r = np.arange(B)
        g_last = gid[r, last]
        with np.errstate(invalid="ignore"):
            wrap = (nk > 0) & (g_last > 0) & (
                (np.pi - a[r, last]) + a[:, 0] <= np.maximum(angtol[:, 0], angtol[r, last]))
        gid = np.where(wrap[:, None] & (gid == g_last[:, None]), 0, gid)
        key = (r[:, None] * (M + 1) + gid)[valid]  # (row, group) of each kept point, row-major
        member = order[valid]
        counts = np.bincount(key, minlength=B * (M + 1))
        low = np.full(B * (M + 1), M, dtype=np.int64)
        np.minimum.at(low, key, member)
        owner = np.repeat(rows, M + 1)
        chosen = (counts >= need) & (low > owner)
        sel = chosen[key]
        if not sel.any():
            continue
        k_sel, m_sel = key[sel], member[sel]
        srt = np.lexsort((m_sel, k_sel))
        k_sel, m_sel = k_sel[srt], m_sel[srt]
        cut = np.flatnonzero(np.diff(k_sel)) + 1
        for kk, mem in zip(k_sel[np.concatenate([[0], cut])], np.split(m_sel, cut)):
            lines.append(np.concatenate([[int(owner[kk])], mem]))
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


def _radial_line_residuals_jit(d_mm, group, n_groups, k, c_mm, z_scale, want_jac):
    """Residuals (N,) and, with ``want_jac``, Jacobian (N, n) of the straightness cost, compiled.

    Equal to :func:`_line_residuals` of ``undistort(d_mm, k, c_mm)`` with
    ``dpts`` the derivatives by the unknowns ``z_j = k_j z_scale[j]``
    (:func:`psdcal.calibration._straightness_kernel.radial_residuals`).
    """
    from psdcal.calibration._straightness_kernel import radial_residuals

    return radial_residuals(
        np.ascontiguousarray(d_mm, dtype=float), np.ascontiguousarray(group, dtype=np.int64), int(n_groups),
        np.ascontiguousarray(k, dtype=float), np.ascontiguousarray(c_mm, dtype=float),
        np.ascontiguousarray(z_scale, dtype=float), bool(want_jac),
    )


def _compiled_for(pts, members, lengths) -> bool:
    """``psdcal._jit.use_compiled`` of the number of grouped points (counted only where it decides)."""
    if not _jit.use_compiled(pts.shape[0] * members.size):  # an upper bound
        return False
    if _jit.use_compiled(0):
        return True
    # "auto" mode, kernels not loaded: the points of the (view, line) pairs with >= 3 valid ones
    try:
        ok = np.all(np.isfinite(pts[:, members]), axis=-1)
    except IndexError:
        return False  # (numpy's error, from the reference)
    ends = np.cumsum(lengths)
    csum = np.concatenate([np.zeros((ok.shape[0], 1), dtype=np.int64), np.cumsum(ok, axis=1)], axis=1)
    counts = csum[:, ends] - csum[:, ends - lengths]  # valid points of each (view, line)
    return _jit.use_compiled(int(counts[counts >= 3].sum()))


@functools.cache
def _kernel():
    """:mod:`psdcal.calibration._straightness_kernel`, imported at the first compiled solve (it imports numba)."""
    from psdcal.calibration import _straightness_kernel

    return _straightness_kernel


#: the straightness step's solver settings (a starting value: 1e-9 relative is far below what the
#: refinement needs; noiseless data still converge to round-off, the residual reaching 0)
_SOLVER = dict(ftol=1e-9, xtol=1e-9, gtol=1e-10, max_iterations=50)


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

    With :func:`psdcal._jit.use_compiled`, the whole estimate (grouping, cost,
    Jacobian, solver) is one compiled call,
    :func:`psdcal.calibration._straightness_kernel.solve_radial`; the numpy
    reference (:func:`_line_residuals` of
    :func:`~psdcal.model.distortion.undistort`, minimised by
    :func:`psdcal.calibration._lm.levenberg_marquardt`) runs otherwise.
    """
    pts = np.asarray(points_mm, dtype=float)
    c = np.asarray(c_mm, dtype=float)
    if (
        lines and type(n_terms) in (int, np.int64) and 1 <= n_terms <= 3
        and pts.ndim == 3 and pts.shape[2] == 2 and c.size == 2
    ):
        members = np.concatenate(lines)
        lengths = np.fromiter(map(len, lines), dtype=np.int64, count=len(lines))
        if members.dtype.kind in "iu" and _compiled_for(pts, members, lengths):
            kernel = _kernel()
            k, cost, status, _, n_groups, n_points, _, _ = kernel.solve_radial(
                np.ascontiguousarray(pts), members.astype(np.int64, copy=False),
                lengths, np.ascontiguousarray(c.reshape(2)),
                n_terms, _SOLVER["ftol"], _SOLVER["xtol"], _SOLVER["gtol"], _SOLVER["max_iterations"],
            )
            if status != kernel.BAD_INDEX:  # (a bad index: numpy's IndexError below)
                if n_groups == 0:
                    return StraightnessResult(np.zeros(n_terms), c, 0, float("nan"), False)
                rms = math.sqrt(2 * cost / max(n_points, 1))
                return StraightnessResult(k, c, n_groups, rms, bool(status > 0 and math.isfinite(rms) and np.isfinite(k).all()))
    return _estimate_radial_reference(pts, lines, c, n_terms)


def _estimate_radial_reference(pts, lines, c, n_terms) -> StraightnessResult:
    """:func:`estimate_radial` in numpy (the reference of the compiled solve), ``pts`` and ``c`` float arrays."""
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

    sol = levenberg_marquardt(fun, jac, np.zeros(n_terms), SolverOptions(**_SOLVER))
    k = sol.x / scale
    rms = float(np.sqrt(2 * sol.cost / max(len(flat), 1)))
    # a non-finite cost is no solution, whatever the stopping test said
    return StraightnessResult(k, c, n_groups, rms, bool(sol.status > 0 and np.isfinite(rms) and np.all(np.isfinite(k))))
