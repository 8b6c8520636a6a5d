"""Live four-channel input: raw interleaved samples from stdin or a localhost TCP socket, or a NI DAQ.

A raw stream is a sequence of frames, one per sample time, each holding the
four channels ``vx1, vx2, vy1, vy2`` in that order (or in the order given as
``order``, :func:`parse_order`; no frame carries names, so a stream wired in
another order is only caught by the x/y sums check of
:mod:`psdcal.measure.channel_order`), little-endian, as
``float32``, ``float64`` or ``int16`` (multiplied by ``scale``, e.g. volts per
count).  No header: the sampling rate is given.  A stream source behaves like
:class:`psdcal.signal.recording.Recording` for the demodulation: its
:meth:`RawStream.chunks` yields ``(t0_s, block)`` with ``block`` float64
``(4, m)`` as soon as whole frames arrive (``m`` varies), so windows complete
while the data come in.

Sources (``open_stream``):

``-``
    standard input (binary).
``tcp://127.0.0.1:PORT`` (or ``tcp://localhost:PORT``, ``tcp://[::1]:PORT``)
    connects to a local server that sends the frames; other hosts are refused
    (this is not a network service).
``nidaqmx://DEVICE/ai0:3``
    a National Instruments DAQ (optional extra ``psdcal[daq]``: the
    ``nidaqmx`` package and NI's driver): four analog inputs read continuously.
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np

from psdcal.errors import InputError

#: The order of the channels in a frame unless told otherwise (``--raw-order``).
DOCUMENTED_ORDER = ("vx1", "vx2", "vy1", "vy2")
#: Accepted sample types of a raw stream.
DTYPES = {"float32": "<f4", "float64": "<f8", "int16": "<i2"}
_LOCAL = ("127.0.0.1", "localhost", "::1", "[::1]")


def parse_order(spec: str | None, *, field: str = "raw_order") -> tuple[int, ...] | None:
    """Frame order ``"vx1,vy1,vx2,vy2"`` -> indices ``p`` with ``documented = frame[p]``.

    None for None or for the documented order itself.

    Raises
    ------
    InputError
        Not the four names ``vx1, vx2, vy1, vy2``, each once.
    """
    if spec is None:
        return None
    names = [s.strip().lower() for s in str(spec).split(",")]
    if sorted(names) != sorted(DOCUMENTED_ORDER):
        raise InputError(f"the channel order must name vx1, vx2, vy1, vy2 once each (the frame's channels in "
                         f"their order), got {spec!r}", field=field)
    perm = tuple(names.index(n) for n in DOCUMENTED_ORDER)
    return None if perm == (0, 1, 2, 3) else perm


def is_stream_source(name: str) -> bool:
    """Whether ``name`` names a live source rather than a file."""
    return name == "-" or name.startswith("tcp://") or name.startswith("nidaqmx://")


@dataclass
class RawStream:
    """A live stream of four-channel frames.

    Attributes
    ----------
    path : str
        The source as given.
    rate_hz : float
    dtype : str
        ``"float32"``, ``"float64"`` or ``"int16"``.
    scale : float
        Factor applied to every sample.
    n_samples : None
        Unknown in advance.
    arrivals : list of (samples_received, perf_counter_s)
        When each block of frames arrived (for the latency measurement).
    order : tuple of int or None
        Frame positions of ``vx1, vx2, vy1, vy2`` (:func:`parse_order`); None: the documented order.
    """

    path: str
    rate_hz: float
    dtype: str = "float64"
    scale: float = 1.0
    read_bytes: int = 1 << 14
    _reader: object = field(default=None, repr=False)
    _close: object = field(default=None, repr=False)
    n_samples: None = None
    t0_s: float = 0.0
    arrivals: list = field(default_factory=list, repr=False)
    order: tuple | None = None
    #: ``readinto``-like reader (``readinto1`` of a file, ``recv_into`` of a socket), or None
    _readinto: object = field(default=None, repr=False)
    #: ``rows`` blocks: whether the last block filled the read buffer (a backlog: more may be waiting)
    backlog: bool = field(default=False, repr=False)

    def chunks(self, chunk_samples: int = 0, *, rows: bool = False, check_finite: bool = True,
               read_bytes: int | None = None) -> Iterator[tuple[float, np.ndarray]]:
        """Yield ``(t0_s, block)`` as frames arrive (``chunk_samples`` is ignored: blocks are what came).

        ``rows``: yield ``(m, 4)`` float64 blocks (one frame a row, the documented channel order)
        read into one buffer reused from block to block (a block is valid until the next one is
        asked for), as large as what has arrived, up to :data:`ROWS_READ_BYTES` (a backlog is
        taken in large blocks; frames arriving in real time are yielded as they come, as without
        it).  ``check_finite=False`` (with ``rows``) leaves the finiteness check to the caller
        (:meth:`check_rows`, same message).  ``read_bytes`` (with ``rows``): the most a read asks
        for instead of :data:`ROWS_READ_BYTES` (a smaller buffer stays in the processor's cache; the
        caller then gathers the blocks of a backlog itself: :attr:`backlog` says whether the last
        block filled the buffer, i.e. more data may be waiting).
        """
        if rows:
            yield from self._rows(check_finite, read_bytes)
            return
        dt = np.dtype(DTYPES[self.dtype])
        frame = 4 * dt.itemsize
        buf = b""
        n = 0
        try:
            while True:
                data = self._reader(self.read_bytes)
                if not data:
                    break
                now = time.perf_counter()
                buf += data
                m = len(buf) // frame
                if m == 0:
                    continue
                raw = np.frombuffer(buf[: m * frame], dtype=dt).reshape(m, 4)
                buf = buf[m * frame :]
                block = raw.T.astype(np.float64) if self.order is None else raw.T[list(self.order)].astype(np.float64)
                if self.scale != 1.0:
                    block *= self.scale
                if not np.all(np.isfinite(block)):
                    ch, i = np.argwhere(~np.isfinite(block))[0]
                    raise InputError(f"sample {n + int(i)} of channel {ch + 1} is not a finite number", path=self.path)
                self.arrivals.append((n + m, now))
                yield self.t0_s + n / self.rate_hz, block
                n += m
        finally:
            if self._close is not None:
                self._close()
        if buf:
            print(f"psdcal: warning: {self.path}: the stream ended inside a frame ({len(buf)} bytes dropped)",
                  file=sys.stderr)


    def check_rows(self, rows: np.ndarray, first_sample: int) -> None:
        """Raise :class:`InputError` naming the first non-finite sample of ``rows`` (m, 4), if any: the
        message of :meth:`chunks`' own check (``first_sample``: the index of the first row in the stream)."""
        rows = np.asarray(rows)
        if math.isfinite(np.sum(rows)):  # finite samples have a finite total (one pass); else sample by sample
            return
        bad = ~np.isfinite(rows.T)
        if np.any(bad):
            ch, i = np.argwhere(bad)[0]
            raise InputError(f"sample {first_sample + int(i)} of channel {ch + 1} is not a finite number",
                             path=self.path)

    def _rows(self, check: bool, read_bytes: int | None = None) -> Iterator[tuple[float, np.ndarray]]:
        """The ``rows=True`` blocks of :meth:`chunks`."""
        dt = np.dtype(DTYPES[self.dtype])
        frame = 4 * dt.itemsize
        most = ROWS_READ_BYTES if read_bytes is None else int(read_bytes)
        cap = max(frame, (max(int(self.read_bytes), most) // frame) * frame)
        direct = dt == np.dtype(np.float64) and self.order is None and self.scale == 1.0
        ring = bytearray(cap + frame)
        mv = memoryview(ring)
        readinto = self._readinto
        carry = 0
        n = 0
        try:
            while True:
                if readinto is not None:
                    got = readinto(mv[carry: carry + cap])
                else:  # a reader of bytes (the NI DAQ's): copied in
                    data = self._reader(cap)
                    got = len(data) if data else 0
                    if got:
                        ring[carry: carry + got] = data
                if not got:
                    break
                now = time.perf_counter()
                size = carry + got
                m = size // frame
                if m:
                    raw = np.frombuffer(ring, dtype=dt, count=4 * m).reshape(m, 4)
                    if direct:
                        block = raw
                    else:
                        block = raw if self.order is None else raw[:, list(self.order)]
                        block = block.astype(np.float64)
                        if self.scale != 1.0:
                            block *= self.scale
                    if check:
                        self.check_rows(block, n)
                    self.arrivals.append((n + m, now))
                    self.backlog = got == cap  # the buffer filled: more may be waiting
                    yield self.t0_s + n / self.rate_hz, block
                    n += m
                    del raw, block
                carry = size - m * frame
                if carry and m:
                    ring[:carry] = ring[m * frame: size]
        finally:
            if self._close is not None:
                self._close()
        if carry:
            print(f"psdcal: warning: {self.path}: the stream ended inside a frame ({carry} bytes dropped)",
                  file=sys.stderr)


#: Bytes a ``rows`` read of a live stream asks for at most (8 MB: 262144 frames of float64).
ROWS_READ_BYTES = 1 << 23


def open_stream(source: str, rate_hz: float | None, *, dtype: str = "float64", scale: float = 1.0,
                timeout_s: float = 10.0, stdin=None, order: str | None = None) -> RawStream:
    """Open a live source (see the module docstring).

    ``order``: the frame's channels in their order when not ``vx1,vx2,vy1,vy2``
    (``"vx1,vy1,vx2,vy2"``, :func:`parse_order`); the blocks yielded are in the
    documented order.

    Raises
    ------
    InputError
        No rate, an unknown sample type, a non-local host, a refused
        connection, or (``nidaqmx://``) the NI package or driver missing.
    """
    if rate_hz is None or not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise InputError("a live stream needs --rate-hz", path=source, field="rate_hz")
    if dtype not in DTYPES:
        raise InputError(f"unknown sample type {dtype!r}; use one of {sorted(DTYPES)}", field="raw_dtype")
    if not (math.isfinite(scale) and scale != 0):
        raise InputError(f"the scale must be a finite non-zero number, got {scale}", field="raw_scale")
    perm = parse_order(order)
    stream = _open_source(source, rate_hz, dtype, scale, timeout_s, stdin)
    stream.order = perm
    return stream


def _open_source(source, rate_hz, dtype, scale, timeout_s, stdin) -> RawStream:
    if source == "-":
        fh = stdin if stdin is not None else sys.stdin.buffer
        reader = getattr(fh, "read1", None) or fh.read
        return RawStream(source, float(rate_hz), dtype, float(scale), _reader=reader,
                         _readinto=getattr(fh, "readinto1", None))
    if source.startswith("tcp://"):
        import socket

        hostport = source[len("tcp://") :]
        host, _, port = hostport.rpartition(":")
        if host not in _LOCAL:
            raise InputError(f"only localhost streams are read (127.0.0.1, localhost, [::1]), not {host!r}",
                             path=source)
        try:
            port_n = int(port)
        except ValueError:
            raise InputError(f"not a port number: {port!r}", path=source) from None
        host = host.strip("[]")
        try:
            sock = socket.create_connection((host, port_n), timeout=timeout_s)
        except OSError as exc:
            raise InputError(f"cannot connect: {exc.strerror or exc}", path=source) from None
        sock.settimeout(None)
        return RawStream(source, float(rate_hz), dtype, float(scale), _reader=sock.recv, _close=sock.close,
                         _readinto=sock.recv_into)
    if source.startswith("nidaqmx://"):
        return _open_nidaqmx(source, float(rate_hz), scale)
    raise InputError("not a live source ('-', tcp://127.0.0.1:PORT or nidaqmx://DEVICE/ai0:3)", path=source)


def _open_nidaqmx(source: str, rate_hz: float, scale: float) -> RawStream:
    """Continuous four-channel acquisition from a NI DAQ (``nidaqmx://Dev1/ai0:3``)."""
    try:
        import nidaqmx
        from nidaqmx.constants import AcquisitionType
    except ImportError:
        raise InputError("reading a NI DAQ needs the nidaqmx package: pip install 'psdcal[daq]' (and NI-DAQmx)",
                         path=source) from None
    channels = source[len("nidaqmx://") :]
    try:
        task = nidaqmx.Task()
        task.ai_channels.add_ai_voltage_chan(channels)
        task.timing.cfg_samp_clk_timing(rate_hz, sample_mode=AcquisitionType.CONTINUOUS)
        task.start()
    except Exception as exc:  # the driver raises its own types (DaqNotFoundError, DaqError, OSError...)
        msg = " ".join(str(exc).split())[:200]
        raise InputError(f"the NI-DAQmx driver or device is not available: {msg}", path=source) from None
    per_read = max(1, int(rate_hz * 0.005))  # 5 ms of samples per read

    def reader(_n):
        data = np.asarray(task.read(number_of_samples_per_channel=per_read), dtype="<f8")
        if data.ndim != 2 or data.shape[0] != 4:
            raise InputError(f"expected 4 channels, got data of shape {data.shape}", path=source)
        return np.ascontiguousarray(data.T).tobytes()

    def close():
        task.stop()
        task.close()

    return RawStream(source, rate_hz, "float64", scale, _reader=reader, _close=close)
