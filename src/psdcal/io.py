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
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psdcal._atomic import atomic_path, write_text_atomic
from psdcal.errors import InputError
from psdcal.model.readout import LX_MM, LY_MM, impact_point

TEMPLATE_HEADER = ("point_id", "X_mm", "Y_mm")
POINTS_HEADER = ("image_id", "point_id", "x_mm", "y_mm")
AMPLITUDES_HEADER = ("image_id", "point_id", "vx1", "vx2", "vy1", "vy2")


def _read_rows(path):
    path = Path(path)
    if not path.exists():
        raise InputError("file not found", path=path)
    if path.is_dir():
        raise InputError("is a directory, expected a CSV file", path=path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputError("not a text (UTF-8) CSV file", path=path) from None
    lines = text.splitlines()
    if not lines or not any(ln.strip() for ln in lines):
        raise InputError("empty file", path=path)
    reader = csv.reader(lines)
    rows = []
    for lineno, row in enumerate(reader, start=1):
        if not row or all(not c.strip() for c in row):
            continue  # blank line
        if row[0].lstrip().startswith("#"):
            continue  # comment
        rows.append((lineno, [c.strip() for c in row]))
    if not rows:
        raise InputError("empty file", path=path)
    return path, rows


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
    for lineno, iid, pid, vals in records:
        i, j = images[iid], col[pid]
        if lines[i, j]:
            raise InputError(
                f"duplicate point {pid!r} in image {iid!r} (first on line {lines[i, j]})", path=path, line=lineno, field="point_id"
            )
        lines[i, j] = lineno
        if kind == "amplitudes":
            v = np.array(vals)
            total = v.sum()
            if not abs(total) > 1e-12 * max(np.abs(v).max(), 1e-300):
                raise InputError("sum of the four signals is zero (no light or a dead channel)", path=path, line=lineno, field="vx1")
            amps[i, j] = v
            xy = impact_point(v, *sensor_mm)
        else:
            xy = np.array(vals)
        if check_on_sensor:
            for k, (name, h) in enumerate(((kind_header[2] if kind == "points" else "x", hx), (kind_header[3] if kind == "points" else "y", hy))):
                if abs(xy[k]) > h * (1 + 1e-9):
                    raise InputError(
                        f"point ({xy[0]:.4g}, {xy[1]:.4g}) mm is off the {2 * hx:g} x {2 * hy:g} mm sensor",
                        path=path,
                        line=lineno,
                        field=name,
                    )
        pts[i, j] = xy
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
    write_text_atomic(path, json.dumps(_nan_to_none(obj), indent=2) + "\n")


def _nan_to_none(o):
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, dict):
        return {k: _nan_to_none(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_nan_to_none(v) for v in o]
    return o


def read_json(path) -> dict:
    path = Path(path)
    if not path.exists():
        raise InputError("file not found", path=path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError("not a UTF-8 JSON file", path=path) from None
    if not text.strip():
        raise InputError("empty file", path=path)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"invalid JSON: {exc.msg}", path=path, line=exc.lineno) from None


def save_calibration(path, result) -> None:
    """Write a :class:`~psdcal.calibration.core.CalibrationResult` as calibration JSON (atomically)."""
    write_json(path, result.to_dict())


def load_calibration(path):
    """Read a calibration JSON into a :class:`~psdcal.calibration.core.CalibrationResult`."""
    from psdcal.calibration.core import CalibrationResult

    d = read_json(path)
    if not isinstance(d, dict) or "intrinsics" not in d:
        raise InputError("not a psdcal calibration: no 'intrinsics' key", path=path)
    return CalibrationResult.from_dict(d, source=str(path))


__all__ = [
    "PointsFile",
    "atomic_path",
    "load_calibration",
    "read_json",
    "read_points",
    "read_template",
    "save_calibration",
    "write_amplitudes",
    "write_json",
    "write_points",
    "write_template",
]
