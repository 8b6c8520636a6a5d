"""Streaming demodulation of four-channel recordings (docs/model.md#signal-chain).

* :class:`MultiCarrierLockin`: windowed synchronous demodulation of several
  carriers at once (frequency multiplexing).  Every window of ``n_window``
  samples is fitted by least squares with ``sin`` and ``cos`` of **all**
  carriers plus an offset.  Solving the carriers jointly (instead of one
  lock-in per carrier) removes the cross-talk between carriers even when the
  window is not a whole number of periods of each.  The basis is built on the
  window's own time axis, so one pre-computed projection serves every window;
  the phases are referred back to the recording's time axis (``t0_s`` of the
  chunks), so they stay coherent across chunks.
* The four channels of one emitter share the carrier phase (the light spot
  splits one photocurrent), so each channel's amplitude is the projection of
  its complex amplitude on the common phase: a signed, unbiased estimate with
  Gaussian noise (``hypot(i, q)`` would be biased upwards at low SNR).
* The residual of each window's fit gives the noise of each channel, and the
  least-squares covariance ``sigma^2 (B^T B)^-1`` the noise of the amplitudes.
* :class:`TdmSegmenter`: time multiplexing (LEDs on one at a time, as on the
  calibration template), with segments found from the signal (windows whose
  total amplitude is significant) or given by a schedule.

The single-record functions of :mod:`psdcal.signal.demod` remain the reference;
``MultiCarrierLockin`` with one carrier gives the same amplitude as
:func:`psdcal.signal.demod.lockin_amplitude` on each window.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psdcal.errors import InputError
from psdcal.io import csv_rows_checked

#: A window must hold at least this many periods of the lowest carrier.
MIN_PERIODS = 3.0

#: Relative floor of the fitted noise (of the window's RMS): double rounding is ~1e-16.
NOISE_FLOOR_REL = 1e-12


@dataclass(frozen=True)
class WindowBlock:
    """Demodulated windows (a batch produced from one chunk).

    Attributes
    ----------
    index : (n_w,) int ndarray
        Window number since the start of the recording.
    t_start_s, t_s : (n_w,) ndarrays
        Start and centre time of each window, s.
    amplitude : (n_w, n_carriers, 4) ndarray
        Amplitude (peak) of each carrier on each channel, projected on the
        carrier's common phase (signed; signal unit).
    var_amplitude : (n_w, n_carriers, 4) ndarray
        Its variance from the fit residual, signal unit^2.
    phase_rad : (n_w, n_carriers) ndarray
        Common phase ``theta`` of each carrier, ``v ~ A sin(2 pi f t + theta)``
        in the recording's time.
    noise_sigma : (n_w, 4) ndarray
        RMS residual of each channel's fit (the noise), signal unit.
    """

    index: np.ndarray
    t_start_s: np.ndarray
    t_s: np.ndarray
    amplitude: np.ndarray
    var_amplitude: np.ndarray
    phase_rad: np.ndarray
    noise_sigma: np.ndarray

    def __len__(self) -> int:
        return int(self.index.shape[0])


def check_carriers(rate_hz: float, carriers_hz, window_s: float) -> tuple[int, tuple[float, ...]]:
    """Validate a demodulation set-up; returns ``(n_window, carriers)``.

    Raises
    ------
    InputError
        A carrier at or above Nyquist, repeated carriers, a window shorter than
        :data:`MIN_PERIODS` periods of the lowest carrier, or carriers closer
        than ``1 / window_s`` (they cannot be told apart in one window).
    """
    rate = float(rate_hz)
    if not (rate > 0 and math.isfinite(rate)):
        raise InputError(f"sampling rate must be positive, got {rate_hz}", field="rate_hz")
    carriers = tuple(float(f) for f in carriers_hz)
    if not carriers:
        raise InputError("give at least one carrier frequency", field="carrier_hz")
    for f in carriers:
        if not (f > 0 and math.isfinite(f)):
            raise InputError(f"carrier frequency must be positive, got {f}", field="carrier_hz")
        if f >= rate / 2:
            raise InputError(f"carrier {f:g} Hz is at or above the Nyquist frequency {rate / 2:g} Hz", field="carrier_hz")
    if len(set(carriers)) != len(carriers):
        raise InputError(f"repeated carrier frequency in {list(carriers)}", field="carrier_hz")
    w = float(window_s)
    if not (w > 0 and math.isfinite(w)):
        raise InputError(f"window must be positive, got {window_s} s", field="window_s")
    n = int(round(w * rate))
    w_eff = n / rate
    fmin = min(carriers)
    if w_eff * fmin < MIN_PERIODS:
        raise InputError(
            f"window {w_eff:g} s is shorter than {MIN_PERIODS:g} periods of the {fmin:g} Hz carrier "
            f"(use --window-s >= {MIN_PERIODS / fmin:g})",
            field="window_s",
        )
    if len(carriers) > 1:
        fs = sorted(carriers)
        df = min(b - a for a, b in zip(fs, fs[1:]))
        if w_eff * df < 1.0:
            raise InputError(
                f"carriers {df:g} Hz apart cannot be separated in a {w_eff:g} s window "
                f"(use --window-s >= {1.0 / df:g})",
                field="window_s",
            )
    return n, carriers


def sum_squares_reference(xr: np.ndarray) -> np.ndarray:
    """``sum_n x[w, n, c]^2`` of windows ``xr`` (nw, n, 4) -> (nw, 4): the reference of :func:`_sum_squares`."""
    return np.einsum("wnc,wnc->wc", xr, xr)


_VECDOT = getattr(np, "vecdot", None)  # numpy >= 2.0


def _sum_squares(xr: np.ndarray) -> np.ndarray:
    """Per-window sums of squares (nw, 4) of ``xr`` (nw, n, 4), one pass (``np.vecdot``: 3x einsum's speed)."""
    if _VECDOT is None:  # pragma: no cover - numpy 1.x
        return sum_squares_reference(xr)
    return _VECDOT(xr, xr, axis=1)


#: Samples (per channel) from which a command-line run (``psdcal._jit`` in ``"auto"`` mode) uses the
#: compiled window sums even before numba is loaded: below it, loading the kernel costs more than it saves.
LOCKIN_AUTO_MIN_SAMPLES = 1 << 22


def use_compiled_lockin(n_samples: int = 0) -> bool:
    """Whether a lock-in over ``n_samples`` samples (0: unknown) uses the compiled window sums.

    Always where the library compiles by default (``psdcal._jit`` mode ``"always"``); on the command
    line (``"auto"``) when numba is already loaded or the recording has at least
    :data:`LOCKIN_AUTO_MIN_SAMPLES` samples.  Never without numba (``PSDCAL_JIT=0``).
    """
    import sys

    from psdcal import _jit

    if not _jit.enabled():
        return False
    return bool(_jit.use_compiled(0) or "numba" in sys.modules or n_samples >= LOCKIN_AUTO_MIN_SAMPLES)


class MultiCarrierLockin:
    """Windowed joint lock-in over a stream of chunks (frequency multiplexing).

    Window ``j`` holds samples ``[j n, (j + 1) n)`` counted from the first
    sample given; a last partial window is dropped.

    Parameters
    ----------
    rate_hz : float
    carriers_hz : sequence of float
        One carrier per emitter.
    window_s : float
        Window length, s (rounded to a whole number of samples).
    compiled : bool or None
        Window sums by the compiled kernel (:mod:`psdcal.signal._lockin_kernel`, equal to the numpy
        product to rounding) or by numpy; None: :func:`use_compiled_lockin` decides at the first chunk.

    Examples
    --------
    >>> lk = MultiCarrierLockin(100e3, [1000.0, 1300.0], 0.01)
    >>> for t0, block in recording.chunks():          # doctest: +SKIP
    ...     windows = lk.process(t0, block)
    """

    def __init__(self, rate_hz: float, carriers_hz, window_s: float, *, compiled: bool | None = None):
        n, carriers = check_carriers(rate_hz, carriers_hz, window_s)
        #: the compiled window sums (:mod:`psdcal.signal._lockin_kernel`): True, False, or None (decided at
        #: the first chunk by :func:`use_compiled_lockin`)
        self.compiled = compiled
        self.rate_hz = float(rate_hz)
        self.carriers_hz = carriers
        self.n_window = n
        k = len(carriers)
        tau = np.arange(n) / self.rate_hz
        cols = []
        for f in carriers:
            w = 2 * np.pi * f * tau
            cols += [np.sin(w), np.cos(w)]
        cols.append(np.ones(n))
        basis = np.stack(cols, axis=1)  # (n, 2k + 1)
        gram = basis.T @ basis
        if np.linalg.cond(gram) > 1e10:
            raise InputError("the carriers are not separable in this window (ill-conditioned fit)", field="window_s")
        self._gram = gram
        self._ginv = np.linalg.inv(gram)
        self._proj = np.ascontiguousarray(basis @ self._ginv)  # coef = x @ proj
        self._proj_t = np.ascontiguousarray(self._proj.T)  # (2k + 1, n): coef = proj_t @ rows, per window
        self._gi = np.stack([self._ginv[2 * m : 2 * m + 2, 2 * m : 2 * m + 2] for m in range(k)])  # (k, 2, 2)
        self._omega = 2 * np.pi * np.asarray(carriers)
        self._dof = n - (2 * k + 1)
        self._buf = np.empty((0, 4))
        self._origin_s = None
        self._consumed = 0  # samples received
        self._next_window = 0

    @property
    def window_s(self) -> float:
        """Effective window length, s."""
        return self.n_window / self.rate_hz

    def process(self, t0_s: float, block) -> WindowBlock:
        """Feed the next chunk ``block`` (4, m) starting at ``t0_s``; return the windows it completes."""
        block = np.asarray(block, dtype=float)
        if block.ndim != 2 or block.shape[0] != 4:
            raise InputError(f"a chunk must have shape (4, n), got {block.shape}")
        return self.process_rows(t0_s, block.T)

    def process_rows(self, t0_s: float, rows) -> WindowBlock:
        """As :meth:`process`, for a chunk given as rows ``(m, 4)`` (one sample of the four channels a row).

        The layout of a ``(n, 4)`` ``.npy`` recording: the chunk is used as it
        lies (no transpose), any strides.
        """
        return self.windows(*self.fit_rows(t0_s, rows))

    def fit_rows(self, t0_s: float, rows) -> tuple[int, np.ndarray, np.ndarray]:
        """The least-squares sums of the windows a chunk of rows ``(m, 4)`` completes.

        The first half of :meth:`process_rows`: returns ``(j0, coef, xx)``,
        the number of the first window completed, ``coef`` (nw, 2k + 1, 4)
        the fitted ``sin, cos`` of each carrier and the offset, ``xx`` (nw, 4)
        the sums of squares of each window and channel (finite only when
        every sample is).  :meth:`windows` turns them (those of several
        chunks together, consecutive) into a :class:`WindowBlock`.
        """
        rows = np.asarray(rows, dtype=float)
        if rows.ndim != 2 or rows.shape[1] != 4:
            raise InputError(f"a chunk of rows must have shape (n, 4), got {rows.shape}")
        if self._origin_s is None:
            self._origin_s = float(t0_s)
        else:
            expected = self._origin_s + self._consumed / self.rate_hz
            if abs(float(t0_s) - expected) > 0.5 / self.rate_hz:
                raise InputError(f"gap in the recording: chunk at {t0_s:.9g} s, expected {expected:.9g} s")
        self._consumed += rows.shape[0]
        n = self.n_window
        held = self._buf.shape[0]
        if held and held + rows.shape[0] >= n:
            # the window begun in the previous chunk is completed alone (the rest of the chunk is not
            # copied to join it); every window's sums are computed alike, whatever the chunking
            head = np.concatenate([self._buf, rows[: n - held]], axis=0)
            self._buf = np.empty((0, 4))
            j0, c1, x1 = self._fit(head.reshape(1, n, 4))
            _, c2, x2 = self._fit_rows_rest(rows[n - held:])
            return j0, np.concatenate([c1, c2]), np.concatenate([x1, x2])
        return self._fit_rows_rest(rows)

    def _fit_rows_rest(self, rows) -> tuple[int, np.ndarray, np.ndarray]:
        """:meth:`fit_rows` of rows that follow what is held (checked and counted by the caller)."""
        n = self.n_window
        x = rows if self._buf.shape[0] == 0 else np.concatenate([self._buf, rows], axis=0)
        nw = x.shape[0] // n
        used = nw * n
        self._buf = x[used:].copy() if used < x.shape[0] else np.empty((0, 4))
        return self._fit(x[:used].reshape(nw, n, 4))

    @property
    def pending_samples(self) -> int:
        """Samples received but not yet in a complete window (held for the next chunk)."""
        return int(self._buf.shape[0])

    def _fit(self, xr: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
        """``(j0, coef, xx)`` of windows ``xr`` (nw, n, 4): one matrix product per window with the projection table."""
        j0 = self._next_window
        self._next_window += xr.shape[0]
        if xr.shape[0] == 0:
            return j0, np.zeros((0, self._proj_t.shape[0], 4)), np.zeros((0, 4))
        if self.compiled is None:
            self.compiled = use_compiled_lockin()
        if self.compiled:
            return j0, *self._fit_compiled(xr)
        coef = np.matmul(self._proj_t, xr)  # (nw, 2k+1, 4): the least-squares fit of every window and channel
        return j0, coef, _sum_squares(xr)

    def _fit_compiled(self, xr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(coef, xx)`` of :meth:`_fit` by the compiled kernel (one pass per window; numpy's to rounding)."""
        from psdcal.signal import _lockin_kernel as kern

        if getattr(self, "_kern_table", None) is None:
            self._kern_table = kern.padded_table(self._proj_t)
        nw, n = xr.shape[0], self.n_window
        coef = np.empty((nw, self._proj_t.shape[0], 4))
        xx = np.empty((nw, 4))
        kern.window_sums(self._kern_table, xr.reshape(nw * n, 4), n, coef, xx)
        return coef, xx

    def _demodulate_rows(self, xr: np.ndarray) -> WindowBlock:
        """Windows ``xr`` (nw, n, 4) -> amplitudes (:meth:`_fit`, then :meth:`windows`).

        Same estimate as :meth:`_demodulate` (the numpy reference, on the
        channel-major layout): ``coef = P x`` with ``P = G^-1 B^T`` computed
        once, the residual from ``|x|^2 - coef^T G coef``.
        """
        return self.windows(*self._fit(xr))

    def windows(self, j0: int, coef: np.ndarray, xx: np.ndarray) -> WindowBlock:
        """Windows ``j0, j0 + 1, ...`` from their sums (:meth:`fit_rows`): amplitudes, noise, phases."""
        n = self.n_window
        k = len(self.carriers_hz)
        nw = coef.shape[0]
        index = np.arange(j0, j0 + nw)
        if nw == 0:
            e = np.zeros((0, k, 4))
            t0 = np.zeros(0)
            return WindowBlock(index, t0, t0, e, e, np.zeros((0, k)), np.zeros((0, 4)))
        t_start = self._origin_s + index * n / self.rate_hz
        # a non-finite sample (found and named by the caller from the sums) must not print numpy warnings
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            return self._windows(coef, xx, index, t_start)

    def _windows(self, coef, xx, index, t_start) -> WindowBlock:
        if self.compiled:
            return self._windows_compiled(coef, xx, index, t_start)
        n = self.n_window
        k = len(self.carriers_hz)
        fit = (coef * np.matmul(self._gram, coef)).sum(axis=1)  # coef^T G coef per window and channel (nw, 4)
        var = np.clip(xx - fit, 0.0, None) / max(self._dof, 1)  # (nw, 4)
        # floor: rounding leaves a residual of ~1e-16 of the signal (see _demodulate)
        var = np.maximum(var, (NOISE_FLOOR_REL**2) * xx / n)
        i_ = coef[:, 0 : 2 * k : 2]  # (nw, k, 4): x ~ i sin + q cos on the window's own time
        q_ = coef[:, 1 : 2 * k : 2]
        zr, zi = i_.sum(axis=-1), q_.sum(axis=-1)  # (nw, k): common phase of the four channels
        mag = np.hypot(zr, zi)
        pos = mag > 0
        safe = np.where(pos, mag, 1.0)
        ur = np.where(pos, zr / safe, 1.0)
        ui = np.where(pos, zi / safe, 0.0)
        amp = i_ * ur[..., None] + q_ * ui[..., None]  # Re(z conj(u)), signed
        gi = self._gi
        quad = ur * ur * gi[:, 0, 0] + 2 * ur * ui * gi[:, 0, 1] + ui * ui * gi[:, 1, 1]  # (nw, k)
        var_amp = var[:, None, :] * quad[..., None]
        phase = np.arctan2(zi, zr) - self._omega[None, :] * (t_start - self._origin_s)[:, None]
        phase = np.angle(np.exp(1j * phase))
        return WindowBlock(
            index=index,
            t_start_s=t_start,
            t_s=t_start + 0.5 * (n - 1) / self.rate_hz,
            amplitude=amp,
            var_amplitude=var_amp,
            phase_rad=phase,
            noise_sigma=np.sqrt(var),
        )

    def _windows_compiled(self, coef, xx, index, t_start) -> WindowBlock:
        """:meth:`_windows` by the compiled per-window loop (its numpy code is the reference; equal to rounding)."""
        from psdcal.signal._lockin_kernel import window_stats

        n = self.n_window
        var, amp, var_amp, zr, zi = window_stats(coef, xx, self._gram, self._gi, n, self._dof, NOISE_FLOOR_REL**2)
        phase = np.arctan2(zi, zr) - self._omega[None, :] * (t_start - self._origin_s)[:, None]
        # wrapped by a remainder (the numpy code's angle(exp(1j phase)) costs ten times more): the same angle
        # to the rounding of the phase itself, in [-pi, pi)
        phase += np.pi
        np.remainder(phase, 2.0 * np.pi, out=phase)
        phase -= np.pi
        return WindowBlock(index=index, t_start_s=t_start, t_s=t_start + 0.5 * (n - 1) / self.rate_hz,
                           amplitude=amp, var_amplitude=var_amp, phase_rad=phase, noise_sigma=np.sqrt(var))

    def _demodulate(self, xw: np.ndarray) -> WindowBlock:
        """Numpy reference of :meth:`_demodulate_rows` on the channel-major layout ``xw`` (4, nw, n)."""
        n = self.n_window
        k = len(self.carriers_hz)
        nw = xw.shape[1]
        j0 = self._next_window
        self._next_window += nw
        index = np.arange(j0, j0 + nw)
        t_start = self._origin_s + index * n / self.rate_hz
        if nw == 0:
            e = np.zeros((0, k, 4))
            return WindowBlock(index, t_start, t_start, e, e, np.zeros((0, k)), np.zeros((0, 4)))
        coef = xw @ self._proj  # (4, nw, 2k+1)
        xx = np.einsum("cwn,cwn->cw", xw, xw)
        fit = np.einsum("cwi,ij,cwj->cw", coef, self._gram, coef)
        var = np.clip(xx - fit, 0.0, None) / max(self._dof, 1)  # (4, nw)
        # Floor: rounding leaves a residual of ~1e-16 of the signal; a constant or
        # noiseless record must not give amplitudes of 1e-17 with sigma 0.
        var = np.maximum(var, (NOISE_FLOOR_REL**2) * xx / n)
        iq = coef[..., : 2 * k].reshape(4, nw, k, 2)  # (i, q) per carrier
        z = iq[..., 0] + 1j * iq[..., 1]  # x ~ i sin + q cos on the window's own time
        zsum = z.sum(axis=0)  # (nw, k): common phase of the four channels
        mag = np.abs(zsum)
        u = np.where(mag > 0, zsum / np.where(mag > 0, mag, 1.0), 1.0)
        amp = (z * np.conj(u)).real  # (4, nw, k), signed
        # Var of the projection: u^T Ginv_k u sigma^2 with u = (Re u, Im u) over (i, q)
        gi = np.stack([self._ginv[2 * m : 2 * m + 2, 2 * m : 2 * m + 2] for m in range(k)])  # (k, 2, 2)
        ur, ui = u.real, u.imag
        quad = ur * ur * gi[:, 0, 0] + 2 * ur * ui * gi[:, 0, 1] + ui * ui * gi[:, 1, 1]  # (nw, k)
        var_amp = var[:, :, None] * quad[None]
        # common phase in the recording's time: x = A sin(w tau + th_l) = A sin(w t + th_l - w t_start)
        phase = np.angle(zsum) - self._omega[None, :] * (t_start - self._origin_s)[:, None]
        phase = np.angle(np.exp(1j * phase))
        return WindowBlock(
            index=index,
            t_start_s=t_start,
            t_s=t_start + 0.5 * (n - 1) / self.rate_hz,
            amplitude=np.moveaxis(amp, 0, -1),
            var_amplitude=np.moveaxis(var_amp, 0, -1),
            phase_rad=phase,
            noise_sigma=np.sqrt(var).T,
        )


# --------------------------------------------------------------------------- time multiplexing
@dataclass(frozen=True)
class ScheduleEntry:
    """One line of a schedule: ``emitter`` is on during ``[t_start_s, t_end_s]``."""

    emitter: str
    t_start_s: float
    t_end_s: float


def load_schedule(path) -> tuple[ScheduleEntry, ...]:
    """Read a schedule CSV with header ``emitter,t_start_s,t_end_s``.

    Raises
    ------
    InputError
        Naming the file, the line and the field.
    """
    import io as _io

    from psdcal.io import read_text_file

    path = Path(path)
    fh = _io.StringIO(read_text_file(path, "schedule file"), newline="")
    out = []
    with fh:
        rows = csv_rows_checked(csv.reader(fh), path)
        header = [h.strip() for h in next(rows, [])]
        for col in ("emitter", "t_start_s", "t_end_s"):
            if col not in header:
                raise InputError(f"missing column '{col}' (header must be emitter,t_start_s,t_end_s)", path=path,
                                 line=1, field=col)
        ie, i0, i1 = (header.index(c) for c in ("emitter", "t_start_s", "t_end_s"))
        for lineno, row in enumerate(rows, start=2):
            if not row or not any(c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise InputError(f"expected {len(header)} fields, found {len(row)}", path=path, line=lineno)
            vals = {}
            for col, i in (("t_start_s", i0), ("t_end_s", i1)):
                try:
                    vals[col] = float(row[i])
                except ValueError:
                    raise InputError(f"not a number: {row[i]!r}", path=path, line=lineno, field=col) from None
                if not math.isfinite(vals[col]):
                    raise InputError("not a finite number", path=path, line=lineno, field=col)
            if not vals["t_end_s"] > vals["t_start_s"]:
                raise InputError("t_end_s must be after t_start_s", path=path, line=lineno, field="t_end_s")
            out.append(ScheduleEntry(row[ie].strip(), vals["t_start_s"], vals["t_end_s"]))
    if not out:
        raise InputError("the schedule has no entries", path=path)
    out = sorted(out, key=lambda e: e.t_start_s)
    for a, b in zip(out, out[1:]):
        if b.t_start_s < a.t_end_s:
            raise InputError(f"{b.emitter!r} starts at {b.t_start_s:g} s before {a.emitter!r} ends at {a.t_end_s:g} s: "
                             "schedule entries must not overlap", path=path, field="t_start_s")
    return tuple(out)


@dataclass(frozen=True)
class Segment:
    """An emitter's on-time, its windows averaged.

    Attributes
    ----------
    emitter : str
    t_start_s, t_end_s : float
        Span of the windows used, s.
    n_windows : int
    amplitude : (4,) ndarray
        Mean amplitude per channel.
    var_amplitude : (4,) ndarray
        Variance of that mean (from the windows' residual noise).
    """

    emitter: str
    t_start_s: float
    t_end_s: float
    n_windows: int
    amplitude: np.ndarray
    var_amplitude: np.ndarray

    @property
    def t_s(self) -> float:
        """Centre of the segment, s."""
        return 0.5 * (self.t_start_s + self.t_end_s)


class _Acc:
    __slots__ = ("t0", "t1", "n", "sa", "sv")

    def __init__(self):
        self.t0, self.t1, self.n = math.inf, -math.inf, 0
        self.sa = np.zeros(4)
        self.sv = np.zeros(4)

    def add(self, t0, t1, a, v):
        self.t0 = min(self.t0, t0)
        self.t1 = max(self.t1, t1)
        self.n += a.shape[0]
        self.sa = self.sa + a.sum(0)
        self.sv = self.sv + v.sum(0)

    def segment(self, name):
        return Segment(name, self.t0, self.t1, self.n, self.sa / self.n, self.sv / self.n**2)


def _check_schedule(sched) -> None:
    """Refuse overlapping schedule entries (two LEDs would share the same windows)."""
    order = sorted(sched, key=lambda e: e.t_start_s)
    for a, b in zip(order, order[1:]):
        if b.t_start_s < a.t_end_s:
            raise InputError(
                f"schedule entries '{a.emitter}' ({a.t_start_s:g}-{a.t_end_s:g} s) and '{b.emitter}' "
                f"({b.t_start_s:g}-{b.t_end_s:g} s) overlap: two LEDs cannot be on together in time "
                "multiplexing", field="t_start_s")


class TdmSegmenter:
    """Time multiplexing: one emitter on at a time on one carrier.

    Without a schedule, a window is *on* when its total amplitude exceeds
    ``min_snr`` times its standard deviation; each run of on-windows is a
    segment.  A run is also split where the spot jumps: where the channel
    ratios ``a_i / sum(a)`` of consecutive windows differ by more than
    ``split_sigma`` times their noise and by more than ``split_floor`` (LEDs
    switched back to back, without a dark gap), and where the total amplitude
    of consecutive windows differs by more than ``split_sigma`` times its noise
    and by more than ``level_floor`` of its value (a window straddling a dark
    gap shorter than the window holds less light than its neighbours: the two
    LEDs around the gap are not merged).  The first and last windows of
    a run (which may straddle the switching) are dropped when the run is
    longer than two windows; a run of one or two windows next to a jump (a
    transition across a short gap, or the partly lit edge of a run) is
    discarded.  Segments are named ``1, 2, ...`` (modulo ``n_emitters``
    when the emitters repeat in cycles).  With a schedule, the windows lying
    entirely inside an entry's interval are that entry's segment.

    Self-checks (never a relabelling):

    * ``n_emitters`` given: at :meth:`finish`, a number of segments that is not
      a multiple of ``n_emitters`` raises :class:`InputError` (a merged or
      split LED would shift every later label).
    * a schedule whose entries overlap raises :class:`InputError` at
      construction (two LEDs would share windows).
    * :attr:`warnings` collects what a user should see: schedule entries that
      received no window, segments much shorter than the others.

    Parameters
    ----------
    window_s : float
        Window length (to know each window's end).
    carrier_index : int
        Which carrier of the :class:`WindowBlock` to use.
    min_snr : float
        Detection threshold (amplitude / its 1-sigma).
    schedule : sequence of ScheduleEntry, optional
    n_emitters : int, optional
        Number of emitters in a cycle (names repeat modulo it).
    split_sigma, split_floor : float
        Jump detection between consecutive windows (see above); the floor
        1e-3 of the ratio is about 0.01 mm on a 9 mm PSD.
    level_floor : float
        Relative change of the total amplitude between consecutive windows
        that counts as a switch (with ``split_sigma``).
    """

    def __init__(self, window_s: float, *, carrier_index: int = 0, min_snr: float = 20.0, schedule=None,
                 n_emitters: int | None = None, split_sigma: float = 8.0, split_floor: float = 1e-3,
                 level_floor: float = 0.1):
        self.window_s = float(window_s)
        if n_emitters is not None and int(n_emitters) < 1:
            raise InputError(f"--n-emitters must be at least 1, got {n_emitters}", field="n_emitters")
        if schedule is not None:
            _check_schedule(tuple(schedule))
        self.level_floor = float(level_floor)
        self.warnings: list[str] = []
        self.segments: list[Segment] = []  # every segment returned so far
        self.n_transitions = 0  # windows between two spots, discarded
        self.n_dropped_runs = 0  # runs of such windows
        self.k = int(carrier_index)
        self.min_snr = float(min_snr)
        self.schedule = None if schedule is None else tuple(schedule)
        self.n_emitters = None if n_emitters is None else int(n_emitters)
        self.split_sigma = float(split_sigma)
        self.split_floor = float(split_floor)
        self._count = 0
        self._run: _Acc | None = None
        self._run_len = 0
        self._run_after_jump = False
        self._first = None  # held-back first window of the run
        self._pending = None  # held-back latest window of the run
        self._last_ratio = None  # (ratio (4,), its sigma (4,)) of the latest on-window
        self._sched_acc: dict[int, _Acc] = {}
        self._sched_next = 0

    def _name(self) -> str:
        self._count += 1
        if self.n_emitters:
            return str((self._count - 1) % self.n_emitters + 1)
        return str(self._count)

    def feed(self, block: WindowBlock) -> list[Segment]:
        """Consume a :class:`WindowBlock`; return the segments it completes."""
        a = block.amplitude[:, self.k, :]
        v = block.var_amplitude[:, self.k, :]
        t0 = block.t_start_s
        t1 = t0 + self.window_s
        if self.schedule is not None:
            return self._feed_schedule(t0, t1, a, v)
        total = a.sum(-1)
        sd = np.sqrt(v.sum(-1))
        on = total > self.min_snr * sd
        safe = np.where(on, total, 1.0)
        ratio = a / safe[:, None]
        ratio_sd = np.sqrt(v) / np.abs(safe)[:, None]
        out = self._record([])
        for i in range(len(on)):  # a few windows per chunk: a Python loop is cheap here
            w = (t0[i], t1[i], a[i : i + 1], v[i : i + 1])
            if on[i]:
                if self._run is None:
                    self._start(w, after_jump=False)
                elif self._jumped(ratio[i], ratio_sd[i], total[i], sd[i]):
                    out.extend(self._close_run(jump=True))
                    self._start(w, after_jump=True)
                else:
                    self._run_len += 1
                    if self._pending is not None:
                        self._run.add(*self._pending)
                    self._pending = w
                self._last_ratio = (ratio[i], ratio_sd[i], total[i], sd[i])
            elif self._run is not None:
                out.extend(self._close_run(jump=False))
        return self._record(out)

    def _record(self, segs: list[Segment]) -> list[Segment]:
        self.segments.extend(segs)
        return segs

    def _start(self, w, *, after_jump: bool) -> None:
        self._run, self._run_len, self._first, self._pending = _Acc(), 1, w, None
        self._run_after_jump = after_jump

    def _jumped(self, r, r_sd, total, total_sd) -> bool:
        r0, sd0, total0, total_sd0 = self._last_ratio
        diff = np.abs(r - r0)
        if np.any((diff > self.split_sigma * np.hypot(r_sd, sd0)) & (diff > self.split_floor)):
            return True
        dl = abs(total - total0)
        return bool(dl > self.split_sigma * math.hypot(total_sd, total_sd0)
                    and dl > self.level_floor * max(abs(total), abs(total0)))

    def _close_run(self, *, jump: bool = False) -> list[Segment]:
        run, n = self._run, self._run_len
        self._run = None
        if n <= 2 and (jump or self._run_after_jump):
            self.n_transitions += n
            self.n_dropped_runs += 1
            return []  # transition window(s) between two spots, or the partly lit edge of a run
        if n <= 2:  # too short to drop edges: keep what there is
            for w in (self._first, self._pending):
                if w is not None:
                    run.add(*w)
        return [run.segment(self._name())]

    def _feed_schedule(self, t0, t1, a, v) -> list[Segment]:
        out = []
        if len(t0) == 0:
            return out
        eps = 1e-9
        sched = self.schedule
        for j in range(self._sched_next, len(sched)):
            e = sched[j]
            if e.t_start_s > t1[-1]:
                break
            m = (t0 >= e.t_start_s - eps) & (t1 <= e.t_end_s + eps)
            if np.any(m):
                self._sched_acc.setdefault(j, _Acc()).add(t0[m].min(), t1[m].max(), a[m], v[m])
        # entries that can receive no more windows
        t_now = t0[-1] if len(t0) else -math.inf
        while self._sched_next < len(sched) and sched[self._sched_next].t_end_s < t_now + self.window_s:
            j = self._sched_next
            acc = self._sched_acc.pop(j, None)
            if acc is not None:
                out.append(acc.segment(sched[j].emitter))
            else:
                self._no_window(sched[j])
            self._sched_next += 1
        return self._record(out)

    def _no_window(self, e: ScheduleEntry) -> None:
        self.warnings.append(
            f"schedule entry '{e.emitter}' ({e.t_start_s:g}-{e.t_end_s:g} s) holds no whole "
            f"{self.window_s:g} s window: no row for it (shorten --window-s)")

    def finish(self) -> list[Segment]:
        """Segments still open at the end of the recording."""
        out = []
        if self.schedule is not None:
            for j in range(self._sched_next, len(self.schedule)):
                if j in self._sched_acc:
                    out.append(self._sched_acc[j].segment(self.schedule[j].emitter))
                elif self.schedule[j].t_start_s >= 0:
                    self._no_window(self.schedule[j])
            self._sched_acc.clear()
            self._sched_next = len(self.schedule)
        elif self._run is not None:
            out.extend(self._close_run())
        self._record(out)
        if self.schedule is None:
            self._check_count()
        return out

    def _check_count(self) -> None:
        """The self-checks of a segmentation from the signal (see the class docstring)."""
        segs = self.segments
        n = len(segs)
        if self.n_emitters and n % self.n_emitters:
            durs = ", ".join(f"{s.t_end_s - s.t_start_s:.3g}" for s in segs[:12])
            raise InputError(
                f"time multiplexing: found {n} segments, not a multiple of --n-emitters {self.n_emitters} "
                f"(segment lengths {durs}{' ...' if n > 12 else ''} s): two LEDs merged or one split; "
                "refusing to label them (give a --schedule, or check with 'psdcal inspect')",
                field="n_emitters")
        if self.n_dropped_runs > 2 * n + 2:  # a segment has at most two partly lit edges
            self.warnings.append(
                f"time multiplexing: {self.n_dropped_runs} runs of 1-2 windows were discarded as transitions "
                f"against {n} segments kept: the {self.window_s:g} s window may be too long for the LEDs' "
                "on-times (leave --window-s out to choose it from the recording, or see 'psdcal inspect')")
        if n >= 3:
            d = np.array([s.t_end_s - s.t_start_s for s in segs])
            med = float(np.median(d))
            short = np.flatnonzero(d < 0.5 * med - 1e-12)
            if short.size:
                self.warnings.append(
                    f"time multiplexing: {short.size} of {n} segments are shorter than half the median "
                    f"({med:.3g} s): segment(s) {', '.join(segs[i].emitter for i in short[:10])} may be a split "
                    "LED or a transition")
