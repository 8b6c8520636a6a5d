"""From recordings to angles and positions: the ``psdcal locate`` pipeline.

recording chunks (:mod:`psdcal.signal.recording`) -> windowed joint lock-in
(:mod:`psdcal.signal.stream`) -> impact points and angles with uncertainty
(:mod:`psdcal.measure.aoa`) -> positions (:mod:`psdcal.measure.positioning`) -> CSV rows
written as they come.  Memory is bounded by the chunk size, whatever the
length of the recording.

Output columns (one row per window and emitter, or per time-multiplexed
segment)::

    t_s,emitter,x_mm,y_mm,alpha_x_deg,alpha_y_deg[,X_mm,Y_mm],
    sigma_x_mm,sigma_y_mm,sigma_alpha_x_deg,sigma_alpha_y_deg[,sigma_X_mm,sigma_Y_mm]

``x_mm, y_mm`` is the measured impact point (Eq 1-2, after the channel-gain
correction) and its sigma the signal noise alone; the angle and position
sigmas combine the signal noise and the calibration covariance.  With
several sensors::

    t_s,emitter,X_mm,Y_mm,Z_mm,sigma_X_mm,sigma_Y_mm,sigma_Z_mm,n_sensors,chi2,dof,flagged

``chi2`` is the row's ray residual against the stated noise with ``dof``
(``2 n_sensors - 3``) degrees of freedom; ``flagged`` is 1 where it fails its
test at the false-alarm rate 1e-3.  When all the rows of the file together
disagree with the stated noise, every row's sigma includes one extra ray noise
estimated from all of them (:func:`locate_multi_to_csv`).
"""
from __future__ import annotations

import csv
import dataclasses
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from psdcal._atomic import atomic_path
from psdcal.measure.aoa import angles_from_points, impact_from_amplitudes
from psdcal.measure._csvtext import _NpyRows, _rows_text, _write_rows  # noqa: F401  (live.py, tests)
from psdcal.measure.channel_order import SumCheck
from psdcal.errors import InputError, PsdcalError, ZeroSignalError
from psdcal.measure.positioning import plane_position
from psdcal.signal.recording import DEFAULT_CHUNK, Recording
from psdcal.measure.sensor_model import SensorModel
from psdcal.signal.stream import MultiCarrierLockin, TdmSegmenter

_DEG = 180.0 / math.pi


@dataclass(frozen=True)
class LocateConfig:
    """Options of the locate pipeline.

    Attributes
    ----------
    carriers_hz : tuple of float
        One carrier per emitter (frequency multiplexing); one carrier for
        time multiplexing.
    window_s : float or None
        Demodulation window, s: one output per window (default 0.01 s).
        None: 0.01 s, or for time multiplexing a window chosen from the
        on-times measured on the start of the recording
        (:func:`psdcal.signal.inspect.choose_tdm_window`).
    distance_mm : float or None
        Plane distance ``S`` for ``X_mm, Y_mm`` (single sensor).
    emitters : tuple of str or None
        Names of the carriers' emitters (default ``"<f>Hz"``).
    min_snr : float
        A window (or segment) whose total amplitude is below ``min_snr`` times
        its 1-sigma gives no row (emitter off or out of view).
    tdm : bool
        Time multiplexing: one row per segment (found from the signal, or
        from ``schedule``).
    schedule : tuple of ScheduleEntry or None
    n_emitters : int or None
        TDM without schedule: emitters per cycle (segment names repeat).
    chunk_samples : int
        Samples per channel read at once (bounds the memory).
    check_carriers : bool
        Measure the carriers on the start of the recording and warn when an
        asked one is off (:func:`psdcal.signal.inspect.check_carrier`).
    output_format : {"csv", "npy"}
        ``csv``: text rows (10 significant digits); ``npy``: one NumPy
        structured array (a field per column, full float64 precision, the
        emitter names as strings), readable with ``np.load(path)``.
    """

    carriers_hz: tuple
    window_s: float | None = 0.01
    distance_mm: float | None = None
    emitters: tuple | None = None
    min_snr: float = 10.0
    tdm: bool = False
    schedule: tuple | None = None
    n_emitters: int | None = None
    chunk_samples: int = DEFAULT_CHUNK
    check_carriers: bool = True
    output_format: str = "csv"

    def emitter_names(self) -> tuple[str, ...]:
        if self.emitters is None:
            return tuple(f"{f:g}Hz" for f in self.carriers_hz)
        if len(self.emitters) != len(self.carriers_hz):
            raise InputError(
                f"{len(self.emitters)} emitter names for {len(self.carriers_hz)} carriers", field="emitter"
            )
        return tuple(self.emitters)


@dataclass(frozen=True)
class LocateSummary:
    """What a locate run did.

    Attributes
    ----------
    n_samples : int
        Samples per channel read.
    n_windows : int
        Windows demodulated.
    n_rows : int
        Rows written.
    n_skipped : int
        Window/emitter pairs (or segments) without a row (below ``min_snr``).
    duration_s : float
        Signal duration processed.
    columns : tuple of str
    warnings : tuple of str
        What the self-checks found (carrier off its measured frequency, TDM
        segments suspicious, schedule entries without a window).
    window_s : float or None
        The window used (chosen from the recording when not given).
    n_segments : int or None
        Time multiplexing: segments found.
    """

    n_samples: int
    n_windows: int
    n_rows: int
    n_skipped: int
    duration_s: float
    columns: tuple
    warnings: tuple = ()
    window_s: float | None = None
    n_segments: int | None = None
    #: Several sensors: rows whose own chi-squared test failed (the ``flagged`` column).
    n_flagged: int | None = None
    #: Several sensors: the file's pooled chi-squared check (:class:`psdcal._consistency.Check`).
    checks: tuple = ()
    #: Several sensors: the extra ray variance (normalised coordinates^2) added to every row's rays (0: none).
    extra_var_n: float | None = None


def prescan(recording: Recording, config: LocateConfig) -> tuple[float, list[str]]:
    """The demodulation window and the self-check warnings, from the start of a recording.

    Returns ``(window_s, warnings)``: ``config.window_s`` when given, else a
    window chosen from the measured TDM on-times (0.01 s without TDM); a
    warning per asked carrier that is not where it was asked (carrier
    finder of :mod:`psdcal.signal.inspect`).  Only recordings in files
    (kinds npy, csv, hdf5, tdms) are scanned: a live stream is not read twice.
    """
    from psdcal.signal.inspect import (check_carrier, choose_tdm_window, measure_carrier, read_prefix, scan_tdm,
                                      schedule_timing)

    warnings: list[str] = []
    window_s = config.window_s
    # only files can be read twice (a live stream must not lose its first chunk to the scan)
    rereadable = getattr(recording, "kind", None) in ("npy", "csv", "hdf5", "tdms")
    need_scan = rereadable and (config.check_carriers or (config.tdm and (window_s is None or config.schedule)))
    # one chunk's worth (the memory the user allowed), at least 4096 samples
    n_scan = min(max(int(config.chunk_samples), 4096), 1 << 18)
    # (without time multiplexing only the spectrum reads it, at once: the rows as they lie in the file, any
    # layout gives the same spectrum)
    x = read_prefix(recording, n_scan, rows_view=not config.tdm) if need_scan else None
    scan = None
    if config.tdm and x is not None and x.shape[1] >= 64 and (window_s is None or config.schedule):
        scan = scan_tdm(x, recording.rate_hz, config.carriers_hz[0], min_snr=config.min_snr)
    if window_s is None:
        window_s = choose_tdm_window(scan, config.carriers_hz[0]) if scan is not None else 0.01
    if scan is not None and config.schedule:
        msg = schedule_timing(scan, config.schedule, recording.rate_hz, x.shape[1] / recording.rate_hz)
        if msg:
            warnings.append(f"{recording.path}: {msg}")
    if config.check_carriers and x is not None and x.shape[1] >= 64:
        cache: dict = {}  # one spectrum for all the carriers
        for f in config.carriers_hz:
            measured = measure_carrier(x, recording.rate_hz, f, tdm=config.tdm, min_snr=config.min_snr,
                                       spectrum_cache=cache)
            chk = check_carrier(f, measured, window_s, tdm=config.tdm)
            if not chk.ok:
                warnings.append(f"{recording.path}: {chk.message}")
    return window_s, warnings


def single_columns(with_plane: bool) -> tuple[str, ...]:
    """Output columns of a single-sensor run."""
    cols = ["t_s", "emitter", "x_mm", "y_mm", "alpha_x_deg", "alpha_y_deg"]
    if with_plane:
        cols += ["X_mm", "Y_mm"]
    cols += ["sigma_x_mm", "sigma_y_mm", "sigma_alpha_x_deg", "sigma_alpha_y_deg"]
    if with_plane:
        cols += ["sigma_X_mm", "sigma_Y_mm"]
    return tuple(cols)


def _no_nan_sigmas(alpha_deg, sigma_deg, model: SensorModel) -> None:
    """InputError when an angle is finite but its sigma is not (a calibration whose covariance or
    distortion overflows): a NaN sigma is never written as if it were a measurement's."""
    if math.isfinite(sigma_deg.sum()):  # every sigma finite (the usual case): nothing to look for
        return
    bad = np.all(np.isfinite(alpha_deg), axis=-1) & ~np.all(np.isfinite(sigma_deg), axis=-1)
    if np.any(bad):
        raise InputError(f"the calibration gives non-finite sigmas for {int(bad.sum())} finite angle(s) (its "
                         "covariance or distortion overflows): refusing to write them", path=model.source,
                         field="covariance")


def _rows_single(t_s, names, a, var_a, model: SensorModel, distance_mm, min_snr, sums=None, fast: bool = False):
    """Columns for rows (t, emitter) of amplitudes a (n, 4); drops low-SNR rows.

    ``sums``: a :class:`psdcal.measure.channel_order.SumCheck` that the kept rows are added to.
    ``fast``: impact points by the compiled loop (:mod:`psdcal.measure._impact_kernel`, equal to
    :func:`psdcal.measure.aoa.impact_from_amplitudes` to rounding), decided once per run.
    """
    total = a.sum(-1)
    sd = np.sqrt(var_a.sum(-1))
    keep = total > min_snr * sd
    if not math.isfinite(total.sum()):  # (a finite total has four finite amplitudes: no row to look at else)
        keep &= np.all(np.isfinite(a), axis=-1)
    if not keep.all():  # (every row kept: the arrays as given, no copies)
        t_s, names, a, var_a = t_s[keep], names[keep], a[keep], var_a[keep]
    if sums is not None:
        sums.add(a, var_a, compiled=fast)
    if fast:
        from psdcal.measure._impact_kernel import impact_compiled

        d, cov_d, dd_dg, _ = impact_compiled(a, model.gains, var_a, model.lx_mm, model.ly_mm)
    else:
        imp = impact_from_amplitudes(a, model, var_a, on_zero="nan")
        d, cov_d, dd_dg = imp.d_mm, imp.cov_d_mm2, imp.dd_dgains
    res = angles_from_points(d, model, cov_d, dd_dg, derivatives=False)
    res_d = np.sqrt(np.maximum(np.diagonal(cov_d, axis1=-2, axis2=-1), 0.0))  # (np.clip(., 0, None) is this)
    alpha = res.alpha_rad * _DEG
    sa = res.sigma_alpha_rad * _DEG
    _no_nan_sigmas(alpha, sa, model)
    cols = {
        "t_s": t_s,
        "emitter": names,
        "x_mm": d[:, 0],
        "y_mm": d[:, 1],
        "alpha_x_deg": alpha[:, 0],
        "alpha_y_deg": alpha[:, 1],
        "sigma_x_mm": res_d[:, 0],
        "sigma_y_mm": res_d[:, 1],
        "sigma_alpha_x_deg": sa[:, 0],
        "sigma_alpha_y_deg": sa[:, 1],
    }
    if distance_mm is not None:
        pos = plane_position(res, distance_mm)
        cols["X_mm"], cols["Y_mm"] = pos.xy_mm[:, 0], pos.xy_mm[:, 1]
        sp = pos.sigma_xy_mm
        cols["sigma_X_mm"], cols["sigma_Y_mm"] = sp[:, 0], sp[:, 1]
    return cols, int((~keep).sum())


#: Rows computed at once (angles, CSV text), at most: the windows of several chunks are batched
#: (fewer calls), up to ``chunk_samples / BATCH_SAMPLES_PER_ROW`` rows so that the memory stays
#: bounded by the chunk size.
BATCH_ROWS = 2048
BATCH_SAMPLES_PER_ROW = 32


def _demodulated(recording, lockin: MultiCarrierLockin, chunk: int, batch_windows: int = 1):
    """Yield ``(samples read so far, [WindowBlock, ...])`` per chunk of ``recording``.

    A ``.npy`` recording is read as rows straight into one reused buffer
    (``readinto``: no conversion, no transpose; the lock-in keeps copies of
    what it holds for the next chunk) and its samples are checked through the
    lock-in's per-window sums of squares: they are finite only when every
    sample is, so a block is scanned for the bad sample (the error names it)
    only when they are not, or when its tail is left waiting for the next
    window.  (A memory map would save the copy, but the compiled window sums
    read a map's scattered 4 KiB pages slower than the kernel copies them into
    a buffer that stays in the cache: 10.1 against 8.1 ms for 20 s of two
    carriers.)  Its windows' sums are gathered over chunks and turned into
    amplitudes ``batch_windows`` at a time (the per-window arithmetic is a few
    dozen numpy calls whatever their number); the list is empty for a chunk
    whose windows wait.
    """
    n_done = 0
    if not (getattr(recording, "kind", None) == "npy" and isinstance(recording, Recording)):
        for t0, block in recording.chunks(chunk):
            wb = lockin.process(t0, block)
            n_done += block.shape[1]
            yield n_done, [wb]
        return
    cap = max(int(batch_windows), chunk // lockin.n_window + 1)
    acc_c = np.empty((cap, 2 * len(lockin.carriers_hz) + 1, 4))
    acc_x = np.empty((cap, 4))
    fill, j_first = 0, 0
    for t0, rows in recording.chunks(chunk, rows=True, check_finite=False, reuse_buffer=True):
        j0, coef, xx = lockin.fit_rows(t0, rows)
        # (the sums of squares are finite, hence their total, only when every sample is: one call, not two;
        # a total that overflows only asks for the scan)
        if lockin.pending_samples or not math.isfinite(xx.sum()):
            recording.check_block(rows, n_done, rows=True)
        n_done += rows.shape[0]
        out = []
        nw = xx.shape[0]
        if fill and fill + nw > cap:
            out.append(lockin.windows(j_first, acc_c[:fill], acc_x[:fill]))
            fill = 0
        if nw:
            if fill == 0:
                j_first = j0
            acc_c[fill: fill + nw] = coef
            acc_x[fill: fill + nw] = xx
            fill += nw
        if fill >= batch_windows:
            out.append(lockin.windows(j_first, acc_c[:fill], acc_x[:fill]))
            fill = 0
        yield n_done, out
    if fill:
        yield n_done, [lockin.windows(j_first, acc_c[:fill], acc_x[:fill])]


def _stream_single(recording: Recording, config: LocateConfig, out_path, order, make_cols, progress):
    """Shared streaming loop of one recording: chunks -> windows (or TDM segments) -> rows -> CSV.

    ``make_cols(t_s, emitter, a, var_a)`` turns amplitude rows into output
    columns and returns ``(cols, n_skipped)``.
    """
    if config.tdm and len(config.carriers_hz) != 1:
        raise InputError("time multiplexing uses a single carrier", field="carrier_hz")
    names = config.emitter_names()
    window_s, warnings = prescan(recording, config)
    from psdcal.signal.stream import use_compiled_lockin

    lockin = MultiCarrierLockin(recording.rate_hz, config.carriers_hz, window_s,
                                compiled=use_compiled_lockin(int(getattr(recording, "n_samples", 0) or 0)))
    if config.distance_mm is not None and not (config.distance_mm > 0):
        raise InputError(f"--distance-mm must be positive, got {config.distance_mm}", field="distance_mm")
    seg = None
    if config.tdm:
        seg = TdmSegmenter(lockin.window_s, min_snr=config.min_snr, schedule=config.schedule,
                           n_emitters=config.n_emitters)
    chunk = max(1, int(config.chunk_samples) // lockin.n_window) * lockin.n_window
    k = len(names)
    batch_rows = min(BATCH_ROWS, max(1, chunk // BATCH_SAMPLES_PER_ROW))
    names_arr = np.array(names, dtype=str)  # (a text array: the CSV writer codes it without a Python string a row)

    if config.output_format not in ("csv", "npy"):
        raise InputError(f"output format must be 'csv' or 'npy', got {config.output_format!r}", field="format")
    try:
        return _stream_rows(recording, config, out_path, order, make_cols, progress, names, window_s, warnings,
                            lockin, seg, chunk, k, batch_rows, names_arr)
    except PsdcalError as exc:
        # what the pre-scan found (a carrier or a rate off) is usually the cause: said in the same line
        if warnings:
            exc.args = (f"{exc} (the pre-scan found: {'; '.join(warnings)})",) + exc.args[1:]
        raise


def _stream_rows(recording, config, out_path, order, make_cols, progress, names, window_s, warnings, lockin, seg,
                 chunk, k, batch_rows, names_arr):
    """The loop of :func:`_stream_single` (chunks -> rows), after its set-up."""
    n_samples = n_windows = n_rows = n_skipped = 0

    def segment_rows(segments):
        if not segments:
            return None, 0
        t = np.array([s.t_s for s in segments])
        nm = np.array([s.emitter for s in segments], dtype=object)
        a = np.stack([s.amplitude for s in segments])
        v = np.stack([s.var_amplitude for s in segments])
        return make_cols(t, nm, a, v)

    npy = _NpyRows(order) if config.output_format == "npy" else None
    with atomic_path(out_path, suffix="." + config.output_format) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            if npy is None:
                fh.write(",".join(order) + "\n")
                write = _write_rows
            else:  # rows are collected and written as one array below
                def write(_fh, cols, _order):
                    return npy.write(cols)
            # windows not yet turned into rows, batched across chunks in buffers allocated once
            # (the memory does not change from chunk to chunk)
            cap = batch_rows + k * (max(batch_rows // k, chunk // lockin.n_window) + 2)  # a batch and a block
            pend_t, pend_e = np.empty(cap), np.empty(cap, dtype=np.intp)
            pend_a, pend_v = np.empty((cap, 4)), np.empty((cap, 4))
            fill = 0
            emitter_index = np.arange(k)

            def flush():
                nonlocal n_rows, n_skipped, fill
                if fill == 0:
                    return
                cols, skipped = make_cols(pend_t[:fill], names_arr[pend_e[:fill]], pend_a[:fill], pend_v[:fill])
                fill = 0
                n_skipped += skipped
                if cols is not None:
                    n_rows += write(fh, {c: np.array(v, copy=True) for c, v in cols.items()} if npy is not None else cols,
                                    order)  # the npy writer keeps the arrays: no views of the buffers

            for n_samples, blocks in _demodulated(recording, lockin, chunk, max(1, batch_rows // k)):
                for wb in blocks:
                    n_windows += len(wb)
                    if not len(wb):
                        continue
                    if seg is not None:
                        cols, skipped = segment_rows(seg.feed(wb))
                        n_skipped += skipped
                        if cols is not None:
                            n_rows += write(fh, cols, order)
                    else:
                        r = len(wb) * k
                        if fill + r > cap:
                            flush()
                        if r > cap:  # (not expected: a block is at most cap rows) rows at once
                            cols, skipped = make_cols(np.repeat(wb.t_s, k), np.tile(names_arr, len(wb)),
                                                      wb.amplitude.reshape(-1, 4), wb.var_amplitude.reshape(-1, 4))
                            n_skipped += skipped
                            if cols is not None:
                                n_rows += write(fh, cols, order)
                        else:
                            pend_t[fill: fill + r] = np.repeat(wb.t_s, k)
                            pend_e[fill: fill + r] = np.tile(emitter_index, len(wb))
                            pend_a[fill: fill + r] = wb.amplitude.reshape(-1, 4)
                            pend_v[fill: fill + r] = wb.var_amplitude.reshape(-1, 4)
                            fill += r
                            if fill >= batch_rows:
                                flush()
                if progress is not None:
                    progress(n_samples)
            flush()
            if seg is not None:
                cols, skipped = segment_rows(seg.finish())
                n_skipped += skipped
                if cols is not None:
                    n_rows += write(fh, cols, order)
                warnings.extend(seg.warnings)
        if npy is not None and n_rows > 0:
            npy.save(tmp)
        if n_windows == 0:
            raise InputError(
                f"the recording is shorter than one {lockin.window_s:g} s window ({n_samples} samples)",
                path=recording.path,
            )
        if n_rows == 0:
            raise ZeroSignalError(
                f"{recording.path}: no window has a carrier of {list(config.carriers_hz)} Hz above "
                f"--min-snr {config.min_snr:g} (emitter off, wrong carrier, or dead channels)"
            )
    return LocateSummary(n_samples, n_windows, n_rows, n_skipped, n_samples / recording.rate_hz, tuple(order),
                         warnings=tuple(warnings), window_s=lockin.window_s,
                         n_segments=None if seg is None else len(seg.segments))


def locate_to_csv(recording: Recording, model: SensorModel, out_path, config: LocateConfig,
                  progress: Callable[[int], None] | None = None, models: dict | None = None) -> LocateSummary:
    """Demodulate a recording of one sensor and write angles (and positions) to CSV.

    Parameters
    ----------
    recording : Recording
        From :func:`psdcal.signal.recording.open_recording`.
    model : SensorModel
    out_path : str or Path
        Output CSV, written atomically (an existing file is untouched on error).
    config : LocateConfig
    progress : callable, optional
        Called with the number of samples (per channel) read after each chunk.
    models : dict, optional
        ``{emitter name: SensorModel}``: a model per emitter (e.g. channel
        gains per carrier); emitters not in it use ``model``.

    Returns
    -------
    LocateSummary
    """

    # the x and y channel sums agree in the documented channel order (a wrong order or wrong gains show)
    sums = {}

    def sum_check(m):
        if id(m) not in sums:
            sums[id(m)] = SumCheck.for_model(m, str(recording.path))
        return sums[id(m)]

    # the compiled impact points with the compiled lock-in (decided once: every row alike)
    from psdcal.signal.stream import use_compiled_lockin

    fast = use_compiled_lockin(int(getattr(recording, "n_samples", 0) or 0))

    def make_cols(t, nm, a, v):
        if not models:
            return _rows_single(t, nm, a, v, model, config.distance_mm, config.min_snr, sum_check(model), fast)
        parts, skipped = [], 0
        order = np.argsort(t, kind="stable")
        t, nm, a, v = t[order], nm[order], a[order], v[order]
        groups = {}
        for i, name in enumerate(nm):
            groups.setdefault(name, []).append(i)
        for name, idx in groups.items():
            idx = np.array(idx)
            m = models.get(name, model)
            cols, sk = _rows_single(t[idx], nm[idx], a[idx], v[idx], m, config.distance_mm, config.min_snr,
                                    sum_check(m), fast)
            parts.append(cols)
            skipped += sk
        merged = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
        back = np.argsort(merged["t_s"], kind="stable")
        return {c: merged[c][back] for c in merged}, skipped

    summary = _stream_single(recording, config, out_path, single_columns(config.distance_mm is not None), make_cols,
                             progress)
    extra = tuple(w for w in (c.warning() for c in sums.values()) if w)
    return dataclasses.replace(summary, warnings=summary.warnings + extra) if extra else summary


AMPLITUDE_COLUMNS = ("t_s", "emitter", "vx1", "vx2", "vy1", "vy2",
                     "sigma_vx1", "sigma_vx2", "sigma_vy1", "sigma_vy2")


def amplitudes_to_csv(recording: Recording, out_path, config: LocateConfig, *, image_id=None,
                      progress: Callable[[int], None] | None = None) -> LocateSummary:
    """Demodulate a recording and write the carrier amplitudes (no calibration needed).

    Without ``image_id`` the columns are :data:`AMPLITUDE_COLUMNS` (one row
    per window and emitter, or per time-multiplexed segment).  With
    ``image_id`` the output is a calibration points CSV from raw amplitudes
    (docs/model.md#calibration-json): ``image_id,point_id,vx1,vx2,vy1,vy2``, ``point_id`` the
    emitter (segment or schedule name): one view of the calibration template.

    Rows whose total amplitude is below ``config.min_snr`` sigma are dropped.

    Returns
    -------
    LocateSummary
    """

    def make_cols(t, nm, a, v):
        keep = (a.sum(-1) > config.min_snr * np.sqrt(v.sum(-1))) & np.all(np.isfinite(a), axis=-1)
        sd = np.sqrt(v[keep])
        cols = {"t_s": t[keep], "emitter": nm[keep], "point_id": nm[keep],
                "image_id": np.full(int(keep.sum()), str(image_id))}
        for c, name in enumerate(("vx1", "vx2", "vy1", "vy2")):
            cols[name] = a[keep, c]
            cols["sigma_" + name] = sd[:, c]
        return cols, int((~keep).sum())

    order = AMPLITUDE_COLUMNS if image_id is None else ("image_id", "point_id", "vx1", "vx2", "vy1", "vy2")
    return _stream_single(recording, config, out_path, order, make_cols, progress)


# --------------------------------------------------------------------------- impact points -> angles
#: Columns ``aoa`` computes: on an input (e.g. a ``locate`` output) they are replaced, never duplicated.
AOA_COMPUTED = ("x_mm", "y_mm", "alpha_x_deg", "alpha_y_deg", "X_mm", "Y_mm", "sigma_alpha_x_deg",
                "sigma_alpha_y_deg", "sigma_X_mm", "sigma_Y_mm", "sigma_x_mm", "sigma_y_mm")
#: Rows of an ``aoa`` input converted at once (bounds memory on large files).
AOA_CHUNK_ROWS = 65536


def aoa_csv(points_path, model: SensorModel, out_path, *, distance_mm: float | None = None,
            sigma_d_mm: float = 0.0, chunk_rows: int = AOA_CHUNK_ROWS) -> int:
    """Convert a points CSV to angles (``psdcal aoa``), streaming ``chunk_rows`` rows at a time.

    The input has ``x_mm,y_mm`` (measured impact points) or
    ``vx1,vx2,vy1,vy2`` (amplitudes; the sensor's gains are applied); other
    columns (``image_id``, ``point_id``, ``t_s``, ``emitter``...) are copied to
    the output, then ``x_mm,y_mm,alpha_x_deg,alpha_y_deg[,X_mm,Y_mm]`` and the
    sigma columns (columns the input already had among those are replaced).
    The input's own uncertainties are used: ``sigma_x_mm,sigma_y_mm`` (a
    ``locate`` output) or ``sigma_vx1..sigma_vy2`` (an ``amplitudes`` output),
    added to ``sigma_d_mm``. A point off the sensor's active area is an error
    naming the line; a sigma that cannot be computed is written empty.

    Parameters
    ----------
    points_path, out_path : str or Path
    model : SensorModel
    distance_mm : float, optional
    sigma_d_mm : float
        1-sigma noise of the impact points (isotropic), mm, added to the input's.

    Returns
    -------
    int, the number of rows written.
    """
    from psdcal.io import check_regular_file

    path = check_regular_file(points_path, "points file")
    if not (math.isfinite(sigma_d_mm) and sigma_d_mm >= 0):
        raise InputError(f"sigma_d_mm must be a non-negative number, got {sigma_d_mm}", field="sigma_d_mm")
    try:
        fh = open(path, newline="", encoding="utf-8-sig")
    except OSError as exc:
        raise InputError(f"cannot read the points file: {exc.strerror or exc}", path=path) from None
    n = 0
    with fh:
        from psdcal.io import csv_rows_checked

        it = csv_rows_checked(csv.reader(fh), path, line_numbers=True)
        first = next(it, None)
        if first is None:
            raise InputError("empty file", path=path)
        header = [h.strip() for h in first[1]]
        if len(set(header)) != len(header):
            dup = sorted({h for h in header if header.count(h) > 1})
            raise InputError(f"repeated column(s) {dup}", path=path, line=1)
        amp_cols = ("vx1", "vx2", "vy1", "vy2")
        if all(c in header for c in ("x_mm", "y_mm")):
            use = ("x_mm", "y_mm")
        elif all(c in header for c in amp_cols):
            use = amp_cols
        else:
            raise InputError("the header must name x_mm,y_mm or vx1,vx2,vy1,vy2", path=path, line=1)
        sig_cols = ("sigma_x_mm", "sigma_y_mm") if use == ("x_mm", "y_mm") else tuple(f"sigma_{c}" for c in amp_cols)
        if not all(c in header for c in sig_cols):
            sig_cols = ()
        idx = [header.index(c) for c in use]
        sidx = [header.index(c) for c in sig_cols]
        keep_cols = [c for c in header if c not in (*AOA_COMPUTED, *amp_cols, *sig_cols)]
        keep_idx = [header.index(c) for c in keep_cols]
        order = [*keep_cols, "x_mm", "y_mm", "alpha_x_deg", "alpha_y_deg"]
        if distance_mm is not None:
            order += ["X_mm", "Y_mm"]
        order += ["sigma_alpha_x_deg", "sigma_alpha_y_deg"]
        if distance_mm is not None:
            order += ["sigma_X_mm", "sigma_Y_mm"]
        with atomic_path(out_path, suffix=".csv") as tmp:
            with open(tmp, "w", encoding="utf-8", newline="") as out:
                out.write(",".join(order) + "\n")
                while True:
                    chunk = []
                    for item in it:
                        if item[1] and any(c.strip() for c in item[1]):
                            chunk.append(item)
                            if len(chunk) >= chunk_rows:
                                break
                    if not chunk:
                        break
                    n += _aoa_chunk(chunk, out, path, header, use, idx, sig_cols, sidx, keep_cols, keep_idx, order,
                                    model, distance_mm, sigma_d_mm)
                    if len(chunk) < chunk_rows:
                        break
    return n


def _aoa_chunk(chunk, out, path, header, use, idx, sig_cols, sidx, keep_cols, keep_idx, order, model, distance_mm,
               sigma_d_mm) -> int:
    """Convert and write one block of ``aoa`` rows; returns the number written."""
    m = len(chunk)
    vals = np.empty((m, len(use)))
    sig = np.zeros((m, len(sig_cols)))
    extra = []
    body = []
    for k, (lineno, row) in enumerate(chunk):
        if len(row) != len(header):
            raise InputError(f"expected {len(header)} fields, found {len(row)}", path=path, line=lineno)
        for j, (c, i) in enumerate(zip(use, idx)):
            try:
                v = float(row[i])
            except ValueError:
                raise InputError(f"not a number: {row[i][:40]!r}", path=path, line=lineno, field=c) from None
            if not math.isfinite(v):
                raise InputError("not a finite number", path=path, line=lineno, field=c)
            vals[k, j] = v
        for j, (c, i) in enumerate(zip(sig_cols, sidx)):
            try:
                v = float(row[i]) if row[i].strip() else 0.0
            except ValueError:
                raise InputError(f"not a number: {row[i][:40]!r}", path=path, line=lineno, field=c) from None
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"a sigma must be a non-negative number, got {row[i]!r}", path=path, line=lineno,
                                 field=c)
            sig[k, j] = v
        body.append(lineno)
        extra.append([row[i] for i in keep_idx])
    if use == ("x_mm", "y_mm"):
        d, dd_dg = vals, None
        var = sig ** 2 if sig_cols else np.zeros((m, 2))
        cov_d = np.zeros((m, 2, 2))
        cov_d[:, 0, 0] = var[:, 0] + sigma_d_mm ** 2
        cov_d[:, 1, 1] = var[:, 1] + sigma_d_mm ** 2
    else:
        try:
            imp = impact_from_amplitudes(vals, model, sig ** 2 if sig_cols else None)
        except ZeroSignalError:
            bad = np.flatnonzero(~((vals / model.gains).sum(-1) > 0))
            line = body[int(bad[0])] if bad.size else None
            raise InputError("the sum of the four amplitudes is not positive", path=path, line=line) from None
        d, dd_dg = imp.d_mm, imp.dd_dgains
        cov_d = sigma_d_mm ** 2 * np.eye(2) + (imp.cov_d_mm2 if getattr(imp, "cov_d_mm2", None) is not None
                                                else np.zeros((m, 2, 2)))
    off = (np.abs(d[:, 0]) > model.lx_mm / 2 * (1 + 1e-9)) | (np.abs(d[:, 1]) > model.ly_mm / 2 * (1 + 1e-9))
    if off.any():
        k = int(np.flatnonzero(off)[0])
        raise InputError(f"point ({d[k, 0]:.4g}, {d[k, 1]:.4g}) mm is off the {model.lx_mm:g} x {model.ly_mm:g} mm "
                         "sensor: no light reaches it there", path=path, line=body[k], field=use[0])
    res = angles_from_points(d, model, cov_d, dd_dg, derivatives=False)
    alpha = res.alpha_rad * _DEG
    sa = res.sigma_alpha_rad * _DEG
    _no_nan_sigmas(alpha, sa, model)
    cols = {c: np.array([e[j] for e in extra], dtype=object) for j, c in enumerate(keep_cols)}
    cols.update({"x_mm": d[:, 0], "y_mm": d[:, 1], "alpha_x_deg": alpha[:, 0], "alpha_y_deg": alpha[:, 1]})
    if distance_mm is not None:
        pos = plane_position(res, distance_mm)
        cols["X_mm"], cols["Y_mm"] = pos.xy_mm[:, 0], pos.xy_mm[:, 1]
        cols["sigma_X_mm"], cols["sigma_Y_mm"] = pos.sigma_xy_mm[:, 0], pos.sigma_xy_mm[:, 1]
    cols["sigma_alpha_x_deg"], cols["sigma_alpha_y_deg"] = sa[:, 0], sa[:, 1]
    lists = []
    for c in order:
        a = cols[c]
        if isinstance(a, np.ndarray) and a.dtype.kind == "f":
            lists.append(["%.10g" % v if math.isfinite(v) else "" for v in a.tolist()])
        else:
            lists.append([str(v) for v in np.asarray(a).tolist()])
    out.write("\n".join(",".join(r) for r in zip(*lists)) + "\n")
    return m


# the several-sensor path lives in its own module; its names stay importable from here
from psdcal.measure.locate_multi import EXTRA_GRID, MULTI_COLUMNS, locate_multi_to_csv  # noqa: F401
