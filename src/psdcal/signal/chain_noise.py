"""Impact-point noise of the simulated signal chain: its first-order prediction and its measurement.

docs/model.md#snr-definition and the paper's Section 4.4 (Figures 7-8). From an SNR (dB) to the
standard deviation of the measured impact point (mm):

* :func:`amplitude_noise_factor`: the amplitude estimator's variance per unit noise variance
  (lock-in: least squares on sin, cos, 1; band-pass: its filter's white-noise gain);
* :func:`predicted_point_cov` / :func:`predicted_point_std`: that variance carried through
  Eq 1-2 to first order, for any gains, PSD distortion ``l1`` and method;
* :func:`point_noise_vs_snr`: the same measured by simulation (any ``concurrent.futures``
  executor or Dask client, one child random stream per SNR);
* :func:`measure_point_trial`: one noisy measurement, a trial for
  :func:`psdcal.study.montecarlo.run_trials`.

The chain itself (settings, gains, amplitudes, records, estimators) is :mod:`psdcal.signal.chain`;
these names are also reachable from there.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np
from scipy import signal as _sig

from psdcal.errors import InputError
from psdcal.signal import demod
from psdcal.signal.chain import (
    _EXACT_FACTOR_MAX_SAMPLES,
    _SIGN_X,
    _SIGN_Y,
    ChainSettings,
    measure_points,
    noise_sigma,
    signal_amplitudes,
)



def amplitude_noise_factor(settings: ChainSettings | None = None) -> float:
    """First-order variance of the amplitude estimate per unit noise variance.

    Both estimators are, to first order in the noise, linear:
    ``A_hat - A = w . noise``; this returns ``|w|^2``, so that
    ``var(A_hat) = sigma^2 |w|^2`` (independent of ``A``).

    * lock-in: least squares on ``(sin, cos, 1)`` with Gram matrix ``G``;
      ``A_hat`` moves along the signal's phasor ``u = (cos phase, sin phase, 0)``,
      so ``|w|^2 = u^T G^-1 u``, which is ``2 / n`` for a whole number of
      periods (``var(A_hat) = 2 sigma^2 / n``).
    * band-pass: ``A_hat^2 = 2/m sum_W y^2 / g^2`` over the kept window
      ``W`` of ``m`` samples, ``y = F v`` the zero-phase filter output,
      ``g = |H(f_c)|^2``; so ``w = 2 F^T (y_W) / (m g^2 A_hat)`` for a unit
      carrier, computed exactly by filtering the unit vectors (``n^2``
      samples) up to ``n = 16384``; for longer records the approximation
      ``2 / m`` (edge effects neglected; 4 % high at the defaults).

    Parameters
    ----------
    settings : ChainSettings

    Returns
    -------
    float
        ``|w|^2``, dimensionless.
    """
    s = ChainSettings() if settings is None else settings
    return _noise_factor(replace(s, snr_db=None))


@functools.lru_cache(maxsize=32)
def _noise_factor(s: ChainSettings) -> float:
    n = s.n_samples
    t = s.time_s()
    wt = 2.0 * np.pi * s.carrier_hz * t
    if s.method == "lockin":
        basis = np.stack([np.sin(wt), np.cos(wt), np.ones(n)])
        gram = basis @ basis.T
        u = np.array([np.cos(s.phase_rad), np.sin(s.phase_rad), 0.0])
        return float(u @ np.linalg.solve(gram, u))
    sos = demod.butterworth_bandpass(s.rate_hz, s.carrier_hz, s.bandwidth_hz, int(s.filter_order))
    _, h = _sig.sosfreqz(sos, worN=[s.carrier_hz], fs=s.rate_hz)
    g = float(np.abs(h[0]) ** 2)
    y = _sig.sosfiltfilt(sos, s.carrier())
    win = demod.bandpass_window(n, s.rate_hz, s.carrier_hz, s.settle_periods)
    if n > _EXACT_FACTOR_MAX_SAMPLES:
        return 2.0 / (win.stop - win.start)
    v = np.zeros(n)
    v[win] = y[win]
    m = v[win].size
    a_hat = np.sqrt(2.0 * np.mean(y[win] ** 2)) / g
    # (F^T v)_j = (F e_j) . v, filtering blocks of unit vectors
    ftv = np.empty(n)
    step = max(1, 2**21 // n)
    for j0 in range(0, n, step):
        j1 = min(n, j0 + step)
        e = np.zeros((j1 - j0, n))
        e[np.arange(j1 - j0), np.arange(j0, j1)] = 1.0
        ftv[j0:j1] = _sig.sosfiltfilt(sos, e, axis=-1) @ v
    w = 2.0 * ftv / (m * g * g * a_hat)
    return float(w @ w)


def predicted_point_cov(xy_mm, settings: ChainSettings, gains=None, l1: float = 0.0):
    """First-order covariance of the measured impact point from the signal noise, mm^2.

    Each channel's amplitude estimate has variance
    ``s_A^2 = sigma^2 |w|^2`` (:func:`noise_sigma`,
    :func:`amplitude_noise_factor`), independent across channels.  Eq 1-2,
    ``x = Lx/2 N_x / S`` with ``N_x = sum_i c_i A_i``, ``S = sum_i A_i``
    (``c = (-1, 1, 1, -1)``), give ``dx/dA_i = (Lx/2 c_i - x) / S``, so

    ``var(x) = s_A^2 sum_i (Lx/2 c_i - x)^2 / S^2 = s_A^2 (Lx^2 + 4 x^2) / S^2``

    and ``cov(x, y) = 4 x y s_A^2 / S^2``.  With equal gains
    (``S = 4 A_mean``) and the lock-in (``|w|^2 = 2/n``):
    ``std(x) = sqrt(Lx^2 + 4 x^2) / (4 sqrt(n) 10^(snr_db/20))`` at spots
    inside the diamond ``|2x/Lx| + |2y/Ly| <= 1``.

    Parameters
    ----------
    xy_mm : (..., 2) array_like
        True spot positions, mm.
    settings : ChainSettings
        ``snr_db`` must be set.
    gains : (4,) array_like or None
    l1 : float

    Returns
    -------
    (..., 2, 2) ndarray
        Covariance of ``(x, y)``, mm^2.
    """
    if settings.snr_db is None:
        raise InputError("a noise prediction needs an SNR", field="snr_db")
    amps = signal_amplitudes(xy_mm, settings, gains, l1)
    s_a2 = noise_sigma(amps, settings.snr_db) ** 2 * amplitude_noise_factor(settings)
    total = amps.sum(axis=-1)
    x = 0.5 * settings.lx_mm * (amps @ _SIGN_X) / total  # Eq 1
    y = 0.5 * settings.ly_mm * (amps @ _SIGN_Y) / total  # Eq 2
    dx_da = (0.5 * settings.lx_mm * _SIGN_X - x[..., None]) / total[..., None]
    dy_da = (0.5 * settings.ly_mm * _SIGN_Y - y[..., None]) / total[..., None]
    jac = np.stack([dx_da, dy_da], axis=-2)  # (..., 2, 4)
    return s_a2[..., None, None] * (jac @ np.swapaxes(jac, -1, -2))


def predicted_point_std(xy_mm, settings: ChainSettings, gains=None, l1: float = 0.0):
    """First-order standard deviation of the measured ``(x, y)``, mm, shape (..., 2).

    Square roots of the diagonal of :func:`predicted_point_cov`.
    """
    cov = predicted_point_cov(xy_mm, settings, gains, l1)
    return np.sqrt(np.stack([cov[..., 0, 0], cov[..., 1, 1]], axis=-1))


@dataclass(frozen=True)
class NoiseVsSnr:
    """Impact-point noise against SNR at one spot (:func:`point_noise_vs_snr`).

    Attributes
    ----------
    snr_db : (k,) ndarray
    measured_std_mm : (k, 2) ndarray
        Sample standard deviation of the measured ``(x, y)``, mm.
    measured_std_se_mm : (k, 2) ndarray
        Its standard error (:func:`psdcal._stats.std_standard_error`).
    predicted_std_mm : (k, 2) ndarray
        First-order prediction (:func:`predicted_point_std`).
    mean_mm : (k, 2) ndarray
        Mean measured point (the noiseless readout plus any noise bias).
    xy_mm : (2,) ndarray
        True spot position.
    n : int
        Noise realisations per SNR.
    settings : ChainSettings
        With ``snr_db`` None (it varies along the table).
    """

    snr_db: np.ndarray
    measured_std_mm: np.ndarray
    measured_std_se_mm: np.ndarray
    predicted_std_mm: np.ndarray
    mean_mm: np.ndarray
    xy_mm: np.ndarray
    n: int
    settings: ChainSettings

    @property
    def ratio(self) -> np.ndarray:
        """Measured over predicted std, (k, 2)."""
        return self.measured_std_mm / self.predicted_std_mm


def _noise_at_snr(spots_mm, settings: ChainSettings, gains, gen, l1: float):
    """One SNR of :func:`point_noise_vs_snr`: (std (2,), its standard error (2,), mean (2,)), mm.

    A top-level function, so that an executor can pickle it to another process.
    """
    from psdcal._stats import std_standard_error

    pts = measure_points(spots_mm, settings, gains, gen, l1)
    se = np.array([std_standard_error(pts[:, 0]), std_standard_error(pts[:, 1])])
    return pts.std(axis=0, ddof=1), se, pts.mean(axis=0)


def point_noise_vs_snr(
    snr_db_values,
    settings: ChainSettings | None = None,
    n: int = 2000,
    rng=None,
    *,
    xy_mm=(0.0, 0.0),
    gains=None,
    l1: float = 0.0,
    executor=None,
) -> NoiseVsSnr:
    """Measure the impact-point noise of one spot at several SNRs, by simulation.

    For each SNR, ``n`` independent noisy records of the spot at ``xy_mm``
    go through the whole chain (:func:`measure_points`); the sample standard
    deviation of ``x`` and ``y`` is compared with :func:`predicted_point_std`.

    Parameters
    ----------
    snr_db_values : (k,) array_like
        SNRs, dB.
    settings : ChainSettings
        Its ``snr_db`` is ignored.
    n : int
        Realisations per SNR (>= 2).
    rng : numpy.random.Generator, int or None
        Each SNR gets its own child stream (``Generator.spawn``), so a
        result does not depend on the other SNRs in the list.
    xy_mm : (2,) array_like
        True spot position, mm.
    gains, l1
        As in :func:`measure_points`.
    executor : concurrent.futures.Executor, optional
        Runs one task per SNR (each with its own child stream, so the result is
        the same bit for bit as without one): a ``ProcessPoolExecutor``, or a
        Dask cluster's ``distributed.Client(address).get_executor()``. It is
        not shut down. None: in this process.

    Returns
    -------
    NoiseVsSnr
    """
    s = ChainSettings() if settings is None else settings
    snrs = np.atleast_1d(np.asarray(snr_db_values, dtype=float))
    if snrs.ndim != 1 or snrs.size == 0 or not np.all(np.isfinite(snrs)):
        raise InputError("SNR values must be a non-empty list of finite numbers", field="snr_db")
    if int(n) < 2:
        raise InputError(f"need at least 2 realisations, got {n}", field="n")
    p = np.asarray(xy_mm, dtype=float)
    if p.shape != (2,):
        raise ValueError(f"xy_mm must have shape (2,), got {p.shape}")
    if not (abs(p[0]) <= s.lx_mm / 2 and abs(p[1]) <= s.ly_mm / 2):
        raise InputError(f"spot ({p[0]:g}, {p[1]:g}) mm lies outside the active area", field="xy_mm")
    streams = np.random.default_rng(rng).spawn(snrs.size)
    spots = np.broadcast_to(p, (int(n), 2))
    std = np.empty((snrs.size, 2))
    se = np.empty((snrs.size, 2))
    mean = np.empty((snrs.size, 2))
    pred = np.empty((snrs.size, 2))
    tasks = [(spots, replace(s, snr_db=float(snr)), gains, gen, l1) for snr, gen in zip(snrs, streams)]
    if executor is None:
        done = [_noise_at_snr(*t) for t in tasks]
    else:
        futures = [executor.submit(_noise_at_snr, *t) for t in tasks]
        done = [f.result() for f in futures]
    for k, (task, (std_k, se_k, mean_k)) in enumerate(zip(tasks, done)):
        std[k], se[k], mean[k] = std_k, se_k, mean_k
        pred[k] = predicted_point_std(p, task[1], gains, l1)
    return NoiseVsSnr(snrs, std, se, pred, mean, p, int(n), replace(s, snr_db=None))


def measure_point_trial(rng, *, x_mm: float = 0.0, y_mm: float = 0.0, snr_db: float | None = None,
                        method: str | None = None, settings: ChainSettings | None = None, gains=None,
                        l1: float = 0.0) -> dict:
    """One noisy measurement of one spot: a trial function for :func:`psdcal.study.montecarlo.run_trials`.

    ``snr_db`` and ``method``, when given, override ``settings``.

    Returns
    -------
    dict
        ``{"x_mm": ..., "y_mm": ...}``, the measured impact point.
    """
    s = ChainSettings() if settings is None else settings
    changes = {}
    if snr_db is not None:
        changes["snr_db"] = float(snr_db)
    if method is not None:
        changes["method"] = method
    if changes:
        s = replace(s, **changes)
    x, y = measure_points(np.array([x_mm, y_mm]), s, gains, rng, l1)
    return {"x_mm": float(x), "y_mm": float(y)}
