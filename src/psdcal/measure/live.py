"""``locate`` on a live stream: rows written (and flushed) as windows complete.

The same demodulation and angle computation as :func:`psdcal.measure.locate.locate_to_csv`
(the same rows, to the last digit, for the same samples), but the output is
written progressively instead of atomically at the end, and the latency of
every window (from the arrival of the data that complete it to its row being
flushed) is measured.
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass

import numpy as np

from psdcal.measure.channel_order import SumCheck
from psdcal.measure.locate import LocateConfig, _rows_single, _write_rows, single_columns
from psdcal.signal.stream import MultiCarrierLockin, TdmSegmenter


#: Bytes a read of a live stream asks for (a backlog is read in pieces this size, which stay in the cache).
LIVE_READ_BYTES = 1 << 22
#: Windows gathered from a backlog's pieces before they are turned into rows.
BATCH_WINDOWS = 1024


@dataclass(frozen=True)
class LiveSummary:
    """What a live run did.

    Attributes
    ----------
    n_samples, n_windows, n_rows, n_skipped : int
    latency_s : (n_windows,) ndarray
        Per window: time from the arrival of its last sample to its row written and flushed, s.
    warnings : tuple of str
        What the self-checks found (the x and y channel sums disagree: channel order or gains,
        :mod:`psdcal.measure.channel_order`); each was also printed on stderr when found.
    """

    n_samples: int
    n_windows: int
    n_rows: int
    n_skipped: int
    latency_s: np.ndarray
    warnings: tuple = ()

    def latency_text(self) -> str:
        if not len(self.latency_s):
            return "no windows"
        ms = self.latency_s * 1e3
        return (f"latency per window {np.median(ms):.3g} ms median, {np.percentile(ms, 99):.3g} ms p99, "
                f"{ms.max():.3g} ms max")


def locate_stream(stream, model, out_path, config: LocateConfig, *, on_rows=None) -> LiveSummary:
    """Demodulate a live ``stream`` (:class:`psdcal.signal.live.RawStream`) of one sensor; write rows as they come.

    Parameters
    ----------
    stream : RawStream
    model : SensorModel
    out_path : str or Path
        Output CSV (written progressively, flushed after every block; ``-``: stdout).
    config : LocateConfig
    on_rows : callable, optional
        Called with every batch of rows (a dict of the output's column arrays) right after it is written,
        e.g. :meth:`psdcal.measure.track_live.LiveTrackWriter.add`.

    Returns
    -------
    LiveSummary
    """
    from psdcal.errors import InputError

    if config.tdm and len(config.carriers_hz) != 1:
        raise InputError("time multiplexing uses a single carrier", field="carrier_hz")
    names = np.array(config.emitter_names(), dtype=str)  # (a text array: see locate)
    lockin = MultiCarrierLockin(stream.rate_hz, config.carriers_hz, config.window_s)
    seg = None
    if config.tdm:
        seg = TdmSegmenter(lockin.window_s, min_snr=config.min_snr, schedule=config.schedule,
                           n_emitters=config.n_emitters)
    order = single_columns(config.distance_mm is not None)
    k = len(names)

    sums = SumCheck.for_model(model, str(stream.path))
    warned: list[str] = []

    from psdcal.signal.stream import use_compiled_lockin

    fast = use_compiled_lockin()  # the compiled impact points with the compiled lock-in, decided once

    def make_cols(t, nm, a, v):
        return _rows_single(t, nm, a, v, model, config.distance_mm, config.min_snr, sums, fast)

    def check_sums():
        # said as soon as the data show it (a live run may go on for hours), once
        if not warned:
            w = sums.warning()
            if w:
                warned.append(w)
                print(f"psdcal: warning: {w}", file=sys.stderr, flush=True)

    def seg_cols(segments):
        if not segments:
            return None, 0
        t = np.array([s.t_s for s in segments])
        nm = np.array([s.emitter for s in segments], dtype=object)
        return make_cols(t, nm, np.stack([s.amplitude for s in segments]),
                         np.stack([s.var_amplitude for s in segments]))

    fh = sys.stdout if str(out_path) == "-" else open(out_path, "w", encoding="utf-8", newline="")
    lat = []
    n_samples = n_windows = n_rows = n_skipped = 0
    try:
        fh.write(",".join(order) + "\n")
        fh.flush()
        # rows read into one reused buffer, as large as what has arrived (a backlog in large blocks), checked
        # through the lock-in's sums (below); a stream without that reader: (4, m) blocks, checked on arrival
        as_rows = hasattr(stream, "check_rows")
        # a backlog (a read that filled the buffer: more data waiting) is read in cache-sized pieces and its
        # windows' sums are gathered (up to BATCH_WINDOWS) before they become rows: the copy out of the
        # pipe stays in the cache and the per-block work is paid once per batch; data arriving in real
        # time (a read that did not fill the buffer) is turned into rows at once, as before
        acc: list = []  # (j0, coef, xx, arrival time) of the windows gathered
        n_acc = 0

        def emit(wb, arrivals):
            nonlocal n_windows, n_rows, n_skipped
            n_windows += len(wb)
            if seg is not None:
                cols, skipped = seg_cols(seg.feed(wb))
            else:
                cols, skipped = make_cols(np.repeat(wb.t_s, k), np.tile(names, len(wb)),
                                          wb.amplitude.reshape(-1, 4), wb.var_amplitude.reshape(-1, 4))
            n_skipped += skipped
            if cols is not None:
                n_rows += _write_rows(fh, cols, order)
            fh.flush()
            now = time.perf_counter()
            for nw, arrived in arrivals:
                lat.extend([now - arrived] * nw)
            if cols is not None and on_rows is not None:  # after the latency's time stamp: the rows are out
                on_rows(cols)
            check_sums()

        def flush_acc():
            nonlocal n_acc
            if not acc:
                return
            if len(acc) == 1:
                j0, coef, xx, _ = acc[0]
            else:
                j0 = acc[0][0]
                coef = np.concatenate([a[1] for a in acc])
                xx = np.concatenate([a[2] for a in acc])
            arrivals = [(a[2].shape[0], a[3]) for a in acc]
            acc.clear()
            n_acc = 0
            emit(lockin.windows(j0, coef, xx), arrivals)

        chunks = (stream.chunks(rows=True, check_finite=False, read_bytes=LIVE_READ_BYTES) if as_rows
                  else stream.chunks())
        for t0, block in chunks:
            arrived = stream.arrivals[-1][1] if stream.arrivals else time.perf_counter()
            if as_rows:
                first, m = n_samples, block.shape[0]
                n_samples += m
                j0, coef, xx = lockin.fit_rows(t0, block)
                # the windows' sums are finite only when every sample is; the tail held for the next window
                # is checked now (an error names the sample before any row of this block is written)
                try:
                    if not math.isfinite(xx.sum()):  # (see locate._demodulated)
                        stream.check_rows(block, first)
                    tail = min(lockin.pending_samples, m)
                    if tail:
                        stream.check_rows(block[m - tail:], first + m - tail)
                except InputError:
                    flush_acc()  # the rows of the blocks before the bad sample are written, as they came
                    raise
                if xx.shape[0]:
                    # (the sums are the kernel's own arrays or copies: not views of the read buffer)
                    acc.append((j0, coef, xx, arrived))
                    n_acc += xx.shape[0]
                if n_acc >= BATCH_WINDOWS or not getattr(stream, "backlog", False):
                    flush_acc()
                continue
            n_samples += block.shape[1]
            wb = lockin.process(t0, block)
            if not len(wb):
                continue
            emit(wb, [(len(wb), arrived)])
        flush_acc()
        if seg is not None:
            cols, skipped = seg_cols(seg.finish())
            n_skipped += skipped
            if cols is not None:
                n_rows += _write_rows(fh, cols, order)
            fh.flush()
            if cols is not None and on_rows is not None:
                on_rows(cols)
    finally:
        if fh is not sys.stdout:
            fh.close()
    check_sums()
    return LiveSummary(n_samples, n_windows, n_rows, n_skipped, np.array(lat), tuple(warned))
