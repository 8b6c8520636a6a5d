"""Tracking live rows as they come: :func:`psdcal.measure.tracking.track_csv`'s filter and file, row by row.

``locate --track`` on live input writes each tracked row right after its located row, so that a running
system reads filtered positions while it runs, not when the sources end. The filter is
:class:`psdcal.measure.tracking.Tracker` (the file's own, one row at a time); it is fed the values as the
located file holds them (10 significant digits), so the tracked rows are those ``psdcal track`` would write
from the located file, byte for byte, whenever both use the same gap thresholds: always with
``max_gap_s``, and on evenly spaced rows otherwise (the live filter knows only the intervals seen so
far, :class:`~psdcal.measure.tracking.Tracker`). The checks, warnings and the q advice come when the
sources end (they test the whole run), as :func:`~psdcal.measure.tracking.track_csv` gives them.

Memory: a few numbers per row for the checks at the end (about 30 bytes a row), and the first
``_Q_ROWS`` measurements for the q advice.
"""
from __future__ import annotations

import math
from array import array

import numpy as np

from psdcal.errors import InputError
from psdcal.measure.tracking import (
    _KINDS,
    _Q_ROWS,
    STATUSES,
    TrackConfig,
    Tracker,
    _restart_warnings,
    estimate_q_factor,
    nis_checks,
    track_columns,
    track_info,
    track_line,
    track_warnings,
)


def _as_written(x: np.ndarray) -> np.ndarray:
    """The values as the located CSV holds them: ``%.10g`` text read back (NaN stays NaN, written empty)."""
    return np.array([float(f"{v:.10g}") if math.isfinite(v) else math.nan for v in x.tolist()])


class LiveTrackWriter:
    """Write the track of located rows to ``path`` as the rows come (:meth:`add`), the checks at :meth:`close`.

    Parameters
    ----------
    path : str or Path
        The tracked CSV (:func:`psdcal.measure.tracking.track_columns`); written and flushed batch by batch.
    columns : sequence of str
        The located rows' columns: the tracked ones are chosen from them as ``track_csv`` chooses
        (``X_mm,Y_mm,Z_mm``, else ``X_mm,Y_mm``, else ``alpha_x_deg,alpha_y_deg``, with their ``sigma_``).
    q : float, optional
        Process noise (``track_csv``'s default for the unit when None); ``"auto"`` needs the whole run and is
        refused here (track the located file afterwards with ``psdcal track --q auto``).
    gate_p, max_gated, max_gap_s
        See :class:`psdcal.measure.tracking.TrackConfig`.
    """

    def __init__(self, path, columns, *, q: float | None = None, gate_p: float = 0.999, max_gated: int = 5,
                 max_gap_s: float | None = None):
        if isinstance(q, str):
            raise InputError("--track-q auto needs the whole run: with live input give a number, or track the "
                             "located file afterwards (psdcal track FILE --q auto)", field="track_q")
        for cols, sig, unit in _KINDS:
            if all(c in columns for c in cols + sig):
                break
        else:
            raise InputError("no X_mm,Y_mm[,Z_mm] or alpha_x_deg,alpha_y_deg columns with their sigma_ columns to "
                             "track", field="track")
        self.cols, self.sig, self.unit = cols, sig, unit
        q0 = 1e6 if unit == "mm" else 10.0
        self.config = TrackConfig(q=q0 if q is None else float(q), gate_p=gate_p, max_gated=max_gated,
                                  init_sigma_v=2000.0 if unit == "mm" else 100.0, max_gap_s=max_gap_s)
        self.d = len(cols)
        self._filter = Tracker(self.config, self.d)
        self._t, self._nis, self._dist = array("d"), array("d"), array("d")
        self._status = array("b")
        self._em = array("l")
        self._names: dict = {}
        self._first: list = []  # (t, name, z, R) of the first _Q_ROWS rows, for the q advice
        self._n_used = 0
        self.path = path
        self.columns = track_columns(cols)
        self._fh = open(path, "w", encoding="utf-8", newline="")
        self._fh.write(",".join(self.columns) + "\n")
        self._fh.flush()

    def add(self, rows: dict) -> int:
        """Track a batch of located rows (columns as arrays, in time order); write and flush them. Returns the count."""
        t = _as_written(np.asarray(rows["t_s"], dtype=float))
        names = list(rows["emitter"])
        z = np.stack([_as_written(np.asarray(rows[c], dtype=float)) for c in self.cols], -1)
        s = np.stack([_as_written(np.asarray(rows[c], dtype=float)) for c in self.sig], -1)
        d, filt, nan = self.d, self._filter, np.full(self.d, math.nan)
        lines = []
        for i in range(len(t)):
            name = str(names[i])
            R = np.diag(s[i] ** 2)
            ok = bool(np.isfinite(z[i]).all() and np.isfinite(R).all() and math.isfinite(t[i]))
            status, nis, dist, trk = ("invalid", math.nan, math.nan, None)
            if len(self._first) < _Q_ROWS:  # track_csv estimates q on the file's first rows, invalid ones too
                self._first.append((t[i], name, z[i], R))
            if ok:
                status, nis, dist, trk = filt.step(t[i], name, z[i], R)
            if trk is None:
                p = v = sp = sv = nan
            else:
                self._n_used += 1
                var = np.clip(np.diagonal(trk.P), 0, None)
                p, v, sp, sv = trk.x[:d], trk.x[d:], np.sqrt(var[:d]), np.sqrt(var[d:])
            lines.append(track_line(t[i], name, p, v, sp, sv, nis, status))
            self._t.append(t[i])
            self._nis.append(nis)
            self._dist.append(dist)
            self._status.append(STATUSES.index(status))
            self._em.append(self._names.setdefault(name, len(self._names)))
        self._fh.write("".join(lines))
        self._fh.flush()
        return len(lines)

    def close(self) -> dict:
        """Close the file; the checks over the whole run, their warnings and advice (``track_csv``'s summary)."""
        self._fh.close()
        t = np.frombuffer(self._t, dtype=float)
        nis = np.frombuffer(self._nis, dtype=float)
        dist = np.frombuffer(self._dist, dtype=float)
        status = np.array(STATUSES, dtype=object)[np.frombuffer(self._status, dtype=np.int8)]
        em = np.array(list(self._names), dtype=object)[np.frombuffer(self._em, dtype=self._em.typecode)] \
            if self._names else np.array([], dtype=object)
        cfg = self.config
        checks = nis_checks(nis, status, self.d, cfg.gate_p, emitter=em)
        gaps = self._filter.gaps_s()
        warnings = _restart_warnings(t, em, status, dist, gaps, self.unit) + [c.line() for c in checks
                                                                               if c.passed is False]
        q_factor = None
        if any(c.passed is False for c in checks) and self._first:
            ft, fe, fz, fR = zip(*self._first)
            q_factor = estimate_q_factor(np.array(ft), np.array(fe, dtype=object), np.array(fz), np.array(fR), cfg)
        warnings += track_warnings(checks, q_factor, cfg, self.unit, False)
        return track_info(t, status, nis, self._n_used, self.columns, self.d, cfg, q_factor, False, gaps, checks,
                          warnings)
