"""Plane-to-sensor homographies by the direct linear transform (Eq 17-18, 36-38).

Hartley normalisation (R. Hartley, "In defense of the eight-point algorithm",
IEEE PAMI 19(6), 1997; the paper's Section 3.3): both point sets are centred
and scaled to a mean distance of sqrt(2) from the origin before the DLT, and
the solution is denormalised as ``H = T_Q^-1 H^o T_P`` (Eq 38).
"""
from __future__ import annotations

import functools

import numpy as np

from psdcal import _jit
from psdcal.errors import DegenerateViewsError

@functools.cache
def linear_kernels():
    """The compiled linear-stage module :mod:`psdcal.calibration._linear_kernel`, imported at the first
    compiled call (it imports numba)."""
    from psdcal.calibration import _linear_kernel

    return _linear_kernel


# the errors of a view without a homography (the compiled and the numpy paths raise the same)
def _few_points(label, count: int) -> DegenerateViewsError:
    return DegenerateViewsError(f"{label}: {count} points, a homography needs at least 4")


def _collinear(label) -> DegenerateViewsError:
    return DegenerateViewsError(f"{label}: its points are collinear, a homography needs points spread on the plane")


def _rank_deficient(label) -> DegenerateViewsError:
    return DegenerateViewsError(f"{label}: the points do not determine a homography (rank-deficient DLT)")


def collinearity(pts) -> float:
    """Ratio of the smaller to the larger singular value of centred (n, 2) points (0 = collinear)."""
    pts = np.asarray(pts, dtype=float)
    s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    return float(s[-1] / s[0]) if s[0] > 0 else 0.0


def collinearity_batch(pts, valid) -> np.ndarray:
    """:func:`collinearity` of the valid points of each of many point sets at once.

    Parameters
    ----------
    pts : (n, M, 2) array_like
        Points, mm (any value where not valid).
    valid : (n, M) bool
        Which points of each set count.

    Returns
    -------
    (n,) ndarray: smaller over larger singular value of each set's centred
    valid points (0 = collinear, and for sets with no spread or no point).
    The invalid rows are zeroed after centring, which leaves the singular
    values unchanged; they come from each set's 2 x 2 scatter matrix in
    closed form (the smaller one summed across the principal direction).
    """
    pts = np.asarray(pts, dtype=float)
    valid = np.asarray(valid, dtype=bool)
    w = valid[..., None]
    cnt = np.maximum(valid.sum(axis=1), 1)[:, None]
    mean = np.where(w, pts, 0.0).sum(axis=1) / cnt
    centred = np.where(w, pts - mean[:, None, :], 0.0)
    # singular values of the centred points: square roots of the eigenvalues of their 2 x 2 scatter matrix
    a = np.einsum("nm,nm->n", centred[..., 0], centred[..., 0])
    b = np.einsum("nm,nm->n", centred[..., 0], centred[..., 1])
    c = np.einsum("nm,nm->n", centred[..., 1], centred[..., 1])
    # the smaller eigenvalue as the scatter across the principal direction, summed from the points
    # themselves (no cancellation: exact to round-off relative to itself, even for nearly collinear sets)
    theta = 0.5 * np.arctan2(2.0 * b, a - c)
    across = centred[..., 1] * np.cos(theta)[:, None] - centred[..., 0] * np.sin(theta)[:, None]
    lam_min = np.einsum("nm,nm->n", across, across)
    lam_max = a + c - lam_min
    out = np.zeros(a.shape[0])
    pos = lam_max > 0
    out[pos] = np.sqrt(lam_min[pos] / lam_max[pos])
    return out


def homography(src, dst, *, normalize: bool = True, label: str = "view") -> np.ndarray:
    """Homography H (3, 3) with ``dst ~ H src`` by the DLT (Eq 17-18), optionally normalised.

    One view of :func:`homographies`.

    Parameters
    ----------
    src : (n, 2) array_like
        Template points (X, Y), mm.
    dst : (n, 2) array_like
        Image points (x, y), mm.
    normalize : bool
        Hartley normalisation (Eq 36-38); ``False`` gives the plain DLT the
        paper compares against.
    label : str
        Names the view in error messages.

    Returns
    -------
    H : (3, 3) ndarray scaled to unit Frobenius norm with ``H[2, 2] >= 0``.

    Raises
    ------
    DegenerateViewsError
        Fewer than 4 points, or collinear points.
    """
    dst = np.asarray(dst, dtype=float)
    return homographies(src, dst[None], normalize=normalize, labels=[label])[0]


def apply_homography(H, pts) -> np.ndarray:
    """Map (..., 2) points through H (3, 3)."""
    pts = np.asarray(pts, dtype=float)
    ph = pts @ H[:, :2].T + H[:, 2]
    return ph[..., :2] / ph[..., 2:3]


def homographies(src, dst, *, normalize: bool = True, labels=None) -> np.ndarray:
    """Homographies of many views at once (batched DLT, Eq 17-18 and 36-38).

    Parameters
    ----------
    src : (M, 2) array_like
        Template points, mm.
    dst : (n_views, M, 2) array_like
        Image points, mm; NaN rows are missing points (they add zero rows to
        the DLT, which leave its solution unchanged).
    labels : sequence of str, optional
        Names of the views for error messages (default "image i").

    Returns
    -------
    (n_views, 3, 3) ndarray, each as :func:`homography` returns it.

    With :func:`psdcal._jit.use_compiled`, the checks and the DLT of all
    views are one compiled call (:func:`psdcal.calibration._linear_kernel.homographies_kernel`:
    Householder QR and one-sided Jacobi SVD instead of LAPACK's); the numpy code
    below is its reference, with the same errors on the same views.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    n, M = dst.shape[:2]
    if n and dst.shape == (n, M, 2) and src.shape == (M, 2) and _jit.use_compiled(n * M):
        lk = linear_kernels()
        H, code, i, cnt = lk.homographies_kernel(np.ascontiguousarray(src), np.ascontiguousarray(dst), bool(normalize))
        if code == lk.H_OK:
            return H
        if code != lk.H_USE_REFERENCE:  # (an SVD that did not converge: the numpy code below decides)
            labels = [f"image {j}" for j in range(n)] if labels is None else list(labels)
            if code == lk.H_FEW_POINTS:
                raise _few_points(labels[i], cnt)
            if code == lk.H_COLLINEAR:
                raise _collinear(labels[i])
            raise _rank_deficient(labels[i])
    labels = [f"image {i}" for i in range(n)] if labels is None else list(labels)
    ok = np.all(np.isfinite(dst), axis=-1)  # (n, M)
    n_valid = ok.sum(axis=1)
    all_seen = bool(ok.all())  # every view sees every point: the template's own terms are the same for all views
    flat_src = (collinearity_batch(src[None], ok[:1]) if all_seen else
                collinearity_batch(np.broadcast_to(src, dst.shape), ok))
    flat = np.minimum(flat_src, collinearity_batch(dst, ok)) < 1e-6  # (n,)
    # the first view that fails either test names the error, as a loop over the views would
    for i in np.flatnonzero((n_valid < 4) | flat)[:1]:
        if n_valid[i] < 4:
            raise _few_points(labels[i], int(n_valid[i]))
        raise _collinear(labels[i])
    w = ok.astype(float)
    cnt = w.sum(axis=1)
    dst0 = np.where(ok[..., None], dst, 0.0)  # missing points at 0 (their DLT rows are zero)
    src_n = np.broadcast_to(src, dst.shape)
    if normalize:
        # per-view similarities of both point sets (Hartley), over the valid points
        def norm_mats(p, w=w, cnt=cnt):  # p (k, M, 2), finite
            mean = np.einsum("nm,nmk->nk", w, p) / cnt[:, None]
            d = p - mean[:, None]
            dist = np.einsum("nm,nm->n", w, np.hypot(d[..., 0], d[..., 1])) / cnt
            s = np.sqrt(2.0) / dist
            T = np.zeros((p.shape[0], 3, 3))
            T[:, 0, 0] = T[:, 1, 1] = s
            T[:, :2, 2] = -s[:, None] * mean
            T[:, 2, 2] = 1.0
            return T

        if all_seen:  # one similarity and one normalised template for all views
            Tp = np.broadcast_to(norm_mats(np.array(src_n[:1]), w[:1], cnt[:1]), (n, 3, 3))
            p = np.broadcast_to(src @ Tp[0, :2, :2].T + Tp[0, :2, 2], dst.shape)
        else:
            Tp = norm_mats(np.array(src_n))  # a copy (order "K"), summed in the same order as before
            p = np.einsum("nij,nmj->nmi", Tp[:, :2, :2], src_n) + Tp[:, None, :2, 2]
        Tq = norm_mats(dst0)
        q = np.einsum("nij,nmj->nmi", Tq[:, :2, :2], dst0) + Tq[:, None, :2, 2]
    else:
        p = src_n
        q = dst0
    X, Y = p[..., 0] * w, p[..., 1] * w
    x, y = q[..., 0], q[..., 1]
    A = np.zeros((n, 2 * M, 9))  # rows (X, Y, 1, 0, 0, 0, -xX, -xY, -x), then (0, 0, 0, X, Y, 1, -yX, -yY, -y)
    A[:, :M, 0], A[:, :M, 1], A[:, :M, 2] = X, Y, w
    A[:, M:, 3], A[:, M:, 4], A[:, M:, 5] = X, Y, w
    A[:, :M, 6], A[:, :M, 7], A[:, :M, 8] = -x * X, -x * Y, -x * w
    A[:, M:, 6], A[:, M:, 7], A[:, M:, 8] = -y * X, -y * Y, -y * w
    # the SVD of the (9, 9) triangular factor of A: the same singular values and right vectors as A's,
    # without A's (2M, 9) left vectors
    _, s, Vt = np.linalg.svd(np.linalg.qr(A, mode="r"))
    bad = s[:, 7] <= 1e-12 * s[:, 0]
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise _rank_deficient(labels[i])
    H = Vt[:, -1].reshape(n, 3, 3)
    if normalize:
        H = np.linalg.solve(Tq, H @ Tp)  # Eq 38
    H = H / np.linalg.norm(H, axis=(1, 2), keepdims=True)
    return np.where(H[:, 2:3, 2:3] >= 0, H, -H)
