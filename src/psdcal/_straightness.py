"""Preliminary distortion estimate by line straightness (the paper's Section 3.2).

Template points that are collinear stay collinear under perspective, so after
a correct undistortion their measured points are collinear again. The paper's
slope form (Eq 30-35) has misprinted derivatives; as MODEL.md 6.1 says, we
minimise instead the squared distance of each undistorted point to the
total-least-squares line of its group, divided by the group's spread along
the line (which makes the cost invariant to a common scaling and rules out the
trivial "shrink everything" solution).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from .distortion import undistort


def find_lines(template_mm, *, min_points: int = 3, tol_rel: float = 1e-6) -> list[np.ndarray]:
    """All maximal sets of >= ``min_points`` collinear template points.

    Parameters
    ----------
    template_mm : (M, 2) array_like
    tol_rel : float
        Distance tolerance as a fraction of the template's extent.

    Returns
    -------
    list of int arrays (sorted indices), one per line, without duplicates.
    """
    P = np.asarray(template_mm, dtype=float)
    M = P.shape[0]
    extent = float(np.ptp(P, axis=0).max()) if M else 0.0
    tol = tol_rel * max(extent, 1e-12)
    seen: set[tuple[int, ...]] = set()
    lines = []
    for i in range(M - 1):
        dirs = P[i + 1 :] - P[i]
        norms = np.linalg.norm(dirs, axis=1)
        for jj in np.flatnonzero(norms > tol):
            j = i + 1 + jj
            u = dirs[jj] / norms[jj]
            n = np.array([-u[1], u[0]])
            dist = np.abs((P - P[i]) @ n)
            members = tuple(np.flatnonzero(dist <= tol))
            if len(members) >= min_points and members not in seen:
                seen.add(members)
                lines.append(np.array(members))
    return lines


@dataclass(frozen=True)
class StraightnessResult:
    """Preliminary radial distortion (k1 [mm^-2], k2 [mm^-4]) about ``c_mm``."""

    k: np.ndarray
    c_mm: np.ndarray
    n_lines: int
    rms_rel: float
    success: bool


def _line_residuals(pts_list):
    out = []
    for pts in pts_list:
        m = pts.mean(axis=0)
        q = pts - m
        # smallest principal direction of the 2x2 scatter = the line's normal
        C = q.T @ q
        w, V = np.linalg.eigh(C)
        spread = np.sqrt(max(w[1], 1e-300) / len(pts))
        out.append((q @ V[:, 0]) / spread)
    return np.concatenate(out) if out else np.zeros(0)


def estimate_radial(points_mm, lines, *, c_mm=(0.0, 0.0), n_terms: int = 2) -> StraightnessResult:
    """Estimate k1 (and k2) that make the measured lines straight (Section 3.2).

    Parameters
    ----------
    points_mm : (n_images, M, 2) array_like
        Measured impact points, NaN where missing.
    lines : list of index arrays from :func:`find_lines`
    c_mm : (2,) centre of distortion (the electrical centre by default).
    n_terms : 1 or 2

    Returns
    -------
    StraightnessResult (k has ``n_terms`` entries; zeros when there is no line).
    """
    pts = np.asarray(points_mm, dtype=float)
    c = np.asarray(c_mm, dtype=float)
    groups = []
    for img in pts:
        for idx in lines:
            g = img[idx]
            g = g[np.all(np.isfinite(g), axis=1)]
            if len(g) >= 3:
                groups.append(g)
    if not groups or n_terms < 1:
        return StraightnessResult(np.zeros(max(n_terms, 0)), c, 0, float("nan"), False)
    allp = np.concatenate(groups)
    rmax2 = float(np.max(np.sum((allp - c) ** 2, axis=1)))
    # unknowns scaled so that k_i * rmax^(2i) is O(1)
    scale = np.array([rmax2 ** (i + 1) for i in range(n_terms)])
    sizes = [len(g) for g in groups]
    flat = np.concatenate(groups)
    splits = np.cumsum(sizes)[:-1]

    def fun(z):
        coef = np.zeros(7)
        coef[:n_terms] = z / scale
        u = undistort(flat, coef, c)
        return _line_residuals(np.split(u, splits))

    sol = least_squares(fun, np.zeros(n_terms), method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14)
    k = sol.x / scale
    return StraightnessResult(k, c, len(groups), float(np.sqrt(np.mean(sol.fun**2))), bool(sol.success))
