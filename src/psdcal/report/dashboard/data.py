"""What the dashboard shows, read from the files the commands write.

Rows (one CSV line each) become compact lists, the form the page receives:

``positions``  (``psdcal locate --sensors`` rows, :data:`MULTI_COLUMNS`)
    ``[t_s, emitter, X_mm, Y_mm, Z_mm, sigma_X_mm, sigma_Y_mm, sigma_Z_mm, n_sensors, chi2, flag]``
``tracks``     (``psdcal track`` / ``locate --track`` rows)
    ``[t_s, emitter, X_mm, Y_mm, Z_mm, sigma_X_mm, sigma_Y_mm, sigma_Z_mm, gated]``
``sensor``     (one sensor's ``locate`` angles or ``amplitudes`` rows, ``--sensor-rows NAME=FILE``)
    ``[t_s, sensor, emitter, snr, chi2, angles]`` (``snr`` from amplitude rows, ``chi2``
    of the sensor's angles against the located position, 2 dof; ``angles`` =
    ``[alpha_x_deg, alpha_y_deg, sigma_alpha_x_deg, sigma_alpha_y_deg]`` from
    angle rows, the page draws the ray; None when unknown)

``flag`` is 1 when the row's chi2 exceeds the 99.9 % quantile of chi2 with
``2 n_sensors - 3`` degrees of freedom (:data:`psdcal._consistency.ALPHA`).
A single flagged row is drawn in red; a *warning* is raised only when
:data:`RUN` rows of the same emitter in a row are flagged (false-alarm rate
``ALPHA ** RUN`` = 1e-9 per row on correct data), so that a room running for
hours does not cry wolf every few seconds.
"""
from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from psdcal._consistency import ALPHA
from psdcal._stats import chi2_isf
from psdcal.errors import InputError

#: Consecutive flagged rows of one emitter (or sensor) that raise a warning.
RUN = 3

POSITION_KEYS = ("X_mm", "Y_mm", "Z_mm", "sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm")


def _chi2_limit(dof: int) -> float:
    return _LIMITS.setdefault(dof, float(chi2_isf(ALPHA, dof)))


_LIMITS: dict = {}


def kind_of(header: list) -> str | None:
    """``positions``, ``tracks``, ``angles``, ``amplitudes`` or None, from a CSV header."""
    h = set(header)
    if {"t_s", "emitter"} - h:
        return None
    if {"vX_mm_s", "gated", *POSITION_KEYS} <= h:
        return "tracks"
    if set(POSITION_KEYS) <= h:
        return "positions"
    if {"alpha_x_deg", "alpha_y_deg", "sigma_alpha_x_deg", "sigma_alpha_y_deg"} <= h:
        return "angles"
    if {"vx1", "vx2", "vy1", "vy2", "sigma_vx1", "sigma_vx2", "sigma_vy1", "sigma_vy2"} <= h:
        return "amplitudes"
    return None


def _num(v):
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


@dataclass
class Warner:
    """Raise one warning per run of :data:`RUN` flagged rows of one key (emitter or sensor)."""

    runs: dict = field(default_factory=dict)

    def see(self, key, flagged: bool) -> bool:
        n = self.runs.get(key, 0) + 1 if flagged else 0
        self.runs[key] = n
        return n == RUN


class RowParser:
    """Turns the lines of one followed CSV into records (see the module docstring).

    Parameters
    ----------
    role : str
        ``rows`` (positions or tracks, found from the header) or ``sensor``.
    sensor : str
        The sensor's name for ``sensor`` rows.
    source : str
        Shown in warnings (the file name).
    """

    def __init__(self, role: str, *, sensor: str = "", source: str = ""):
        self.role, self.sensor, self.source = role, sensor, source
        self.header: list | None = None
        self.kind: str | None = None
        self.warner = Warner()
        self.gated_run: dict = {}
        self.bad_lines = 0

    def reset(self) -> None:
        self.header, self.kind = None, None

    def feed(self, lines) -> dict:
        """Records of ``lines``: ``{"positions": [...], "tracks": [...], "sensor": [...], "warnings": [...]}``."""
        out = {"positions": [], "tracks": [], "sensor": [], "warnings": []}
        for line in lines:
            if not line.strip():
                continue
            try:
                cells = next(csv.reader([line]))
            except csv.Error:  # a stray CR or NUL inside a line: no row of psdcal's
                cells = [None]
            if self.header is None:
                self.header, self.kind = cells, kind_of(cells)
                if self.kind is None:
                    out["warnings"].append(_warn(None, self.source, f"{self.source}: not a psdcal rows CSV (header "
                                                                    f"{','.join(cells[:6])}...): ignored"))
                continue
            if self.kind is None or len(cells) != len(self.header):
                self.bad_lines += 1
                continue
            row = dict(zip(self.header, cells))
            t = _num(row["t_s"])
            if t is None:
                self.bad_lines += 1
                continue
            getattr(self, "_" + self.kind)(t, row, out)
        return out

    def _positions(self, t, row, out):
        em = row["emitter"]
        v = [_num(row[k]) for k in POSITION_KEYS]
        if any(x is None for x in v):
            return
        n = _num(row.get("n_sensors"))
        chi2 = _num(row.get("chi2"))
        dof = 2 * int(n) - 3 if n is not None else 0
        flag = int(chi2 is not None and dof >= 1 and chi2 > _chi2_limit(dof))
        out["positions"].append([t, em, *v, None if n is None else int(n), chi2, flag])
        if self.warner.see(em, bool(flag)):
            out["warnings"].append(_warn(t, self.source, f"{em}: chi2 of the sensors' rays above its 99.9 % quantile "
                                                         f"({chi2:.3g} for {dof} dof) {RUN} windows in a row: a "
                                                         "reflection, a moved sensor or a wrong pose"))

    def _tracks(self, t, row, out):
        em = row["emitter"]
        v = [_num(row[k]) for k in POSITION_KEYS]
        if any(x is None for x in v):
            return
        gated = int(_num(row.get("gated")) or 0)
        out["tracks"].append([t, em, *v, gated])
        run = self.gated_run.get(em, 0) + 1 if gated else 0
        self.gated_run[em] = run
        if run == 1:
            out["warnings"].append(_warn(t, self.source, f"{em}: measurement gated by the tracker (not used)"))
        elif run == 5:
            out["warnings"].append(_warn(t, self.source, f"{em}: 5 measurements gated in a row: the track restarts"))

    def _angles(self, t, row, out):
        a = [_num(row[k]) for k in ("alpha_x_deg", "alpha_y_deg", "sigma_alpha_x_deg", "sigma_alpha_y_deg")]
        if any(x is None for x in a):
            return
        out["sensor"].append([t, self.sensor, row["emitter"], None, None, a])

    def _amplitudes(self, t, row, out):
        v = [_num(row[k]) for k in ("vx1", "vx2", "vy1", "vy2")]
        s = [_num(row[k]) for k in ("sigma_vx1", "sigma_vx2", "sigma_vy1", "sigma_vy2")]
        if any(x is None for x in v + s):
            return
        noise = math.sqrt(sum(x * x for x in s))
        snr = sum(v) / noise if noise > 0 else None
        out["sensor"].append([t, self.sensor, row["emitter"], snr, None, None])


def _warn(t, source, text, level="warning"):
    """``[t_s or None, t_unix or None, source, level, text]``."""
    return [t, None, source, level, text]


class SensorChi2:
    """Each sensor's angles against the located positions: chi2 with 2 dof per (window, emitter).

    The position comes from all sensors, this one included, so the chi2 is a
    little below chi2(2) on correct data: the 99.9 % limit of chi2(2) is a
    conservative test (fewer false alarms, not more).
    """

    def __init__(self):
        self.poses: dict = {}  # name -> (R, t)
        self.positions: dict = {}  # (t rounded, emitter) -> P_w (3,)
        self.pending: dict = {}  # (t rounded, emitter) -> list of sensor records waiting for their position
        self.warner = Warner()

    @staticmethod
    def key(t, em):
        return (round(t, 6), em)

    def add_positions(self, recs) -> list:
        """Store positions; returns the sensor records now resolved (chi2 filled in)."""
        done = []
        for r in recs:
            k = self.key(r[0], r[1])
            self.positions[k] = np.array(r[2:5])
            for s in self.pending.pop(k, ()):
                c = self._chi2(s)
                if c is not None:  # a new record: the pending one was sent already without its chi2
                    done.append([s[0], s[1], s[2], None, c, None])
        self._trim()
        return done

    def add_sensor(self, recs) -> None:
        for s in recs:
            if s[5] is None:
                continue
            k = self.key(s[0], s[2])
            if k in self.positions:
                s[4] = self._chi2(s)
            else:
                self.pending.setdefault(k, []).append(s)
        self._trim()

    def _chi2(self, s):
        """chi2 (2 dof) of sensor record ``s``'s angles against the stored position, or None."""
        pose = self.poses.get(s[1])
        p = self.positions.get(self.key(s[0], s[2]))
        if pose is None or p is None:
            return None
        R, t = pose
        pc = R @ p + t
        ax, ay, sx, sy = s[5]
        if pc[2] <= 0 or sx <= 0 or sy <= 0:
            return None
        px, py = math.degrees(math.atan(pc[0] / pc[2])), math.degrees(math.atan(pc[1] / pc[2]))
        return ((ax - px) / sx) ** 2 + ((ay - py) / sy) ** 2

    def _trim(self, keep: int = 20000):
        for d in (self.positions, self.pending):
            while len(d) > keep:
                d.pop(next(iter(d)))

    def warnings(self, recs, source="") -> list:
        out = []
        lim = _chi2_limit(2)
        for s in recs:
            if s[4] is not None and self.warner.see((s[1], s[2]), s[4] > lim):
                out.append(_warn(s[0], source, f"sensor {s[1]}: its angles disagree with the other sensors' position of "
                                               f"{s[2]} (chi2 {s[4]:.3g} for 2 dof, {RUN} windows in a row): a "
                                               "reflection into this sensor, or it moved"))
        return out


def event_record(line: str, source: str):
    """A warning record from one line of a ``psdcal --events`` log, or None."""
    try:
        obj = json.loads(line)
    except ValueError:
        return None
    if not isinstance(obj, dict) or "text" not in obj:
        return None
    t_unix = obj.get("t_unix") if isinstance(obj.get("t_unix"), (int, float)) else None
    return [None, t_unix, f"{obj.get('command') or source}", str(obj.get("level", "warning")), str(obj["text"])]


# -- the room: sensors, surveyed emitters, the planner's map ------------------------------------------------------
def _fov_corners_mm(pose, reach_mm: float) -> list:
    """World points of the four corner rays of the sensor's field of view, cut at the floor or at ``reach_mm``."""
    m = pose.model
    f, fy = m.intrinsics.f_mm, m.intrinsics.fy
    cx, cy = m.intrinsics.cx_mm, m.intrinsics.cy_mm
    R = pose.R
    c = pose.center_w_mm
    out = []
    for x, y in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        d = R.T @ np.array([(x * m.lx_mm / 2 - cx) / f, (y * m.ly_mm / 2 - cy) / fy, 1.0])
        d /= np.linalg.norm(d)
        s = reach_mm
        if d[2] < -1e-9 and c[2] > 0:
            s = min(s, -c[2] / d[2])
        out.append((c + s * d).tolist())
    return out


def read_sensors(path, reach_mm: float = 8000.0) -> list:
    """The sensors of a sensors file (:func:`psdcal.measure.positioning.load_sensors`) as the page draws them.

    Returns a list of dicts: ``name``, ``center_mm`` (3), ``axis_mm`` (a point
    1 m along the optical axis), ``fov_mm`` (4 x 3 corner points),
    ``verdict`` (the calibration's verdict or None), ``calib`` (file name),
    ``R`` and ``t`` (world -> camera) for the chi2 of each sensor's angles.
    """
    from psdcal.io import read_json
    from psdcal.measure.positioning import load_sensors

    poses = _single_sensor(path) or load_sensors(path)
    out = []
    for p in poses:
        verdict = None
        if p.model.source:
            try:
                cal = read_json(Path(p.model.source), "calibration")
                verdict = cal.get("verdict") if isinstance(cal, dict) else None
            except Exception:  # noqa: BLE001 - a verdict is optional; load_sensors already read the file
                verdict = None
        c = p.center_w_mm
        axis = c + 1000.0 * (p.R.T @ np.array([0.0, 0.0, 1.0]))
        out.append({"name": p.name, "center_mm": c.tolist(), "axis_mm": axis.tolist(),
                    "fov_mm": _fov_corners_mm(p, reach_mm), "verdict": verdict if isinstance(verdict, str) else None,
                    "calib": Path(p.model.source).name if p.model.source else None,
                    "R": p.R.tolist(), "t": np.asarray(p.tvec_mm, dtype=float).tolist()})
    return out


def _single_sensor(path):
    """A sensors file of ONE sensor (live input is one sensor; `load_sensors` wants two to triangulate), or None."""
    from psdcal.io import read_json
    from psdcal.measure.positioning import SensorPose, pose_vectors
    from psdcal.measure.sensor_model import SensorModel

    path = Path(path)
    data = read_json(path, "sensors file")
    items = data.get("sensors") if isinstance(data, dict) else data
    if not isinstance(items, list) or len(items) != 1 or not isinstance(items[0], dict):
        return None
    item = items[0]
    for key in ("calib", "rvec", "tvec_mm"):
        if key not in item:
            raise InputError(f"missing key '{key}'", path=path, field=f"sensors[0].{key}")
    vecs = pose_vectors(item, path, "sensors[0]")
    model = SensorModel.load(path.parent / str(item["calib"]))
    return [SensorPose(name=str(item.get("name", "s1")), model=model, rvec=vecs["rvec"], tvec_mm=vecs["tvec_mm"])]


def read_emitters(path) -> list:
    """Surveyed emitters ``emitter,X_m,Y_m,Z_m[,...]`` as ``[{"name", "pos_mm"}]``."""
    path = Path(path)
    with open(path, encoding="utf-8", newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise InputError("empty emitters file", path=path)
    head = [h.strip() for h in rows[0]]
    need = ("emitter", "X_m", "Y_m", "Z_m")
    missing = [k for k in need if k not in head]
    if missing:
        raise InputError(f"missing column(s) {missing} (expected emitter,X_m,Y_m,Z_m)", path=path, field=missing[0])
    idx = [head.index(k) for k in need]
    out = []
    for i, r in enumerate(rows[1:], start=2):
        if not r or not any(c.strip() for c in r):
            continue
        vals = [_num(r[j]) if j < len(r) else None for j in idx[1:]]
        if any(v is None for v in vals):
            raise InputError("X_m, Y_m, Z_m must be finite numbers", path=path, line=i)
        out.append({"name": r[idx[0]], "pos_mm": [1000.0 * v for v in vals]})
    return out


def read_plan(path) -> dict:
    """``psdcal plan --csv`` output as a grid for a heat map: ``x_mm, y_mm, z_mm, sigma_mm (rows of x), n_sensors``."""
    path = Path(path)
    with open(path, encoding="utf-8", newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows or not {"X_m", "Y_m", "sigma_mm", "n_sensors"} <= set(rows[0]):
        raise InputError("not a `psdcal plan --csv` file (columns X_m,Y_m,Z_m,n_sensors,sigma_mm)", path=path)
    xs = sorted({float(r["X_m"]) for r in rows})
    ys = sorted({float(r["Y_m"]) for r in rows})
    sig = [[None] * len(xs) for _ in ys]
    cov = [[0] * len(xs) for _ in ys]
    ix, iy = {x: i for i, x in enumerate(xs)}, {y: i for i, y in enumerate(ys)}
    for r in rows:
        i, j = iy[float(r["Y_m"])], ix[float(r["X_m"])]
        sig[i][j] = _num(r["sigma_mm"])
        cov[i][j] = int(_num(r["n_sensors"]) or 0)
    return {"x_mm": [1000 * x for x in xs], "y_mm": [1000 * y for y in ys], "sigma_mm": sig, "n_sensors": cov,
            "z_mm": 1000 * float(rows[0].get("Z_m") or 0)}
