"""Amplitude estimation of a modulated carrier (MODEL.md 3).

One implementation shared by the signal-chain simulator and the measurement
side (``psdcal locate``).  Signals are arrays whose **last axis is time**;
``rate_hz`` is the sampling rate in Hz and ``carrier_hz`` the carrier
frequency in Hz.  Amplitudes are returned in the signal's unit (peak, not RMS).
"""
from __future__ import annotations

import numpy as np
from scipy import signal as _sig


def lockin_iq(x, rate_hz: float, carrier_hz: float, *, t0_s: float = 0.0):
    """In-phase and quadrature components by synchronous (lock-in) demodulation.

    Projects the record on ``sin`` and ``cos`` of the carrier by least squares
    (the exact 2x2 normal equations, so a record that is not a whole number of
    periods is still unbiased) after removing the mean.

    Parameters
    ----------
    x : (..., n) array_like
        Samples.
    rate_hz, carrier_hz : float
    t0_s : float
        Time of the first sample, s (keeps phases consistent across chunks).

    Returns
    -------
    i, q : (...) ndarrays with ``x ~ i sin(w t) + q cos(w t) + mean``.
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[-1]
    t = t0_s + np.arange(n) / rate_hz
    w = 2 * np.pi * carrier_hz * t
    s, c = np.sin(w), np.cos(w)
    one = np.ones(n)
    basis = np.stack([s, c, one])  # (3, n)
    gram = basis @ basis.T
    rhs = x @ basis.T  # (..., 3)
    coef = np.linalg.solve(gram, rhs[..., None])[..., 0] if rhs.ndim > 1 else np.linalg.solve(gram, rhs)
    return coef[..., 0], coef[..., 1]


def lockin_amplitude(x, rate_hz: float, carrier_hz: float, *, t0_s: float = 0.0):
    """Carrier amplitude (peak) by lock-in demodulation: ``sqrt(i^2 + q^2)``.

    Exact for a pure sinusoid at ``carrier_hz`` of any phase and offset.
    Returns (...) ndarray.
    """
    i, q = lockin_iq(x, rate_hz, carrier_hz, t0_s=t0_s)
    return np.hypot(i, q)


def butterworth_bandpass(rate_hz: float, center_hz: float = 1000.0, bandwidth_hz: float = 600.0, order: int = 4):
    """Second-order sections of the paper's Butterworth band-pass (Section 4.3).

    ``order`` is the prototype order (the band-pass has twice as many poles).
    """
    lo = center_hz - bandwidth_hz / 2
    hi = center_hz + bandwidth_hz / 2
    if lo <= 0 or hi >= rate_hz / 2:
        raise ValueError(f"band {lo}-{hi} Hz does not fit below Nyquist ({rate_hz / 2} Hz)")
    return _sig.butter(order, [lo, hi], btype="bandpass", fs=rate_hz, output="sos")


def bandpass_amplitude(
    x,
    rate_hz: float,
    carrier_hz: float = 1000.0,
    *,
    bandwidth_hz: float = 600.0,
    order: int = 4,
    settle_periods: float = 5.0,
):
    """Carrier amplitude after the paper's Butterworth band-pass (Section 4.3).

    Filters forward and backward (zero phase), drops ``settle_periods``
    carrier periods at each end (the filter transient), then takes the
    amplitude as ``sqrt(2) * RMS`` of what is left.

    Returns (...) ndarray.
    """
    x = np.asarray(x, dtype=float)
    sos = butterworth_bandpass(rate_hz, carrier_hz, bandwidth_hz, order)
    y = _sig.sosfiltfilt(sos, x, axis=-1)
    cut = int(round(settle_periods * rate_hz / carrier_hz))
    if y.shape[-1] > 4 * cut:
        y = y[..., cut:-cut]
    return np.sqrt(2.0 * np.mean(y * y, axis=-1))
