"""``locate --sensors`` on several live sources (or a replayed session): 3D rows written as windows complete.

The same demodulation (:class:`psdcal.signal.stream.MultiCarrierLockin`, one per
sensor) and triangulation (:func:`psdcal.measure.positioning.ray_inputs`,
:func:`psdcal.measure.positioning.triangulate`) as
:func:`psdcal.measure.locate.locate_multi_to_csv`, so the rows are those of the
file path on the same samples.  Each sensor's blocks are demodulated as they
arrive; a window is triangulated as soon as every sensor has completed it, and
its row is written and flushed at once.

Time alignment: every source is a sample clock at the same rate (``rate_hz``);
sensor ``i``'s first sample was taken ``offsets_s[i]`` seconds after the
reference's (0 for a sensor without an offset).  The streams are aligned by
dropping, at the start of each, the whole samples taken before the latest
start ``T = max(offsets)``; rows are stamped ``T + `` the window centre (the
reference's clock).  Rounding to whole samples leaves at most half a sample of
misalignment.  No offset is estimated from the data (see
docs/guide/positioning.md#several-sensors-live).

Latency: for every window, from the arrival (``time.perf_counter`` when its
bytes were read) of the last block that completes it, over all sensors, to its
row written and flushed.
"""
from __future__ import annotations

import inspect
import sys
import time
from dataclasses import dataclass

import numpy as np

from psdcal.errors import InputError, ZeroSignalError
from psdcal.measure.aoa import angles_from_amplitudes
from psdcal.measure.locate import MULTI_COLUMNS, LocateConfig, _write_rows
from psdcal.measure.positioning import ray_inputs, triangulate
from psdcal.signal.session import ENDED, parts
from psdcal.signal.stream import MultiCarrierLockin

#: Whether :func:`triangulate` checks and inflates per call (then turned off: rows as the file path's).
_TRI_INFLATES = "inflate" in inspect.signature(triangulate).parameters


@dataclass(frozen=True)
class MultiLiveSummary:
    """What a several-sensor live run did.

    Attributes
    ----------
    n_samples : int
        Samples per sensor demodulated (after alignment).
    n_windows, n_rows, n_skipped : int
    latency_s : (n_windows,) ndarray
        Per window: from the arrival of the last block completing it to its row flushed, s.
    window_t_s : (n_windows,) ndarray
        The windows' centre times, s (the rows' ``t_s``).
    first_row_s : float
        From the first block's arrival to the first rows flushed, s (the start-up as a user sees it).
    startup_s : float
        Signal time counted as start-up in :meth:`latency_text`.
    """

    n_samples: int
    n_windows: int
    n_rows: int
    n_skipped: int
    latency_s: np.ndarray
    window_t_s: np.ndarray
    first_row_s: float
    startup_s: float
    t_start_s: float = 0.0
    #: Per window: the :func:`time.perf_counter` value when its row was flushed, s.
    written_s: np.ndarray = None
    #: Samples received from each source (before alignment).
    samples_per_source: tuple = ()

    def latency_ms(self, with_startup: bool = True) -> tuple[float, float, int]:
        """``(median, p99, n)`` of the per-window latency in ms, with or without the first ``startup_s`` of signal."""
        lat = self.latency_s
        if not with_startup:
            lat = lat[self.window_t_s - self.t_start_s >= self.startup_s]
        if not len(lat):
            return float("nan"), float("nan"), 0
        ms = lat * 1e3
        return float(np.median(ms)), float(np.percentile(ms, 99)), len(ms)

    def latency_text(self) -> str:
        if not len(self.latency_s):
            return "no windows"
        m, p, _ = self.latency_ms(True)
        m2, p2, n2 = self.latency_ms(False)
        after = (f"; after the first {self.startup_s:g} s: {m2:.3g} ms median, {p2:.3g} ms p99" if n2 else "")
        return (f"latency per window (arrival to row) {m:.3g} ms median, {p:.3g} ms p99, "
                f"{self.latency_s.max() * 1e3:.3g} ms max{after}; first rows {self.first_row_s * 1e3:.4g} ms after "
                "the first data")


def window_columns(amps, vars_, t_s, sensors, names_arr, min_snr: float, R, t_mm, *, names_rows=None):
    """Triangulated columns of ``nw`` windows seen by every sensor (the rows of ``locate --sensors``).

    Parameters
    ----------
    amps, vars_ : sequence (one per sensor) of (nw, n_carriers, 4) ndarrays
        Demodulated amplitudes and their variances (:class:`WindowBlock`).
    t_s : (nw,) ndarray
    sensors : sequence of SensorPose
    names_arr : (n_carriers,) object ndarray
    min_snr : float
    R, t_mm : (k, 3, 3), (k, 3)
    names_rows : (nw,) object ndarray, optional
        TDM: each row's emitter (one carrier), instead of ``names_arr`` repeated.

    Returns
    -------
    (dict of columns, number of window-emitters seen by fewer than two sensors)
    """
    k = len(names_arr)
    nw = len(t_s)
    results, seens = [], []
    for a, v, sp in zip(amps, vars_, sensors):
        a = a.reshape(-1, 4)
        v = v.reshape(-1, 4)
        seen = (a.sum(-1) > min_snr * np.sqrt(v.sum(-1))) & np.all(np.isfinite(a), -1)
        a_safe = np.where(seen[:, None], a, 1.0)
        results.append(angles_from_amplitudes(a_safe, sp.model, v, on_zero="nan"))
        seens.append(seen)
    ns, covs, kw = ray_inputs(results, sensors, seens)
    if _TRI_INFLATES:  # rows as the file path writes them: no per-call inflation (the file's rule is not live)
        kw["inflate"] = False
    tri = triangulate(ns, covs, R, t_mm, **kw)
    scr = None
    if "left_out" in MULTI_COLUMNS:  # a disagreeing sensor left out, as the file path (psdcal.measure.reflections)
        from psdcal.measure.reflections import screen_rays

        scr = screen_rays(ns, covs, R, t_mm, tri, **kw)
        tri = scr.tri
    ok = tri.n_sensors >= 2
    sig = tri.sigma_p_mm
    cols = {
        "t_s": np.repeat(t_s, k)[ok],
        "emitter": (np.tile(names_arr, nw) if names_rows is None else np.asarray(names_rows, dtype=object))[ok],
        "X_mm": tri.p_w_mm[ok, 0],
        "Y_mm": tri.p_w_mm[ok, 1],
        "Z_mm": tri.p_w_mm[ok, 2],
        "sigma_X_mm": sig[ok, 0],
        "sigma_Y_mm": sig[ok, 1],
        "sigma_Z_mm": sig[ok, 2],
        "n_sensors": tri.n_sensors[ok],
        "chi2": tri.chi2[ok],
    }
    if "dof" in MULTI_COLUMNS or "flagged" in MULTI_COLUMNS:  # the per-row test, where the file path has it
        from psdcal._stats import chi2_isf

        dof = 2 * cols["n_sensors"].astype(int) - 3
        cols["dof"] = dof
        thr = {d: chi2_isf(1e-3, float(d)) for d in np.unique(dof) if d > 0}
        cols["flagged"] = np.array([int(d > 0 and c > thr[d]) for d, c in zip(dof, cols["chi2"])], dtype=int)
    if scr is not None:
        from psdcal.measure.reflections import left_out_names

        cols["left_out"] = left_out_names(scr, [sp.name for sp in sensors])[ok]
        cols["reflection"] = scr.flag[ok]
    return cols, int((~ok).sum())


class _Pending:
    """One sensor's demodulated windows (or TDM segments) waiting for the other sensors'."""

    def __init__(self):
        self.parts: list = []
        self.count = 0

    def add(self, amplitude, var_amplitude, t_s, arrival_s, names=None) -> None:
        n = len(t_s)
        if n:
            nm = np.full(n, None, dtype=object) if names is None else np.asarray(names, dtype=object)
            self.parts.append((amplitude, var_amplitude, np.asarray(t_s, dtype=float),
                               np.broadcast_to(arrival_s, (n,)).astype(float), nm))
            self.count += n

    def take(self, n: int):
        cols = [np.concatenate([p[j] for p in self.parts]) for j in range(5)]
        self.parts = [tuple(c[n:] for c in cols)] if n < len(cols[2]) else []
        self.count -= n
        return tuple(c[:n] for c in cols)


def _segments(segs):
    """TDM segments -> (amplitude (n, 1, 4), variance, t_s, emitter names)."""
    return (np.stack([g.amplitude for g in segs])[:, None, :], np.stack([g.var_amplitude for g in segs])[:, None, :],
            np.array([g.t_s for g in segs]), np.array([g.emitter for g in segs], dtype=object))


def locate_live_multi(events, sensors, rate_hz: float, out_path, config: LocateConfig, *, offsets_s=None,
                      max_lag_s: float = 1.0, startup_s: float = 1.0, recorder=None,
                      check_rate: bool = True, on_rows=None) -> MultiLiveSummary:
    """Triangulate several live streams; write rows (``MULTI_COLUMNS``) as the windows complete.

    Parameters
    ----------
    events : iterable of (int, ndarray or ENDED, float or ndarray)
        ``(sensor index, block (4, m), arrival s)`` in arrival order (or, for
        blocks joined by :meth:`LiveSources.events`, a ``(k, 2)`` array of the
        parts' ends and arrivals)
        (:meth:`psdcal.signal.session.LiveSources.events` or
        :func:`psdcal.signal.session.replay_events`).
    sensors : sequence of SensorPose
        One per source, in the sources' order.
    rate_hz : float
        The common sampling rate.
    out_path : str or Path
        Output CSV, written progressively and flushed after every batch of rows (``-``: stdout).
    config : LocateConfig
        ``carriers_hz``, ``window_s`` (default 0.01), ``emitters``, ``min_snr``; ``tdm`` is refused
        (as with files).
    offsets_s : sequence of float, optional
        Each sensor's start after the reference's, s (module docstring).
    max_lag_s : float
        A source this much signal behind another is an error when it ended (while the others go on) or
        delivers under 0.9 ``rate_hz`` (stalled, or another rate): :func:`_check_lag`.
    startup_s : float
        Signal time counted as start-up in the latency figures.
    recorder : SessionWriter, optional
        Every event is also written to this session file (as received, before alignment).
    check_rate : bool
        Whether a lagging live source that delivers under 0.9 ``rate_hz`` is an error (off for a replay,
        whose timing is the recording's).
    on_rows : callable, optional
        Called with every batch of rows (a dict of ``MULTI_COLUMNS`` arrays) right after it is written, e.g.
        :meth:`psdcal.measure.track_live.LiveTrackWriter.add`.

    Returns
    -------
    MultiLiveSummary

    Raises
    ------
    InputError
        Time multiplexing, fewer than two sensors, a source that fails, lags or ends early.
    ZeroSignalError
        No window seen by two sensors.
    """
    n_s = len(sensors)
    if n_s < 2:
        raise InputError("give at least two sensors", field="sensors")
    if config.tdm and config.schedule is None:
        raise InputError("time multiplexing with several sensors needs --schedule (the emitters' on-times, the "
                         "same for every sensor)", field="schedule")
    if config.tdm and len(config.carriers_hz) != 1:
        raise InputError("time multiplexing uses a single carrier", field="carrier_hz")
    if config.output_format != "csv":
        raise InputError("--format npy is not available with --sensors (several sensors): write CSV", field="format")
    offsets = np.zeros(n_s) if offsets_s is None else np.asarray(offsets_s, dtype=float)
    t_start = float(offsets.max())
    skip = [int(round((t_start - d) * rate_hz)) for d in offsets]
    window_s = 0.01 if config.window_s is None else config.window_s
    names_arr = np.array(config.emitter_names(), dtype=object)
    lockins = [MultiCarrierLockin(rate_hz, config.carriers_hz, window_s) for _ in sensors]
    R = np.stack([s.R for s in sensors])
    t_mm = np.stack([np.asarray(s.tvec_mm, dtype=float) for s in sensors])
    pend = [_Pending() for _ in sensors]
    segmenters = None
    if config.tdm:
        from psdcal.signal.stream import TdmSegmenter

        # one row per schedule entry; schedule times are on the first sensor's clock (t_start = 0 without offsets)
        segmenters = [TdmSegmenter(lk.window_s, min_snr=config.min_snr, schedule=config.schedule) for lk in lockins]
    fed = [0] * n_s
    done = [0] * n_s  # samples given to the demodulation
    hold = [[] for _ in sensors]
    marks = [np.zeros((0, 2)) for _ in sensors]
    recv = [0] * n_s
    ended = [False] * n_s
    lag_n = max_lag_s * rate_hz
    lat, wt, wrote = [], [], []
    n_windows = n_rows = n_skipped = 0
    first_arrival = first_row = None
    _warm_up(rate_hz, config, window_s, sensors, names_arr, R, t_mm)
    fh = sys.stdout if str(out_path) == "-" else open(out_path, "w", encoding="utf-8", newline="")
    try:
        fh.write(",".join(MULTI_COLUMNS) + "\n")
        fh.flush()
        for i, block, at in events:
            # at: the arrival, s, or (k, 2) [frames from the block's start to the end of each joined part, arrival]
            stamps = np.array([[block.shape[1] if block is not ENDED else 0, at]]) if np.ndim(at) == 0 else at
            if first_arrival is None:
                first_arrival = float(stamps[0, 1])
            last_at = float(stamps[-1, 1])
            if block is ENDED:
                if recorder is not None:
                    recorder.end(i, last_at)
                ended[i] = True
                if segmenters is not None:
                    segs = segmenters[i].finish()
                    if segs:
                        amp, var, t_seg, nm = _segments(segs)
                        pend[i].add(amp, var, t_seg, last_at, nm)
            else:
                if recorder is not None:
                    for b, t_at in parts(block, at):
                        recorder.write(i, b, t_at)
                m = block.shape[1]
                recv[i] += m
                drop = 0
                if skip[i]:
                    drop = min(skip[i], m)
                    skip[i] -= drop
                    block = block[:, drop:]
                    m -= drop
                if m:
                    # held until a window completes (one demodulation call per window, not per block);
                    # marks: (end of each part in samples since the aligned start, its arrival)
                    hold[i].append(block)
                    ends = fed[i] + np.maximum(stamps[:, 0] - drop, 0)
                    marks[i] = np.concatenate([marks[i], np.column_stack([ends, stamps[:, 1]])])
                    fed[i] += m
                    n_win = lockins[i].n_window
                    if fed[i] - done[i] + lockins[i].pending_samples >= n_win:
                        x = hold[i][0] if len(hold[i]) == 1 else np.concatenate(hold[i], axis=1)
                        wb = lockins[i].process(t_start + done[i] / rate_hz, x)
                        done[i] = fed[i]
                        hold[i] = []
                        # each window: the arrival of the part holding its last sample
                        last = (wb.index + 1) * n_win - 1
                        k = np.minimum(np.searchsorted(marks[i][:, 0], last, side="right"), len(marks[i]) - 1)
                        if segmenters is None:
                            pend[i].add(wb.amplitude, wb.var_amplitude, wb.t_s, marks[i][k, 1])
                        else:  # TDM: a segment is complete when a window past its schedule entry arrives
                            segs = segmenters[i].feed(wb)
                            if segs:
                                pend[i].add(*_segments(segs)[:3], marks[i][k[-1], 1], _segments(segs)[3])
                        marks[i] = marks[i][marks[i][:, 0] > fed[i] - lockins[i].pending_samples]
            ready = min(p.count for p in pend)
            if ready:
                taken = [p.take(ready) for p in pend]
                if segmenters is not None:
                    _check_segments(taken, sensors)
                cols, skipped = window_columns([x[0] for x in taken], [x[1] for x in taken], taken[0][2], sensors,
                                               names_arr, config.min_snr, R, t_mm,
                                               names_rows=None if segmenters is None else taken[0][4])
                n_rows += _write_rows(fh, cols, MULTI_COLUMNS)
                fh.flush()
                now = time.perf_counter()
                if first_row is None:
                    first_row = now
                n_skipped += skipped
                n_windows += ready
                lat.append(now - np.max([x[3] for x in taken], axis=0))
                wrote.append(np.full(ready, now))
                wt.append(taken[0][2])
                if on_rows is not None:  # after the latency's time stamp: the rows are out
                    on_rows(cols)
            _check_lag(fed, recv, ended, lag_n, rate_hz, sensors, last_at - first_arrival if check_rate else 0.0)
    finally:
        if fh is not sys.stdout:
            fh.close()
    if n_windows == 0:
        raise InputError("the sources ended before one window was complete", field="window_s")
    if n_rows == 0:
        raise ZeroSignalError(f"no window has a carrier of {list(config.carriers_hz)} Hz seen by two sensors above "
                              f"--min-snr {config.min_snr:g}")
    cat = lambda a: np.concatenate(a) if a else np.zeros(0)
    return MultiLiveSummary(min(fed), n_windows, n_rows, n_skipped, cat(lat), cat(wt),
                            (first_row or 0.0) - (first_arrival or 0.0), startup_s, t_start, cat(wrote),
                            tuple(recv))


def warm_up(sensors, rate_hz: float, config: LocateConfig) -> None:
    """Demodulate and triangulate one window of a made-up signal (call it before connecting to the sources).

    The first call of the numerical kernels loads (or compiles) them: done
    before the data flow, that start-up is not added to the first rows' latency
    (:func:`locate_live_multi` calls it too; a second call is quick).
    """
    window_s = 0.01 if config.window_s is None else config.window_s
    R = np.stack([s.R for s in sensors])
    t_mm = np.stack([np.asarray(s.tvec_mm, dtype=float) for s in sensors])
    _warm_up(rate_hz, config, window_s, sensors, np.array(config.emitter_names(), dtype=object), R, t_mm)


def _check_segments(taken, sensors) -> None:
    """The sensors' TDM segments pair up (same schedule entries, in order)."""
    for x, sp in zip(taken[1:], sensors[1:]):
        if not (np.array_equal(x[4], taken[0][4]) and np.allclose(x[2], taken[0][2], atol=1e-9)):
            raise InputError(f"the TDM segments of sensor {sp.name} do not pair with the first sensor's (same "
                             "--schedule, aligned streams expected)", field="schedule")


def _warm_up(rate_hz, config, window_s, sensors, names_arr, R, t_mm) -> None:
    lk = MultiCarrierLockin(rate_hz, config.carriers_hz, window_s)
    n = lk.n_window
    tt = np.arange(n) / rate_hz
    x = np.stack([1.0 + 0.01 * c + sum(np.sin(2 * np.pi * f * tt) for f in config.carriers_hz) for c in range(4)])
    wb = lk.process(0.0, x)
    window_columns([wb.amplitude] * len(sensors), [wb.var_amplitude + 1e-6] * len(sensors), wb.t_s, sensors,
                   names_arr, config.min_snr, R, t_mm)


def _check_lag(fed, recv, ended, lag_n, rate_hz, sensors, elapsed_s) -> None:
    """One line when a source falls ``lag_n`` samples behind another.

    A source that ended is then an error at once (the others went on).  A live
    one is an error when it also delivers less than 0.9 ``rate_hz`` on average
    since the first data (after 2 s): stalled, or sampled at another rate.  A
    source read faster than real time (a file) may lag without harm: only its
    demodulated windows wait, a few bytes each.
    """
    lead = max(fed)
    for i, n in enumerate(fed):
        if lead - n <= lag_n:
            continue
        name = getattr(sensors[i], "name", f"#{i + 1}")
        if ended[i]:
            raise InputError(f"source of sensor {name} ended after {n / rate_hz:.6g} s of signal while the "
                             f"others went on ({lead / rate_hz:.6g} s)", field="sources")
        if elapsed_s >= 2.0 and recv[i] < 0.9 * rate_hz * elapsed_s:
            raise InputError(f"source of sensor {name} is {(lead - n) / rate_hz:.3g} s of signal behind the others "
                             f"and delivers {recv[i] / elapsed_s:.6g} samples/s: it stalled, or it is not sampled "
                             f"at --rate-hz {rate_hz:g}", field="sources")
