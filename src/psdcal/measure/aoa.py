"""Angles of arrival with their uncertainty (docs/model.md#angle-of-arrival-and-position, the paper's Eq 39-42).

The chain, for one measurement::

    amplitudes a (4,) --(/ gains, Eq 1-2)--> d --(undistort, Eq 7-16)--> x
       --(A^-1, Eq 4)--> n = (xn, yn) --(atan, Eq 39)--> alpha = (alpha_x, alpha_y)

Every step is differentiated analytically, so the covariance of the result
is first-order propagation (``J Sigma J^T``) of two independent sources:

* the **calibration**: the covariance of the sensor's global parameters
  (:attr:`psdcal.measure.sensor_model.SensorModel.covariance`); this part is
  systematic: it is the same error for every measurement of a sensor;
* the **signal noise**: the covariance of the impact point ``d``, itself
  propagated from the amplitude noise of the demodulation.

The paper's Eq 40-42 are the special case ``alpha_x = atan(ex / f)`` with
only ``x`` and ``f`` uncertain, added in absolute value; here the full
covariance is propagated instead.
"""
from __future__ import annotations

import sys
import threading
from dataclasses import dataclass

import numpy as np

from psdcal.model.distortion import undistort
from psdcal.errors import ZeroSignalError
from psdcal.model.params import DISTORTION_NAMES
from psdcal.model.readout import impact_point
from psdcal.measure.sensor_model import GAIN_NAMES, SensorModel

# Numerator signs of Eq 1 and Eq 2 over (vx1, vx2, vy1, vy2).
_NUM_X = np.array([-1.0, 1.0, 1.0, -1.0])
_NUM_Y = np.array([-1.0, 1.0, -1.0, 1.0])


@dataclass(frozen=True)
class ImpactResult:
    """Impact points from carrier amplitudes (Eq 1-2), with their uncertainty.

    Attributes
    ----------
    d_mm : (..., 2) ndarray
        Measured impact points (after the channel-gain correction), mm; NaN
        where the signal sum was not positive.
    cov_d_mm2 : (..., 2, 2) ndarray
        Covariance of ``d_mm`` from the amplitude noise, mm^2.
    dd_dgains : (..., 2, 3) ndarray
        Derivative of ``d_mm`` with respect to ``(g_x2, g_y1, g_y2)``, mm.
    """

    d_mm: np.ndarray
    cov_d_mm2: np.ndarray
    dd_dgains: np.ndarray


def impact_from_amplitudes(a, model: SensorModel, var_a=None, *, on_zero: str = "raise") -> ImpactResult:
    """Impact point, its noise covariance and gain derivatives from amplitudes.

    The channels are divided by the sensor's relative gains, then Eq 1-2
    (:func:`psdcal.model.readout.impact_point`) gives ``d``.

    Parameters
    ----------
    a : (..., 4) array_like
        Carrier amplitudes ``vx1, vx2, vy1, vy2`` (signal unit).
    model : SensorModel
    var_a : (..., 4) array_like, optional
        Variances of the amplitudes (independent channels), signal unit^2.
        Zero when omitted.
    on_zero : {"raise", "nan"}
        What to do where the sum of the (gain-corrected) amplitudes is not
        positive: raise :class:`ZeroSignalError`, or return NaN there.

    Returns
    -------
    ImpactResult
    """
    a = np.asarray(a, dtype=float)
    g = model.gains
    v = a / g
    total = v.sum(axis=-1)
    bad = ~(total > 1e-12 * np.max(np.abs(v), axis=-1, initial=0.0)) | ~np.all(np.isfinite(v), axis=-1)
    if np.any(bad):
        if on_zero == "raise":
            idx = np.argwhere(np.atleast_1d(bad))[0]
            raise ZeroSignalError(
                f"sum of the four PSD amplitudes is not positive at index {tuple(int(i) for i in idx)}"
            )
        v = np.where(bad[..., None], 1.0, v)  # placeholder, set to NaN below
    d = impact_point(v, model.lx_mm, model.ly_mm)  # Eq 1-2
    s = v.sum(axis=-1)[..., None]
    # dd/dv (..., 2, 4): Eq 1 x = Lx/2 * (N_x . v)/s -> Lx/2 * (N_x s - N_x . v)/s^2
    dx_dv = 0.5 * model.lx_mm * (_NUM_X - (v @ _NUM_X)[..., None] / s) / s
    dy_dv = 0.5 * model.ly_mm * (_NUM_Y - (v @ _NUM_Y)[..., None] / s) / s
    dd_dv = np.stack([dx_dv, dy_dv], axis=-2)
    dd_da = dd_dv / g  # v = a / g
    # dv_i/dg_i = -a_i / g_i^2 = -v_i / g_i ; gains named g_x2, g_y1, g_y2 (g_x1 is the reference)
    dd_dg = (dd_dv * (-v / g)[..., None, :])[..., 1:]
    if var_a is None:
        cov = np.zeros(d.shape + (2,))
    else:
        var_a = np.broadcast_to(np.asarray(var_a, dtype=float), a.shape)
        cov = np.einsum("...ik,...k,...jk->...ij", dd_da, var_a, dd_da)
    if np.any(bad):
        d = np.where(bad[..., None], np.nan, d)
        cov = np.where(bad[..., None, None], np.nan, cov)
        dd_dg = np.where(bad[..., None, None], np.nan, dd_dg)
    return ImpactResult(d_mm=d, cov_d_mm2=cov, dd_dgains=dd_dg)


@dataclass(frozen=True)
class AoAResult:
    """Angles of arrival and their covariance (docs/model.md#angle-of-arrival-and-position, Eq 39).

    Attributes
    ----------
    x_mm : (..., 2) ndarray
        Ideal (undistorted) image points, mm.
    n : (..., 2) ndarray
        Normalised coordinates ``(xn, yn)`` with ``(xn, yn, 1) = A^-1 (x, y, 1)``.
    alpha_rad : (..., 2) ndarray
        ``(alpha_x, alpha_y) = (atan xn, atan yn)``, rad.
    cov_n_calib : (..., 2, 2) ndarray
        Covariance of ``n`` from the calibration covariance (systematic).
    cov_n_noise : (..., 2, 2) ndarray
        Covariance of ``n`` from the impact-point noise (random).
    dn_dp : (..., 2, n_params) ndarray or None
        Derivative of ``n`` with respect to the calibration parameters
        ``names`` (the order of the model's covariance); None when asked
        for without (``derivatives=False``: the covariances do not need it).
    dn_dd : (..., 2, 2) ndarray
        Derivative of ``n`` with respect to the measured impact point.
    names : tuple of str
    """

    x_mm: np.ndarray
    n: np.ndarray
    alpha_rad: np.ndarray
    cov_n_calib: np.ndarray
    cov_n_noise: np.ndarray
    dn_dp: np.ndarray
    dn_dd: np.ndarray
    names: tuple

    @property
    def cov_n(self) -> np.ndarray:
        """Total covariance of ``n`` (..., 2, 2)."""
        return self.cov_n_calib + self.cov_n_noise

    @property
    def dalpha_dn(self) -> np.ndarray:
        """Diagonal of ``d alpha / d n`` (..., 2): ``1 / (1 + n^2)``."""
        return 1.0 / (1.0 + self.n * self.n)

    @property
    def cov_alpha_rad2(self) -> np.ndarray:
        """Total covariance of ``alpha`` (..., 2, 2), rad^2."""
        g = self.dalpha_dn
        return self.cov_n * g[..., :, None] * g[..., None, :]

    @property
    def sigma_alpha_rad(self) -> np.ndarray:
        """1-sigma of ``(alpha_x, alpha_y)`` (..., 2), rad."""
        return np.sqrt(np.clip(np.diagonal(self.cov_n, axis1=-2, axis2=-1), 0.0, None)) * self.dalpha_dn

    @property
    def ray(self) -> np.ndarray:
        """Unit ray direction (..., 3) in the camera frame."""
        r = np.concatenate([self.n, np.ones(self.n.shape[:-1] + (1,))], axis=-1)
        return r / np.linalg.norm(r, axis=-1, keepdims=True)


def angles_from_points(d_mm, model: SensorModel, cov_d_mm2=None, dd_dgains=None, *,
                       derivatives: bool = True) -> AoAResult:
    """Angles of arrival of measured impact points, with their covariance.

    ``x = undistort(d)`` (Eq 7-16), ``yn = (y - cy) / fy``,
    ``xn = (x - cx - skew yn) / f`` (the inverse of Eq 4),
    ``alpha = atan(n)`` (Eq 39).

    Parameters
    ----------
    d_mm : (..., 2) array_like
        Measured impact points (gain-corrected), mm.
    model : SensorModel
    cov_d_mm2 : (..., 2, 2) array_like, optional
        Noise covariance of ``d_mm``, mm^2 (zero when omitted).
    dd_dgains : (..., 2, 3) array_like, optional
        Derivative of ``d_mm`` with respect to ``(g_x2, g_y1, g_y2)``; needed
        for the gain part of the calibration covariance (zero when omitted,
        e.g. for impact points that did not come from raw amplitudes).
    derivatives : bool
        Also return ``dn_dp`` (N x 2 x n_params numbers, what a triangulation
        with correlated calibration errors needs). ``False`` leaves it out
        (``dn_dp`` is None) and saves its cost; every other field is the same.

    Returns
    -------
    AoAResult
    """
    d = np.asarray(d_mm, dtype=float)
    from psdcal import _jit

    if d.ndim >= 1 and d.shape[-1] == 2 and _jit.use_compiled(d.size // 2, _jit.AUTO_MIN_ANGLES):
        return _angles_compiled(d, model, cov_d_mm2, dd_dgains, derivatives)
    return angles_from_points_reference(d, model, cov_d_mm2, dd_dgains, derivatives=derivatives)


def _factor_of(model: SensorModel, covariance_factor):
    """The covariance factor of ``model`` (computed once per model: models are frozen)."""
    key = "_aoa_covariance_factor"
    got = model.__dict__.get(key)
    if got is None:
        got = covariance_factor(model.covariance)
        object.__setattr__(model, key, got)
    return got


#: Output memory (float64 count, 32 MB) from which a call's buffer is kept for the next call: fresh memory
#: costs its first-touch page faults (the system zeroing it), a fifth of the time of a million points in one
#: call, which calls of 65536 points do not pay (below 32 MB the C allocator reuses freed memory itself).
SPARE_MIN = 1 << 22
#: At most this much (float64 count: 2 GB) is kept.
SPARE_MAX = 1 << 28
_spare: list = []  # at most one buffer, kept between calls
_spare_lock = threading.Lock()


def _output_buffer(size: int) -> np.ndarray:
    """``np.empty(size)``, or a part of the kept buffer of an earlier large call once no result uses it.

    The results of a call are views of its buffer: while any is alive the buffer's reference count says
    so and it is not reused (a later call gets fresh memory, which it keeps instead). The check and the
    claim (taking the view) are made under a lock. :func:`release_output_buffers` drops the kept memory.
    """
    if not (SPARE_MIN <= size <= SPARE_MAX):
        return np.empty(size)
    with _spare_lock:
        if _spare:
            b = _spare[0]
            # references: the list, ``b`` and getrefcount's argument; more: a result still uses it
            if sys.getrefcount(b) == 3 and size <= b.shape[0] <= 2 * size:
                return b[:size]
        b = np.empty(size)
        _spare[:] = [b]
        return b[:size]


def release_output_buffers() -> None:
    """Drop the output memory kept by :func:`angles_from_points` for its next large call."""
    with _spare_lock:
        _spare.clear()


def _angles_compiled(d, model: SensorModel, cov_d_mm2, dd_dgains, derivatives: bool = True) -> AoAResult:
    """:func:`angles_from_points` by the compiled kernel (psdcal.measure._aoa_kernel)."""
    from psdcal.measure._aoa_kernel import PARAM_CODES, angles_kernel, covariance_factor

    intr = model.intrinsics
    shape = d.shape[:-1]
    N = int(np.prod(shape)) if shape else 1
    dd = np.ascontiguousarray(d.reshape(N, 2))
    names = model.names
    codes = np.array([PARAM_CODES.index(nm) for nm in names], dtype=np.int64)
    if cov_d_mm2 is None:
        cov_d = np.zeros((0, 2, 2))
    else:
        cov_d = np.ascontiguousarray(np.broadcast_to(np.asarray(cov_d_mm2, dtype=float), shape + (2, 2)).reshape(N, 2, 2))
    if dd_dgains is None:
        ddg = np.zeros((0, 2, 3))
    else:
        ddg = np.ascontiguousarray(np.broadcast_to(np.asarray(dd_dgains, dtype=float), shape + (2, 3)).reshape(N, 2, 3))
    vals = np.array([intr.f_mm, intr.cx_mm, intr.cy_mm, intr.skew, intr.fy], dtype=float)
    # the outputs' memory from numpy (huge pages for large calls: fewer first-touch faults than numba's allocator),
    # that of an earlier large call when its results are gone (_output_buffer)
    buf = _output_buffer(18 * N + (2 * N * len(names) if derivatives else 0))
    x, n, alpha, covc, covn, dn_dp, dn_dd = angles_kernel(
        dd, vals, intr.fy_mm is not None, np.ascontiguousarray(model.distortion.as_array(), dtype=float), codes,
        *_factor_of(model, covariance_factor), cov_d, ddg, bool(derivatives), buf)
    return AoAResult(
        x_mm=x.reshape(shape + (2,)),
        n=n.reshape(shape + (2,)),
        alpha_rad=alpha.reshape(shape + (2,)),
        cov_n_calib=covc.reshape(shape + (2, 2)),
        cov_n_noise=covn.reshape(shape + (2, 2)),
        dn_dp=dn_dp.reshape(shape + (2, len(names))) if derivatives else None,
        dn_dd=dn_dd.reshape(shape + (2, 2)),
        names=names,
    )


def angles_from_points_reference(d_mm, model: SensorModel, cov_d_mm2=None, dd_dgains=None, *,
                                 derivatives: bool = True) -> AoAResult:
    """Numpy reference of :func:`angles_from_points` (the compiled kernel is tested against it)."""
    d = np.asarray(d_mm, dtype=float)
    intr = model.intrinsics
    f, fy, s = intr.f_mm, intr.fy, intr.skew
    c = intr.c
    x, dx_dd, dx_dc, dx_dcoef = undistort(d, model.distortion, c, jacobians=True)
    yn = (x[..., 1] - c[1]) / fy
    xn = (x[..., 0] - c[0] - s * yn) / f
    n = np.stack([xn, yn], axis=-1)
    # dn/dx (2, 2) of the inverse pinhole map
    dn_dx = np.array([[1.0 / f, -s / (f * fy)], [0.0, 1.0 / fy]])
    dn_dd = dn_dx @ dx_dd
    names = model.names
    dn_dp = np.zeros(d.shape[:-1] + (2, len(names)))
    zero = np.zeros_like(xn)
    separate_fy = intr.fy_mm is not None
    for k, name in enumerate(names):
        if name == "f_mm":
            col = np.stack([-xn / f, zero if separate_fy else -yn / f], axis=-1)
            if not separate_fy:  # fy = f also moves xn through yn
                col[..., 0] += s * yn / (f * f)
        elif name == "fy_mm":
            dyn = -yn / fy
            col = np.stack([-s * dyn / f, dyn], axis=-1)
        elif name == "skew":
            col = np.stack([-yn / f, zero], axis=-1)
        elif name == "cx_mm":
            col = dx_dc[..., :, 0] @ dn_dx.T + np.array([-1.0 / f, 0.0])
        elif name == "cy_mm":
            col = dx_dc[..., :, 1] @ dn_dx.T + np.array([s / (f * fy), -1.0 / fy])
        elif name in DISTORTION_NAMES:
            col = dx_dcoef[..., :, DISTORTION_NAMES.index(name)] @ dn_dx.T
        elif name in GAIN_NAMES:
            if dd_dgains is None:
                continue
            col = np.einsum("...ij,...j->...i", dn_dd, np.asarray(dd_dgains)[..., :, GAIN_NAMES.index(name)])
        else:  # pragma: no cover - SensorModel validates names
            raise KeyError(name)
        dn_dp[..., :, k] = col
    cov_calib = dn_dp @ model.covariance @ np.swapaxes(dn_dp, -1, -2)
    if cov_d_mm2 is None:
        cov_noise = np.zeros(d.shape + (2,))
    else:
        cov_noise = dn_dd @ np.asarray(cov_d_mm2, dtype=float) @ np.swapaxes(dn_dd, -1, -2)
    alpha = np.arctan(n)  # Eq 39
    return AoAResult(
        x_mm=x,
        n=n,
        alpha_rad=alpha,
        cov_n_calib=cov_calib,
        cov_n_noise=cov_noise,
        dn_dp=dn_dp if derivatives else None,
        dn_dd=dn_dd,
        names=names,
    )


def angles_from_amplitudes(a, model: SensorModel, var_a=None, *, on_zero: str = "raise",
                           derivatives: bool = True) -> AoAResult:
    """Angles of arrival from the four carrier amplitudes (Eq 1-2, 7-16, 39).

    Parameters
    ----------
    a : (..., 4) array_like
        Amplitudes ``vx1, vx2, vy1, vy2``.
    model : SensorModel
    var_a : (..., 4) array_like, optional
        Amplitude variances (independent channels).
    on_zero : {"raise", "nan"}
        See :func:`impact_from_amplitudes`.
    derivatives : bool
        Also return ``dn_dp`` (see :func:`angles_from_points`).

    Returns
    -------
    AoAResult
    """
    imp = impact_from_amplitudes(a, model, var_a, on_zero=on_zero)
    return angles_from_points(imp.d_mm, model, imp.cov_d_mm2, imp.dd_dgains, derivatives=derivatives)
