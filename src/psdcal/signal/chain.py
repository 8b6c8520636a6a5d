"""Simulated signal chain of the PSD sensor (docs/model.md#signal-chain, the paper's Sections 4.3-4.5).

For each light spot (one LED of the template switched on, time multiplexing)::

    spot (x, y) --[PSD pin-cushion, l1]--> d --[current split, Eq 1-2 inverse]--> I (4,)
      --[transimpedance gains K_i, Eq 43]--> A (4,) --[carrier + white noise]--> v(t) (4, n)
      --[band-pass or lock-in]--> A_hat (4,) --[Eq 1-2]--> measured impact point (2,)

Conventions
-----------
* Channel order ``(vx1, vx2, vy1, vy2)``; lengths in mm, time in s, frequency
  in Hz, photocurrents in A, gains in V/A (ohm), signals in V.
* Each channel carries ``A_i sin(2 pi f_c t + phase) + noise``, ``t = k / rate``
  for ``k = 0 .. n - 1``, ``n = round(rate_hz * duration_s)``.
* **SNR** (docs/model.md#snr-definition): every channel of a spot gets the *same* white Gaussian
  noise, ``sigma = A_mean / sqrt(2) / 10^(snr_db / 20)``, ``A_mean`` the mean
  of the four channel amplitudes (absolute values) of that spot.  The noise
  does not scale with each channel's own light.
* **PSD distortion** ``l1`` [mm^-2] (Section 4.5): the readout of a spot at
  the true position ``p`` is the point ``d`` with ``d (1 + l1 |d|^2) = p``
  (the PSD part of the undistortion model, docs/model.md#distortion, centre (0, 0));
  ``d`` is what the chain feeds to the current split, so Eq 1-2 return ``d``.
* **Signed amplitudes.**  The linear current split of docs/model.md#psd-readout keeps all
  four currents positive only inside the diamond ``|2x/Lx| + |2y/Ly| <= 1``;
  outside it (towards the corners of the square active area) one channel's
  current is negative, i.e. its carrier is in antiphase.  The estimators
  return a magnitude; the chain signs it with the channel's lock-in phase
  relative to the emitter's carrier phase (known in the simulation), so
  Eq 1-2 hold over the whole active area, whatever the channel gains.
* A spot outside the active area (``|x| > Lx/2`` or ``|y| > Ly/2``) gives no
  reading: NaN amplitudes and points, like a missing point in a file.

Defaults (the paper gives neither rate nor record length): 50 kHz sampling,
20 ms records (20 carrier periods of 1 kHz, 1000 samples), noiseless
(``snr_db=None``), lock-in demodulation, the physical gain magnitude.
:meth:`ChainSettings.paper` gives the paper's choices (band-pass, Eq 43).

Processing is vectorised over any leading shape of spots and done in blocks
of spots so that the sampled records never take more than about 16 MiB.
"""
from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass, replace

import numpy as np
from scipy import signal as _sig

from psdcal.signal import demod
from psdcal.errors import ConvergenceError, InputError
from psdcal.model.readout import LX_MM, LY_MM, impact_point, photocurrents

#: Methods of amplitude estimation.
METHODS = ("lockin", "bandpass")
#: Transimpedance gain models: ``"physical"`` |Z| or ``"paper"`` Eq 43.
GAIN_MODELS = ("physical", "paper")

# Numerator signs of Eq 1 (x) and Eq 2 (y) over (vx1, vx2, vy1, vy2).
_SIGN_X = np.array([-1.0, 1.0, 1.0, -1.0])
_SIGN_Y = np.array([-1.0, 1.0, -1.0, 1.0])

# Budget of one block of sampled records, bytes (float64).
_BLOCK_BYTES = 16 * 2**20
# Longest record for which the band-pass noise factor is computed exactly (n^2 work).
_EXACT_FACTOR_MAX_SAMPLES = 16384


@dataclass(frozen=True)
class ChainSettings:
    """Settings of the simulated signal chain (docs/model.md#signal-chain).

    Change with :func:`dataclasses.replace`; never mutated.

    Attributes
    ----------
    rate_hz : float
        Sampling rate, Hz.  Default 50 kHz.
    duration_s : float
        Record length per spot, s.  Default 20 ms (1000 samples at 50 kHz).
    carrier_hz : float
        Carrier (LED modulation) frequency, Hz.  Default 1 kHz (paper).
    phase_rad : float
        Carrier phase at the first sample, rad.
    snr_db : float or None
        SNR in dB as defined in the module docstring; None: noiseless.
    method : {"lockin", "bandpass"}
        Amplitude estimation: synchronous (lock-in) demodulation at the known
        carrier, or the paper's Butterworth band-pass and ``sqrt(2) * RMS``.
    gain_model : {"physical", "paper"}
        ``"physical"``: ``R / sqrt(1 + (2 pi f R C)^2)``; ``"paper"``: Eq 43,
        ``R / (2 pi f R C + 1)``.
    r_ohm, c_farad : float
        Nominal feedback resistor and capacitor of the transimpedance
        amplifiers (paper: 100 kOhm, 100 pF).
    r_tol, c_tol : float
        Relative tolerances of R and C; imbalance draws are uniform within
        them (paper: 0.01 and 0.15).
    f_gain_hz : float
        Frequency at which the gains are evaluated, Hz.  The paper uses
        13.793 kHz, where the imbalance is largest (Section 4.4), not the
        1 kHz carrier; Eq 43 gives 53,572 V/A there at nominal R, C.
    i_total_a : float
        Peak photocurrent of the spot (sum over the four anodes), A.  Only
        scales the signals: the SNR is relative.
    lx_mm, ly_mm : float
        PSD active lengths, mm (S5991-01: 9 x 9).
    bandwidth_hz, filter_order, settle_periods : float, int, float
        The band-pass of ``method="bandpass"``: width (paper: 600 Hz, centred
        on the carrier), Butterworth prototype order, and carrier periods
        dropped at each end of the filtered record (see
        :func:`psdcal.signal.demod.bandpass_amplitude`).
    """

    rate_hz: float = 50_000.0
    duration_s: float = 0.020
    carrier_hz: float = 1_000.0
    phase_rad: float = 0.0
    snr_db: float | None = None
    method: str = "lockin"
    gain_model: str = "physical"
    r_ohm: float = 100e3
    c_farad: float = 100e-12
    r_tol: float = 0.01
    c_tol: float = 0.15
    f_gain_hz: float = 13_793.0
    i_total_a: float = 100e-9
    lx_mm: float = LX_MM
    ly_mm: float = LY_MM
    bandwidth_hz: float = 600.0
    filter_order: int = 4
    settle_periods: float = 5.0

    def __post_init__(self):
        def bad(name, why):
            raise InputError(f"{why}, got {getattr(self, name)!r}", field=name)

        for name in ("rate_hz", "duration_s", "carrier_hz", "r_ohm", "c_farad", "i_total_a", "lx_mm", "ly_mm",
                     "bandwidth_hz"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                bad(name, "must be a positive number")
        for name in ("r_tol", "c_tol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0 <= v < 1):
                bad(name, "must be in [0, 1)")
        if not (np.isfinite(self.f_gain_hz) and self.f_gain_hz >= 0):
            bad("f_gain_hz", "must be >= 0")
        if self.method not in METHODS:
            bad("method", f"must be one of {', '.join(METHODS)}")
        if self.gain_model not in GAIN_MODELS:
            bad("gain_model", f"must be one of {', '.join(GAIN_MODELS)}")
        if self.snr_db is not None and not np.isfinite(self.snr_db):
            bad("snr_db", "must be a finite number or None")
        if not self.carrier_hz < self.rate_hz / 2:
            bad("carrier_hz", f"must be below the Nyquist frequency {self.rate_hz / 2:g} Hz")
        n = int(round(self.rate_hz * self.duration_s))
        if n * self.carrier_hz / self.rate_hz < 1.0:
            bad("duration_s", "must hold at least one carrier period")
        if self.method == "bandpass":
            lo = self.carrier_hz - self.bandwidth_hz / 2
            hi = self.carrier_hz + self.bandwidth_hz / 2
            if lo <= 0 or hi >= self.rate_hz / 2:
                bad("bandwidth_hz", f"band {lo:g}-{hi:g} Hz must lie in (0, {self.rate_hz / 2:g}) Hz")
            if int(self.filter_order) < 1:
                bad("filter_order", "must be >= 1")

    @property
    def n_samples(self) -> int:
        """Samples per record, ``round(rate_hz * duration_s)``."""
        return int(round(self.rate_hz * self.duration_s))

    def time_s(self) -> np.ndarray:
        """Sample times, s, shape ``(n_samples,)``."""
        return np.arange(self.n_samples) / self.rate_hz

    def carrier(self) -> np.ndarray:
        """Unit carrier ``sin(2 pi f_c t + phase)``, shape ``(n_samples,)``."""
        return np.sin(2.0 * np.pi * self.carrier_hz * self.time_s() + self.phase_rad)

    @classmethod
    def paper(cls, **changes) -> "ChainSettings":
        """The paper's choices (Sections 4.3-4.4): band-pass estimation, Eq 43 gains.

        Rate and record length stay at this module's defaults (the paper
        gives neither); ``changes`` override any field.
        """
        return cls(**{"method": "bandpass", "gain_model": "paper", **changes})


# ---------------------------------------------------------------------------
# Gains (Eq 43)
# ---------------------------------------------------------------------------


def transimpedance_gain(r_ohm, c_farad, f_hz, model: str = "physical"):
    """Gain of a transimpedance amplifier with feedback ``R || C``, V/A.

    ``model="paper"``: Eq 43, ``K = R / (2 pi f R C + 1)``.
    ``model="physical"``: the magnitude of ``R / (1 + j 2 pi f R C)``,
    ``K = R / sqrt(1 + (2 pi f R C)^2)``.

    Parameters
    ----------
    r_ohm, c_farad : array_like
        Feedback resistance (ohm) and capacitance (F); broadcast together.
    f_hz : float
        Frequency, Hz.
    model : {"physical", "paper"}

    Returns
    -------
    ndarray
        Gains, V/A, of the broadcast shape.
    """
    r = np.asarray(r_ohm, dtype=float)
    wrc = 2.0 * np.pi * f_hz * r * np.asarray(c_farad, dtype=float)
    if model == "paper":
        return r / (wrc + 1.0)  # Eq 43
    if model == "physical":
        return r / np.sqrt(1.0 + wrc * wrc)
    raise InputError(f"gain model must be one of {', '.join(GAIN_MODELS)}, got {model!r}", field="gain_model")


def gain_variation_first_order(settings: ChainSettings | None = None) -> float:
    """Worst-case first-order change of the gain within the R, C tolerances, V/A.

    ``|dK/dR| R r_tol + |dK/dC| C c_tol`` at the nominal values and
    ``f_gain_hz``.  With the paper's Eq 43 and values this is the 4017.9 of
    Section 4.4 (``K = R / (1 + w R C)``: ``dK/dR = 1 / (1 + w R C)^2``,
    ``dK/dC = -w R^2 / (1 + w R C)^2``).
    """
    s = ChainSettings() if settings is None else settings
    r, c = s.r_ohm, s.c_farad
    x = 2.0 * np.pi * s.f_gain_hz * r * c
    if s.gain_model == "paper":
        dk_dr = 1.0 / (1.0 + x) ** 2
        dk_dc = -x * r / c / (1.0 + x) ** 2
    else:
        dk_dr = 1.0 / (1.0 + x * x) ** 1.5
        dk_dc = -x * x * r / c / (1.0 + x * x) ** 1.5
    return float(abs(dk_dr) * r * s.r_tol + abs(dk_dc) * c * s.c_tol)


def channel_components(settings: ChainSettings | None = None, rng=None):
    """Feedback R and C of the four channels.

    Nominal values when ``rng`` is None; otherwise each drawn uniform in
    ``nominal * (1 +- tol)`` (Section 4.4: ``U[a, b]``), R first, then C.

    Parameters
    ----------
    settings : ChainSettings
    rng : numpy.random.Generator, int or None

    Returns
    -------
    r_ohm, c_farad : (4,) ndarrays
    """
    s = ChainSettings() if settings is None else settings
    if rng is None:
        return np.full(4, s.r_ohm), np.full(4, s.c_farad)
    gen = np.random.default_rng(rng)
    r = s.r_ohm * (1.0 + s.r_tol * gen.uniform(-1.0, 1.0, 4))
    c = s.c_farad * (1.0 + s.c_tol * gen.uniform(-1.0, 1.0, 4))
    return r, c


def channel_gains(settings: ChainSettings | None = None, rng=None) -> np.ndarray:
    """Transimpedance gains of the four channels ``(vx1, vx2, vy1, vy2)``, V/A.

    Nominal (all equal) when ``rng`` is None or both tolerances are 0;
    otherwise R and C of each channel are drawn by :func:`channel_components`
    and the gain follows from ``settings.gain_model`` at ``settings.f_gain_hz``.

    Returns
    -------
    (4,) ndarray
    """
    s = ChainSettings() if settings is None else settings
    r, c = channel_components(s, rng)
    return transimpedance_gain(r, c, s.f_gain_hz, s.gain_model)


# ---------------------------------------------------------------------------
# Spot -> clean amplitudes
# ---------------------------------------------------------------------------


def psd_distort(xy_mm, l1: float):
    """Readout position of a spot under the PSD's pin-cushion distortion.

    Solves ``d (1 + l1 |d|^2) = p`` for ``d`` (docs/model.md#distortion, PSD part, centre
    (0, 0)) with :func:`psdcal.model.distortion.distort` (only ``l1`` set).

    Parameters
    ----------
    xy_mm : (..., 2) array_like
        True spot positions ``p``, mm.
    l1 : float
        PSD radial coefficient, mm^-2 (paper: -1.3058e-3).

    Returns
    -------
    (..., 2) ndarray
        ``d``, mm.  A new array even when ``l1 == 0``.

    Raises
    ------
    ConvergenceError
        Where the inverse does not converge (a finite spot).
    """
    p = np.array(xy_mm, dtype=float)
    if l1 == 0.0:
        return p
    from psdcal.model.distortion import distort
    from psdcal.model.params import Distortion

    res = distort(p, Distortion(l1=float(l1)), (0.0, 0.0))
    finite = np.all(np.isfinite(p), axis=-1)
    if np.any(finite & ~res.converged):
        idx = np.argwhere(np.atleast_1d(finite & ~res.converged))[0]
        raise ConvergenceError(
            f"PSD distortion l1={l1:g} cannot be inverted at spot index {tuple(int(i) for i in idx)}"
        )
    return res.d_mm


def _gains_array(settings: ChainSettings, gains) -> np.ndarray:
    if gains is None:
        return channel_gains(settings)
    g = np.asarray(gains, dtype=float)
    if g.shape != (4,):
        raise ValueError(f"gains must have shape (4,), got {g.shape}")
    return g


def signal_amplitudes(xy_mm, settings: ChainSettings | None = None, gains=None, l1: float = 0.0):
    """Noiseless carrier amplitudes of the four channels, V (signed).

    ``A_i = K_i I_i`` with the current split of docs/model.md#psd-readout at the PSD readout
    position of the spot (:func:`psd_distort`).  Negative where the linear
    split gives a negative current (outside the diamond
    ``|2x/Lx| + |2y/Ly| <= 1``).

    Parameters
    ----------
    xy_mm : (..., 2) array_like
        True spot positions, mm.
    settings : ChainSettings
    gains : (4,) array_like or None
        Channel gains, V/A; None: nominal (:func:`channel_gains` without rng).
    l1 : float
        PSD distortion, mm^-2.

    Returns
    -------
    (..., 4) ndarray
        NaN for spots outside the active area (or not finite).
    """
    s = ChainSettings() if settings is None else settings
    xy = np.asarray(xy_mm, dtype=float)
    if xy.shape[-1:] != (2,):
        raise ValueError(f"xy_mm must have shape (..., 2), got {xy.shape}")
    g = _gains_array(s, gains)
    inside = (np.abs(xy[..., 0]) <= 0.5 * s.lx_mm) & (np.abs(xy[..., 1]) <= 0.5 * s.ly_mm)
    p = np.where(inside[..., None], xy, np.nan)
    d = psd_distort(p, l1)
    return photocurrents(d, s.i_total_a, s.lx_mm, s.ly_mm) * g


def noise_sigma(amplitudes, snr_db: float):
    """Noise standard deviation of a spot's channels for a given SNR (docs/model.md#signal-chain).

    ``sigma = A_mean / sqrt(2) / 10^(snr_db / 20)`` with ``A_mean`` the mean
    of the four channel amplitudes (absolute values): the SNR is the mean
    channel signal power ``A_mean^2 / 2`` over the noise power ``sigma^2``.

    Parameters
    ----------
    amplitudes : (..., 4) array_like
        Clean channel amplitudes (peak), V.
    snr_db : float

    Returns
    -------
    (...) ndarray
        Sigma, V, one value for all four channels of a spot.
    """
    a_mean = np.mean(np.abs(np.asarray(amplitudes, dtype=float)), axis=-1)
    return a_mean / np.sqrt(2.0) / 10.0 ** (snr_db / 20.0)


# ---------------------------------------------------------------------------
# Sampled records and their demodulation
# ---------------------------------------------------------------------------


def _block_points(settings: ChainSettings, block_points) -> int:
    if block_points is not None:
        return max(1, int(block_points))
    return max(1, _BLOCK_BYTES // (4 * 8 * settings.n_samples))


def _records(amplitudes: np.ndarray, settings: ChainSettings, gen) -> np.ndarray:
    """Records (m, 4, n) for clean amplitudes (m, 4); noise drawn from ``gen`` if SNR set."""
    carrier = settings.carrier()
    if settings.snr_db is None:
        return amplitudes[..., None] * carrier
    sigma = noise_sigma(amplitudes, settings.snr_db)
    out = gen.standard_normal(amplitudes.shape + (settings.n_samples,))
    out *= sigma[..., None, None]
    out += amplitudes[..., None] * carrier
    return out


def simulate_signals(xy_mm, settings: ChainSettings | None = None, gains=None, rng=None, l1: float = 0.0):
    """Sampled records of the four channels for each spot.

    ``v_i(t) = A_i sin(2 pi f_c t + phase) + sigma n_i(t)``, ``n_i`` standard
    white Gaussian, independent per channel and spot, ``sigma`` from
    :func:`noise_sigma` (none when ``settings.snr_db`` is None).

    Parameters
    ----------
    xy_mm : (..., 2) array_like
        True spot positions, mm.
    settings : ChainSettings
    gains : (4,) array_like or None
        Channel gains, V/A (None: nominal).
    rng : numpy.random.Generator, int or None
        Noise source (``numpy.random.default_rng(rng)``; None: fresh entropy).
    l1 : float
        PSD distortion, mm^-2.

    Returns
    -------
    (..., 4, n_samples) ndarray
        Volts.  NaN for spots outside the active area.  The whole array is
        allocated: for many spots use :func:`measure_amplitudes`, which works
        in blocks.
    """
    s = ChainSettings() if settings is None else settings
    amps = signal_amplitudes(xy_mm, s, gains, l1)
    gen = np.random.default_rng(rng) if s.snr_db is not None else None
    return _records(amps, s, gen)


def estimate_amplitudes(samples, settings: ChainSettings | None = None):
    """Signed carrier amplitudes of the four channels from their records.

    Magnitude by ``settings.method``: :func:`psdcal.signal.demod.lockin_amplitude`
    or :func:`psdcal.signal.demod.bandpass_amplitude` (the paper's band-pass).  Sign:
    that of ``Re(z_i conj(z_rest))``, ``z`` the lock-in phasors, ``z_rest``
    the sum of the other three channels (see the module docstring).

    Parameters
    ----------
    samples : (..., 4, n) array_like
        Records, the last axis is time sampled at ``settings.rate_hz``.
    settings : ChainSettings

    Returns
    -------
    (..., 4) ndarray
        Peak amplitudes, in the unit of ``samples``.
    """
    s = ChainSettings() if settings is None else settings
    x = np.asarray(samples, dtype=float)
    if x.ndim < 2 or x.shape[-2] != 4:
        raise ValueError(f"samples must have shape (..., 4, n), got {x.shape}")
    # phasor convention: x ~ i sin(w t) + q cos(w t); the carrier's phase cancels in the sign
    i, q = demod.lockin_iq(x, s.rate_hz, s.carrier_hz)
    if s.method == "lockin":
        mag = np.hypot(i, q)  # = demod.lockin_amplitude, without solving twice
    else:
        mag = demod.bandpass_amplitude(
            x,
            s.rate_hz,
            s.carrier_hz,
            bandwidth_hz=s.bandwidth_hz,
            order=int(s.filter_order),
            settle_periods=s.settle_periods,
        )
    # Sign: the channel's phasor against the emitter's carrier phase, which the
    # simulation knows (A sin(w t + phase) has i = A cos(phase), q = A sin(phase)).
    # A reference built from the other channels fails where their sum changes
    # sign (corners of the sensor under strong gain imbalance).
    sign = np.where(i * np.cos(s.phase_rad) + q * np.sin(s.phase_rad) < 0.0, -1.0, 1.0)
    return sign * mag


def measure_amplitudes(
    xy_mm,
    settings: ChainSettings | None = None,
    gains=None,
    rng=None,
    l1: float = 0.0,
    *,
    block_points: int | None = None,
    noise: str = "sampled",
):
    """Estimated channel amplitudes of each spot through the whole chain.

    Spot -> PSD distortion -> current split -> gains -> carrier + noise ->
    demodulation (:func:`estimate_amplitudes`).  Works in blocks of spots
    (at most about 16 MiB of samples at a time); the noise drawn does not
    depend on the block size.  These are the raw amplitudes of the points
    file ``image_id,point_id,vx1,vx2,vy1,vy2`` (docs/model.md#calibration-json).

    Parameters
    ----------
    xy_mm : (..., 2) array_like
        True spot positions, mm.
    settings : ChainSettings
    gains : (4,) array_like or None
        Channel gains, V/A (None: nominal, all equal).
    rng : numpy.random.Generator, int or None
        Noise source (``numpy.random.default_rng(rng)``: None draws fresh
        entropy, not reproducible); unused when ``settings.snr_db`` is None.
    l1 : float
        PSD distortion, mm^-2.
    block_points : int, optional
        Spots per block (default: from the memory budget).
    noise : "sampled" | "closed-form"
        ``"sampled"`` (the reference) draws the records and demodulates them.
        ``"closed-form"`` draws the demodulator's outputs directly from their
        exact law: every estimate is a function of linear maps of the record
        (lock-in ``i, q``; band-pass output on its window), whose noise is
        Gaussian with a covariance computed once per settings and reduced to
        its few significant dimensions (all but ``1e-12`` of the variance);
        same distribution, other draws, about 30x faster (no records, no filter).
        Records longer than 4096 samples are sampled either way.

    Returns
    -------
    (..., 4) ndarray
        Amplitudes ``vx1, vx2, vy1, vy2``, V; NaN for spots outside the
        active area.
    """
    s = ChainSettings() if settings is None else settings
    amps = signal_amplitudes(xy_mm, s, gains, l1)
    flat = amps.reshape(-1, 4)
    out = np.full_like(flat, np.nan)
    valid = np.flatnonzero(np.all(np.isfinite(flat), axis=-1))
    gen = np.random.default_rng(rng) if s.snr_db is not None else None
    if noise not in ("sampled", "closed-form"):
        raise ValueError(f"noise must be 'sampled' or 'closed-form', got {noise!r}")
    if noise == "closed-form" and gen is not None and s.n_samples <= _CLOSED_FORM_MAX_SAMPLES:
        out[valid] = _closed_form_amplitudes(flat[valid], s, gen)
        return out.reshape(amps.shape)
    step = _block_points(s, block_points)
    for start in range(0, valid.size, step):
        idx = valid[start:start + step]
        out[idx] = estimate_amplitudes(_records(flat[idx], s, gen), s)
    return out.reshape(amps.shape)


def measure_points(
    xy_mm,
    settings: ChainSettings | None = None,
    gains=None,
    rng=None,
    l1: float = 0.0,
    *,
    block_points: int | None = None,
):
    """Measured impact points of spots through the whole chain (Eq 1-2 last).

    Same arguments as :func:`measure_amplitudes`.

    Returns
    -------
    (..., 2) ndarray
        ``(x_mm, y_mm)`` read out by Eq 1-2; NaN for spots outside the
        active area.

    Raises
    ------
    ZeroSignalError
        Where the sum of the four amplitudes is zero (no light, all gains 0).
    """
    s = ChainSettings() if settings is None else settings
    amps = measure_amplitudes(xy_mm, s, gains, rng, l1, block_points=block_points)
    flat = amps.reshape(-1, 4)
    out = np.full((flat.shape[0], 2), np.nan)
    ok = np.all(np.isfinite(flat), axis=-1)
    if np.any(ok):
        out[ok] = impact_point(flat[ok], s.lx_mm, s.ly_mm)
    return out.reshape(amps.shape[:-1] + (2,))


# ---------------------------------------------------------------------------
# Closed-form noise (exact in distribution, no records)
# ---------------------------------------------------------------------------

#: Fraction of the demodulator's output noise variance the closed form may drop.
_CLOSED_FORM_DROP = 1e-12
#: Longest record the closed form handles (its set-up is n^2 memory, n^3 time); longer ones are sampled.
_CLOSED_FORM_MAX_SAMPLES = 4096


@functools.lru_cache(maxsize=8)
def _closed_form_basis(s: ChainSettings):
    """What the demodulator makes of a record, reduced to its ``r`` noise dimensions.

    Every estimate :func:`estimate_amplitudes` takes is a function of linear
    maps of the record: the lock-in ``(i, q)`` = ``P v`` and, for the
    band-pass, the kept filter output ``y_W = F_W v``.  For
    ``v = A c + sigma n`` (``c`` the unit carrier, ``n ~ N(0, I)``) the noise
    part ``M n`` of ``M = [F_W; P]`` has the law of ``B z``, ``z ~ N(0, I_r)``,
    ``B B^T = M M^T`` (eigenvectors of ``M M^T`` with eigenvalues above
    ``_CLOSED_FORM_DROP`` of the total dropped); ``B`` is then rotated so that
    ``|y_W noise|^2 = sum_k lam_k z_k^2`` is diagonal.

    Returns
    -------
    dict with ``i0, q0`` (lock-in of the unit carrier), ``c0 = |F_W c|^2``,
    ``a`` (r,) = ``B_W^T F_W c``, ``lam`` (r,), ``pi, pq`` (r,) the lock-in
    rows of ``B``, ``m`` samples kept, ``g`` the filter's power gain, ``r``.
    """
    n = s.n_samples
    eye = np.eye(n)
    pi_rows = np.stack(demod.lockin_iq(eye, s.rate_hz, s.carrier_hz))  # (2, n): (i, q) = P v
    unit = s.carrier()
    i0, q0 = (float(v) for v in pi_rows @ unit)
    if s.method == "lockin":
        mat = pi_rows
        m = 0
        g = 1.0
        y0 = np.zeros(0)
    else:
        sos = demod.butterworth_bandpass(s.rate_hz, s.carrier_hz, s.bandwidth_hz, int(s.filter_order))
        win = demod.bandpass_window(n, s.rate_hz, s.carrier_hz, s.settle_periods)
        fw = _sig.sosfiltfilt(sos, eye, axis=-1)[:, win].T  # (m, n): column j is F e_j on the window
        m = fw.shape[0]
        g = demod._filter_gain(sos, s.rate_hz, s.carrier_hz)
        y0 = fw @ unit
        mat = np.concatenate([fw, pi_rows])
    try:  # one BLAS thread: a 500 x 500 eigh is 100x slower on threads fighting other processes
        from threadpoolctl import threadpool_limits

        limit = threadpool_limits(limits=1, user_api="blas")
    except Exception:  # threadpoolctl missing or unable to introspect: run as is
        limit = contextlib.nullcontext()
    with limit:
        lam_all, vec = np.linalg.eigh(mat @ mat.T)
        order = np.argsort(lam_all)[::-1]
        lam_all, vec = np.clip(lam_all[order], 0.0, None), vec[:, order]
        tail = np.cumsum(lam_all[::-1])[::-1]  # tail[k] = variance from k on
        r = int(np.count_nonzero(tail > _CLOSED_FORM_DROP * tail[0]))
        b = vec[:, :r] * np.sqrt(lam_all[:r])  # (m + 2, r), B B^T ~ M M^T
        bw, bp = b[:m], b[m:]
        if m:
            lam, rot = np.linalg.eigh(bw.T @ bw)  # z^T B_W^T B_W z diagonal in z' = rot^T z
            bw, bp = bw @ rot, bp @ rot
        else:
            lam = np.zeros(r)
    return {"i0": i0, "q0": q0, "c0": float(y0 @ y0), "a": bw.T @ y0, "lam": lam,
            "pi": bp[0].copy(), "pq": bp[1].copy(), "m": m, "g": g, "r": r}


def _closed_form_amplitudes(amplitudes: np.ndarray, s: ChainSettings, gen) -> np.ndarray:
    """:func:`estimate_amplitudes` of :func:`_records` without the records (same law)."""
    k = _closed_form_basis(replace(s, snr_db=None))  # the basis does not depend on the SNR
    sigma = noise_sigma(amplitudes, s.snr_db)[..., None]  # (m, 1)
    z = gen.standard_normal(amplitudes.shape + (k["r"],))
    amp = amplitudes
    i = amp * k["i0"] + sigma * (z @ k["pi"])
    q = amp * k["q0"] + sigma * (z @ k["pq"])
    if s.method == "lockin":
        mag = np.hypot(i, q)
    else:
        ss = amp * amp * k["c0"] + 2.0 * amp * sigma * (z @ k["a"]) + sigma * sigma * ((z * z) @ k["lam"])
        mag = np.sqrt(2.0 * np.maximum(ss, 0.0) / k["m"]) / k["g"]
    sign = np.where(i * np.cos(s.phase_rad) + q * np.sin(s.phase_rad) < 0.0, -1.0, 1.0)
    return sign * mag


#: Names defined in :mod:`psdcal.signal.chain_noise` and reachable from here too (resolved on first use:
#: that module imports this one).
_NOISE_NAMES = frozenset({"amplitude_noise_factor", "predicted_point_cov", "predicted_point_std", "NoiseVsSnr",
                          "point_noise_vs_snr", "measure_point_trial"})


def __getattr__(name: str):
    if name in _NOISE_NAMES:
        from psdcal.signal import chain_noise

        return getattr(chain_noise, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
