"""The dashboard's state: the files it follows, what they hold, and what changed since the last look.

One :class:`Hub` per server. :meth:`Hub.poll` is called on a timer (every
``--poll-ms``); it stats each followed file once, reads only what was added,
and returns the new records as one update, which the server sends to every
page. Nothing here depends on how many pages watch, and nothing is written.

Live: the rows files are followed as they grow (``tail -F``). Replay: the
rows files are read whole at the start and released by their ``t_s`` at
``speed`` times real time, so a finished recording plays like a live room.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

from psdcal._consistency import ALPHA
from psdcal.report.dashboard.data import (RowParser, SensorChi2, event_record, read_emitters, read_plan,
                                          read_sensors)
from psdcal.report.dashboard.follow import FileFollower

KINDS = ("positions", "tracks", "sensor", "warnings")
#: Warnings kept for a new page (the oldest go first).
MAX_WARNINGS = 2000


@dataclass
class Options:
    """What to follow and how (the command's options).

    Attributes
    ----------
    rows : tuple of Path
        ``locate --sensors`` rows and/or track CSVs (kind found from the header).
    sensor_rows : tuple of (str, Path)
        One sensor's angles or amplitudes rows, by sensor name.
    sensors, emitters, plan : Path or None
        Sensors file (poses), surveyed emitters CSV, ``psdcal plan --csv`` map.
    events : tuple of Path
        ``psdcal --events`` logs.
    replay : bool
        Play finished rows files by their ``t_s`` instead of following them.
    speed : float
        Replay speed (1: real time).
    history_s : float
        Rows kept (by ``t_s``) behind the latest for scrubbing back.
    title : str
    """

    rows: tuple = ()
    sensor_rows: tuple = ()
    sensors: Path | None = None
    emitters: Path | None = None
    plan: Path | None = None
    events: tuple = ()
    replay: bool = False
    speed: float = 1.0
    history_s: float = 300.0
    title: str = "psdcal dashboard"
    trail_s: float = 10.0


@dataclass
class _Source:
    follower: FileFollower
    parser: RowParser | None  # None: an events log
    name: str


@dataclass
class _Watched:
    path: Path
    mtime: float = -1.0
    size: int = -1


class Hub:
    """Follows the files of :class:`Options` and keeps the last ``history_s`` of rows."""

    def __init__(self, opts: Options, *, clock=time.monotonic):
        self.opts = opts
        self.clock = clock
        self.history = {k: [] for k in KINDS}
        self.tmax = -math.inf
        self.chi2 = SensorChi2()
        self._restarted = False
        self.room = {"title": opts.title, "sensors": [], "emitters": [], "plan": None,
                     "mode": "replay" if opts.replay else "live", "speed": opts.speed,
                     "history_s": opts.history_s if math.isfinite(opts.history_s) else None,
                     "trail_s": opts.trail_s, "alpha": ALPHA,
                     "files": [str(p) for p in opts.rows] + [f"{n}={p}" for n, p in opts.sensor_rows]}
        self._room_files = {k: _Watched(Path(p)) for k, p in
                            (("sensors", opts.sensors), ("emitters", opts.emitters), ("plan", opts.plan)) if p}
        self._room_dirty = False
        self._load_room(initial=True)
        self.sources = [_Source(FileFollower(p), RowParser("rows", source=Path(p).name), Path(p).name)
                        for p in opts.rows]
        self.sources += [_Source(FileFollower(p), RowParser("sensor", sensor=n, source=Path(p).name), Path(p).name)
                         for n, p in opts.sensor_rows]
        self.events = [_Source(FileFollower(p), None, Path(p).name) for p in opts.events]
        self._queue = None
        if opts.replay:
            self._queue = self._read_all()
            self._t0_data = min((r[0] for k in ("positions", "tracks", "sensor") for r in self._queue[k]),
                                default=0.0)
            self._t0_clock = clock()
            self._next = {k: 0 for k in KINDS}

    # -- room ---------------------------------------------------------------------------------------------------------
    def _load_room(self, initial=False) -> bool:
        changed = False
        for key, w in self._room_files.items():
            try:
                st = os.stat(w.path)
            except OSError:
                if initial:
                    raise
                continue
            if (st.st_mtime, st.st_size) == (w.mtime, w.size):
                continue
            try:
                val = {"sensors": read_sensors, "emitters": read_emitters, "plan": read_plan}[key](w.path)
            except Exception:
                if initial:
                    raise
                continue  # a file being rewritten: keep the last good one, look again next time
            w.mtime, w.size = st.st_mtime, st.st_size
            self.room[key] = val
            changed = True
            if key == "sensors":
                self._load_room_poses()
        return changed

    def _load_room_poses(self) -> None:
        import numpy as np

        self.chi2.poses = {s["name"]: (np.array(s["R"]), np.array(s["t"])) for s in self.room["sensors"]}

    # -- rows ---------------------------------------------------------------------------------------------------------
    def _read_sources(self) -> dict:
        out = {k: [] for k in KINDS}
        for src in self.sources + self.events:
            chunk = src.follower.poll()
            if chunk.reset and src.parser is not None:
                src.parser.reset()
                self._restarted = True  # a new run writes this file: its t_s start again
            if not chunk.lines:
                continue
            if src.parser is None:
                out["warnings"] += [w for w in (event_record(line, src.name) for line in chunk.lines) if w]
                continue
            recs = src.parser.feed(chunk.lines)
            resolved = self.chi2.add_positions(recs["positions"])
            self.chi2.add_sensor(recs["sensor"])
            recs["warnings"] += self.chi2.warnings(resolved + recs["sensor"], src.name)
            recs["sensor"] += resolved
            for k in KINDS:
                out[k] += recs[k]
        return out

    def _read_all(self) -> dict:
        """Replay: everything the rows files hold now, sorted by time."""
        out = {k: [] for k in KINDS}
        events, self.events = self.events, []
        while True:
            got = self._read_sources()
            if not any(got[k] for k in KINDS):
                break
            for k in KINDS:
                out[k] += got[k]
        self.events = events
        for k in ("positions", "tracks", "sensor"):
            out[k].sort(key=lambda r: r[0])
        out["warnings"].sort(key=lambda r: -math.inf if r[0] is None else r[0])
        return out

    def _release(self) -> dict:
        """Replay: the queued records whose time has come."""
        now = self._t0_data + (self.clock() - self._t0_clock) * self.opts.speed
        out = {k: [] for k in KINDS}
        for k in KINDS:
            q, i = self._queue[k], self._next[k]
            j = i
            while j < len(q) and (q[j][0] is None or q[j][0] <= now):
                j += 1
            out[k] = q[i:j]
            self._next[k] = j
        return out

    def replay_done(self) -> bool:
        return self._queue is not None and all(self._next[k] >= len(self._queue[k]) for k in KINDS)

    def poll(self) -> dict | None:
        """New records since the last call as an update message (a dict), or None when nothing changed."""
        room_changed = self._load_room()
        if self._queue is not None:
            new = self._release()
            ev = {k: [] for k in KINDS}
            for src in self.events:  # the event logs are followed live in a replay too
                chunk = src.follower.poll()
                ev["warnings"] += [w for w in (event_record(line, src.name) for line in chunk.lines) if w]
            new["warnings"] += ev["warnings"]
        else:
            self._restarted = False
            new = self._read_sources()
            if self._restarted:  # start the rows over (the warnings stay); the pages get a fresh snapshot
                for k in ("positions", "tracks", "sensor"):
                    self.history[k] = []
                self.tmax = -math.inf
                self.chi2 = SensorChi2()
                self._load_room_poses()
                self._append(new)
                return self.snapshot()
        if not room_changed and not any(new[k] for k in KINDS):
            return None
        now_unix = time.time()
        for w in new["warnings"]:
            if w[1] is None:
                w[1] = now_unix
        self._append(new)
        msg = {"type": "update", **new}
        if room_changed:
            msg["room"] = self.room
        return msg

    def _append(self, new: dict) -> None:
        for k in ("positions", "tracks", "sensor"):
            if new[k]:
                self.history[k] += new[k]
                self.tmax = max(self.tmax, max(r[0] for r in new[k]))
        self.history["warnings"] += new["warnings"]
        lo = self.tmax - self.opts.history_s
        for k in ("positions", "tracks", "sensor"):
            h = self.history[k]
            if h and h[0][0] < lo:
                cut = next((i for i, r in enumerate(h) if r[0] >= lo), len(h))
                del h[:cut]
        if len(self.history["warnings"]) > MAX_WARNINGS:
            del self.history["warnings"][:-MAX_WARNINGS]

    def snapshot(self) -> dict:
        """Everything a new page needs: the room and the rows kept."""
        return {"type": "snapshot", "room": self.room, **{k: list(v) for k, v in self.history.items()}}

    def drain(self) -> dict:
        """Static export: every row now (a replay is released at once), as a snapshot."""
        if self._queue is not None:
            rest = {k: self._queue[k][self._next[k]:] for k in KINDS}
            for k in KINDS:
                self._next[k] = len(self._queue[k])
            self._append(rest)
            self.poll()  # the event logs
        else:
            while self.poll() is not None:
                pass
        return self.snapshot()


__all__ = ["Hub", "Options"]
