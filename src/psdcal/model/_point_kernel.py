"""Compiled undistortion model at one point, shared by the calibration and the angle kernels.

The scalar form of :func:`psdcal.model.distortion.undistort` and its derivatives
(Eq 7-16, docs/model.md#distortion) that both the image-plane cost
(:mod:`psdcal.calibration._image_kernel`) and the angles of arrival
(:mod:`psdcal.measure._aoa_kernel`) evaluate per point; it sits in the model
layer so that neither borrows it from the other.
"""
from __future__ import annotations

from psdcal._jit import njit


@njit
def _model_terms(dx, dy, coef, cx, cy):
    """The undistortion model at one measured point d (Eq 7-16) and the parts of its derivatives.

    Returns ``(x0, x1, h2, ex, ey, r2, G00, G01, G10, G11, U00, U01, U11)``:
    the ideal point x; ``h2 = |d|^2``; ``e = u - c`` with ``u = d s(h2)``
    the PSD-corrected point and ``r2 = |e|^2``; ``G = d(lens correction)/de``
    (so ``dx/du = I + G`` and ``dx/dc = -G``); ``U = du/dd`` (symmetric,
    ``U10 = U01``).
    """
    k1, k2, k3, p1, p2, l1, l2 = coef[0], coef[1], coef[2], coef[3], coef[4], coef[5], coef[6]
    h2 = dx * dx + dy * dy
    s = 1.0 + l1 * h2 + l2 * h2 * h2
    ux, uy = dx * s, dy * s
    ex, ey = ux - cx, uy - cy
    r2 = ex * ex + ey * ey
    rad = r2 * (k1 + r2 * (k2 + r2 * k3))
    x0 = ux + ex * rad + p1 * (r2 + 2 * ex * ex) + 2 * p2 * ex * ey
    x1 = uy + ey * rad + p2 * (r2 + 2 * ey * ey) + 2 * p1 * ex * ey
    g = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))
    G00 = rad + g * ex * ex + 6 * p1 * ex + 2 * p2 * ey
    G01 = g * ex * ey + 2 * p1 * ey + 2 * p2 * ex
    G10 = g * ex * ey + 2 * p2 * ex + 2 * p1 * ey
    G11 = rad + g * ey * ey + 6 * p2 * ey + 2 * p1 * ex
    ds = 2 * (l1 + 2 * l2 * h2)
    U00 = s + ds * dx * dx
    U01 = ds * dx * dy
    U11 = s + ds * dy * dy
    return x0, x1, h2, ex, ey, r2, G00, G01, G10, G11, U00, U01, U11


__all__ = ["_model_terms"]
