"""Several live sources at once, stamped on arrival; a session file to record them and play them back.

Live sources (:func:`open_source`): those of :func:`psdcal.signal.live.open_stream`
(``-`` stdin, ``tcp://127.0.0.1:PORT``, ``nidaqmx://DEVICE/ai0:3``) and
``file:PATH``, raw frames read from a file or a named pipe (FIFO) as they come
(the same frames as the other sources: ``vx1, vx2, vy1, vy2`` interleaved,
``--raw-dtype``, ``--raw-scale``).

:class:`LiveSources` reads every source in its own thread (the standard
library's :mod:`threading` and :mod:`queue`, nothing else) and gives the
blocks in the order they arrived: ``(source index, block (4, m) float64,
arrival s)``, the arrival from :func:`time.perf_counter` taken when the bytes
were read.  :func:`replay_events` gives the events of a session file in the
same form, released at their recorded arrival times divided by ``speed``, so
that a replay goes through the same code as the live session.

Session file (``psdcal record``, ``locate --replay``), little-endian::

    line 1   JSON header + b"\\n": {"format": "psdcal-session", "version": 1,
             "sources": [{"name", "source", "rate_hz", "dtype", "scale"}, ...],
             "started_unix_s": ...}
    then     records, in arrival order:
             uint16 source index, uint32 m (frames), float64 arrival_s (since the
             session start), then m frames of 4 float64 (vx1, vx2, vy1, vy2,
             already scaled); m = 0xFFFFFFFF (no frames) marks the end of that
             source's stream (so that a source that died mid-way dies again in the replay)

Every record is written as it arrives (flushed at least every 0.1 s), so a
session cut short keeps what came before; a truncated last record is dropped
with a warning.
"""
from __future__ import annotations

import json
import math
import queue
import struct
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psdcal.errors import InputError
from psdcal.signal.live import DTYPES, RawStream, is_stream_source, open_stream

FORMAT = "psdcal-session"
VERSION = 1
_REC = struct.Struct("<HId")
_END = 0xFFFFFFFF


def is_live_source(name: str) -> bool:
    """Whether ``name`` names a live source (one of :func:`open_stream`'s, or ``file:PATH``)."""
    return is_stream_source(str(name)) or str(name).startswith("file:")


def open_source(source: str, rate_hz: float | None, *, dtype: str = "float64", scale: float = 1.0,
                timeout_s: float = 10.0) -> RawStream:
    """Open one live source (see the module docstring); ``file:PATH`` reads raw frames from a file or a FIFO."""
    source = str(source)
    if not source.startswith("file:"):
        return open_stream(source, rate_hz, dtype=dtype, scale=scale, timeout_s=timeout_s)
    path = source[len("file:"):]
    # the checks of open_stream (rate, sample type, scale) on a source it accepts
    probe = open_stream("-", rate_hz, dtype=dtype, scale=scale, stdin=_Empty())
    try:
        fh = open(path, "rb", buffering=0)
    except OSError as exc:
        raise InputError(f"cannot read the source: {exc.strerror or exc}", path=path) from None
    return RawStream(source, probe.rate_hz, dtype, probe.scale, _reader=fh.read, _close=fh.close)


class _Empty:
    def read(self, _n):
        return b""


@dataclass(frozen=True)
class SourceInfo:
    """One source of a session: its name (the sensor's), where it came from, its rate and raw sample type."""

    name: str
    source: str
    rate_hz: float
    dtype: str = "float64"
    scale: float = 1.0


class SourceEnded:
    """Marks the end of a source's stream in the events (``block`` of an event)."""


ENDED = SourceEnded()


class LiveSources:
    """Read several :class:`RawStream` at once, one thread each; iterate over ``(index, block, arrival_s)``.

    ``block`` is float64 ``(4, m)``, or :data:`ENDED` once when the source's
    stream has ended.  An error in a source (a lost connection, a non-finite
    sample) is raised by the iteration as :class:`InputError` naming the source.
    """

    def __init__(self, streams):
        self.streams = list(streams)
        self._q: queue.Queue = queue.Queue()
        self._threads = [threading.Thread(target=self._read, args=(i, s), daemon=True)
                         for i, s in enumerate(self.streams)]
        self._started = False

    def _read(self, i, stream):
        try:
            for _t0, block in stream.chunks():
                self._q.put((i, block, stream.arrivals[-1][1]))
            self._q.put((i, ENDED, time.perf_counter()))
        except InputError as exc:
            self._q.put((i, exc, time.perf_counter()))
        except OSError as exc:
            self._q.put((i, InputError(f"the source failed: {exc.strerror or exc}", path=stream.path),
                         time.perf_counter()))
        except Exception as exc:  # noqa: BLE001 - reported in the main thread, one line
            self._q.put((i, InputError(f"the source failed: {exc}", path=stream.path), time.perf_counter()))

    def events(self, stall_s: float = 10.0, coalesce: bool = True) -> Iterator[tuple[int, object, object]]:
        """The blocks in arrival order; :class:`InputError` when nothing at all comes for ``stall_s`` seconds.

        With ``coalesce``, the blocks already waiting when the consumer asks
        are joined per source (the consumer catches up in fewer, larger steps
        when it falls behind); the arrival is then a ``(k, 2)`` array of each
        joined block's end (frames from the start of the joined block) and
        arrival time, so that every window keeps the arrival of its own last
        sample.
        """
        if not self._started:
            for t in self._threads:
                t.start()
            self._started = True
        open_ = len(self.streams)
        while open_:
            try:
                items = [self._q.get(timeout=stall_s)]
            except queue.Empty:
                raise InputError(f"no data from any source for {stall_s:g} s") from None
            if coalesce:
                while True:
                    try:
                        items.append(self._q.get_nowait())
                    except queue.Empty:
                        break
            for i, block, at in _joined(items) if coalesce else items:
                if isinstance(block, InputError):
                    raise block
                if block is ENDED:
                    open_ -= 1
                yield i, block, at


def parts(block: np.ndarray, at) -> list:
    """``[(sub-block, arrival s), ...]``: a joined event (:meth:`LiveSources.events`) split back into its blocks."""
    if np.ndim(at) == 0:
        return [(block, float(at))]
    starts = np.concatenate([[0], at[:-1, 0]]).astype(int)
    return [(block[:, a:int(b)], float(t)) for a, (b, t) in zip(starts, at)]


def _joined(items):
    """Consecutive data blocks of each source joined, in the order of their first arrival; ends and errors after."""
    parts: dict = {}
    tail = []
    for i, block, at in items:
        if isinstance(block, np.ndarray) and not any(t[0] == i for t in tail):
            parts.setdefault(i, []).append((block, at))
        else:
            tail.append((i, block, at))
    out = []
    for i, lst in parts.items():
        if len(lst) == 1:
            out.append((i, lst[0][0], lst[0][1]))
            continue
        ends = np.cumsum([b.shape[1] for b, _ in lst])
        stamps = np.column_stack([ends, [at for _, at in lst]]).astype(float)
        out.append((i, np.concatenate([b for b, _ in lst], axis=1), stamps))
    return out + tail


# --------------------------------------------------------------------------- session files
class SessionWriter:
    """Write a session file as the blocks come (:meth:`write`), flushed at least every 0.1 s."""

    def __init__(self, path, sources: list[SourceInfo]):
        self.path = Path(path)
        try:
            self._fh = open(self.path, "wb")
        except OSError as exc:
            raise InputError(f"cannot write the session: {exc.strerror or exc}", path=path) from None
        self._t0 = None
        self._last_flush = 0.0
        self.n_records = 0
        self.n_frames = [0] * len(sources)
        head = {"format": FORMAT, "version": VERSION, "started_unix_s": time.time(),
                "sources": [{"name": s.name, "source": s.source, "rate_hz": s.rate_hz, "dtype": s.dtype,
                             "scale": s.scale} for s in sources]}
        self._fh.write(json.dumps(head).encode() + b"\n")
        self._fh.flush()

    def start(self, t0_perf_s: float) -> None:
        """Arrival times are written relative to ``t0_perf_s`` (a :func:`time.perf_counter` value)."""
        self._t0 = t0_perf_s

    def write(self, index: int, block: np.ndarray, arrival_perf_s: float) -> None:
        if self._t0 is None:
            self._t0 = arrival_perf_s
        m = int(block.shape[1])
        self._fh.write(_REC.pack(index, m, arrival_perf_s - self._t0))
        self._fh.write(np.ascontiguousarray(block.T, dtype="<f8").tobytes())
        self.n_records += 1
        self.n_frames[index] += m
        if arrival_perf_s - self._last_flush > 0.1:
            self._fh.flush()
            self._last_flush = arrival_perf_s

    def end(self, index: int, arrival_perf_s: float) -> None:
        """The end of source ``index``'s stream."""
        if self._t0 is None:
            self._t0 = arrival_perf_s
        self._fh.write(_REC.pack(index, _END, arrival_perf_s - self._t0))
        self._fh.flush()

    def close(self) -> None:
        self._fh.close()


def read_session_header(path) -> tuple[list[SourceInfo], int]:
    """The sources of a session file and the byte offset of its first record."""
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise InputError(f"cannot read the session: {exc.strerror or exc}", path=path) from None
    with fh:
        line = fh.readline(1 << 20)
    try:
        head = json.loads(line)
        ok = head.get("format") == FORMAT
    except (ValueError, AttributeError):
        ok = False
    if not ok:
        raise InputError("not a psdcal session file (see `psdcal record --help`)", path=path, line=1)
    if head.get("version") != VERSION:
        raise InputError(f"session format version {head.get('version')!r}, this psdcal reads {VERSION}", path=path,
                         line=1, field="version")
    try:
        sources = [SourceInfo(str(s["name"]), str(s["source"]), float(s["rate_hz"]), str(s.get("dtype", "float64")),
                              float(s.get("scale", 1.0))) for s in head["sources"]]
    except (KeyError, TypeError, ValueError):
        raise InputError("the header's 'sources' must each have name, source and rate_hz", path=path, line=1,
                         field="sources") from None
    if not sources:
        raise InputError("the session has no sources", path=path, line=1, field="sources")
    for s in sources:
        if not (s.rate_hz > 0 and math.isfinite(s.rate_hz)):
            raise InputError(f"source {s.name}: rate_hz must be a positive number", path=path, line=1,
                             field="rate_hz")
    return sources, len(line)


def replay_events(path, speed: float = 1.0, *, chunk_records: int = 256) -> Iterator[tuple[int, object, float]]:
    """The events of a session file, as :meth:`LiveSources.events` gives them live.

    Each record is released when ``(its arrival_s) / speed`` has passed since
    the replay started (``speed`` 0 or infinite: as fast as they can be read);
    the event's arrival stamp is the time it was released.  Every source ends
    with :data:`ENDED`.
    """
    sources, offset = read_session_header(path)
    n_src = len(sources)
    fast = not speed or math.isinf(speed)
    if not fast and not speed > 0:
        raise InputError(f"--speed must be positive (0: as fast as possible), got {speed}", field="speed")
    with open(path, "rb") as fh:
        fh.seek(offset)
        start = time.perf_counter()
        n = 0
        ended: set = set()
        while True:
            head = fh.read(_REC.size)
            if not head:
                break
            if len(head) < _REC.size:
                _warn_truncated(path)
                break
            i, m, at = _REC.unpack(head)
            if i >= n_src:
                raise InputError(f"record {n + 1}: source index {i} but the header lists {n_src} sources", path=path)
            if m == _END:
                if i not in ended:
                    ended.add(i)
                    yield i, ENDED, time.perf_counter()
                continue
            data = fh.read(m * 32)
            if len(data) < m * 32:
                _warn_truncated(path)
                break
            block = np.frombuffer(data, dtype="<f8").reshape(m, 4).T.copy()
            n += 1
            if not fast:
                wait = start + at / speed - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            yield i, block, time.perf_counter()
    now = time.perf_counter()
    for i in range(n_src):
        if i not in ended:
            yield i, ENDED, now


def _warn_truncated(path) -> None:
    print(f"psdcal: warning: {path}: the session ends inside a record (cut short): the rest is dropped",
          file=sys.stderr)


def check_dtype(dtype: str) -> None:
    if dtype not in DTYPES:
        raise InputError(f"unknown sample type {dtype!r}; use one of {sorted(DTYPES)}", field="raw_dtype")


def estimate_offsets(events, n_sources: int, rate_hz: float, learn_s: float = 0.5):
    """Each source's start relative to the first source's, from the arrival times of its first blocks.

    Sample ``n - 1`` of a source exists before the block ending with it arrives,
    so its first sample was taken at or before ``arrival - (n - 1) / rate_hz``;
    the smallest such bound over the blocks of the first ``learn_s`` seconds of
    signal (the block that came fastest) estimates the start.  The offsets are
    the differences of those starts from the first source's.  It holds for
    sources that deliver as they sample (a DAQ, a sender at the real rate),
    with equal transport delays; the error is the spread of the fastest
    deliveries (about a millisecond on a loaded machine, tests/test_live_multi.py),
    not a sample.

    Returns
    -------
    (offsets_s (n_sources,) ndarray, events)
        ``events``: the same events, the ones read for the estimate first.
    """
    import itertools

    it = iter(events)
    buf = []
    recv = [0] * n_sources
    best = np.full(n_sources, np.inf)
    ended = [False] * n_sources
    need = learn_s * rate_hz
    for ev in it:
        buf.append(ev)
        i, block, at = ev
        if block is ENDED:
            ended[i] = True
        else:
            for b, t in parts(block, at):
                recv[i] += b.shape[1]
                if b.shape[1]:
                    best[i] = min(best[i], t - (recv[i] - 1) / rate_hz)
        if all(r >= need or e for r, e in zip(recv, ended)):
            break
    if not np.all(np.isfinite(best)):
        raise InputError("cannot estimate the offsets: a source sent no data", field="offset_s")
    return best - best[0], itertools.chain(buf, it)
