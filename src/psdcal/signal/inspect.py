"""What a recording holds, measured before demodulating it (``psdcal inspect``).

* :func:`find_carriers`: the carriers present in a four-channel record, with
  their frequency (Hann-windowed spectrum, peak refined by parabolic
  interpolation of the log power) and their SNR per channel.
* :func:`check_carrier`: compares an asked carrier with the measured one.  A
  carrier off by ``df`` leaves, in a window of ``T`` seconds, a phase drift
  whose residual has mean square ``A^2 (pi df T)^2 / 6`` (linear phase error
  ``2 pi df (t - T/2)`` over the window); the fitted noise, hence every sigma,
  grows by ``sqrt(1 + A^2 (pi df T)^2 / (6 sigma^2))`` and the amplitude drops
  by ``sinc(df T)``.  The check warns when that inflation exceeds
  :data:`MAX_SIGMA_INFLATION` or the amplitude loss exceeds
  :data:`MAX_AMPLITUDE_LOSS`.
* :func:`scan_tdm`: the on-times and dark gaps of a time-multiplexed record
  (segments found with a short window), and :func:`choose_tdm_window`, a
  demodulation window from them.

All functions read a bounded prefix of the recording
(:data:`DEFAULT_SCAN_SAMPLES` samples per channel).
"""
from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass

import numpy as np

from psdcal.errors import InputError

#: Samples per channel read for a scan (bounds memory and time).
DEFAULT_SCAN_SAMPLES = 1 << 18
#: A carrier mismatch that inflates the sigmas by more than this is reported.
MAX_SIGMA_INFLATION = 1.2
#: ... or that loses more than this fraction of the amplitude.
MAX_AMPLITUDE_LOSS = 0.01
#: Minimum SNR of a spectral peak to count as a carrier, dB (power over the median floor).
MIN_CARRIER_SNR_DB = 20.0
#: A peak this far (dB) below a stronger carrier close to it is a side-band, not a carrier.
SIDEBAND_DB = 20.0
#: A peak this far (dB) below the strongest carrier is not listed (use carrier_near for a weak one).
WEAK_DB = 30.0


@dataclass(frozen=True)
class Carrier:
    """A carrier found in a record.

    Attributes
    ----------
    freq_hz : float
        Measured frequency (peak of the spectrum, interpolated).
    resolution_hz : float
        Bin width of the spectrum (rate / samples), Hz.
    snr_db : (4,) ndarray
        The carrier's power in its spectral bin over the noise power in one
        bin (``(A sum(w) / 2)^2 / (sigma^2 sum(w^2))``), dB, per channel.
    amplitude : (4,) ndarray
        Peak amplitude per channel (signal unit; averaged over the record, so
        a time-multiplexed LED's amplitude times its duty cycle).
    noise_sigma : (4,) ndarray
        White-noise sigma per sample of each channel (from the median floor).
    precision_hz : float
        Standard error of ``freq_hz`` when the estimator gives one
        (:func:`carrier_in_bursts`); nan for a spectral peak (whose
        precision is taken as a tenth of ``resolution_hz``).
    """

    freq_hz: float
    resolution_hz: float
    snr_db: np.ndarray
    amplitude: np.ndarray
    noise_sigma: np.ndarray
    precision_hz: float = math.nan


def read_prefix(recording, max_samples: int = DEFAULT_SCAN_SAMPLES, *, rows_view: bool = False) -> np.ndarray:
    """The first ``max_samples`` samples (4, n) of a :class:`~psdcal.signal.recording.Recording`.

    ``rows_view``: for a ``.npy`` recording read as rows, the (4, n) transpose of the rows as they lie
    (the same values; :func:`spectrum` gives the same spectrum for either layout): a prefix within one
    chunk is then a read-only view of the file's memory map (no copy; the map stays while the view is
    held; read it at once, as a block of :meth:`Recording.chunks`), a longer one a copy of the rows (no
    transposing copy).  Without it, a (4, n) C-order copy.
    """
    parts, n = [], 0
    # a .npy as rows: a (n, 4) file is then read without a transposing copy (the same checked samples)
    rows = getattr(recording, "kind", None) == "npy"
    kw = {"rows": True, "mapped": True} if rows else {}  # (mapped: views of the file, checked, no copy)
    for _, block in recording.chunks(min(int(max_samples), 1 << 16), **kw):
        if rows and rows_view:
            parts.append(block[: max_samples - n])
            n += parts[-1].shape[0]
        else:
            parts.append(block[: max_samples - n].T if rows else block[:, : max_samples - n])
            n += parts[-1].shape[1]
        if n >= max_samples:
            break
    if not parts:
        return np.zeros((4, 0))
    if rows and rows_view:
        return (parts[0] if len(parts) == 1 else np.concatenate(parts, axis=0)).T
    return np.concatenate(parts, axis=1)


@functools.lru_cache(maxsize=8)
def _hann_cached(n: int) -> np.ndarray:
    w = np.hanning(n)
    w.flags.writeable = False
    return w


def _hann(n: int) -> np.ndarray:
    """``np.hanning(n)``, computed once per length (read-only)."""
    return _hann_cached(int(n))


_spectrum_scratch = threading.local()
#: The largest windowed block (samples, all channels) whose buffers are kept for the next scan (16 MB).
_KEEP_SPECTRUM_SAMPLES = 1 << 20


def _spectrum_buffers(c: int, n: int):
    """``(xw, z)``: (c, n) float64 and (c, n // 2 + 1) complex buffers, this thread's own, reused."""
    kept = getattr(_spectrum_scratch, "bufs", None)
    if kept is not None and kept[0].shape == (c, n):
        return kept
    bufs = (np.empty((c, n)), np.empty((c, n // 2 + 1), dtype=complex))
    if c * n <= _KEEP_SPECTRUM_SAMPLES:
        _spectrum_scratch.bufs = bufs
    return bufs


def spectrum(x, rate_hz: float):
    """Hann-windowed amplitude spectrum of each channel.

    Parameters
    ----------
    x : (4, n) ndarray
    rate_hz : float

    Returns
    -------
    freq_hz : (n // 2 + 1,) ndarray
    power : (4, n // 2 + 1) ndarray
        ``|X_k|^2`` of the mean-removed, Hann-windowed channels.
    wsum, w2sum : float
        Sum of the window and of its square (to convert to amplitudes and noise).
    """
    x = np.asarray(x, dtype=float)
    c, n = x.shape
    w = _hann(n)
    m = n // 2 + 1
    # the windowed channels and their transforms in buffers kept between calls (a scan's 4 x 65,536
    # samples: fresh arrays would be faulted in every time), one transform call for all the channels
    # (the same values as one call a channel)
    xw, z = _spectrum_buffers(c, n)
    for i in range(c):
        np.subtract(x[i], x[i].mean(), out=xw[i])
        xw[i] *= w
    np.fft.rfft(xw, axis=1, out=z)
    # |X|^2 as re^2 + im^2 (np.abs's hypot and the square cost more than the FFT's last passes), squared
    # in place
    zf = z.view(np.float64).reshape(c, m, 2)
    np.square(zf, out=zf)
    p = np.add(zf[:, :, 0], zf[:, :, 1])
    return np.fft.rfftfreq(n, 1.0 / rate_hz), p, float(w.sum()), float((w * w).sum())


def _median_rows(q: np.ndarray) -> np.ndarray:
    """``np.median(q, axis=1)``, the same values, by one partition with a single pivot (numpy's median asks
    for two, which costs several times more on a spectrum's 32,769 bins): the lower middle value of an even
    count is the largest of the lower half.  Long rows are first bracketed (:func:`_median_bracketed`)."""
    m = q.shape[1]
    h = m // 2
    if m < 2:
        return np.median(q, axis=1)
    if m >= _BRACKET_MIN_COUNT:
        out = _median_bracketed(q)
        if out is not None:
            return out
    part = np.partition(q, h, axis=1)
    if np.isnan(part[:, -1]).any():  # (numpy's NaN rule: NaN)
        return np.median(q, axis=1)
    hi = part[:, h]
    if m % 2:
        return hi.copy()
    return (part[:, :h].max(axis=1) + hi) / 2


#: Rows at least this long are bracketed before the partition (:func:`_median_bracketed`).
_BRACKET_MIN_COUNT = 4096
#: Every this many values of a row form the sample that brackets its median.
_BRACKET_STEP = 16


def _median_bracketed(q: np.ndarray) -> np.ndarray | None:
    """``np.median(q, axis=1)`` of long rows from the few values around it, or None (then partition all).

    A sample (every :data:`_BRACKET_STEP`-th value) gives bounds ``lo <= hi`` four binomial sigmas
    either side of its middle; the values below ``lo`` are only counted, the values in ``[lo, hi]`` (about
    a tenth) partitioned.  When the middle rank(s) of the row fall among them, the value at a rank is the
    one at that rank less the count below ``lo`` in the bracketed values: exactly numpy's (the same two
    values, the same mean for an even count).  Otherwise (a sample far off its expectation: about 6e-5 of
    the rows), or with a NaN in the rows, None.
    """
    c, m = q.shape
    h = m // 2
    if np.isnan(q).any():
        return None
    sample = q[:, ::_BRACKET_STEP]
    ns = sample.shape[1]
    d = int(2.0 * math.sqrt(ns)) + 2  # four sigmas of the sample's middle rank (sigma = sqrt(ns) / 2)
    k_lo, k_hi = max(0, ns // 2 - d), min(ns - 1, ns // 2 + d)
    sample = np.partition(sample, (k_lo, k_hi), axis=1)
    lo, hi = sample[:, k_lo], sample[:, k_hi]
    out = np.empty(c)
    for i in range(c):
        row = q[i]
        below = int(np.count_nonzero(row < lo[i]))
        inside = row[(row >= lo[i]) & (row <= hi[i])]
        r = h - below
        need = r - 1 if m % 2 == 0 else r  # the lowest rank asked
        if need < 0 or r >= inside.shape[0]:
            return None
        if m % 2:
            out[i] = np.partition(inside, r)[r]
        else:
            part = np.partition(inside, (r - 1, r))
            out[i] = (part[r - 1] + part[r]) / 2
    return out


def _spectrum_and_floor(x, rate_hz: float):
    """:func:`spectrum` of a (4, n) block with its bin width, per-channel noise floor (median power)
    and the power summed over the channels; at least 64 samples."""
    x = np.asarray(x, dtype=float)
    n = x.shape[1]
    if n < 64:
        raise InputError(f"too few samples to find carriers ({n}; at least 64)", field="samples")
    freq, p, wsum, w2sum = spectrum(x, rate_hz)
    floor = _median_rows(p[:, 1:])  # (4,)
    floor = np.where(floor > 0, floor, np.finfo(float).tiny)
    return freq, p, wsum, w2sum, rate_hz / n, floor, p.sum(axis=0)


def find_carriers(x, rate_hz: float, *, min_snr_db: float = MIN_CARRIER_SNR_DB, max_carriers: int = 8,
                  min_hz: float = 1.0) -> list[Carrier]:
    """Carriers in a record, strongest first.

    A carrier is a peak of the summed power spectrum that exceeds the median
    noise floor by ``min_snr_db``, dominates its neighbourhood of +-2 % of
    its frequency, is not more than :data:`SIDEBAND_DB` below a stronger
    carrier within 50 % of it nor :data:`WEAK_DB` below the strongest one (so the side-bands of on/off keying are not
    counted as carriers).

    Parameters
    ----------
    x : (4, n) ndarray
    rate_hz : float
    min_snr_db : float
    max_carriers : int
    min_hz : float
        Lowest frequency considered (DC and drift are not carriers).

    Returns
    -------
    list of Carrier
    """
    freq, p, wsum, w2sum, df, floor, ptot = _spectrum_and_floor(x, rate_hz)
    ftot = floor.sum()
    lo = max(2, int(math.ceil(min_hz / df)))
    cand = np.flatnonzero((ptot[lo:-1] > ftot * 10 ** (min_snr_db / 10))
                          & (ptot[lo:-1] >= ptot[lo - 1:-2]) & (ptot[lo:-1] >= ptot[lo + 1:])) + lo
    cand = cand[np.argsort(ptot[cand])[::-1]]
    out: list[Carrier] = []
    peaks: list[float] = []
    for k in cand:
        half = max(2, int(0.02 * freq[k] / df))
        if ptot[k] < ptot[max(1, k - half): k + half + 1].max():
            continue
        if any(abs(c.freq_hz - freq[k]) < 0.02 * freq[k] + 2 * df for c in out):
            continue
        if out and ptot[k] < peaks[0] * 10 ** (-WEAK_DB / 10):
            continue  # far below the strongest carrier: keying side-bands, harmonics
        # side-band of on/off keying: > SIDEBAND_DB below a carrier within 50 % of it
        if any(abs(c.freq_hz - freq[k]) < 0.5 * c.freq_hz and ptot[k] < pk * 10 ** (-SIDEBAND_DB / 10)
               for c, pk in zip(out, peaks)):
            continue
        peaks.append(ptot[k])
        out.append(_carrier_at(k, p, ptot, floor, df, wsum, w2sum))
        if len(out) >= max_carriers:
            break
    return out


def _carrier_at(k, p, ptot, floor, df, wsum, w2sum) -> Carrier:
    # parabolic interpolation of the log power around the peak bin k
    a, b, c = np.log(ptot[k - 1: k + 2] + 1e-300)
    den = a - 2 * b + c
    delta = 0.5 * (a - c) / den if den < 0 else 0.0
    delta = float(np.clip(delta, -0.5, 0.5))
    # Hann scalloping: the response at delta bins off the peak is sinc(delta) / (1 - delta^2)
    amp = 2 * np.sqrt(p[:, k]) / wsum / (np.sinc(delta) / (1.0 - delta * delta))
    sigma = np.sqrt(floor / (math.log(2) * w2sum))  # white noise: median of |X|^2 = ln2 sigma^2 sum w^2
    return Carrier(
        freq_hz=float((k + delta) * df),
        resolution_hz=float(df),
        # the carrier's power in its bin over the noise power in one bin
        snr_db=20 * np.log10(np.maximum(amp * wsum / 2, 1e-300) / (sigma * math.sqrt(w2sum))),
        amplitude=amp,
        noise_sigma=sigma,
    )


def carrier_near(x, rate_hz: float, asked_hz: float, *, rel: float = 0.05,
                 min_snr_db: float = MIN_CARRIER_SNR_DB, spectrum_cache: dict | None = None) -> Carrier | None:
    """The strongest spectral peak within ``+-rel`` of ``asked_hz`` (None when below ``min_snr_db``).

    Unlike :func:`find_carriers` no side-band rule applies: a weak emitter
    near a strong one is still measured.  ``spectrum_cache``: a dict kept
    between calls on the same ``x`` (several carriers): the spectrum is
    computed once.
    """
    if spectrum_cache is not None and spectrum_cache.get("x") is x and spectrum_cache.get("rate_hz") == rate_hz:
        spec = spectrum_cache["spec"]
    else:
        spec = _spectrum_and_floor(x, rate_hz)
        if spectrum_cache is not None:
            spectrum_cache.update(x=x, rate_hz=rate_hz, spec=spec)
    freq, p, wsum, w2sum, df, floor, ptot = spec
    lo = max(1, int(math.floor(asked_hz * (1 - rel) / df)))
    hi = min(len(freq) - 2, int(math.ceil(asked_hz * (1 + rel) / df)))
    if hi < lo:
        return None
    k = lo + int(np.argmax(ptot[lo: hi + 1]))
    if ptot[k] <= floor.sum() * 10 ** (min_snr_db / 10):
        return None
    return _carrier_at(max(k, 1), p, ptot, floor, df, wsum, w2sum)


#: Windows of a burst (after its two edge windows are dropped) needed for a phase slope.
MIN_BURST_WINDOWS = 3


def carrier_in_bursts(x, rate_hz: float, asked_hz: float, *, min_snr: float = 10.0) -> Carrier | None:
    """The carrier of a time-multiplexed or blinking record, from the phase slope inside its bursts.

    The spectrum of a record whose LEDs take turns is the carrier convolved
    with the on/off pattern: when each slot starts with its own phase (a
    different LED, or an LED switched on again), the strongest peak near the
    carrier is often a keying side-band, and :func:`carrier_near` would
    report it as the carrier (the tutorial's views: 985 Hz for 1000 Hz).
    Here the record is demodulated at ``asked_hz`` in short windows
    (:data:`psdcal.signal.stream.MIN_PERIODS` periods, at least 32 samples);
    the windows whose total amplitude exceeds ``min_snr`` sigmas form the
    bursts, cut where the channel ratios or the phase jump (another LED with
    no dark window between); windows below 0.8 of their burst's median
    amplitude (part of the window dark) and the two edge windows of each
    burst are dropped.  In each burst, the samples between the end of its
    first window and the start of its last one (the LED certainly on, no
    switching inside) are cut into sub-windows of one period; their common
    phase drifts as ``2 pi (f - asked) t``.
    The slope is fitted per burst (weights from the windows' own noise) and
    the bursts are averaged, inverse-variance weighted: a phase that jumps
    from burst to burst does not matter.

    Returns
    -------
    Carrier or None
        ``freq_hz = asked_hz + slope / 2 pi`` with ``precision_hz`` its
        standard error (scaled up by the fit's reduced chi-squared when above
        one); ``amplitude`` and ``noise_sigma`` are the medians over the
        burst windows (an LED's amplitude while it is on, not the duty-cycle
        average); ``resolution_hz`` is one over the longest burst; ``snr_db``
        as :class:`Carrier` for the on-samples.  None when no burst has
        :data:`MIN_BURST_WINDOWS` clean windows (then use :func:`carrier_near`).
    """
    from psdcal.signal.stream import MIN_PERIODS, MultiCarrierLockin

    x = np.asarray(x, dtype=float)
    periods = max(MIN_PERIODS, math.ceil(32 * asked_hz / rate_hz))
    w0 = math.ceil(periods / asked_hz * rate_hz) / rate_hz
    if x.ndim != 2 or x.shape[1] < 3 * round(w0 * rate_hz):
        return None
    try:
        lk = MultiCarrierLockin(rate_hz, [asked_hz], w0)
    except InputError:
        return None
    wb = lk.process(0.0, x)
    a = wb.amplitude[:, 0, :]  # (nw, 4)
    total = a.sum(-1)
    var_total = wb.var_amplitude[:, 0, :].sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        on = np.isfinite(total) & (total > min_snr * np.sqrt(var_total))
    idx = np.flatnonzero(on)
    if idx.size == 0:
        return None
    ratio = a / np.where(total != 0, total, 1.0)[:, None]
    sd_ratio = np.sqrt(wb.var_amplitude[:, 0, :].max(-1)) / np.where(total > 0, total, 1.0)
    step = np.angle(np.exp(1j * np.diff(wb.phase_rad[:, 0])))  # wrapped phase step between windows
    sd_step = np.sqrt(var_total[:-1] / np.maximum(total[:-1], 1e-300) ** 2
                      + var_total[1:] / np.maximum(total[1:], 1e-300) ** 2)
    m_step = float(np.median(step[on[:-1] & on[1:]])) if np.any(on[:-1] & on[1:]) else 0.0
    # a burst ends where the windows stop being consecutive, or where another LED takes over with no dark
    # window between (the channel ratios or the phase jump)
    cut = (np.diff(idx) > 1)
    j = idx[:-1]
    cut |= np.max(np.abs(ratio[j + 1] - ratio[j]), axis=-1) > 0.02 + 6 * np.hypot(sd_ratio[j], sd_ratio[j + 1])
    cut |= np.abs(np.angle(np.exp(1j * (step[j] - m_step)))) > 0.2 + 6 * sd_step[j]
    runs = []
    for r in np.split(idx, np.flatnonzero(cut) + 1):
        # windows that hold only part of the on-time are weaker: dropped, and the rest split where they were
        r = r[total[r] >= 0.8 * np.median(total[r])]
        runs += np.split(r, np.flatnonzero(np.diff(r) > 1) + 1)
    n_w = lk.n_window
    period = max(4, int(round(rate_hz / asked_hz)))  # samples per sub-window: one period, at least 4 samples
    slopes, weights, chi2, dof, spans, amps, sigmas, n_on = [], [], 0.0, 0, [], [], [], 0
    for r in runs:
        if r.size < 3:
            continue
        # the LED is on from the end of the run's first window to the start of its last one: only those
        # samples are used (a window that holds the switching has a biased phase)
        s0, s1 = int(r[0] + 1) * n_w, int(r[-1]) * n_w
        k = min((s1 - s0) // period, 64)
        if k < MIN_BURST_WINDOWS:
            continue
        m = (s1 - s0) // k
        fit = _sub_window_phases(x[:, s0: s0 + k * m], rate_hz, asked_hz, s0 / rate_hz, k, m)
        if fit is None:
            continue
        for piece in _phase_pieces(fit[1], fit[2], fit[5]):
            t, ph, var_ph = fit[0][piece], fit[1][piece], fit[2][piece]
            b, sxx, c2 = _phase_slope(t, ph, var_ph)
            chi2 += c2
            dof += piece.size - 2
            slopes.append(b)
            weights.append(sxx)
            spans.append(piece.size * m / rate_hz)
            amps.append(fit[3])
            sigmas.append(fit[4])
            n_on += piece.size * m
    if not slopes:
        return None
    slopes, weights = np.array(slopes), np.array(weights)
    b = float(np.sum(weights * slopes) / weights.sum())
    var_b = 1.0 / weights.sum()
    if len(slopes) > 1:
        chi2 += float(np.sum(weights * (slopes - b) ** 2))
        dof += len(slopes) - 1
    if dof > 0:
        var_b *= max(1.0, chi2 / dof)
    amp = np.median(np.array(amps), axis=0)
    sigma = np.median(np.array(sigmas), axis=0)
    snr = 20 * np.log10(np.maximum(amp * n_on / 2, 1e-300) / np.maximum(sigma * math.sqrt(n_on), 1e-300))
    return Carrier(freq_hz=asked_hz + b / (2 * math.pi), resolution_hz=float(1.0 / max(spans)), snr_db=snr,
                   amplitude=amp, noise_sigma=sigma, precision_hz=float(math.sqrt(var_b) / (2 * math.pi)))


def _phase_slope(t, ph, var_ph):
    """Weighted straight-line fit ``ph ~ p0 + b (t - tm)``: ``(b, sum w (t - tm)^2, chi2)`` (``w = 1 / var_ph``)."""
    w = 1.0 / var_ph
    tm = np.sum(w * t) / w.sum()
    sxx = float(np.sum(w * (t - tm) ** 2))
    pm = np.sum(w * ph) / w.sum()
    b = float(np.sum(w * (t - tm) * (ph - pm)) / sxx)
    return b, sxx, float(np.sum(w * (ph - pm - b * (t - tm)) ** 2))


def _phase_pieces(ph, var_ph, mag):
    """Runs of sub-windows of one LED: amplitude ``mag`` at least 0.8 of the median, phase steps that
    agree with the median step within 6 sigma.

    A weaker sub-window holds a switching (part dark, or two LEDs whose phases cancel in part); a
    step that disagrees is another LED.  The burst is cut there, the sub-windows on both sides of a
    bad step are dropped, and runs shorter than :data:`MIN_BURST_WINDOWS` are left out.
    """
    full = mag >= 0.8 * np.median(mag)
    step = np.diff(ph)
    both = full[:-1] & full[1:]
    med = float(np.median(step[both])) if np.any(both) else 0.0
    sd = np.sqrt(var_ph[:-1] + var_ph[1:])
    bad = ~both | (np.abs(np.angle(np.exp(1j * (step - med)))) > 6 * sd)
    keep = full.copy()
    keep[:-1] &= ~bad | ~full[1:]  # a bad step to a weak sub-window only drops the weak one
    keep[1:] &= ~bad | ~full[:-1]
    idx = np.flatnonzero(keep)
    pieces = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if idx.size else []
    return [p for p in pieces if p.size >= MIN_BURST_WINDOWS]


def _sub_window_phases(xs, rate_hz: float, f_hz: float, t0_s: float, k: int, m: int):
    """Common phase of ``k`` consecutive sub-windows of ``m`` samples of ``xs`` (4, k m) starting at ``t0_s``.

    Each sub-window is fitted by least squares with ``sin, cos`` at ``f_hz`` and an offset on its own
    time axis; the phase is referred to the recording's time.  Returns ``(t_s, phase_rad (unwrapped),
    var_phase, amplitude (4,), noise_sigma (4,), |sum of the complex amplitudes| (k,))`` (amplitude
    and noise_sigma medians over the sub-windows), or None
    when the carrier vanishes in a sub-window.
    """
    tau = np.arange(m) / rate_hz
    wt = 2 * np.pi * f_hz * tau
    basis = np.stack([np.sin(wt), np.cos(wt), np.ones(m)], axis=1)  # (m, 3)
    gram = basis.T @ basis
    coef = np.einsum("cjm,mp->jpc", xs.reshape(4, k, m), basis @ np.linalg.inv(gram))  # (k, 3, 4)
    res = xs.reshape(4, k, m) - np.einsum("jpc,mp->cjm", coef, basis)
    var_c = (res ** 2).sum(-1).T / max(m - 3, 1)  # (k, 4)
    z = coef[:, 0, :] + 1j * coef[:, 1, :]  # x ~ i sin + q cos
    zs = z.sum(-1)  # (k,)
    mag = np.abs(zs)
    if np.any(mag <= 0) or not np.all(np.isfinite(mag)):
        return None
    gi = np.linalg.inv(gram)[:2, :2]
    u = zs / mag
    # variance of the component of the summed amplitude across its phase, over |z|^2
    perp = (u.real ** 2) * gi[1, 1] - 2 * u.real * u.imag * gi[0, 1] + (u.imag ** 2) * gi[0, 0]
    var_ph = np.maximum(var_c.sum(-1) * perp / mag ** 2, 1e-300)
    t_start = t0_s + np.arange(k) * m / rate_hz
    ph = np.unwrap(np.angle(zs) - 2 * np.pi * f_hz * (t_start - t0_s))
    amp = np.median(np.abs((z * np.conj(u)[:, None]).real), axis=0)
    return t_start + 0.5 * (m - 1) / rate_hz, ph, var_ph, amp, np.median(np.sqrt(var_c), axis=0), mag


@dataclass(frozen=True)
class CarrierCheck:
    """An asked carrier against the measured one.

    Attributes
    ----------
    asked_hz : float
    measured : Carrier or None
        The strongest peak within +-5 % of the asked one (None: none found).
    offset_hz : float
        ``measured - asked`` (nan when none found).
    sigma_inflation : float
        Predicted factor on the demodulated sigmas (see the module docstring).
    amplitude_loss : float
        Predicted relative loss of amplitude, ``1 - sinc(df T)``.
    ok : bool
    message : str
        Empty when ``ok``.
    """

    asked_hz: float
    measured: Carrier | None
    offset_hz: float
    sigma_inflation: float
    amplitude_loss: float
    ok: bool
    message: str


def check_carrier(asked_hz: float, measured: Carrier | None, window_s: float, *, tdm: bool = False) -> CarrierCheck:
    """Compare ``asked_hz`` with the carrier measured near it (:func:`carrier_near`).

    Parameters
    ----------
    asked_hz : float
    measured : Carrier or None
    window_s : float
        Demodulation window, s.
    tdm : bool
        Time multiplexing (a missing carrier may just be an LED that is off
        in the scanned part; the amplitude is then not the duty-cycle average).
        Measure a time-multiplexed carrier with :func:`carrier_in_bursts`
        (see :func:`measure_carrier`): the spectral peak may be a side-band.
    """
    if measured is None:
        return CarrierCheck(asked_hz, None, math.nan, math.nan, math.nan, False,
                            f"no carrier found within 5 % of {asked_hz:g} Hz; "
                            "check --carrier-hz and --rate-hz with 'psdcal inspect'")
    c = measured
    off = c.freq_hz - asked_hz
    # the measurement's own precision: three standard errors when the estimator gives one
    # (carrier_in_bursts), else a tenth of a bin (Hann + parabolic interpolation)
    tol = 3.0 * c.precision_hz if math.isfinite(c.precision_hz) else 0.1 * c.resolution_hz
    eff = max(abs(off) - tol, 0.0)
    x = math.pi * eff * window_s
    a = float(np.max(c.amplitude))
    s = float(np.max(c.noise_sigma[np.argmax(c.amplitude)]))
    # tdm with a spectral measurement: the record-averaged amplitude underestimates an LED's (a lower bound);
    # with carrier_in_bursts the amplitude is the on-time one
    infl = math.sqrt(1.0 + (a * x) ** 2 / (6.0 * max(s, 1e-300) ** 2))
    loss = 1.0 - (math.sin(x) / x if x > 0 else 1.0)
    ok = infl <= MAX_SIGMA_INFLATION and loss <= MAX_AMPLITUDE_LOSS
    prec = (f"standard error {c.precision_hz:.2g} Hz in the bursts" if math.isfinite(c.precision_hz)
            else f"resolution {c.resolution_hz:.2g} Hz")
    msg = "" if ok else (
        f"carrier asked at {asked_hz:g} Hz is measured at {c.freq_hz:.6g} Hz ({off:+.3g} Hz, {prec}): in a {window_s:g} s window this inflates the sigmas about "
        f"{infl:.3g}x and loses {100 * loss:.2g} % of the amplitude (check --carrier-hz and --rate-hz)")
    return CarrierCheck(asked_hz, c, off, infl, loss, ok, msg)


def measure_carrier(x, rate_hz: float, asked_hz: float, *, tdm: bool = False, min_snr: float = 10.0,
                    spectrum_cache: dict | None = None) -> Carrier | None:
    """The carrier near ``asked_hz``: from the bursts' phase slope for time multiplexing
    (:func:`carrier_in_bursts`, falling back on the spectrum when no burst is found), else
    the spectral peak (:func:`carrier_near`)."""
    if tdm:
        c = carrier_in_bursts(x, rate_hz, asked_hz, min_snr=min_snr)
        if c is not None:
            return c
    return carrier_near(x, rate_hz, asked_hz, spectrum_cache=spectrum_cache)


@dataclass(frozen=True)
class TdmScan:
    """On-times and gaps of a time-multiplexed record.

    Attributes
    ----------
    window_s : float
        Short window used for the scan, s.
    segments : list of Segment
        Segments found with that window (names 1, 2, ...).
    on_s : (n,) ndarray
        Estimated on-time of each segment (span plus the two edge windows), s.
    gap_s : (n - 1,) ndarray
        Time between consecutive segments, s (0 for LEDs back to back).
    """

    window_s: float
    segments: list
    on_s: np.ndarray
    gap_s: np.ndarray


def scan_tdm(x, rate_hz: float, carrier_hz: float, *, min_snr: float = 10.0) -> TdmScan:
    """Segments of a time-multiplexed record found with a short window.

    The window holds :data:`psdcal.signal.stream.MIN_PERIODS` periods of the
    carrier (at least 32 samples).
    """
    from psdcal.signal.stream import MIN_PERIODS, MultiCarrierLockin, TdmSegmenter

    periods = max(MIN_PERIODS, math.ceil(32 * carrier_hz / rate_hz))
    w0 = math.ceil(periods / carrier_hz * rate_hz) / rate_hz
    lk = MultiCarrierLockin(rate_hz, [carrier_hz], w0)
    seg = TdmSegmenter(lk.window_s, min_snr=min_snr)
    segs = seg.feed(lk.process(0.0, x)) + seg.finish()
    w = lk.window_s
    # an edge window on each side was dropped (runs longer than two windows)
    on = np.array([s.t_end_s - s.t_start_s + (2 * w if s.n_windows > 2 else 0.0) for s in segs])
    st = np.array([s.t_start_s - (w if s.n_windows > 2 else 0.0) for s in segs])
    gaps = np.clip(st[1:] - (st[:-1] + on[:-1]), 0.0, None) if len(segs) > 1 else np.zeros(0)
    return TdmScan(w, segs, on, gaps)


def choose_tdm_window(scan: TdmScan, carrier_hz: float, *, max_window_s: float = 0.01) -> float:
    """A demodulation window for time multiplexing from the measured on-times.

    An eighth of the shortest on-time (a segment keeps about six clean
    windows after its two edge windows are dropped), rounded down to a whole
    number of carrier periods, at least :data:`~psdcal.signal.stream.MIN_PERIODS`
    periods (the scan's window) and at most ``max_window_s``.

    Raises
    ------
    InputError
        No segment found in the scanned part.
    """
    if len(scan.on_s) == 0:
        raise InputError(f"no time-multiplexed segment of the {carrier_hz:g} Hz carrier found in the scanned part "
                         "(check --carrier-hz, --min-snr, or give --window-s)", field="window_s")
    # the median of the on-times: a lone short edge segment must not shrink the window
    on = float(np.median(scan.on_s))
    w = min(on / 8.0, max_window_s)
    w = math.floor(w * carrier_hz) / carrier_hz
    return max(w, scan.window_s + 0.1 / carrier_hz)


#: A schedule whose times the on-times found follow with a scale off by more than this (and 5 standard
#: errors) names the sampling rate.
MAX_TIME_SCALE_ERROR = 0.005


def schedule_timing(scan: TdmScan, schedule, rate_hz: float, scanned_s: float) -> str | None:
    """Whether the on-times found in the signal fall where the schedule puts them.

    Times in a recording are sample numbers over ``--rate-hz``: with a wrong
    rate every time found is scaled by ``true rate / given rate`` while the
    schedule's times are not, so the slots drift off the LEDs (the windows of
    one LED then hold the next one, or the dark, and the calibration sees a
    permuted template).  The ``k``-th segment found is paired with the
    ``k``-th schedule entry (segments ending within 2 scan windows of the end
    of the scanned part are left out) and their centres fitted as
    ``t_found = s t_schedule + t0``.

    Parameters
    ----------
    scan : TdmScan
    schedule : sequence of ScheduleEntry
    rate_hz : float
        The rate given.
    scanned_s : float
        Duration of the scanned part, s.

    Returns
    -------
    str or None
        A message naming the rate when ``|s - 1|`` exceeds
        :data:`MAX_TIME_SCALE_ERROR` and 5 standard errors and the pairing is
        consistent (residuals within a scan window); None otherwise (nothing
        to say, or not enough segments to tell).
    """
    sched = sorted(schedule, key=lambda e: e.t_start_s)
    w = scan.window_s
    segs = [sg for sg in scan.segments if sg.t_end_s < scanned_s - 2 * w]
    n = min(len(segs), len(sched))
    if n < 3:
        return None
    c_found = np.array([0.5 * (sg.t_start_s + sg.t_end_s) for sg in segs[:n]])
    c_sched = np.array([0.5 * (e.t_start_s + e.t_end_s) for e in sched[:n]])
    dc = c_sched - c_sched.mean()
    sxx = float(np.sum(dc * dc))
    if sxx <= 0:
        return None
    slope = float(np.sum(dc * (c_found - c_found.mean())) / sxx)
    res = c_found - c_found.mean() - slope * dc
    if np.sqrt(np.mean(res ** 2)) > w:
        return None  # LEDs missing or merged: the pairing by order does not hold
    # a centre is known to about a window (edges found window by window)
    se = w / math.sqrt(12.0) * math.sqrt(2.0) / math.sqrt(sxx)
    if abs(slope - 1.0) <= max(MAX_TIME_SCALE_ERROR, 5 * se):
        return None
    shift_ms = float(np.max(np.abs(c_found - c_sched))) * 1e3
    return (f"the {n} on-times found in the signal fall at {slope:.4g} x the schedule's times (the last one "
            f"{shift_ms:.3g} ms off): --rate-hz {rate_hz:g} is probably wrong, the schedule fits "
            f"{rate_hz * slope:.6g} Hz (a wrong rate moves every slot off its LED and the calibration then "
            f"sees the LEDs out of order)")
