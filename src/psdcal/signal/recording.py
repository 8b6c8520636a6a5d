"""Recordings of the four PSD channels, read in chunks (constant memory).

A recording holds the four amplified anode signals ``vx1, vx2, vy1, vy2``
sampled at ``rate_hz``.  :func:`open_recording` picks a reader from the file
extension; every reader's :meth:`Recording.chunks` yields
``(t0_s, block)`` with ``block`` a float64 array of shape ``(4, n_chunk)``
(rows in channel order) and ``t0_s`` the time of its first sample, so that a
recording larger than memory streams through.

Formats
-------
``.npy``
    A ``(n, 4)`` array (columns vx1, vx2, vy1, vy2), or ``(4, n)``; memory
    mapped.  No rate metadata: give ``rate_hz``.
``.csv``
    A header naming ``vx1,vx2,vy1,vy2`` (any order, other columns ignored),
    optionally ``t_s`` (the rate and the start time are then taken from it).
``.h5`` / ``.hdf5`` (needs ``h5py``: ``pip install psdcal[hdf5]``)
    Four 1-D datasets ``vx1, vx2, vy1, vy2`` (in the root or in ``group``), or
    one ``(n, 4)`` dataset named by ``dataset`` (default: ``signals``, or the
    only 2-D dataset).  The rate from an attribute ``rate_hz`` (or
    ``sample_rate``) of the dataset, its group or the file.
``.tdms`` (needs ``npTDMS``: ``pip install psdcal[tdms]``)
    A group (``group``, default: the first one holding the four channels)
    with channels ``vx1, vx2, vy1, vy2``; the rate from the channel property
    ``wf_increment`` (or ``rate_hz``), the start time from ``wf_start_offset``.

Channel names can be changed with ``channels=(name_vx1, name_vx2, name_vy1,
name_vy2)`` (CSV columns, HDF5 datasets, TDMS channels).
"""
from __future__ import annotations

import contextlib
import csv
import io
import math
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from psdcal.errors import InputError, PsdcalError
from psdcal.model.readout import CHANNELS

DEFAULT_CHUNK = 1 << 16
_CSV_RATE_ROWS = 10_001
#: Relative tolerance between --rate-hz and a rate read from a file (CSV time stamps may be rounded).
RATE_RTOL = 1e-4


class MissingDependencyError(InputError):
    """An optional package needed for a file format is not installed."""


def _check_finite(block: np.ndarray, path, first_sample: int, *, line_offset: int | None = None) -> None:
    # the total of finite samples is finite (one pass, no mask); a total that overflows is checked sample by sample
    if math.isfinite(np.sum(block)) or np.all(np.isfinite(block)):
        return
    ch, i = np.argwhere(~np.isfinite(block))[0]
    sample = first_sample + int(i)
    line = None if line_offset is None else line_offset + sample
    raise InputError(
        f"sample {sample} of channel {CHANNELS[ch]} is not a finite number",
        path=path,
        line=line,
        field=CHANNELS[ch],
    )


@dataclass(frozen=True)
class Recording:
    """A four-channel recording on disk.

    Attributes
    ----------
    path : str
    rate_hz : float
        Sampling rate.
    n_samples : int or None
        Samples per channel (None when unknown before reading, e.g. CSV).
    t0_s : float
        Time of the first sample, s.
    kind : str
        ``"npy"``, ``"csv"``, ``"hdf5"`` or ``"tdms"``.
    options : dict
        Reader options (channel names, dataset, group).
    """

    path: str
    rate_hz: float
    n_samples: int | None
    t0_s: float = 0.0
    kind: str = "npy"
    options: dict = field(default_factory=dict)

    @property
    def duration_s(self) -> float | None:
        """Length of the recording, s (None when unknown)."""
        return None if self.n_samples is None else self.n_samples / self.rate_hz

    def chunks(self, chunk_samples: int = DEFAULT_CHUNK, *, rows: bool = False, check_finite: bool = True,
               reuse_buffer: bool = False, mapped: bool = False,
               mapped_chunk_samples: int | None = None) -> Iterator[tuple[float, np.ndarray]]:
        """Yield ``(t0_s, block)``, ``block`` float64 (4, <= chunk_samples).

        Parameters
        ----------
        chunk_samples : int
            Samples per channel per block (the last one may be shorter).
        rows : bool
            Yield ``(<= chunk_samples, 4)`` blocks instead (one sample of the
            four channels a row, any strides).  A ``(n, 4)`` float64 ``.npy``
            file (native byte order, C order) is read straight into the block
            (no conversion, no transpose); other ``.npy`` layouts are
            converted from a memory map, other formats give the transpose (a
            view) of their block.
        check_finite : bool
            Check every sample (below).  ``False`` (``rows`` blocks of ``.npy``
            recordings only) leaves the check to the caller, who runs
            :meth:`check_block` on a block whose sums came out non-finite
            (``psdcal locate`` uses the lock-in's per-window sums of squares,
            which are finite only when every sample is).
        reuse_buffer : bool
            ``rows`` blocks of ``.npy`` recordings: fill one buffer again for
            every chunk (no allocation per chunk); a block is then valid only
            until the next one is asked for: copy what must be kept.
        mapped : bool
            ``rows`` blocks of a ``(n, 4)`` float64 ``.npy`` file (native byte
            order, C order): read-only views of a memory map of the file, no
            copy at all (the carrier pre-scan of ``psdcal locate`` reads its
            prefix so; the demodulation itself copies chunks into one buffer
            with ``reuse_buffer``: its compiled sums read a cached buffer
            faster than a map's scattered pages).  The
            file's size is checked before each block (a file truncated after
            opening is named as such); a block is valid until the next one is
            asked for.  Other layouts: as without it.
        mapped_chunk_samples : int, optional
            With ``mapped``: the block size when the blocks are views of the
            map (they hold no memory of their own: larger blocks, fewer calls);
            ``chunk_samples`` otherwise.

        Raises
        ------
        InputError
            On a non-finite sample (naming the file, the sample or CSV line,
            and the channel) or a malformed CSV row.
        """
        chunk_samples = int(chunk_samples)
        if chunk_samples < 1:
            raise InputError(f"chunk size must be positive, got {chunk_samples}", field="chunk_samples")
        if rows and self.kind == "npy":
            yield from _rows_npy(self, chunk_samples, check_finite, reuse_buffer, mapped,
                                 int(mapped_chunk_samples) if mapped_chunk_samples else chunk_samples)
            return
        reader = {"npy": _chunks_npy, "csv": _chunks_csv, "hdf5": _chunks_hdf5, "tdms": _chunks_tdms}[self.kind]
        for t0, block in reader(self, chunk_samples):
            yield t0, (block.T if rows else block)

    def check_block(self, block: np.ndarray, first_sample: int, *, rows: bool = False) -> None:
        """Raise :class:`InputError` naming the first non-finite sample of ``block``, if any.

        ``block`` is (4, m), or (m, 4) with ``rows``; ``first_sample`` is the
        index of its first sample in the recording.
        """
        b = np.asarray(block)
        _check_finite(b.T if rows else b, self.path, first_sample)


# --------------------------------------------------------------------------- open
def open_recording(path, rate_hz: float | None = None, *, channels=None, dataset: str | None = None,
                   group: str | None = None) -> Recording:
    """Open a recording and read its metadata (not its samples).

    Parameters
    ----------
    path : str or Path
        ``.npy``, ``.csv``, ``.h5``/``.hdf5`` or ``.tdms``.
    rate_hz : float, optional
        Sampling rate; needed when the file does not carry one.  When both are
        given they must agree (to :data:`RATE_RTOL` relative).
    channels : 4 str, optional
        Names of the channels in the file, in the order vx1, vx2, vy1, vy2.
    dataset, group : str, optional
        HDF5 dataset / group, TDMS group.

    Returns
    -------
    Recording

    Raises
    ------
    InputError
        Unknown extension, missing file, channel or rate;
        :class:`MissingDependencyError` when ``h5py`` / ``npTDMS`` is missing.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("recording not found", path=path)
    from psdcal.io import check_regular_file

    check_regular_file(path, "recording")
    names = tuple(channels) if channels is not None else CHANNELS
    if len(names) != 4:
        raise InputError(f"give exactly 4 channel names (vx1, vx2, vy1, vy2), got {list(names)}", field="channels")
    if len(set(names)) != 4:
        raise InputError(f"the 4 channel names must differ, got {list(names)}", field="channels")
    if rate_hz is not None and not (math.isfinite(float(rate_hz)) and float(rate_hz) > 0):
        raise InputError(f"sampling rate must be a positive finite number, got {rate_hz}", field="rate_hz")
    ext = path.suffix.lower()
    opts = {"channels": names, "dataset": dataset, "group": group}
    openers = {".npy": _open_npy, ".csv": _open_csv, ".h5": _open_hdf5, ".hdf5": _open_hdf5, ".tdms": _open_tdms}
    if ext not in openers:
        raise InputError(
            f"unknown recording format '{ext or '(no extension)'}'; use .npy, .csv, .h5/.hdf5 or .tdms", path=path
        )
    try:
        rec = openers[ext](path, opts)
    except InputError:
        raise
    except UnicodeDecodeError:
        raise InputError("not UTF-8 text (save the CSV recording as UTF-8)", path=path) from None
    except MemoryError:
        raise InputError("the file's header asks for more memory than there is: a corrupt recording", path=path) from None
    except (OSError, ValueError, TypeError, KeyError, AttributeError, IndexError, OverflowError, EOFError,
            csv.Error, struct.error, SyntaxError) as exc:
        raise InputError(f"not a readable {ext[1:].upper()} recording ({type(exc).__name__}: "
                         f"{' '.join(str(exc).split())[:200]})", path=path) from None
    file_rate = rec.rate_hz
    if file_rate is None or not np.isfinite(file_rate):
        if rate_hz is None:
            raise InputError("the file gives no sampling rate: pass --rate-hz", path=path, field="rate_hz")
        final = float(rate_hz)
    else:
        final = float(file_rate)
        if rate_hz is not None and not math.isclose(final, float(rate_hz), rel_tol=RATE_RTOL):
            raise InputError(
                f"--rate-hz {float(rate_hz):g} disagrees with the file's sampling rate {final:g} Hz",
                path=path,
                field="rate_hz",
            )
    if not (final > 0 and np.isfinite(final)):
        raise InputError(f"sampling rate must be positive, got {final}", path=path, field="rate_hz")
    return Recording(path=rec.path, rate_hz=final, n_samples=rec.n_samples, t0_s=rec.t0_s, kind=rec.kind,
                     options=rec.options)


# --------------------------------------------------------------------------- npy
def _npy_array(path):
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception as exc:  # numpy's header parser raises ValueError, SyntaxError, tokenize.TokenError...
        raise InputError(f"not a readable .npy array ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})",
                         path=path) from None
    if np.issubdtype(arr.dtype, np.complexfloating):
        raise InputError(f"complex samples ({arr.dtype}): expected real voltages", path=path)
    if arr.ndim != 2 or 4 not in arr.shape or not np.issubdtype(arr.dtype, np.number):
        raise InputError(
            f"expected a numeric (n, 4) array of channels vx1, vx2, vy1, vy2, got shape {arr.shape} {arr.dtype}",
            path=path,
        )
    return arr


def _open_npy(path, opts):
    arr = _npy_array(path)
    n = arr.shape[0] if arr.shape[1] == 4 else arr.shape[1]
    return Recording(path=str(path), rate_hz=None, n_samples=int(n), kind="npy", options=opts)


def _chunks_npy(rec: Recording, chunk: int):
    arr = _npy_array(rec.path)
    by_rows = arr.shape[1] == 4
    n = rec.n_samples
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        part = arr[start:stop] if by_rows else arr[:, start:stop]
        block = np.empty((4, stop - start))
        block[...] = part.T if by_rows else part
        _check_finite(block, rec.path, start)
        yield rec.t0_s + start / rec.rate_hz, block


def _rows_npy(rec: Recording, chunk: int, check: bool, reuse: bool, mapped: bool = False,
              mapped_chunk: int | None = None):
    """(m, 4) float64 blocks of a ``.npy`` recording.

    A ``(n, 4)`` float64 file (native byte order, C order) is read with ``readinto``
    (into one buffer kept between chunks with ``reuse``): copying from the page
    cache costs less than faulting the pages of a memory map in.  Other layouts
    and dtypes are converted from the memory map.
    """
    arr = _npy_array(rec.path)
    by_rows = arr.shape[1] == 4
    n = rec.n_samples
    offset = getattr(arr, "offset", None)
    direct = (by_rows and arr.dtype == np.dtype(np.float64) and arr.flags.c_contiguous and isinstance(offset, int)
              and chunk * 32 <= 1 << 30)
    if not direct:
        for start in range(0, n, chunk):
            stop = min(n, start + chunk)
            part = arr[start:stop] if by_rows else arr[:, start:stop].T
            block = np.asarray(part, dtype=np.float64)  # no copy for native float64
            if check:
                _check_finite(block.T, rec.path, start)
            yield rec.t0_s + start / rec.rate_hz, block
        return
    del arr
    if mapped:
        yield from _rows_mapped(rec, max(1, mapped_chunk or chunk), check, offset)
        return
    buf = np.empty((min(chunk, n), 4)) if reuse else None
    with open(rec.path, "rb") as fh:
        fh.seek(offset)
        for start in range(0, n, chunk):
            m = min(n, start + chunk) - start
            block = buf[:m] if reuse else np.empty((m, 4))
            got = fh.readinto(memoryview(block).cast("B"))
            if got != m * 32:
                raise InputError(f"the file ends after {start + (got or 0) // 32} of its {n} samples: a truncated "
                                 "recording", path=rec.path)
            if check:
                _check_finite(block.T, rec.path, start)
            yield rec.t0_s + start / rec.rate_hz, block


def _rows_mapped(rec: Recording, chunk: int, check: bool, offset: int):
    """(m, 4) read-only views of a memory map of a ``(n, 4)`` float64 C-order ``.npy`` (see ``chunks(mapped=)``)."""
    import mmap

    n = rec.n_samples
    if n == 0:
        return

    def truncated(size):
        got = max(0, size - offset) // 32
        return InputError(f"the file ends after {got} of its {n} samples: a truncated recording", path=rec.path)

    with open(rec.path, "rb") as fh:
        fd = fh.fileno()
        if os.fstat(fd).st_size < offset + 32 * n:
            raise truncated(os.fstat(fd).st_size)
        mm = mmap.mmap(fd, offset + 32 * n, access=mmap.ACCESS_READ)
        try:
            arr = np.frombuffer(mm, dtype=np.float64, count=4 * n, offset=offset).reshape(n, 4)
            for start in range(0, n, chunk):
                m = min(n, start + chunk) - start
                # the mapped file's size before each block (touching a truncated map is a crash, not an error)
                size = os.fstat(fd).st_size
                if size < offset + 32 * (start + m):
                    raise truncated(size)
                block = arr[start: start + m]
                if check:
                    _check_finite(block.T, rec.path, start)
                yield rec.t0_s + start / rec.rate_hz, block
        finally:
            arr = block = None  # noqa: F841  (no view may outlive the map)
            try:
                mm.close()
            except BufferError:  # a caller still holds a block: the map closes when it is dropped
                pass


# --------------------------------------------------------------------------- csv
def _csv_header(path, names):
    with open(path, newline="", encoding="utf-8-sig") as fh:
        first = fh.readline()
    header = [h.strip() for h in next(csv.reader([first]), [])]
    missing = [c for c in names if c not in header]
    if missing:
        raise InputError(f"missing column(s) {missing}; the header must name {list(names)}", path=path, line=1,
                         field=missing[0])
    cols = [header.index(c) for c in names]
    tcol = header.index("t_s") if "t_s" in header else None
    return header, cols, tcol


def _parse_rows(lines, ncol, usecols, path, first_line):
    """Parse CSV lines; on failure find the bad line with the csv module."""
    try:
        data = np.loadtxt(io.StringIO("".join(lines)), delimiter=",", usecols=usecols, ndmin=2, dtype=float)
    except ValueError:
        for k, row in enumerate(csv.reader(lines)):
            if len(row) != ncol:
                raise InputError(f"expected {ncol} fields, found {len(row)}", path=path, line=first_line + k) from None
            for j in usecols:
                try:
                    float(row[j])
                except ValueError:
                    raise InputError(f"not a number: {row[j]!r}", path=path, line=first_line + k, field=None) from None
        raise InputError("malformed rows", path=path, line=first_line) from None
    return data


def _open_csv(path, opts):
    header, cols, tcol = _csv_header(path, opts["channels"])
    rate, t0 = None, 0.0
    if tcol is not None:
        # the rate from the span of the first rows (robust to rounded time stamps)
        with open(path, newline="", encoding="utf-8-sig") as fh:
            fh.readline()
            lines = []
            for ln in fh:
                if ln.strip():
                    lines.append(ln)
                if len(lines) == _CSV_RATE_ROWS:
                    break
        if lines:
            t = _parse_rows(lines, len(header), [tcol], path, 2)[:, 0]
            t0 = float(t[0])
            if len(t) >= 2:
                dt = np.diff(t)
                if not np.all(dt > 0):
                    raise InputError("t_s must increase", path=path, line=3 + int(np.argmin(dt > 0)), field="t_s")
                rate = (len(t) - 1) / (t[-1] - t[0])
    opts = dict(opts, header=header, cols=cols, tcol=tcol)
    return Recording(path=str(path), rate_hz=rate, n_samples=None, t0_s=t0, kind="csv", options=opts)


def _chunks_csv(rec: Recording, chunk: int):
    opts = rec.options
    header, cols = opts["header"], opts["cols"]
    n_done = 0
    with open(rec.path, newline="", encoding="utf-8") as fh:
        fh.readline()
        while True:
            lines = []
            for line in fh:
                if line.strip():
                    lines.append(line)
                    if len(lines) == chunk:
                        break
            if not lines:
                return
            data = _parse_rows(lines, len(header), cols, rec.path, 2 + n_done)
            block = np.ascontiguousarray(data.T)
            _check_finite(block, rec.path, n_done, line_offset=2)
            yield rec.t0_s + n_done / rec.rate_hz, block
            n_done += len(lines)
            if len(lines) < chunk:
                return


# --------------------------------------------------------------------------- hdf5
#: What a file-format library raises on a corrupt file (h5py: OSError, RuntimeError, KeyError; npTDMS:
#: ValueError, KeyError, struct.error, EOFError...); turned into one InputError naming the file.
_LIBRARY_ERRORS = (OSError, RuntimeError, KeyError, ValueError, IndexError, TypeError, EOFError, AttributeError,
                   struct.error)


@contextlib.contextmanager
def _unreadable(path, what: str):
    """A corrupt file met by a reader library (when opened or while read) is one line naming the file."""
    try:
        yield
    except PsdcalError:
        raise
    except _LIBRARY_ERRORS as exc:
        msg = " ".join(str(exc).split())[:200]
        raise InputError(f"not a readable {what} file ({type(exc).__name__}: {msg})", path=path) from None


def _import_h5py(path):
    try:
        import h5py
    except ImportError:
        raise MissingDependencyError(
            "reading HDF5 recordings needs h5py: install psdcal[hdf5] (pip install 'psdcal[hdf5]')", path=path
        ) from None
    return h5py


def _rate_attr(*objs):
    for obj in objs:
        for key in ("rate_hz", "sample_rate", "sampling_rate_hz"):
            if key in obj.attrs:
                v = np.asarray(obj.attrs[key]).ravel()
                try:
                    rate = float(v[0])
                except (IndexError, TypeError, ValueError):
                    raise InputError(f"attribute '{key}' must be a number, got {obj.attrs[key]!r}", path=obj.file.filename,
                                     field=key) from None
                if not (math.isfinite(rate) and rate > 0):
                    raise InputError(f"attribute '{key}' must be a positive sampling rate, got {rate}",
                                     path=obj.file.filename, field=key)
                return rate
    return None


def _h5_locate(f, rec_path, opts):
    """(datasets, is_matrix, rate) of an open HDF5 file."""
    h5py = _import_h5py(rec_path)
    grp = f
    if opts.get("group"):
        if opts["group"] not in f:
            raise InputError(f"no group '{opts['group']}'", path=rec_path, field=opts["group"])
        grp = f[opts["group"]]
    names = opts["channels"]
    if opts.get("dataset"):
        if opts["dataset"] not in grp:
            raise InputError(f"no dataset '{opts['dataset']}'", path=rec_path, field=opts["dataset"])
        ds = grp[opts["dataset"]]
        if not isinstance(ds, h5py.Dataset):
            raise InputError(f"'{opts['dataset']}' is a group, expected a dataset", path=rec_path, field=opts["dataset"])
        if ds.ndim != 2 or 4 not in ds.shape:
            raise InputError(f"dataset must be (n, 4), got shape {ds.shape}", path=rec_path, field=opts["dataset"])
        return [ds], True, _rate_attr(ds, grp, f)
    if all(n in grp for n in names):
        dss = [grp[n] for n in names]
        for n, d in zip(names, dss):
            if not isinstance(d, h5py.Dataset):
                raise InputError(f"'{n}' is a group, expected a dataset of samples", path=rec_path, field=n)
        lens = {d.shape for d in dss}
        if len(lens) != 1 or dss[0].ndim != 1:
            raise InputError(f"datasets {list(names)} must be 1-D and of equal length", path=rec_path)
        return dss, False, _rate_attr(dss[0], grp, f)
    two_d = [k for k, v in grp.items() if isinstance(v, h5py.Dataset) and v.ndim == 2 and 4 in v.shape]
    if "signals" in grp and "signals" in two_d:
        two_d = ["signals"]
    if len(two_d) == 1:
        ds = grp[two_d[0]]
        return [ds], True, _rate_attr(ds, grp, f)
    missing = [n for n in names if n not in grp]
    raise InputError(
        f"no datasets {missing} and no single (n, 4) dataset; name one with --dataset", path=rec_path,
        field=missing[0] if missing else None,
    )


def _open_hdf5(path, opts):
    h5py = _import_h5py(path)
    with _unreadable(path, "HDF5"), h5py.File(path, "r") as f:
        dss, matrix, rate = _h5_locate(f, path, opts)
        ds = dss[0]
        for d in dss:
            if not (np.issubdtype(d.dtype, np.integer) or np.issubdtype(d.dtype, np.floating)):
                raise InputError(f"dataset '{d.name}' holds {d.dtype}, expected real numbers", path=path,
                                 field=d.name)
        n = (ds.shape[0] if ds.shape[1] == 4 else ds.shape[1]) if matrix else ds.shape[0]
    return Recording(path=str(path), rate_hz=rate, n_samples=int(n), kind="hdf5", options=opts)


def _chunks_hdf5(rec: Recording, chunk: int):
    h5py = _import_h5py(rec.path)
    with _unreadable(rec.path, "HDF5"), h5py.File(rec.path, "r") as f:
        dss, matrix, _ = _h5_locate(f, rec.path, rec.options)
        n = rec.n_samples
        for start in range(0, n, chunk):
            stop = min(n, start + chunk)
            block = np.empty((4, stop - start))
            if matrix:
                ds = dss[0]
                if ds.shape[1] == 4:
                    block[...] = ds[start:stop].T
                else:
                    block[...] = ds[:, start:stop]
            else:
                for i, ds in enumerate(dss):
                    block[i] = ds[start:stop]
            _check_finite(block, rec.path, start)
            yield rec.t0_s + start / rec.rate_hz, block


# --------------------------------------------------------------------------- tdms
def _import_nptdms(path):
    try:
        import nptdms
    except ImportError:
        raise MissingDependencyError(
            "reading TDMS recordings needs npTDMS: install psdcal[tdms] (pip install 'psdcal[tdms]')", path=path
        ) from None
    return nptdms


def _tdms_channels(f, path, opts):
    names = opts["channels"]
    groups = f.groups()
    if not groups:
        raise InputError("no data groups: not a readable TDMS recording, or an empty one", path=path)
    if opts.get("group"):
        sel = [g for g in groups if g.name == opts["group"]]
        if not sel:
            raise InputError(f"no group '{opts['group']}' (groups: {[g.name for g in groups]})", path=path,
                             field=opts["group"])
    else:
        sel = [g for g in groups if all(n in [c.name for c in g.channels()] for n in names)]
        if not sel:
            have = [c.name for g in groups for c in g.channels()]
            missing = [n for n in names if n not in have]
            raise InputError(f"no group holds the channels {list(names)} (missing {missing})", path=path,
                             field=(missing or [None])[0])
    grp = sel[0]
    have = {c.name: c for c in grp.channels()}
    missing = [n for n in names if n not in have]
    if missing:
        raise InputError(f"group '{grp.name}' has no channel(s) {missing}", path=path, field=missing[0])
    chans = [have[n] for n in names]
    lens = {len(c) for c in chans}
    if len(lens) != 1:
        raise InputError(f"channels {list(names)} have different lengths {sorted(lens)}", path=path)
    return chans


def _open_tdms(path, opts):
    nptdms = _import_nptdms(path)
    with _unreadable(path, "TDMS"), nptdms.TdmsFile.open(path) as f:
        chans = _tdms_channels(f, path, opts)
        props = chans[0].properties
        rate = None
        if "wf_increment" in props and float(props["wf_increment"]) > 0:
            rate = 1.0 / float(props["wf_increment"])
        elif "rate_hz" in props:
            rate = float(props["rate_hz"])
        t0 = float(props.get("wf_start_offset", 0.0))
        n = len(chans[0])
    return Recording(path=str(path), rate_hz=rate, n_samples=int(n), t0_s=t0, kind="tdms", options=opts)


def _chunks_tdms(rec: Recording, chunk: int):
    nptdms = _import_nptdms(rec.path)
    with _unreadable(rec.path, "TDMS"), nptdms.TdmsFile.open(rec.path) as f:
        chans = _tdms_channels(f, rec.path, rec.options)
        n = rec.n_samples
        for start in range(0, n, chunk):
            stop = min(n, start + chunk)
            block = np.empty((4, stop - start))
            for i, ch in enumerate(chans):
                block[i] = ch.read_data(start, stop - start)
            _check_finite(block, rec.path, start)
            yield rec.t0_s + start / rec.rate_hz, block
