"""CSV text of numeric columns, compiled: the same bytes as Python's ``"%.10g" % x`` and ``"%d" % i``.

``psdcal locate`` writes one row per window and emitter; formatting its
floats one by one in Python (``"%.10g" % x``, ~0.1 us a value) costs as much
as the demodulation.  :func:`rows_text` formats whole blocks of rows in a
compiled loop instead.  A float is written with 10 significant digits as
``%g`` does (fixed notation for decimal exponents -4 to 9, else ``d.ddde+XX``;
trailing zeros dropped; ``nan``, ``inf``, ``-0``).

Exactness: the 10 digits are ``round(|x| 10^(9 - e))``, the scaling done with
exact powers of ten (at most two roundings, < 3e-6 absolute on a value below
1e10).  Where that product lies within 1e-4 of a rounding tie, or the value is
outside 1e-280..1e290 (where the scaling is not exact enough), the kernel
leaves the value to Python's own formatting; so the text equals
``"%.10g" % x`` byte for byte for every double (the tests compare both on
random, edge and tie values).  :func:`rows_text_reference` is the Python
reference.

The kernels are deferred (:func:`psdcal._jit.deferred_njit`): numba is
imported at the first compiled call, not with this module, so a writer that
takes the Python path (:func:`_write_rows` below ``psdcal._jit.AUTO_MIN_CSV_ROWS``
rows in the command line's one-shot runs) never imports it.
"""
from __future__ import annotations

import math
import threading

import numpy as np

from psdcal._jit import deferred_njit as njit, deferred_njit_inline as njit_inline

#: Bytes reserved per formatted value ("-1.234567891e-100" is 17; an int64 20); the ten digits
#: of a float are written in their place (at most the text's 17 bytes and a few more are touched).
SLOT = 32
_P10 = np.array([10.0**i for i in range(23)])  # exact doubles
_LUT = np.frombuffer("".join(f"{i:02d}" for i in range(100)).encode(), dtype=np.uint8).copy()  # "00".."99"


_U0, _U1, _U2, _U10, _U100 = (np.uint64(v) for v in (0, 1, 2, 10, 100))
_U10000, _U1000000, _U100000000 = (np.uint64(10**k) for k in (4, 6, 8))


@njit_inline
def _ix(i):  # pragma: no cover - compiled
    """An index known to be >= 0 as unsigned: numba then writes ``out[i]`` without the check that wraps a
    negative index around (a compare and a select at every byte of the text)."""
    return np.uint64(i)


@njit_inline
def _scaled(ax, k):  # pragma: no cover - compiled
    """|x| 10^k with exact powers of ten (at most two roundings); -1.0 when |k| > 44."""
    if 0 <= k <= 22:
        return ax * _P10[k]
    if 22 < k <= 44:
        return (ax * _P10[22]) * _P10[k - 22]
    if -22 <= k < 0:
        return ax / _P10[-k]
    if -44 <= k < -22:
        return (ax / _P10[22]) / _P10[-k - 22]
    return -1.0


@njit_inline
def _fmt_int(v, out, b):  # pragma: no cover - compiled
    """Write ``"%d" % v`` into ``out[b:]``; its length, or -1 (int64's minimum: left to Python)."""
    if v == -9223372036854775807 - 1:
        return -1
    p = 0
    if v < 0:
        out[_ix(b + 0)] = 45
        p = 1
        v = -v
    nd = 1
    t = v
    while t >= 10:
        t //= 10
        nd += 1
    for i in range(nd - 1, -1, -1):
        out[_ix(b + p + i)] = 48 + v % 10
        v //= 10
    return p + nd


@njit_inline
def _digits(x, bits):  # pragma: no cover - compiled
    """The decimal form of ``"%.10g" % x`` without its text: ``(state, u, e, nd)``.

    ``state``: 0 a finite non-zero value (``|x| = u 10^(e - 9)``, ``u`` (uint64) its ten digits, of which
    the first ``nd`` are significant: the rest are zeros), 1 nan, 2 inf, 3 zero, -1 left to Python (near a
    rounding tie, or an extreme exponent).
    """
    if x != x:
        return 1, _U0, 0, 0
    ax = abs(x)
    if ax == math.inf:
        return 2, _U0, 0, 0
    if ax == 0.0:
        return 3, _U0, 0, 0
    if ax < 1e-280 or ax > 1e290:
        return -1, _U0, 0, 0
    # decimal exponent from the binary one (libm's log10 costs more than all the rest):
    # floor((e2 - 1) log10 2) <= log10|x| < that + 2; the check below moves it up by one
    e2 = ((bits >> 52) & 2047) - 1022  # |x| = mantissa 2^e2, mantissa in [0.5, 1)
    e = ((e2 - 1) * 78913) >> 18  # floor((e2 - 1) log10 2) for |e2| < 1700
    k = 9 - e
    if 0 <= k <= 22:
        y = ax * _P10[k]
    elif -22 <= k < 0:
        y = ax / _P10[-k]
    else:
        y = _scaled(ax, k)
    if y >= 1e10:  # the estimate one low: rescale from |x| itself
        e += 1
        y = _scaled(ax, 9 - e)
    elif y < 1e9:  # (not expected; kept for safety)
        e -= 1
        y = _scaled(ax, 9 - e)
    if not (1e9 <= y < 1e10):
        return -1, _U0, 0, 0
    fl = math.floor(y)
    frac = y - fl
    if abs(frac - 0.5) < 1e-4:  # too near a tie for the scaling's rounding: Python decides
        return -1, _U0, 0, 0
    m = np.int64(fl)
    if frac > 0.5:
        m += 1
    if m == 10_000_000_000:
        m = 1_000_000_000
        e += 1
    # the significant digits: m without its trailing zeros (unsigned: a division by a constant is a multiply)
    u = np.uint64(m)
    t = u
    nd = 10
    while nd > 1:
        t10 = t // _U10
        if t - t10 * _U10 != _U0:
            break
        t = t10
        nd -= 1
    return 0, u, e, nd


@njit_inline
def _put_float(state, neg, u, e, nd, out, b):  # pragma: no cover - compiled
    """Write the text of :func:`_digits`' ``(state, u, e, nd)`` (``neg``: the sign bit, also of -0.0) into
    ``out[b:]`` (``out`` has SLOT bytes of room after ``b``; bytes after the text may be overwritten); its
    length, or -1 (``state`` -1: left to Python)."""
    if state == 1:
        out[_ix(b + 0)], out[_ix(b + 1)], out[_ix(b + 2)] = 110, 97, 110  # nan
        return 3
    if state < 0:
        return -1
    # branch-free where the data decide (a sign, an exponent that changes from row to row: mispredicted
    # branches cost more than the few operations they save): the '-' is written always, the text starts
    # after it or on it
    out[_ix(b)] = 45  # '-'
    p = 1 if neg else 0
    if state == 2:
        out[_ix(b + p)], out[_ix(b + p + 1)], out[_ix(b + p + 2)] = 105, 110, 102  # inf
        return p + 3
    if state == 3:
        out[_ix(b + p)] = 48
        return p + 1
    # the ten digits as five pairs, each from u alone (no chain of divisions; unsigned: a division by a
    # constant is a multiply), written where the text wants them: digit i at q + s + i, one byte further
    # on from the '.' (at q + dot) on; "0.000" first (what a fixed number below 1 starts with; the digits
    # overwrite it otherwise); the zeros after the nd significant digits are past the text's end, or the
    # zeros of an integer before its '.'
    q = b + p
    fixed = -4 <= e < 10  # %g: fixed notation, else d.ddde+XX (s = 0, dot = 1)
    s = max(-e, 0) if fixed else 0
    dot = (max(e, 0) if fixed else 0) + 1
    if s:
        out[_ix(q)], out[_ix(q + 1)], out[_ix(q + 2)], out[_ix(q + 3)], out[_ix(q + 4)] = 48, 46, 48, 48, 48
    i2 = (u // _U100000000) * _U2
    out[_ix(q + s + (s >= dot))] = _LUT[i2]
    out[_ix(q + s + 1 + (s + 1 >= dot))] = _LUT[i2 + _U1]
    i2 = ((u // _U1000000) % _U100) * _U2
    out[_ix(q + s + 2 + (s + 2 >= dot))] = _LUT[i2]
    out[_ix(q + s + 3 + (s + 3 >= dot))] = _LUT[i2 + _U1]
    i2 = ((u // _U10000) % _U100) * _U2
    out[_ix(q + s + 4 + (s + 4 >= dot))] = _LUT[i2]
    out[_ix(q + s + 5 + (s + 5 >= dot))] = _LUT[i2 + _U1]
    i2 = ((u // _U100) % _U100) * _U2
    out[_ix(q + s + 6 + (s + 6 >= dot))] = _LUT[i2]
    out[_ix(q + s + 7 + (s + 7 >= dot))] = _LUT[i2 + _U1]
    i2 = (u % _U100) * _U2
    out[_ix(q + s + 8 + (s + 8 >= dot))] = _LUT[i2]
    out[_ix(q + s + 9 + (s + 9 >= dot))] = _LUT[i2 + _U1]
    out[_ix(q + dot)] = 46
    # the digits and their '.' (s + nd + 1), or an integer (fixed notation, s + nd <= dot): no '.'
    p += max(s + nd + (s + nd > dot), dot)
    if fixed:
        return p
    out[_ix(b + p)] = 101  # 'e'
    out[_ix(b + p + 1)] = 45 if e < 0 else 43
    p += 2
    ae = -e if e < 0 else e
    if ae >= 100:
        out[_ix(b + p)] = 48 + ae // 100
        p += 1
    out[_ix(b + p)] = 48 + (ae // 10) % 10
    out[_ix(b + p + 1)] = 48 + ae % 10
    return p + 2


@njit_inline
def _fmt_float(x, bits, out, b):  # pragma: no cover - compiled
    """Write ``"%.10g" % x`` into ``out[b:]`` (``out`` has SLOT bytes of room after ``b``; the bytes after the
    text may be overwritten); its length, or -1 (left to Python)."""
    state, u, e, nd = _digits(x, bits)
    return _put_float(state, bits < 0, u, e, nd, out, b)


#: Rows whose floats' digits are found (first pass of :func:`format_rows`) before their text is written.
_BLOCK_ROWS = 64


@njit
def format_rows(F, I, kind, src, codes, table, offsets, out, fb_pos, fb_cell):  # pragma: no cover - compiled
    """The CSV text (uint8) of a block of rows, written straight into ``out``; returns ``(length, n_left)``.

    ``kind[j]``: 0 float (row ``src[j]`` of ``F``, a column a row), 1 integer (of ``I``), 2 text
    (``table[offsets[c]:offsets[c + 1]]`` with ``c = codes[row, src[j]]``); ``,`` between cells,
    ``\n`` after each row.  ``out`` must hold the longest possible text plus SLOT bytes.  A cell
    left to Python (a float near a rounding tie or with an extreme exponent, int64's minimum) is
    written as nothing: its place in the text goes to ``fb_pos``, its ``row * ncol + column`` to
    ``fb_cell`` (``n_left`` of them; when there are more than ``fb_pos`` holds, ``n_left`` is
    ``-1`` and the text is incomplete).
    """
    n = F.shape[1]
    ncol = kind.shape[0]
    FB = F.view(np.int64)  # the bits of the floats
    # two passes over each block of rows: the floats' digits first (independent of one another: the
    # processor overlaps them), then the text (each cell's place known from the one before)
    nb = _BLOCK_ROWS * ncol
    st = np.empty(nb, dtype=np.int64)
    du = np.empty(nb, dtype=np.uint64)
    de = np.empty(nb, dtype=np.int64)
    dn = np.empty(nb, dtype=np.int64)
    p = 0
    nfb = 0
    for r0 in range(0, n, _BLOCK_ROWS):
        r1 = min(n, r0 + _BLOCK_ROWS)
        for r in range(r0, r1):
            for j in range(ncol):
                if kind[_ix(j)] == 0:
                    c = _ix((r - r0) * ncol + j)
                    sj, rr = _ix(src[_ix(j)]), _ix(r)
                    st[c], du[c], de[c], dn[c] = _digits(F[sj, rr], FB[sj, rr])
        for r in range(r0, r1):
            for j in range(ncol):
                if j > 0:
                    out[_ix(p)] = 44
                    p += 1
                kd = kind[_ix(j)]
                if kd == 2:
                    c = codes[r, src[j]]
                    for i in range(offsets[c], offsets[c + 1]):
                        out[_ix(p)] = table[_ix(i)]
                        p += 1
                    continue
                if kd == 1:
                    ln = _fmt_int(I[r, src[j]], out, p)
                else:
                    c = _ix((r - r0) * ncol + j)
                    sj, rr = _ix(src[_ix(j)]), _ix(r)
                    ln = _put_float(st[c], FB[sj, rr] < 0, du[c], de[c], dn[c], out, p)
                if ln < 0:
                    if nfb < fb_pos.shape[0]:
                        fb_pos[nfb] = p
                        fb_cell[nfb] = r * ncol + j
                        nfb += 1
                    else:
                        return p, -1
                else:
                    p += ln
            out[_ix(p)] = 10
            p += 1
    return p, nfb


# --------------------------------------------------------------------------- Python side
def _kind_of(a: np.ndarray) -> str:
    if a.dtype.kind in "OUS":
        return "s"
    if a.dtype.kind in "iub":
        return "d"
    return "g"


def rows_text_reference(columns) -> str:
    """CSV text of equal-length columns: floats ``"%.10g"``, integers ``"%d"``, others ``"%s"``.

    The reference of :func:`rows_text` (one Python ``%`` formatting per value).
    """
    parts, lists = [], []
    for a in columns:
        a = np.asarray(a)
        parts.append({"s": "%s", "d": "%d", "g": "%.10g"}[_kind_of(a)])
        lists.append(a.tolist())
    fmt = ",".join(parts)
    return "\n".join([fmt % row for row in zip(*lists)]) + "\n"


def _table(texts):
    """UTF-8 table of strings: (bytes as uint8, offsets (len + 1,))."""
    enc = [t.encode("utf-8") for t in texts]
    offsets = np.zeros(len(enc) + 1, dtype=np.int64)
    offsets[1:] = np.cumsum([len(b) for b in enc])
    # a writable copy: one compiled signature for the kernels whatever the table (numba types read-only apart)
    table = np.frombuffer(b"".join(enc), dtype=np.uint8).copy() if offsets[-1] else np.zeros(1, dtype=np.uint8)
    return table, offsets


def _codes(a: np.ndarray, values=None):
    """Integer codes of a text column and the UTF-8 table of its distinct values (``"%s" % v``)
    (``values``: ``a.tolist()`` when the caller has it)."""
    if values is None and a.dtype.kind == "U":  # (no Python string per row) the distinct values one at a time
        first = a[0]
        other = a != first
        codes = other.astype(np.int64)  # 0: the first value; 1: another one (the second, when only two)
        distinct = [str(first)]
        while len(distinct) < 16 and other.any():
            v = a[int(other.argmax())]
            same = a == v
            distinct.append(str(v))
            if len(distinct) > 2:
                codes[same] = len(distinct) - 1
            other &= ~same
        if not other.any():
            table, offsets = _table(distinct)
            return codes, table, offsets
    if values is None:
        values = a.tolist()
    distinct = list(dict.fromkeys(values))
    if len(distinct) <= 16:  # a few emitter names: one vectorised comparison each
        codes = np.zeros(a.shape[0], dtype=np.int64)
        for i, v in enumerate(distinct[1:], start=1):
            codes[a == v] = i
    else:
        index = {v: i for i, v in enumerate(distinct)}
        codes = np.fromiter((index[v] for v in values), dtype=np.int64, count=a.shape[0])
    table, offsets = _table(["%s" % v for v in distinct])
    return codes, table, offsets


def rows_text(columns) -> str:
    """CSV text of equal-length 1-D columns (no header), byte for byte :func:`rows_text_reference`.

    Floats (any float dtype) as ``"%.10g"``, integers and booleans as
    ``"%d"``, strings and objects as ``"%s"``; rows end with ``\\n``.
    """
    return rows_bytes(columns).decode("utf-8")


def rows_bytes(columns) -> bytes:
    """:func:`rows_text` as UTF-8 bytes (what the file receives: no decoding and encoding again)."""
    return bytes(_rows_buffer(columns))


_scratch = threading.local()  # each thread's text buffer, reused from call to call


def _text_buffer(size: int) -> np.ndarray:
    """A uint8 buffer of at least ``size`` bytes, this thread's own, reused (not faulted in again each call)."""
    buf = getattr(_scratch, "buf", None)
    if buf is None or buf.shape[0] < size:
        buf = np.empty(max(size, 1 << 16), dtype=np.uint8)
        if size <= _KEEP_BYTES:  # (a one-off larger text is not kept)
            _scratch.buf = buf
    return buf


#: The largest text buffer kept for the next call (locate's batches need about 1 MB).
_KEEP_BYTES = 1 << 23


def _rows_buffer(columns):
    """:func:`rows_bytes`' text as a bytes-like object; a view of this thread's reused buffer, valid until
    the thread's next call (the caller writes it at once)."""
    cols = [np.asarray(a) for a in columns]
    n = cols[0].shape[0]
    if n == 0:
        return b""
    kinds = [_kind_of(a) for a in cols]
    lists = {j: a.tolist() for j, a in enumerate(cols) if a.dtype.kind == "O"}
    if any(a.ndim != 1 for a in cols) or any(a.dtype == np.uint64 for a in cols) or any(
            set(map(type, v)) != {str} for v in lists.values()):
        return rows_text_reference(cols).encode("utf-8")  # what the compiled path does not cover: Python's own
    fcols = [a for a, k in zip(cols, kinds) if k == "g"]
    icols = [a for a, k in zip(cols, kinds) if k == "d"]
    scols = [(a, lists.get(j)) for j, (a, k) in enumerate(zip(cols, kinds)) if k == "s"]
    F = np.empty((max(1, len(fcols)), n))  # a column a row: plain copies
    for j, a in enumerate(fcols):
        F[j] = a  # float16/32 -> float64 is exact: the same decimal text
    I = np.zeros((n, max(1, len(icols))), dtype=np.int64)
    for j, a in enumerate(icols):
        I[:, j] = a
    kind = np.array([{"g": 0, "d": 1, "s": 2}[k] for k in kinds], dtype=np.int64)
    src = np.zeros(len(cols), dtype=np.int64)
    count = {"g": 0, "d": 0, "s": 0}
    for j, k in enumerate(kinds):
        src[j] = count[k]
        count[k] += 1
    codes = None if len(scols) == 1 else np.zeros((n, max(1, len(scols))), dtype=np.int64)
    tables, offs, base = [], [np.zeros(1, dtype=np.int64)], 0
    n_codes = 0
    longest_text = 0
    for j, (a, values) in enumerate(scols):
        c, table, offsets = _codes(a, values)
        if codes is None:  # one text column: its codes as they are
            codes = c.reshape(n, 1)
        else:
            codes[:, j] = c + n_codes
        n_codes += len(offsets) - 1
        tables.append(table[: offsets[-1]])
        offs.append(offsets[1:] + base)
        base += int(offsets[-1])
        longest_text += int(np.diff(offsets).max(initial=0))
    table = np.concatenate(tables) if tables and base else np.zeros(1, dtype=np.uint8)
    offsets = np.concatenate(offs)
    # the longest text: 24 bytes a number ("-1.234567891e-100" is 17, an int64 20) and a separator
    out = _text_buffer(n * (25 * (len(fcols) + len(icols)) + len(scols) + longest_text) + SLOT)
    fb_cap = 64 + (n * len(cols)) // 64
    fb_pos = np.empty(fb_cap, dtype=np.int64)
    fb_cell = np.empty(fb_cap, dtype=np.int64)
    length, n_left = format_rows(F, I, kind, src, codes, table, offsets, out, fb_pos, fb_cell)
    if n_left < 0:  # (not expected: a 64th of the cells near a rounding tie) Python's formatting throughout
        return rows_text_reference(cols).encode("utf-8")
    if n_left == 0:
        return memoryview(out)[:length]
    # the cells left to Python (rare: values near a rounding tie, extreme exponents), spliced in
    rr, jj = np.divmod(fb_cell[:n_left], len(cols))
    parts, at = [], 0
    text = memoryview(out)  # the segments joined without copies of their own
    for pos, r, j in zip(fb_pos[:n_left].tolist(), rr.tolist(), jj.tolist()):
        parts.append(text[at:pos])
        parts.append((("%.10g" % F[src[j], r]) if kind[j] == 0 else ("%d" % I[r, src[j]])).encode())
        at = pos
    parts.append(text[at:length])
    return b"".join(parts)


# --------------------------------------------------------------------------- writers of locate's rows
def _write_rows(fh, cols: dict, order) -> int:
    """Write columns (equal-length arrays) as CSV rows; floats with 10 significant digits.

    The text is formatted by the compiled writer (:func:`psdcal.measure._csvtext.rows_text`, the same
    bytes as Python's ``"%.10g"``/``"%d"``/``"%s"``), or by :func:`_rows_text` without numba.
    """
    n = len(cols["t_s"])
    if n == 0:
        return 0
    from psdcal import _jit

    if _jit.use_compiled(n, _jit.AUTO_MIN_CSV_ROWS):
        text = _rows_buffer([cols[c] for c in order])
        raw = getattr(fh, "buffer", None)
        if raw is not None and getattr(fh, "encoding", "").lower().replace("-", "") == "utf8":
            fh.flush()  # the text written so far (the header) first
            raw.write(text)
        else:
            fh.write(bytes(text).decode("utf-8"))
    else:
        fh.write(_rows_text(cols, order))
    return n


def _rows_text(cols: dict, order) -> str:
    """The CSV text of :func:`_write_rows` by Python's ``%`` formatting (the reference)."""
    return rows_text_reference([cols[c] for c in order])


class _NpyRows:
    """Collects output columns and writes them as one NumPy structured array (``--format npy``)."""

    def __init__(self, order):
        self.order = tuple(order)
        self.parts = {c: [] for c in self.order}

    def write(self, cols: dict) -> int:
        n = len(cols["t_s"])
        for c in self.order:
            self.parts[c].append(np.asarray(cols[c]))
        return n

    def save(self, path) -> None:
        fields, data = [], []
        for c in self.order:
            a = np.concatenate(self.parts[c]) if self.parts[c] else np.zeros(0)
            if a.dtype.kind in "OUS":
                a = a.astype(str)
                if a.size == 0:
                    a = a.astype("U1")
            elif a.dtype.kind not in "iub":
                a = a.astype(np.float64)
            fields.append((c, a.dtype))
            data.append(a)
        out = np.empty(len(data[0]) if data else 0, dtype=fields)
        for (c, _), a in zip(fields, data):
            out[c] = a
        with open(path, "wb") as fh:
            np.save(fh, out, allow_pickle=False)
