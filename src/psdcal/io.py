"""Reading and writing psdcal's files (docs/model.md#calibration-json).

- Template CSV: ``point_id,X_mm,Y_mm``.
- Impact points CSV: ``image_id,point_id,x_mm,y_mm`` (a missing point is a missing row),
  or raw amplitudes ``image_id,point_id,vx1,vx2,vy1,vy2``.
- Calibration JSON: :meth:`psdcal.calibration.core.CalibrationResult.to_dict`.

Every reader validates as it goes and raises :class:`psdcal.errors.InputError`
naming the file, the line (1-based; the header is line 1) and the field.
Writers are atomic: an output file is replaced only when writing succeeded.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psdcal._atomic import atomic_path, write_text_atomic
from psdcal.errors import InputError
from psdcal.model.readout import LX_MM, LY_MM, impact_point

#: Largest text input read whole (CSV, JSON), bytes; larger files are refused before reading.
MAX_TEXT_BYTES = 256 * 1024 * 1024
#: Largest field of a CSV file, characters (a longer one is a corrupt file, not data).
MAX_FIELD_CHARS = 4096

TEMPLATE_HEADER = ("point_id", "X_mm", "Y_mm")
POINTS_HEADER = ("image_id", "point_id", "x_mm", "y_mm")
AMPLITUDES_HEADER = ("image_id", "point_id", "vx1", "vx2", "vy1", "vy2")


def check_regular_file(path, what: str = "file") -> Path:
    """``path`` as a Path if it is an existing regular file (not a folder, device or pipe), else InputError."""
    import stat

    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise InputError(f"{what} not found", path=path) from None
    except OSError as exc:
        raise InputError(f"cannot read the {what}: {exc.strerror or exc}", path=path) from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"is a directory, expected a {what}", path=path)
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"not a regular file (a device or a pipe), expected a {what}", path=path)
    return path


def read_text_file(path, what: str = "text file", *, max_bytes: int = MAX_TEXT_BYTES) -> str:
    """The text of a UTF-8 file (a BOM is dropped), validated; InputError naming the file otherwise.

    Refuses folders, devices (``/dev/zero``), files over ``max_bytes``,
    binary files (NUL bytes), UTF-16/32 and other non-UTF-8 encodings.
    """
    path = check_regular_file(path, what)
    size = path.stat().st_size
    if size > max_bytes:
        raise InputError(f"{size / 2**20:.0f} MiB is more than the {max_bytes / 2**20:.0f} MiB a {what} may have",
                         path=path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read the {what}: {exc.strerror or exc}", path=path) from None
    if data[:2] in (b"\xff\xfe", b"\xfe\xff"):
        raise InputError(f"UTF-16 encoded; save the {what} as UTF-8", path=path)
    if b"\x00" in data:
        raise InputError(f"binary data (NUL bytes), expected a UTF-8 {what}", path=path)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise InputError(f"not UTF-8 text (byte 0x{data[exc.start]:02x}; Latin-1? save the {what} as UTF-8)",
                         path=path, line=line) from None
    return text


def csv_rows(path, what: str = "CSV file") -> list:
    """All rows of a CSV file as lists of strings, after :func:`read_text_file`'s checks (InputError otherwise)."""
    path = Path(path)
    text = read_text_file(path, what)
    reader = csv.reader(text.splitlines())
    rows = list(csv_rows_checked(reader, path))
    for k, row in enumerate(rows, start=1):
        for c in row:
            if len(c) > MAX_FIELD_CHARS:
                raise InputError(f"a field of {len(c)} characters (more than {MAX_FIELD_CHARS})", path=path, line=k)
    return rows


def _read_rows(path):
    path = Path(path)
    text = read_text_file(path, "CSV file")
    lines = text.splitlines()
    if not lines or not any(ln.strip() for ln in lines):
        raise InputError("empty file", path=path)
    rows = []
    if max(map(len, lines)) > MAX_FIELD_CHARS * 8:
        for lineno, ln in enumerate(lines, start=1):
            if len(ln) > MAX_FIELD_CHARS * 8:
                raise InputError(f"line of {len(ln)} characters: not a psdcal CSV line", path=path, line=lineno)
    reader = csv.reader(lines)
    for lineno, row in enumerate(csv_rows_checked(reader, path), start=1):
        if not "".join(row).strip():
            continue  # blank line (no cell with more than white space)
        if row[0].lstrip().startswith("#"):
            continue  # comment
        cells = [c.strip() for c in row]
        if max(map(len, cells)) > MAX_FIELD_CHARS:
            for k, c in enumerate(cells):
                if len(c) > MAX_FIELD_CHARS:
                    raise InputError(f"field {k + 1} has {len(c)} characters (more than {MAX_FIELD_CHARS})",
                                     path=path, line=lineno)
        rows.append((lineno, cells))
    if not rows:
        raise InputError("empty file", path=path)
    return path, rows


def csv_rows_checked(reader, path, *, line_numbers: bool = False):
    """Rows of a ``csv.reader``; a malformed CSV (e.g. a field over the csv module's limit) or bytes that
    are not UTF-8 raise :class:`InputError` naming the line. With ``line_numbers``: ``(line, row)`` pairs."""
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            raise InputError(f"malformed CSV: {exc}", path=path, line=reader.line_num) from None
        except UnicodeDecodeError:
            raise InputError("not UTF-8 text", path=path, line=reader.line_num + 1) from None
        yield (reader.line_num, row) if line_numbers else row


def _header(path, rows, expected_options):
    lineno, head = rows[0]
    for expected in expected_options:
        if tuple(head) == expected:
            return expected
    exp = " or ".join(",".join(e) for e in expected_options)
    raise InputError(f"wrong header {','.join(head)!r}, expected {exp!r}", path=path, line=lineno)


def _ident(text, path, lineno, field):
    if text == "":
        raise InputError("empty identifier", path=path, line=lineno, field=field)
    try:
        return int(text)
    except ValueError:
        return text


def _number(text, path, lineno, field):
    try:
        v = float(text)
    except ValueError:
        raise InputError(f"not a number: {text!r}", path=path, line=lineno, field=field) from None
    if not math.isfinite(v):
        raise InputError(f"not a finite number: {text!r} (leave a missing point out instead)", path=path, line=lineno, field=field)
    return v


def read_template(path):
    """Read a template CSV.

    Returns
    -------
    point_ids : list (M,) of int or str
    xy_mm : (M, 2) ndarray
    """
    path, rows = _read_rows(path)
    _header(path, rows, [TEMPLATE_HEADER])
    ids, xy, seen = [], [], {}
    for lineno, row in rows[1:]:
        if len(row) != 3:
            raise InputError(f"expected 3 fields, got {len(row)}", path=path, line=lineno)
        pid = _ident(row[0], path, lineno, "point_id")
        if pid in seen:
            raise InputError(f"duplicate point_id {pid!r} (first on line {seen[pid]})", path=path, line=lineno, field="point_id")
        seen[pid] = lineno
        ids.append(pid)
        xy.append((_number(row[1], path, lineno, "X_mm"), _number(row[2], path, lineno, "Y_mm")))
    if len(ids) < 4:
        raise InputError(f"{len(ids)} template points; calibration needs at least 4", path=path)
    xy = np.array(xy)
    s = np.linalg.svd(xy - xy.mean(0), compute_uv=False)
    if s[1] <= 1e-9 * s[0]:
        raise InputError("all template points are collinear; a planar template needs points spread in 2D", path=path)
    return ids, xy


@dataclass(frozen=True)
class PointsFile:
    """The content of a points file, aligned with a template.

    Attributes
    ----------
    image_ids : list (n_images,)
    points_mm : (n_images, M, 2), NaN where missing
    amplitudes : (n_images, M, 4) or None, raw amplitudes when the file carries them
    line_numbers : (n_images, M) int, the line of each point in the file (0 if missing)
    kind : "points" | "amplitudes"
    """

    image_ids: list
    points_mm: np.ndarray
    amplitudes: np.ndarray | None
    line_numbers: np.ndarray
    kind: str
    path: str


def read_points(path, template_ids, *, sensor_mm=(LX_MM, LY_MM), check_on_sensor: bool = True) -> PointsFile:
    """Read an impact-points CSV (either format), aligned to ``template_ids``.

    Points off the sensor (``|x| > Lx/2`` or ``|y| > Ly/2``), unknown point
    ids, duplicate (image_id, point_id) pairs, NaN, and a zero signal sum
    (amplitude files) are errors naming the line.
    """
    path, rows = _read_rows(path)
    kind_header = _header(path, rows, [POINTS_HEADER, AMPLITUDES_HEADER])
    kind = "points" if kind_header == POINTS_HEADER else "amplitudes"
    nf = len(kind_header)
    col = {pid: j for j, pid in enumerate(template_ids)}
    images: dict = {}
    records = []
    for lineno, row in rows[1:]:
        if len(row) != nf:
            raise InputError(f"expected {nf} fields, got {len(row)}", path=path, line=lineno)
        iid = _ident(row[0], path, lineno, "image_id")
        pid = _ident(row[1], path, lineno, "point_id")
        if pid not in col:
            raise InputError(f"point_id {pid!r} is not in the template", path=path, line=lineno, field="point_id")
        try:
            vals = [float(c) for c in row[2:]]
        except ValueError:
            vals = None
        if vals is None or not all(map(math.isfinite, vals)):  # the error, naming the first field that is not a number
            vals = [_number(row[k], path, lineno, kind_header[k]) for k in range(2, nf)]
        images.setdefault(iid, len(images))
        records.append((lineno, iid, pid, vals))
    if not records:
        raise InputError("no data rows after the header", path=path)
    n, M = len(images), len(template_ids)
    pts = np.full((n, M, 2), np.nan)
    amps = np.full((n, M, 4), np.nan) if kind == "amplitudes" else None
    lines = np.zeros((n, M), dtype=int)
    hx, hy = sensor_mm[0] / 2, sensor_mm[1] / 2
    first: dict = {}  # (i, j) -> line: the duplicate check
    at_i, at_j, at_line, at_xy, at_amp = [], [], [], [], []  # put into the arrays at once, after the checks
    for lineno, iid, pid, vals in records:
        i, j = images[iid], col[pid]
        if (i, j) in first:
            raise InputError(
                f"duplicate point {pid!r} in image {iid!r} (first on line {first[i, j]})", path=path, line=lineno, field="point_id"
            )
        first[i, j] = lineno
        if kind == "amplitudes":
            v = np.array(vals)
            total = v.sum()
            if not abs(total) > 1e-12 * max(np.abs(v).max(), 1e-300):
                raise InputError("sum of the four signals is zero (no light or a dead channel)", path=path, line=lineno, field="vx1")
            at_amp.append(v)
            xy = impact_point(v, *sensor_mm)
        else:
            xy = vals  # two floats (a list: no array per row)
        if check_on_sensor:
            for k, (name, h) in enumerate(((kind_header[2] if kind == "points" else "x", hx), (kind_header[3] if kind == "points" else "y", hy))):
                if abs(xy[k]) > h * (1 + 1e-9):
                    raise InputError(
                        f"point ({xy[0]:.4g}, {xy[1]:.4g}) mm is off the {2 * hx:g} x {2 * hy:g} mm sensor",
                        path=path,
                        line=lineno,
                        field=name,
                    )
        at_i.append(i)
        at_j.append(j)
        at_line.append(lineno)
        at_xy.append(xy)
    lines[at_i, at_j] = at_line
    pts[at_i, at_j] = at_xy
    if amps is not None:
        amps[at_i, at_j] = at_amp
    return PointsFile(list(images), pts, amps, lines, kind, str(path))


def write_template(path, point_ids, xy_mm) -> None:
    """Write a template CSV atomically."""
    rows = [",".join(TEMPLATE_HEADER)]
    rows += [f"{pid},{x:.9f},{y:.9f}" for pid, (x, y) in zip(point_ids, np.asarray(xy_mm, dtype=float))]
    write_text_atomic(path, "\n".join(rows) + "\n")


def _write_per_point(path, header, image_ids, point_ids, values, fmt) -> None:
    """One row per (image, point) with finite ``values[i, j]`` (missing rows otherwise), atomically."""
    V = np.asarray(values, dtype=float)
    rows = [",".join(header)]
    for i, iid in enumerate(image_ids):
        for j, pid in enumerate(point_ids):
            if np.all(np.isfinite(V[i, j])):
                rows.append(f"{iid},{pid}," + ",".join(fmt.format(v) for v in V[i, j]))
    write_text_atomic(path, "\n".join(rows) + "\n")


def write_points(path, image_ids, point_ids, points_mm) -> None:
    """Write an impact-points CSV atomically; NaN points are left out (missing rows)."""
    _write_per_point(path, POINTS_HEADER, image_ids, point_ids, points_mm, "{:.12f}")


def write_amplitudes(path, image_ids, point_ids, amplitudes) -> None:
    """Write a raw-amplitude points CSV (``image_id,point_id,vx1,vx2,vy1,vy2``) atomically."""
    _write_per_point(path, AMPLITUDES_HEADER, image_ids, point_ids, amplitudes, "{:.12g}")


def write_json(path, obj) -> None:
    """Write JSON atomically (indented, NaN written as null)."""
    write_text_atomic(path, json_text(obj) + "\n")


def json_text(obj) -> str:
    """``json.dumps(obj, indent=2)`` with NaN and infinities as null, byte for byte (:func:`_json_reference`).

    Python's json module encodes indented output in pure Python (its C
    encoder writes only the compact form): this writer builds the same text
    with whole lists of plain floats joined at once, several times faster on a
    calibration file. Anything but str/int/float/bool/None, lists, tuples and
    dicts with string keys (numpy scalars, other key types) goes to the
    reference.
    """
    try:
        return _json_fast(obj, "")
    except _NotPlain:
        return _json_reference(obj)


def _json_reference(obj) -> str:
    """The reference of :func:`json_text`: the json module's indented encoder after :func:`_nan_to_none`."""
    import json

    return json.dumps(_nan_to_none(obj), indent=2)


class _NotPlain(Exception):
    """A value :func:`_json_fast` leaves to the json module."""


try:  # json.dumps' default string encoder (ensure_ascii): the C function json.encoder uses, without loading json
    from _json import encode_basestring_ascii as _json_str
except ImportError:  # pragma: no cover - an interpreter without the C accelerator
    from json.encoder import encode_basestring_ascii as _json_str
_float_repr = float.__repr__
_isfinite = math.isfinite


_NUMBERS = frozenset((int, float))


class _NotFinite(Exception):
    """A NaN or infinity in a row of :func:`_number_repr` (the row is written by the general path: null)."""


def _number_repr(v) -> str:
    """JSON of a finite float or an int (``repr`` of either, exactly as :func:`_json_fast` writes them)."""
    if v.__class__ is float and not _isfinite(v):
        raise _NotFinite
    return v.__repr__()


def _json_fast(o, ind: str) -> str:
    t = type(o)
    if t is float:
        return _float_repr(o) if _isfinite(o) else "null"
    if t is str:
        return _json_str(o)
    if o is None:
        return "null"
    if o is True:
        return "true"
    if o is False:
        return "false"
    if t is int:
        return int.__repr__(o)
    inner = ind + "  "
    sep = ",\n" + inner
    if t is list or t is tuple:
        if not o:
            return "[]"
        if all(type(v) is float for v in o) and all(map(_isfinite, o)):  # a numeric column: one join
            return "[\n" + inner + sep.join(map(_float_repr, o)) + "\n" + ind + "]"
        if type(o[0]) is list and all(type(v) is list and v and _NUMBERS.issuperset(map(type, v)) for v in o):
            # a table of numeric rows (the residuals, the points): each row joined at once
            sep2 = ",\n" + inner + "  "
            open_, close = "[\n" + inner + "  ", "\n" + inner + "]"
            try:
                rows = [open_ + sep2.join(map(_number_repr, v)) + close for v in o]
            except _NotFinite:
                pass
            else:
                return "[\n" + inner + sep.join(rows) + "\n" + ind + "]"
        parts = []
        for v in o:  # the scalars of a row inline (ints and floats), anything else by recursion
            tv = type(v)
            if tv is float:
                parts.append(_float_repr(v) if _isfinite(v) else "null")
            elif tv is int:
                parts.append(int.__repr__(v))
            else:
                parts.append(_json_fast(v, inner))
        return "[\n" + inner + sep.join(parts) + "\n" + ind + "]"
    if t is dict:
        if not o:
            return "{}"
        if not all(type(k) is str for k in o):
            raise _NotPlain
        return "{\n" + inner + sep.join([_json_str(k) + ": " + _json_fast(v, inner) for k, v in o.items()]) + "\n" \
            + ind + "}"
    raise _NotPlain


def _nan_to_none(o):
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, dict):
        return {k: _nan_to_none(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_nan_to_none(v) for v in o]
    return o


def read_json(path, what: str = "JSON file") -> dict:
    """Parse a UTF-8 JSON file; InputError with the file and line otherwise (NaN/Infinity are refused)."""
    path = Path(path)
    text = read_text_file(path, what)
    if not text.strip():
        raise InputError("empty file", path=path)

    import json

    def no_constant(name):
        raise ValueError(f"{name} is not JSON (write null)")

    try:
        return json.loads(text, parse_constant=no_constant)
    except json.JSONDecodeError as exc:
        raise InputError(f"invalid JSON: {exc.msg}", path=path, line=exc.lineno) from None
    except (ValueError, RecursionError) as exc:
        raise InputError(f"invalid JSON: {exc}", path=path) from None


def save_calibration(path, result) -> None:
    """Write a :class:`~psdcal.calibration.core.CalibrationResult` as calibration JSON (atomically)."""
    write_json(path, result.to_dict())


def load_calibration(path):
    """Read a calibration JSON into a :class:`~psdcal.calibration.core.CalibrationResult`."""
    from psdcal.calibration.core import CalibrationResult

    d = read_json(path, "calibration file")
    if not isinstance(d, dict) or "intrinsics" not in d:
        raise InputError("not a psdcal calibration: no 'intrinsics' key", path=path)
    validate_calibration_dict(d, path)
    return CalibrationResult.from_dict(d, source=str(path))


def _software_version_check(d, path):
    """InputError for a calibration written by a newer major version of psdcal; a warning string for a newer minor."""
    sw = d.get("software")
    if sw is None:
        return None
    if not isinstance(sw, dict):
        raise InputError("'software' must be an object", path=path, field="software")
    v = sw.get("version")
    if v is None:
        return None
    from psdcal import __version__

    def parse(text):
        out = []
        for part in str(text).split(".")[:3]:
            digits = "".join(ch for ch in part if ch.isdigit()) if part[:1].isdigit() else ""
            out.append(int(digits) if digits else 0)
        return tuple(out + [0] * (3 - len(out)))

    if not isinstance(v, str):
        raise InputError(f"'software.version' must be a string, got {v!r}", path=path, field="software.version")
    theirs, ours = parse(v), parse(__version__)
    if theirs[0] > ours[0]:
        raise InputError(f"written by psdcal {v}, a newer major version than this psdcal {__version__}: upgrade psdcal",
                         path=path, field="software.version")
    if theirs > ours:
        return f"{path}: written by psdcal {v}, newer than this psdcal {__version__}; fields it added are ignored"
    return None


def validate_calibration_dict(d: dict, path=None) -> None:
    """Check a calibration JSON's types and ranges (docs/model.md#calibration-json); InputError naming the key.

    A newer minor ``software.version`` is a warning (Python ``UserWarning``), a newer major one an error.
    """
    import warnings

    def bad(msg, key):
        return InputError(msg, path=path, field=key)

    def is_num(v):
        return _finite(v) is not None

    def need_obj(key, required=False):
        v = d.get(key)
        if v is None:
            if required:
                raise bad(f"missing object '{key}'", key)
            return {}
        if not isinstance(v, dict):
            raise bad(f"'{key}' must be an object, got {type(v).__name__}", key)
        return v

    intr = need_obj("intrinsics", True)
    for k in ("f_mm", "cx_mm", "cy_mm"):
        if k not in intr:
            raise bad(f"missing number '{k}'", f"intrinsics.{k}")
    for k, v in intr.items():
        if v is None and k not in ("f_mm", "cx_mm", "cy_mm"):
            continue
        if not is_num(v):
            raise bad(f"must be a finite number, got {_short(v)}", f"intrinsics.{k}")
    for k in ("f_mm", "fy_mm"):
        if k in intr and intr[k] is not None and not intr[k] > 0:
            raise bad(f"focal length must be positive, got {intr[k]!r}", f"intrinsics.{k}")
    for k, v in need_obj("distortion").items():
        if v is not None and not is_num(v):
            raise bad(f"must be a finite number, got {_short(v)}", f"distortion.{k}")
    for k, v in need_obj("sensor").items():
        if k in ("lx_mm", "ly_mm") and (not is_num(v) or v <= 0):
            raise bad(f"must be a positive number, got {_short(v)}", f"sensor.{k}")
    _check_model(need_obj("model"), bad)
    res = need_obj("residuals")
    if "points" in res and not isinstance(res["points"], dict):
        raise bad("'residuals.points' must be an object", "residuals.points")
    rows = res.get("points", {}).get("rows", []) if isinstance(res.get("points"), dict) else []
    if not isinstance(rows, list) or not all(
            isinstance(r, list) and len(r) >= 4 and all(_is_id(x) for x in r[:2])
            and all(x is None or is_num(x) for x in r[2:4]) for r in rows):
        raise bad("'residuals.points.rows' must be a list of [image_id, point_id, dx_mm, dy_mm]", "residuals.points.rows")
    for k in ("rms_mm", "cost_rms", "sigma_mm"):
        if res.get(k) is not None and not is_num(res[k]):
            raise bad(f"must be a finite number or null, got {_short(res[k])}", f"residuals.{k}")
    pir = res.get("per_image_rms_mm")
    if pir is not None and not (isinstance(pir, list) and all(x is None or is_num(x) for x in pir)):
        raise bad("must be a list of numbers", "residuals.per_image_rms_mm")
    ext = d.get("extrinsics", [])
    if not isinstance(ext, list) or not all(isinstance(e, dict) and _is_id(e.get("image_id")) for e in ext):
        raise bad("'extrinsics' must be a list of objects with image_id, rvec, tvec_mm", "extrinsics")
    for i, e in enumerate(ext):
        for k, n in (("rvec", 3), ("tvec_mm", 3)):
            v = e.get(k)
            if not (isinstance(v, list) and len(v) == n and all(is_num(x) for x in v)):
                raise bad(f"must be a list of {n} numbers", f"extrinsics[{i}].{k}")
        v = e.get("std")
        if v is not None and not (isinstance(v, list) and len(v) == 6 and all(x is None or is_num(x) for x in v)):
            raise bad("must be a list of 6 numbers (or null)", f"extrinsics[{i}].std")
    g = d.get("gains")
    if g is not None and not (isinstance(g, list) and len(g) == 4 and all(is_num(x) and x > 0 for x in g)):
        raise bad(f"'gains' must be 4 positive numbers, got {_short(g)}", "gains")
    std = need_obj("std")
    for k, v in std.items():
        if v is not None and (not is_num(v) or not v >= 0):
            raise bad(f"a standard error must be a non-negative number or null, got {_short(v)}", f"std.{k}")
    for k, types, what in (("iterations", int, "a whole number"), ("converged", bool, "true or false"),
                           ("cost", str, "a string"), ("message", str, "a string"), ("created", str, "a string"),
                           ("verdict", str, "a string"), ("checks", list, "a list"), ("stages", dict, "an object"),
                           ("problem", dict, "an object")):
        v = d.get(k)
        if v is not None and (not isinstance(v, types) or (types is int and (isinstance(v, bool) or v < 0))):
            raise bad(f"must be {what}, got {_short(v)}", k)
    cov = d.get("covariance")
    if cov is not None:
        if not isinstance(cov, dict) or not isinstance(cov.get("names"), list) or not isinstance(cov.get("matrix"), list):
            raise bad("'covariance' must be an object with a list 'names' and a list of lists 'matrix'", "covariance")
        names = cov["names"]
        if not all(isinstance(n, str) for n in names) or len(set(names)) != len(names):
            raise bad("'covariance.names' must be distinct strings", "covariance.names")
        try:
            m = np.array(cov["matrix"], dtype=float)
        except (TypeError, ValueError, OverflowError):
            raise bad("'covariance.matrix' must be a list of lists of numbers", "covariance.matrix") from None
        n = len(names)
        if m.shape != (n, n) and not (n == 0 and m.size == 0):
            raise bad(f"'covariance.matrix' must be {n}x{n}, got shape {m.shape}", "covariance.matrix")
        check_covariance(m, path, "covariance.matrix")
    check_plausible_distortion(intr, need_obj("distortion"), need_obj("sensor"), path)
    if "sensor_id" in d and d["sensor_id"] is not None and not isinstance(d["sensor_id"], str):
        raise bad(f"'sensor_id' must be a string, got {d['sensor_id']!r}", "sensor_id")
    w = _software_version_check(d, path)
    if w:
        warnings.warn(w, UserWarning, stacklevel=3)


def _finite(v):
    """``float(v)`` for a finite JSON number (not a bool); None otherwise (an integer too large is not finite)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    try:
        f = float(v)
    except OverflowError:
        return None
    return f if math.isfinite(f) else None


def _is_id(v) -> bool:
    """An image or point id as JSON writes one: a string or a whole number."""
    return isinstance(v, str) or (isinstance(v, int) and not isinstance(v, bool))


def _short(v) -> str:
    """``repr(v)``, cut to 40 characters (an error message stays one short line)."""
    r = repr(v)
    return r if len(r) <= 40 else r[:37] + "..."


def _check_model(m: dict, bad) -> None:
    """The calibration JSON's ``model`` object: counts of terms and switches."""
    for k, hi in (("radial", 3), ("psd_radial", 2)):
        v = m.get(k)
        if v is not None and not (_finite(v) is not None and 0 <= v <= hi and float(v).is_integer()):
            raise bad(f"must be a whole number 0..{hi}, got {_short(v)}", f"model.{k}")
    for k in ("tangential", "skew", "aspect", "fit_gains"):
        v = m.get(k)
        if v is not None and not isinstance(v, bool):
            raise bad(f"must be true or false, got {_short(v)}", f"model.{k}")


#: A distortion that moves a point of the sensor by more than this many sensor diagonals is not a lens.
MAX_DISTORTION_DIAGONALS = 10.0


def check_plausible_distortion(intr: dict, dist: dict, sensor: dict, path=None) -> None:
    """The distortion of a calibration JSON maps the sensor to a finite, plausible region.

    The undistortion (Eq 7-16) is evaluated on a 9 x 9 grid over the PSD: a
    non-finite point, or one moved by more than :data:`MAX_DISTORTION_DIAGONALS`
    sensor diagonals (``k1 = 1e300``: every sigma then overflows to NaN) is
    refused, naming the largest term.
    """
    from psdcal.model.distortion import undistort
    from psdcal.model.params import DISTORTION_NAMES

    lx = _finite(sensor.get("lx_mm", LX_MM)) or LX_MM
    ly = _finite(sensor.get("ly_mm", LY_MM)) or LY_MM
    coef = np.array([_finite(dist.get(n, 0.0)) or 0.0 for n in DISTORTION_NAMES])
    c = np.array([_finite(intr.get("cx_mm", 0.0)) or 0.0, _finite(intr.get("cy_mm", 0.0)) or 0.0])
    g = np.stack(np.meshgrid(np.linspace(-lx / 2, lx / 2, 9), np.linspace(-ly / 2, ly / 2, 9)), -1).reshape(-1, 2)
    with np.errstate(all="ignore"):
        x = undistort(g, coef, c)
        move = np.max(np.hypot(*(x - g).T))
    diag = math.hypot(lx, ly)
    if not (np.all(np.isfinite(x)) and move <= MAX_DISTORTION_DIAGONALS * diag):
        names = [n for n in DISTORTION_NAMES if dist.get(n)]
        worst = max(names, key=lambda n: abs(coef[DISTORTION_NAMES.index(n)]) * (diag / 2) ** (
            {"k1": 2, "k2": 4, "k3": 6, "p1": 1, "p2": 1, "l1": 2, "l2": 4}[n]), default="k1")
        amount = "to infinity" if not np.isfinite(move) else f"by {move:.3g} mm"
        raise InputError(f"implausible distortion: it moves points of the {lx:g} x {ly:g} mm sensor {amount} "
                         f"(more than {MAX_DISTORTION_DIAGONALS:g} sensor diagonals; {worst} = "
                         f"{coef[DISTORTION_NAMES.index(worst)]:.3g})", path=path, field=f"distortion.{worst}")


def check_covariance(m, path=None, field="covariance.matrix") -> None:
    """InputError unless ``m`` is a finite, symmetric, positive semi-definite matrix (relative tolerance 1e-9)."""
    m = np.asarray(m, dtype=float)
    if m.size == 0:
        return
    if not np.all(np.isfinite(m)):
        raise InputError("has non-finite entries (NaN or infinity)", path=path, field=field)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        scale = np.sqrt(np.abs(np.outer(np.diag(m), np.diag(m)))) + 1e-300
        symmetric = bool(np.allclose(m / scale, m.T / scale, atol=1e-6))
    if not symmetric:
        raise InputError("is not symmetric", path=path, field=field)
    if np.any(np.diag(m) < 0):
        raise InputError("has a negative variance on its diagonal", path=path, field=field)
    d = np.sqrt(np.diag(m))
    ok = d > 0
    if ok.any():
        c = m[np.ix_(ok, ok)] / np.outer(d[ok], d[ok])
        ev = np.linalg.eigvalsh(0.5 * (c + c.T))
        if ev.min() < -1e-8:
            raise InputError(f"is not positive semi-definite (smallest eigenvalue of the correlation {ev.min():.3g})",
                             path=path, field=field)


__all__ = [
    "PointsFile",
    "atomic_path",
    "load_calibration",
    "read_json",
    "read_text_file",
    "validate_calibration_dict",
    "read_points",
    "read_template",
    "save_calibration",
    "write_amplitudes",
    "write_json",
    "write_points",
    "write_template",
]
