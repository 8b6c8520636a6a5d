"""The electrical calibration as a file-to-file step (``psdcal gains``).

Spots at known positions on the bare PSD (lens removed) are read through the
electronics; :func:`psdcal.calibration.gains.calibrate_gains` fits the three
relative gains ``g_x2, g_y1, g_y2`` (``g_x1 = 1``) and their covariance
(companion paper, Sensors 2016, 16(5), 619).  This module reads the bench
files, writes and reads the gains JSON, and puts the gains into a
:class:`~psdcal.measure.sensor_model.SensorModel` so that ``locate`` and
``aoa`` correct the channels with them and carry their covariance into every
angle's uncertainty (``dd_dgains`` of :mod:`psdcal.measure.aoa`).

Gains JSON::

    {"kind": "psdcal-gains", "gains": [1, g_x2, g_y1, g_y2],
     "covariance": {"names": ["g_x2", "g_y1", "g_y2"], "matrix": [[...], ...]},
     "std": {"g_x2": ..., ...}, "rms_mm": ..., "n_spots": ..., "sensor": {"lx_mm": .., "ly_mm": ..},
     "per_carrier": [{"carrier_hz": f, "gains": [...], "covariance": {...}, ...}, ...]}   (FDM only)

With several carriers (a ``carrier_hz`` column in the amplitudes), a set of
gains is fitted per carrier: a transimpedance amplifier's gain depends on
frequency (Eq 43).
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from psdcal.errors import InputError

GAIN_NAMES = ("g_x2", "g_y1", "g_y2")
AMP_COLS = ("vx1", "vx2", "vy1", "vy2")


def _read_csv(path: Path):
    """Header and rows of a text CSV; the project's checked reader (no device, no binary, size and field limits)."""
    import io as _io

    from psdcal.io import csv_rows_checked, read_text_file

    text = read_text_file(path, "CSV file")
    rows = list(csv_rows_checked(csv.reader(_io.StringIO(text, newline="")), path))
    if not rows:
        raise InputError("empty file", path=path)
    return [h.strip() for h in rows[0]], rows[1:]


def _num(row, i, path, lineno, field):
    try:
        v = float(row[i])
    except (ValueError, IndexError):
        raise InputError(f"not a number: {row[i] if i < len(row) else ''!r}", path=path, line=lineno,
                         field=field) from None
    if not math.isfinite(v):
        raise InputError("not a finite number", path=path, line=lineno, field=field)
    return v


def read_positions(path) -> dict[str, np.ndarray]:
    """Known spot positions: CSV ``point_id,x_mm,y_mm`` -> {point_id: (2,) mm}."""
    path = Path(path)
    header, rows = _read_csv(path)
    for c in ("point_id", "x_mm", "y_mm"):
        if c not in header:
            raise InputError(f"missing column '{c}' (header must be point_id,x_mm,y_mm)", path=path, line=1, field=c)
    ip, ix, iy = (header.index(c) for c in ("point_id", "x_mm", "y_mm"))
    out: dict[str, np.ndarray] = {}
    for lineno, row in enumerate(rows, start=2):
        if not row or not any(c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(f"expected {len(header)} fields, found {len(row)}", path=path, line=lineno)
        pid = row[ip].strip()
        if pid in out:
            raise InputError(f"point_id {pid!r} given twice", path=path, line=lineno, field="point_id")
        out[pid] = np.array([_num(row, ix, path, lineno, "x_mm"), _num(row, iy, path, lineno, "y_mm")])
    if not out:
        raise InputError("no positions", path=path)
    return out


#: The spots the amplitudes give may differ from the positions by the gains' projective map, not by more
#: than this (largest element of ``A - I`` of the affine fit ``measured = A positions + b``).
MAX_POSITION_MAP_ERROR = 0.5


def check_spot_positions(spots_mm, amplitudes, lx_mm: float, ly_mm: float, path=None) -> None:
    """The known positions agree with the spots the amplitudes give (before the gains are fitted).

    Unequal gains move the measured spots by a mild projective map (a few %
    for a few % of imbalance).  An affine fit ``measured = A positions + b``
    shows what no gains explain: positions in another unit (``sqrt|det A|``
    far from 1: metres give 1000), x and y swapped or an axis mirrored
    (``det A < 0`` or an element of ``A - I`` above :data:`MAX_POSITION_MAP_ERROR`),
    a spot outside the PSD.

    Raises
    ------
    InputError
        Naming the positions file and what is wrong.
    """
    from psdcal.model.readout import impact_point

    p = np.asarray(spots_mm, dtype=float)
    half = np.array([lx_mm, ly_mm]) / 2
    out = np.flatnonzero(np.any(np.abs(p) > half, axis=1))
    if out.size:
        x, y = p[out[0]]
        raise InputError(f"spot at ({x:g}, {y:g}) mm is outside the {lx_mm:g} x {ly_mm:g} mm PSD (positions are "
                         "millimetres from the PSD's centre)", path=path, field="x_mm")
    if p.shape[0] < 4:
        return
    m = impact_point(np.asarray(amplitudes, dtype=float), lx_mm, ly_mm)
    design = np.c_[p, np.ones(len(p))]
    coef, *_ = np.linalg.lstsq(design, m, rcond=None)
    a = coef[:2].T  # measured ~ a @ p + b
    if np.linalg.matrix_rank(design) < 3 or not np.all(np.isfinite(a)):
        raise InputError("the spots are collinear: they cannot determine the gains", path=path, field="x_mm")
    det = float(np.linalg.det(a))
    scale = math.sqrt(abs(det))
    if not 0.2 < scale < 5.0:
        raise InputError(f"the spots the amplitudes give are {scale:.3g}x the positions: another unit? (x_mm, y_mm "
                         "are millimetres; positions in metres give 1000x)", path=path, field="x_mm")
    if np.abs(a - np.eye(2)).max() > MAX_POSITION_MAP_ERROR:
        r = np.round(a / scale, 2) + 0.0
        what = ("x and y swapped" if abs(r[0, 1]) > abs(r[0, 0]) and abs(r[1, 0]) > abs(r[1, 1]) and det < 0
                else "an axis mirrored" if det < 0 else "rotated or mislabelled")
        raise InputError(f"the positions do not match the spots the amplitudes give: measured = "
                         f"[[{r[0, 0]:g}, {r[0, 1]:g}], [{r[1, 0]:g}, {r[1, 1]:g}]] x positions ({what}; the gains "
                         f"only bend the spots by a few %)", path=path, field="x_mm")


def read_bench_amplitudes(path, positions: dict) -> dict:
    """Bench amplitudes -> {carrier_hz or None: (spots (n, 2) mm, amplitudes (n, 4))}.

    The CSV has ``vx1,vx2,vy1,vy2`` and a ``point_id`` (or ``emitter``)
    column naming the spot in the positions file; an optional ``carrier_hz``
    column splits the rows by carrier.  Several rows of one spot (and
    carrier) are averaged.
    """
    path = Path(path)
    header, rows = _read_csv(path)
    for c in AMP_COLS:
        if c not in header:
            raise InputError(f"missing column '{c}' (need vx1,vx2,vy1,vy2)", path=path, line=1, field=c)
    key = "point_id" if "point_id" in header else "emitter" if "emitter" in header else None
    if key is None:
        raise InputError("missing column 'point_id' (or 'emitter') naming the spot", path=path, line=1,
                         field="point_id")
    ik = header.index(key)
    ia = [header.index(c) for c in AMP_COLS]
    ic = header.index("carrier_hz") if "carrier_hz" in header else None
    acc: dict = {}
    for lineno, row in enumerate(rows, start=2):
        if not row or not any(c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(f"expected {len(header)} fields, found {len(row)}", path=path, line=lineno)
        pid = row[ik].strip()
        if pid not in positions:
            raise InputError(f"spot {pid!r} is not in the positions file", path=path, line=lineno, field=key)
        car = None if ic is None else _num(row, ic, path, lineno, "carrier_hz")
        a = np.array([_num(row, i, path, lineno, c) for i, c in zip(ia, AMP_COLS)])
        if not a.sum() > 0:
            raise InputError("the sum of the four amplitudes is not positive", path=path, line=lineno)
        acc.setdefault(car, {}).setdefault(pid, []).append(a)
    if not acc:
        raise InputError("no amplitude rows", path=path)
    out = {}
    for car, spots in acc.items():
        ids = sorted(spots)
        out[car] = (np.array([positions[i] for i in ids]), np.array([np.mean(spots[i], axis=0) for i in ids]))
    return out


def fit_bench(spots_mm, amplitudes, lx_mm: float = 9.0, ly_mm: float = 9.0):
    """Relative gains from amplitudes of spots at known positions (a :class:`GainCalibration`)."""
    from psdcal.calibration.gains import calibrate_gains
    from psdcal.model.readout import impact_point

    spots = np.asarray(spots_mm, dtype=float)
    if spots.shape[0] < 4:
        raise InputError(f"the electrical calibration needs at least 4 spots, got {spots.shape[0]}", field="point_id")
    measured = impact_point(np.asarray(amplitudes, dtype=float), lx_mm, ly_mm)
    return calibrate_gains(spots, measured, lx_mm, ly_mm)


def _entry(gc) -> dict:
    return {
        "gains": [float(v) for v in gc.gains],
        "covariance": {"names": list(GAIN_NAMES), "matrix": np.asarray(gc.covariance, dtype=float).tolist()},
        "std": dict(zip(GAIN_NAMES, (float(v) for v in gc.std))),
        "rms_mm": float(gc.rms_mm),
        "n_spots": int(gc.n_spots),
        "converged": bool(gc.converged),
    }


def gains_document(fits: dict, lx_mm: float, ly_mm: float) -> dict:
    """The gains JSON (module docstring) from {carrier_hz or None: GainCalibration}."""
    keys = sorted(fits, key=lambda k: -1.0 if k is None else k)
    main = fits[keys[0]]
    doc = {"kind": "psdcal-gains", **_entry(main), "sensor": {"lx_mm": float(lx_mm), "ly_mm": float(ly_mm)}}
    if len(fits) > 1 or keys[0] is not None:
        doc["per_carrier"] = [{"carrier_hz": float(k), **_entry(fits[k])} for k in keys if k is not None]
    return doc


def load_gains(path, carrier_hz: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read a gains JSON: ``(gains (4,), covariance (3, 3) of g_x2, g_y1, g_y2)``.

    With ``carrier_hz`` and a ``per_carrier`` list, the entry of that carrier
    (within 0.5 %) is used; a carrier not in the list is an error.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("gains file not found", path=path) from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"not a JSON file ({type(exc).__name__})", path=path) from None
    if not isinstance(data, dict) or data.get("kind") != "psdcal-gains":
        raise InputError("not a gains file (no \"kind\": \"psdcal-gains\"; make one with 'psdcal gains')", path=path)
    entry = data
    per = data.get("per_carrier")
    if carrier_hz is not None and per:
        if not isinstance(per, list):
            raise InputError("'per_carrier' must be a list", path=path, field="per_carrier")
        match = [e for e in per if isinstance(e, dict) and isinstance(e.get("carrier_hz"), (int, float))
                 and abs(e["carrier_hz"] - carrier_hz) <= 5e-3 * carrier_hz]
        if not match:
            have = [e.get("carrier_hz") for e in per if isinstance(e, dict)]
            raise InputError(f"no gains for the {carrier_hz:g} Hz carrier (the file has {have})", path=path,
                             field="per_carrier")
        entry = match[0]
    return check_gains_entry(entry, path)


def check_gains_entry(entry, path=None) -> tuple[np.ndarray, np.ndarray]:
    """One gains entry ``{gains, covariance: {names, matrix}}`` checked: ``(gains / gains[0], covariance)``.

    The rules ``locate/aoa --gains`` read a gains file by; ``psdcal gains`` applies them to what it is
    about to write (a file it writes is one they read).

    Raises
    ------
    InputError
        Naming ``path`` and the field.
    """
    try:
        g = np.asarray(entry["gains"], dtype=float)
        cov = np.asarray(entry["covariance"]["matrix"], dtype=float)
        names = list(entry["covariance"]["names"])
    except (KeyError, TypeError, ValueError):
        raise InputError("'gains' (4 numbers) and 'covariance' {names, matrix} are required", path=path,
                         field="gains") from None
    if g.shape != (4,) or not np.all(np.isfinite(g)) or np.any(g <= 0):
        raise InputError(f"'gains' must be 4 positive numbers, got {entry['gains']!r}", path=path, field="gains")
    if names != list(GAIN_NAMES) or cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
        raise InputError(f"'covariance' must be 3x3 over {list(GAIN_NAMES)}", path=path, field="covariance")
    if not np.allclose(cov, cov.T, rtol=1e-9, atol=0) or np.linalg.eigvalsh(0.5 * (cov + cov.T)).min() < 0:
        raise InputError("'covariance' is not symmetric positive semi-definite", path=path, field="covariance")
    return g / g[0], cov


def with_gains(model, gains, cov_gains):
    """A copy of a SensorModel using bench ``gains`` (4,) and their covariance (3, 3).

    The gain names replace any in the calibration's covariance; the bench
    measurement is independent of the geometric calibration, so the new
    covariance is block diagonal.
    """
    import dataclasses

    keep = [i for i, n in enumerate(model.names) if n not in GAIN_NAMES]
    names = tuple(model.names[i] for i in keep) + GAIN_NAMES
    k = len(keep)
    cov = np.zeros((k + 3, k + 3))
    cov[:k, :k] = np.asarray(model.covariance)[np.ix_(keep, keep)]
    cov[k:, k:] = np.asarray(cov_gains, dtype=float)
    # the model's own class (a SensorModel, psdcal.measure): a copy with the bench gains
    return dataclasses.replace(model, names=names, covariance=cov, gains=np.asarray(gains, dtype=float))
