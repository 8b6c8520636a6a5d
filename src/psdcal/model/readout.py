"""PSD readout: four amplified anode signals <-> impact point (docs/model.md#psd-readout).

Pin-cushion (improved tetra-lateral) PSD, channel order everywhere in psdcal:
``(vx1, vx2, vy1, vy2)``.  Lengths in mm, signals in any unit (they cancel).
"""
from __future__ import annotations

import numpy as np

from psdcal.errors import InputError, ZeroSignalError

#: Active area of the Hamamatsu S5991-01, mm (docs/model.md#frames-and-units).
LX_MM = 9.0
LY_MM = 9.0
CHANNELS = ("vx1", "vx2", "vy1", "vy2")

# Rows: channel; columns: coefficient of (1, a, b) in the current split, a = 2x/Lx, b = 2y/Ly.
_SPLIT = 0.25 * np.array(
    [
        [1.0, -1.0, -1.0],  # x1
        [1.0, 1.0, 1.0],  # x2
        [1.0, 1.0, -1.0],  # y1
        [1.0, -1.0, 1.0],  # y2
    ]
)
# Numerator signs of Eq 1 and Eq 2 over (vx1, vx2, vy1, vy2).
_NUM_X = np.array([-1.0, 1.0, 1.0, -1.0])
_NUM_Y = np.array([-1.0, 1.0, -1.0, 1.0])


def impact_point(v, lx_mm: float = LX_MM, ly_mm: float = LY_MM, *, min_sum: float = 0.0):
    """Impact point from the four signals (Eq 1, 2).

    Parameters
    ----------
    v : (..., 4) array_like
        Signals ``vx1, vx2, vy1, vy2`` (amplitudes, any unit).
    lx_mm, ly_mm : float
        PSD active lengths, mm.
    min_sum : float
        A sum whose magnitude is ``<= min_sum`` (after a relative floor of
        1e-12 of the largest signal) raises :class:`ZeroSignalError`.

    Returns
    -------
    (..., 2) ndarray
        ``(x_mm, y_mm)`` in the sensor frame.
    """
    v = np.asarray(v, dtype=float)
    if v.shape[-1] != 4:
        raise ValueError(f"signals must have shape (..., 4), got {v.shape}")
    total = v.sum(axis=-1)
    scale = np.max(np.abs(v), axis=-1)
    bad = ~(np.abs(total) > np.maximum(min_sum, 1e-12 * scale)) | ~np.isfinite(total)
    if np.any(bad):
        idx = np.argwhere(np.atleast_1d(bad))[0]
        raise ZeroSignalError(
            f"sum of the four PSD signals is zero or not finite at index {tuple(int(i) for i in idx)}"
        )
    x = 0.5 * lx_mm * (v @ _NUM_X) / total
    y = 0.5 * ly_mm * (v @ _NUM_Y) / total
    return np.stack([x, y], axis=-1)


def photocurrents(xy_mm, total=1.0, lx_mm: float = LX_MM, ly_mm: float = LY_MM):
    """Split of the photocurrent of a spot at ``xy_mm`` over the four anodes.

    The split ``I (1 +- a +- b) / 4`` (docs/model.md#psd-readout) makes :func:`impact_point`
    return ``xy_mm`` exactly.

    Parameters
    ----------
    xy_mm : (..., 2) array_like
    total : float or (...) array_like
        Total photocurrent (any unit).

    Returns
    -------
    (..., 4) ndarray
        Currents ``ix1, ix2, iy1, iy2``.
    """
    xy = np.asarray(xy_mm, dtype=float)
    a = 2.0 * xy[..., 0] / lx_mm
    b = 2.0 * xy[..., 1] / ly_mm
    basis = np.stack([np.ones_like(a), a, b], axis=-1)
    return np.asarray(total, dtype=float)[..., None] * (basis @ _SPLIT.T)


def gain_map(xy_mm, gains, lx_mm: float = LX_MM, ly_mm: float = LY_MM, *, jacobians: bool = False):
    """Point read out through channels with unequal gains (a projective map).

    With the current split of :func:`photocurrents`, each channel gain
    ``g_i`` scales an affine function of the true spot position, so numerator
    and denominator of Eq 1-2 stay affine and the readout is a homography of
    the sensor plane.  A common factor of the gains cancels: only the ratios
    matter.

    Parameters
    ----------
    xy_mm : (..., 2) array_like
        True spot positions.
    gains : (4,) array_like
        Channel gains ``(g_x1, g_x2, g_y1, g_y2)``.
    jacobians : bool
        Also return ``dxy_meas/dxy_true`` (..., 2, 2) and
        ``dxy_meas/dgains`` (..., 2, 4).

    Returns
    -------
    (..., 2) ndarray, the measured impact point.
    """
    g = np.asarray(gains, dtype=float)
    xy = np.asarray(xy_mm, dtype=float)
    a = 2.0 * xy[..., 0] / lx_mm
    b = 2.0 * xy[..., 1] / ly_mm
    basis = np.stack([np.ones_like(a), a, b], axis=-1)  # (..., 3)
    cur = basis @ _SPLIT.T  # (..., 4) currents per unit total
    v = cur * g
    s = v.sum(-1)
    nx = v @ _NUM_X
    ny = v @ _NUM_Y
    out = np.stack([0.5 * lx_mm * nx / s, 0.5 * ly_mm * ny / s], axis=-1)
    if not jacobians:
        return out
    # d(cur)/d(a,b): _SPLIT[:, 1:] (4, 2); dv/d(a,b) = g[:,None] * _SPLIT[:,1:]
    dv_dab = g[:, None] * _SPLIT[:, 1:]  # (4, 2)
    ds_dab = dv_dab.sum(0)
    dnx_dab = _NUM_X @ dv_dab
    dny_dab = _NUM_Y @ dv_dab
    dab_dxy = np.diag([2.0 / lx_mm, 2.0 / ly_mm])
    dx_dab = 0.5 * lx_mm * (dnx_dab[None] * s[..., None] - nx[..., None] * ds_dab[None]) / s[..., None] ** 2
    dy_dab = 0.5 * ly_mm * (dny_dab[None] * s[..., None] - ny[..., None] * ds_dab[None]) / s[..., None] ** 2
    dout_dxy = np.stack([dx_dab, dy_dab], axis=-2) @ dab_dxy
    # dv/dg_i = cur_i e_i
    dx_dg = 0.5 * lx_mm * (cur * _NUM_X * s[..., None] - nx[..., None] * cur) / s[..., None] ** 2
    dy_dg = 0.5 * ly_mm * (cur * _NUM_Y * s[..., None] - ny[..., None] * cur) / s[..., None] ** 2
    dout_dg = np.stack([dx_dg, dy_dg], axis=-2)
    return out, dout_dxy, dout_dg


def gain_homography(gains, lx_mm: float = LX_MM, ly_mm: float = LY_MM):
    """The 3x3 homography H with ``[x_meas, y_meas, 1] ~ H [x_true, y_true, 1]``.

    Exact closed form of :func:`gain_map` (docs/model.md#gain-homography derives it).
    """
    g = np.asarray(gains, dtype=float)
    w = g[:, None] * _SPLIT  # (4, 3): v = w @ (1, a, b)
    num_x = 0.5 * lx_mm * (_NUM_X @ w)
    num_y = 0.5 * ly_mm * (_NUM_Y @ w)
    den = w.sum(0)
    # rows act on (1, a, b); convert to (x, y, 1) columns.
    conv = np.array([[0.0, 0.0, 1.0], [2.0 / lx_mm, 0.0, 0.0], [0.0, 2.0 / ly_mm, 0.0]])
    return np.stack([num_x, num_y, den]) @ conv


def sensor_grid_mm(sensor_mm=(9.0, 9.0), n: int = 41, *, margin_mm: float = 0.0) -> np.ndarray:
    """A regular grid of points over the sensor.

    Parameters
    ----------
    sensor_mm : (Lx, Ly), mm
    n : int
        Points per side.
    margin_mm : float
        Keep this far from the sensor's edges.

    Returns
    -------
    (n, n, 2) ndarray, mm; ``[i, j]`` is row ``i`` (y) and column ``j`` (x).
    """
    hx, hy = sensor_mm[0] / 2 - margin_mm, sensor_mm[1] / 2 - margin_mm
    if hx <= 0 or hy <= 0:
        raise InputError(f"margin {margin_mm} mm leaves nothing of the {sensor_mm[0]:g} x {sensor_mm[1]:g} mm sensor",
                         field="margin_mm")
    xs = np.linspace(-hx, hx, n)
    ys = np.linspace(-hy, hy, n)
    X, Y = np.meshgrid(xs, ys)
    return np.stack([X, Y], axis=-1)

