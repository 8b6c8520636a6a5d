"""The undistortion model and its inverse (docs/model.md#distortion, the paper's Eq 7-16).

``undistort`` maps a measured impact point ``d`` to the ideal pinhole point
``x``; ``distort`` solves ``undistort(d) = x`` for ``d`` by Newton's method.

Conventions: points are (..., 2) arrays in mm on the sensor; ``c`` is the
optical centre (2,) in mm; ``coeffs`` is (7,) in the order of
:data:`psdcal.model.params.DISTORTION_NAMES` = (k1, k2, k3, p1, p2, l1, l2).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psdcal.model.params import Distortion


def _as_coeffs(dist) -> np.ndarray:
    if isinstance(dist, Distortion):
        return dist.as_array()
    a = np.asarray(dist, dtype=float)
    if a.shape != (7,):
        raise ValueError(f"distortion coefficients must have shape (7,), got {a.shape}")
    return a


#: Points per block of a large :func:`undistort` call: its dozen temporaries per block stay in the cache
#: (a million points in one call ran at 0.8 of the rate of calls of 65536; per point the same arithmetic).
BLOCK_POINTS = 32768


def _in_blocks(fn, d: np.ndarray, *args, **kwargs):
    """``fn(d, ...)`` over blocks of :data:`BLOCK_POINTS` points of ``d`` (..., 2), the outputs (arrays
    with the points first, or a tuple of them) assembled in arrays allocated once."""
    lead = d.shape[:-1]
    flat = d.reshape(-1, 2)
    n = flat.shape[0]
    outs = None
    for s in range(0, n, BLOCK_POINTS):
        r = fn(flat[s: s + BLOCK_POINTS], *args, **kwargs)
        parts = r if isinstance(r, tuple) else (r,)
        if outs is None:
            outs = [np.empty((n,) + p.shape[1:], dtype=p.dtype) for p in parts]
        for o, p in zip(outs, parts):
            o[s: s + p.shape[0]] = p
    outs = [o.reshape(lead + o.shape[1:]) for o in outs]
    return tuple(outs) if isinstance(r, tuple) else outs[0]


def undistort(d_mm, dist, c_mm, *, jacobians: bool = False):
    """Ideal pinhole point from a measured impact point (Eq 7-16, docs/model.md#distortion).

    ``u = d (1 + l1 h^2 + l2 h^4)`` with ``h = |d|`` (PSD, Eq 7-10); then with
    ``e = u - c``, ``r = |e|``:
    ``x = u + e (k1 r^2 + k2 r^4 + k3 r^6) + tangential(e)`` (Eq 11-16).

    Parameters
    ----------
    d_mm : (..., 2) array_like
        Measured impact points, mm.
    dist : Distortion or (7,) array_like
    c_mm : (2,) array_like
        Optical centre (cx, cy), mm.
    jacobians : bool or "d"
        Also return ``dx_dd`` (..., 2, 2), ``dx_dc`` (..., 2, 2) and
        ``dx_dcoeffs`` (..., 2, 7); ``"d"`` returns ``dx_dd`` only.

    Returns
    -------
    x : (..., 2) ndarray, ideal points in mm (and the Jacobians if asked).
    """
    d = np.asarray(d_mm, dtype=float)
    # (blocks only with one centre and one set of coefficients: per-point ones would need slicing too)
    if (d.ndim >= 2 and d.shape[-1] == 2 and d.size > 4 * BLOCK_POINTS and np.shape(c_mm) == (2,)
            and np.shape(_as_coeffs(dist)) == (7,)):
        return _in_blocks(_undistort, d, dist, c_mm, jacobians=jacobians)
    return _undistort(d, dist, c_mm, jacobians=jacobians)


def _undistort(d, dist, c_mm, *, jacobians=False):
    """:func:`undistort` of one block of points."""
    k1, k2, k3, p1, p2, l1, l2 = _as_coeffs(dist)
    c = np.asarray(c_mm, dtype=float)
    h2 = np.einsum("...i,...i->...", d, d)
    s = 1.0 + l1 * h2 + l2 * h2 * h2
    u = d * s[..., None]
    e = u - c
    ex, ey = e[..., 0], e[..., 1]
    r2 = ex * ex + ey * ey
    rad = r2 * (k1 + r2 * (k2 + r2 * k3))
    tx = p1 * (r2 + 2 * ex * ex) + 2 * p2 * ex * ey
    ty = p2 * (r2 + 2 * ey * ey) + 2 * p1 * ex * ey
    x = u + e * rad[..., None] + np.stack([tx, ty], axis=-1)
    if not jacobians:
        return x
    if jacobians == "d":  # only dx/dd (Newton steps of distort)
        drad_dr2 = k1 + r2 * (2 * k2 + 3 * k3 * r2)
        g = 2 * drad_dr2
        G = np.empty(d.shape[:-1] + (2, 2))
        G[..., 0, 0] = 1 + rad + g * ex * ex + 6 * p1 * ex + 2 * p2 * ey
        G[..., 0, 1] = g * ex * ey + 2 * p1 * ey + 2 * p2 * ex
        G[..., 1, 0] = g * ex * ey + 2 * p2 * ex + 2 * p1 * ey
        G[..., 1, 1] = 1 + rad + g * ey * ey + 6 * p2 * ey + 2 * p1 * ex
        if l1 == 0.0 and l2 == 0.0:
            return x, G
        ds = 2 * (l1 + 2 * l2 * h2)
        du_dd = np.empty_like(G)
        du_dd[..., 0, 0] = s + ds * d[..., 0] * d[..., 0]
        du_dd[..., 0, 1] = du_dd[..., 1, 0] = ds * d[..., 0] * d[..., 1]
        du_dd[..., 1, 1] = s + ds * d[..., 1] * d[..., 1]
        return x, G @ du_dd
    eye = np.eye(2)
    # G = d(lens correction)/de
    drad_dr2 = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    G = rad[..., None, None] * eye + 2 * drad_dr2[..., None, None] * (e[..., :, None] * e[..., None, :])
    G[..., 0, 0] += 6 * p1 * ex + 2 * p2 * ey
    G[..., 0, 1] += 2 * p1 * ey + 2 * p2 * ex
    G[..., 1, 0] += 2 * p2 * ex + 2 * p1 * ey
    G[..., 1, 1] += 6 * p2 * ey + 2 * p1 * ex
    dx_du = eye + G
    ds_dh2 = l1 + 2 * l2 * h2
    du_dd = s[..., None, None] * eye + 2 * ds_dh2[..., None, None] * (d[..., :, None] * d[..., None, :])
    dx_dd = dx_du @ du_dd
    dx_dc = -G
    dx_dcoef = np.zeros(d.shape[:-1] + (2, 7))
    dx_dcoef[..., :, 0] = e * r2[..., None]
    dx_dcoef[..., :, 1] = e * (r2 * r2)[..., None]
    dx_dcoef[..., :, 2] = e * (r2 * r2 * r2)[..., None]
    dx_dcoef[..., 0, 3] = r2 + 2 * ex * ex
    dx_dcoef[..., 1, 3] = 2 * ex * ey
    dx_dcoef[..., 0, 4] = 2 * ex * ey
    dx_dcoef[..., 1, 4] = r2 + 2 * ey * ey
    du_dl1 = d * h2[..., None]
    du_dl2 = d * (h2 * h2)[..., None]
    dx_dcoef[..., :, 5] = np.einsum("...ij,...j->...i", dx_du, du_dl1)
    dx_dcoef[..., :, 6] = np.einsum("...ij,...j->...i", dx_du, du_dl2)
    return x, dx_dd, dx_dc, dx_dcoef


@dataclass(frozen=True)
class DistortResult:
    """Result of :func:`distort`.

    Attributes
    ----------
    d_mm : (..., 2) ndarray
        Measured-plane points; NaN where the inverse did not converge.
    converged : (...) bool ndarray
    iterations : int
        Newton iterations used by the slowest point.
    """

    d_mm: np.ndarray
    converged: np.ndarray
    iterations: int
    dx_dd: np.ndarray | None = None
    dx_dc: np.ndarray | None = None
    dx_dcoeffs: np.ndarray | None = None


def _inv2(J):
    det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
    inv = np.empty_like(J)
    inv[..., 0, 0] = J[..., 1, 1]
    inv[..., 1, 1] = J[..., 0, 0]
    inv[..., 0, 1] = -J[..., 0, 1]
    inv[..., 1, 0] = -J[..., 1, 0]
    return inv / det[..., None, None], det


def distort(
    x_mm,
    dist,
    c_mm,
    *,
    tol_mm: float = 1e-13,
    max_iter: int = 50,
    d0_mm=None,
    keep_failed: bool = False,
    jacobians: bool = False,
) -> DistortResult:
    """Measured point ``d`` with ``undistort(d) = x`` (docs/model.md#distortion), by Newton's method.

    The start is a fixed-point estimate of the radial inverse; each Newton step
    is halved while it does not reduce the residual.  A point is converged when
    ``|undistort(d) - x| <= tol_mm * max(1, |x|)`` and the local Jacobian of
    the model has a positive determinant (a fold of the model is not an
    inverse).

    Parameters
    ----------
    x_mm : (..., 2) array_like
        Ideal pinhole points, mm.
    dist : Distortion or (7,) array_like
    c_mm : (2,) array_like

    Returns
    -------
    DistortResult
    """
    coef = _as_coeffs(dist)
    x_in = np.asarray(x_mm, dtype=float)
    shape = x_in.shape
    x = x_in.reshape(-1, 2)
    c = np.asarray(c_mm, dtype=float)
    k1, k2, k3 = coef[:3]
    if d0_mm is not None:
        d0 = np.broadcast_to(np.asarray(d0_mm, dtype=float), shape).reshape(-1, 2)
        good0 = np.all(np.isfinite(d0), axis=1)
    else:
        good0 = np.zeros(x.shape[0], dtype=bool)
    # start: invert the lens radial part about c by a few fixed-point steps
    d = x.copy()
    if not np.all(good0):
        e = x - c
        for _ in range(3):
            e_d = d - c
            rr = np.einsum("...i,...i->...", e_d, e_d)
            rad = rr * (k1 + rr * (k2 + rr * k3))
            with np.errstate(all="ignore"):
                cand = c + e / (1.0 + rad)[..., None]
            d = np.where(np.isfinite(cand), cand, d)
    if d0_mm is not None:
        d[good0] = d0[good0]
    tol = tol_mm * np.maximum(1.0, np.hypot(x[:, 0], x[:, 1]))
    n = x.shape[0]
    idx = np.arange(n)  # points still iterating
    step = np.zeros((n, 2))
    prev_err = np.full(n, np.inf)
    err = np.full(n, np.inf)
    det = np.zeros(n)
    it_used = 0
    if jacobians:
        Jd_all = np.zeros((n, 2, 2))
        Jc_all = np.zeros((n, 2, 2))
        Jk_all = np.zeros((n, 2, 7))
    for it in range(max_iter + 1):
        if idx.size == 0:
            break
        if jacobians:
            xa, J, Jc, Jk = undistort(d[idx], coef, c, jacobians=True)
        else:
            xa, J = undistort(d[idx], coef, c, jacobians="d")
        res = xa - x[idx]
        e_new = np.hypot(res[:, 0], res[:, 1])
        # backtrack where the last step made things worse
        worse = ~(e_new < prev_err[idx]) & np.isfinite(prev_err[idx])
        if np.any(worse):
            w = idx[worse]
            step[w] *= 0.5
            d[w] += step[w]  # undo half of the step
            keep_going = np.abs(step[w]).max(axis=1) > 1e-16
            prev_err[w[~keep_going]] = np.inf  # give up backtracking, accept
        ok = ~worse
        i_ok = idx[ok]
        err[i_ok] = e_new[ok]
        Jo = J[ok]
        det_o = Jo[:, 0, 0] * Jo[:, 1, 1] - Jo[:, 0, 1] * Jo[:, 1, 0]
        det[i_ok] = det_o
        if jacobians:
            Jd_all[i_ok] = Jo
            Jc_all[i_ok] = Jc[ok]
            Jk_all[i_ok] = Jk[ok]
        done = ok.copy()
        done[ok] = (e_new[ok] <= tol[i_ok]) | ~np.isfinite(e_new[ok])
        active_ok = ok & ~done
        if it == max_iter:
            break
        ia = idx[active_ok]
        Ja = J[active_ok]
        ra = res[active_ok]
        deta = Ja[:, 0, 0] * Ja[:, 1, 1] - Ja[:, 0, 1] * Ja[:, 1, 0]
        sx = (Ja[:, 1, 1] * ra[:, 0] - Ja[:, 0, 1] * ra[:, 1]) / deta
        sy = (-Ja[:, 1, 0] * ra[:, 0] + Ja[:, 0, 0] * ra[:, 1]) / deta
        st = np.stack([sx, sy], axis=1)
        prev_err[ia] = e_new[active_ok]
        step[ia] = st
        d[ia] -= st
        # Newton converges quadratically: after a step s the error is about
        # kappa s^2, with kappa (the model's curvature) well below 1/mm on a
        # PSD. A step below 0.3 sqrt(tol) leaves an error below tol/10: accept
        # those points without evaluating the model again.
        smax = np.abs(st).max(axis=1)
        tiny = smax <= 0.3 * np.sqrt(tol[ia])
        if np.any(tiny):
            it_tiny = ia[tiny]
            err[it_tiny] = smax[tiny] ** 2  # the second-order bound of the remaining error
            ia = ia[~tiny]
        idx = np.concatenate([ia, idx[worse]])
        it_used = it + 1
    ok = np.isfinite(err) & (err <= tol * 10) & (det > 0) & _on_monotone_branch(d, coef, c)
    if not keep_failed:
        d = np.where(ok[:, None], d, np.nan)
    out = DistortResult(d_mm=d.reshape(shape), converged=ok.reshape(shape[:-1]), iterations=it_used)
    if jacobians:
        lead = shape[:-1]
        out = DistortResult(
            out.d_mm,
            out.converged,
            it_used,
            Jd_all.reshape(lead + (2, 2)),
            Jc_all.reshape(lead + (2, 2)),
            Jk_all.reshape(lead + (2, 7)),
        )
    return out


def _on_monotone_branch(d, coef, c):
    """True where ``d`` lies on the branch of the model that starts at the centre.

    Both radial maps (PSD about (0, 0), lens about c) must scale by a positive
    factor and grow with the radius there; otherwise a Newton solution is a
    point folded through the centre, not the physical pre-image.
    """
    k1, k2, k3, _, _, l1, l2 = coef
    h2 = np.einsum("...i,...i->...", d, d)
    s_psd = 1 + h2 * (l1 + l2 * h2)
    ds_psd = 1 + h2 * (3 * l1 + 5 * l2 * h2)
    u = d * s_psd[..., None]
    e = u - c
    r2 = np.einsum("...i,...i->...", e, e)
    s_lens = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    ds_lens = 1 + r2 * (3 * k1 + r2 * (5 * k2 + 7 * r2 * k3))
    with np.errstate(invalid="ignore"):
        return (s_psd > 0) & (ds_psd > 0) & (s_lens > 0) & (ds_lens > 0)


def distort_jacobians(d_mm, dist, c_mm, *, undistort_jacobians=None):
    """Jacobians of the distortion map at its solution ``d`` (implicit function theorem).

    From ``undistort(d; c, coeffs) = x``:
    ``dd/dx = (dx/dd)^-1``, ``dd/dc = -(dx/dd)^-1 dx/dc``,
    ``dd/dcoeffs = -(dx/dd)^-1 dx/dcoeffs``.

    ``undistort_jacobians`` may pass ``(dx_dd, dx_dc, dx_dcoeffs)`` already
    computed at ``d`` (see ``distort(..., jacobians=True)``).

    Returns
    -------
    dd_dx (..., 2, 2), dd_dc (..., 2, 2), dd_dcoeffs (..., 2, 7)
    """
    if undistort_jacobians is None:
        _, dx_dd, dx_dc, dx_dcoef = undistort(d_mm, dist, c_mm, jacobians=True)
    else:
        dx_dd, dx_dc, dx_dcoef = undistort_jacobians
    inv, _ = _inv2(dx_dd)
    return inv, -inv @ dx_dc, -inv @ dx_dcoef
