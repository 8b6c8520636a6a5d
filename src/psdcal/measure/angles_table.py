"""Angle tables from any angle-of-arrival front-end (docs/guide/selfcal.md#the-angles-table).

One row per observation: when (``t_s``), which sensor saw which emitter
(``sensor``, ``emitter``), two angles and their uncertainty. The front-end's
angle convention is declared (an argument, a ``# convention: NAME`` comment
line before the header, or recognised from the angle columns' names) and the
angles are converted to psdcal's normalised direction ``n = (Xc/Zc, Yc/Zc)``
in the sensor's camera frame (docs/model.md#signs-in-the-room-the-lens-inverts-the-image:
``Xc`` right, ``Yc`` down, ``Zc`` forward, seen from behind the sensor), with
its covariance by first-order propagation.

Conventions (angle columns end in ``_deg`` or ``_rad``; their sigmas are
``sigma_<column>`` in the same unit; an optional ``corr`` column is the
correlation of the two angles):

``psdcal``: ``alpha_x, alpha_y``
    psdcal's own angles (``psdcal aoa``/``locate``): ``alpha = atan(n)``, so
    ``n = (tan alpha_x, tan alpha_y)``.
``azel``: ``azimuth, elevation``
    In a sensor frame ``x`` forward (the optical axis), ``y`` left, ``z`` up:
    the ray is ``(cos el cos az, cos el sin az, sin el)``; azimuth positive to
    the left (right-handed about ``z`` up), elevation positive up. Hence
    ``n = (-tan az, -tan el / cos az)``.
``tangent`` (alias ``lighthouse``): ``h, v``
    Tangent pairs such as a Lighthouse base station's sweep angles: in the
    frame ``x`` forward, ``y`` left, ``z`` up the ray is ``(1, tan h, tan v)``;
    hence ``n = (-tan h, -tan v)``.

The camera frame of ``azel`` and ``tangent`` is the sensor frame turned so
that ``Zc = x``, ``Xc = -y``, ``Yc = -z`` (:data:`R_CAMERA_FROM_XFWD`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psdcal.errors import InputError

#: The two angle columns (without their unit suffix) of each convention.
CONVENTIONS = {"psdcal": ("alpha_x", "alpha_y"), "azel": ("azimuth", "elevation"), "tangent": ("h", "v")}
#: Other names accepted for a convention.
ALIASES = {"lighthouse": "tangent", "alpha": "psdcal", "azimuth-elevation": "azel"}
#: Rotation from a sensor frame x forward, y left, z up into psdcal's camera frame (x right, y down, z forward).
R_CAMERA_FROM_XFWD = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
#: Columns every angles table has (the names can be remapped with ``columns=``).
KEY_COLUMNS = ("t_s", "sensor", "emitter")


@dataclass(frozen=True)
class AnglesTable:
    """Observations of emitters by sensors as normalised directions.

    Attributes
    ----------
    t_s : (N,) ndarray
        Time of each observation, s.
    sensor, emitter : (N,) ndarrays of str
    n : (N, 2) ndarray
        Normalised direction ``(Xc/Zc, Yc/Zc)`` in the sensor's camera frame.
    cov_n : (N, 2, 2) ndarray
        Its covariance.
    convention : str
        The front-end's convention the angles were read in.
    path : str or None
    line : (N,) int ndarray
        Line of each row in the file (header = 1); 0 for rows made in memory.
    """

    t_s: np.ndarray
    sensor: np.ndarray
    emitter: np.ndarray
    n: np.ndarray
    cov_n: np.ndarray
    convention: str = "psdcal"
    path: str | None = None
    line: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def sensors(self) -> list:
        """Sensor names, sorted."""
        return sorted(set(self.sensor.tolist()))

    @property
    def emitters(self) -> list:
        """Emitter names, sorted."""
        return sorted(set(self.emitter.tolist()))

    def subset(self, mask) -> AnglesTable:
        """The rows where ``mask`` (bool or index array) holds."""
        line = None if self.line is None else self.line[mask]
        return AnglesTable(self.t_s[mask], self.sensor[mask], self.emitter[mask], self.n[mask], self.cov_n[mask],
                           self.convention, self.path, line)


def canonical_convention(name: str, *, path=None) -> str:
    """The convention's canonical name; InputError naming the known ones otherwise."""
    key = str(name).strip().lower()
    key = ALIASES.get(key, key)
    if key not in CONVENTIONS:
        known = ", ".join(list(CONVENTIONS) + list(ALIASES))
        raise InputError(f"unknown angle convention {name!r} (known: {known})", path=path, field="convention")
    return key


def n_from_angles(angles_rad, convention: str):
    """Normalised directions and their Jacobian from two angles.

    Parameters
    ----------
    angles_rad : (..., 2) array_like
        The two angles of the convention, rad.
    convention : str
        ``psdcal``, ``azel`` or ``tangent`` (see the module's docstring).

    Returns
    -------
    n : (..., 2) ndarray
    dn_da : (..., 2, 2) ndarray
        ``d n / d angles``, per rad.
    """
    conv = canonical_convention(convention)
    a = np.asarray(angles_rad, dtype=float)
    a1, a2 = a[..., 0], a[..., 1]
    J = np.zeros(a.shape[:-1] + (2, 2))
    if conv == "psdcal":
        n = np.tan(a)
        J[..., 0, 0] = 1.0 + n[..., 0] ** 2
        J[..., 1, 1] = 1.0 + n[..., 1] ** 2
    elif conv == "tangent":
        n = -np.tan(a)
        J[..., 0, 0] = -(1.0 + n[..., 0] ** 2)
        J[..., 1, 1] = -(1.0 + n[..., 1] ** 2)
    else:  # azel
        ca = np.cos(a1)
        te = np.tan(a2)
        n = np.stack([-np.tan(a1), -te / ca], axis=-1)
        J[..., 0, 0] = -1.0 / ca**2
        J[..., 1, 0] = -te * np.tan(a1) / ca
        J[..., 1, 1] = -(1.0 + te**2) / ca
    return n, J


def _in_front(a_rad, convention):
    """Where the angles name a ray in front of the sensor (finite n)."""
    lim = 0.5 * math.pi * (1 - 1e-9)
    return np.all(np.abs(a_rad) < lim, axis=-1)


def _column(header, base, path):
    """The column of angle ``base`` and its unit factor to rad (InputError when absent)."""
    for unit, f in (("deg", math.pi / 180.0), ("rad", 1.0)):
        name = f"{base}_{unit}"
        if name in header:
            return name, f
    raise InputError(f"missing column '{base}_deg' or '{base}_rad'", path=path, line=1, field=f"{base}_deg")


def _detect(header, path):
    found = [c for c, (a, b) in CONVENTIONS.items()
             if any(f"{a}_{u}" in header for u in ("deg", "rad")) and any(f"{b}_{u}" in header for u in ("deg", "rad"))]
    if len(found) != 1:
        what = "no" if not found else "several"
        pairs = "; ".join(f"{c}: {a}_deg,{b}_deg" for c, (a, b) in CONVENTIONS.items())
        raise InputError(f"{what} known pair of angle columns: declare the convention ({pairs})", path=path, line=1,
                         field="convention")
    return found[0]


def read_angles(path, convention: str | None = None, *, columns: dict | None = None,
                sigma_rad: float | None = None) -> AnglesTable:
    """Read an angles table (CSV) into normalised directions with their covariance.

    Parameters
    ----------
    path : path-like
        CSV with a header: ``t_s,sensor,emitter``, the two angle columns of the
        convention (``_deg`` or ``_rad``), optionally their ``sigma_`` columns
        and ``corr``. Lines starting with ``#`` are comments; a comment
        ``# convention: NAME`` before the header declares the convention.
    convention : str, optional
        ``psdcal``, ``azel``, ``tangent`` (``lighthouse``). Default: the
        comment line, else recognised from the angle columns.
    columns : dict, optional
        Other names of the key columns in this file, e.g.
        ``{"sensor": "station", "emitter": "sensor"}`` for a Lighthouse log.
    sigma_rad : float, optional
        One sigma for both angles of every row, rad, where the file has no
        ``sigma_`` columns.

    Raises
    ------
    InputError
        One line naming the file, the line and the field: a missing column,
        a value that is not a finite number, a sigma <= 0, ``|corr| >= 1``, a
        ray behind the sensor, an empty name, a repeated
        ``(t_s, sensor, emitter)``, an unknown convention.
    """
    from psdcal.io import _read_rows

    path, rows = _read_rows(path)
    text_conv = None
    for ln in Path(path).read_text(encoding="utf-8-sig").splitlines():
        s = ln.strip()
        if not s:
            continue
        if not s.startswith("#"):
            break
        body = s.lstrip("#").strip()
        if body.lower().startswith("convention"):
            text_conv = body.split(":", 1)[-1].split("=", 1)[-1].strip()
    hline, header = rows[0]
    data = rows[1:]
    if not data:
        raise InputError("no observations after the header", path=path)
    names = {k: k for k in KEY_COLUMNS}
    for k, v in (columns or {}).items():
        if k not in names:
            raise InputError(f"unknown key column {k!r} (known: {', '.join(KEY_COLUMNS)})", field=k)
        names[k] = v
    for k in KEY_COLUMNS:
        if names[k] not in header:
            raise InputError(f"missing column '{names[k]}'", path=path, line=hline, field=names[k])
    if len(set(header)) != len(header):
        dup = next(h for h in header if header.count(h) > 1)
        raise InputError(f"repeated column '{dup}'", path=path, line=hline, field=dup)
    conv = convention if convention is not None else text_conv
    conv = canonical_convention(conv, path=path) if conv is not None else _detect(header, path)
    (c1, f1), (c2, f2) = (_column(header, b, path) for b in CONVENTIONS[conv])
    lines = np.array([ln for ln, _ in data])
    for ln, row in data:
        if len(row) != len(header):
            raise InputError(f"expected {len(header)} fields, found {len(row)}", path=path, line=ln)
    col = {h: [row[i] for _, row in data] for i, h in enumerate(header)}

    def numbers(name):
        try:
            v = np.array(col[name], dtype=float)
        except ValueError:
            for ln, text in zip(lines, col[name]):
                try:
                    float(text)
                except ValueError:
                    raise InputError(f"not a number: {text!r}", path=path, line=int(ln), field=name) from None
            raise  # pragma: no cover
        bad = ~np.isfinite(v)
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(f"not a finite number: {col[name][i]!r} (leave a missing observation out)",
                             path=path, line=int(lines[i]), field=name)
        return v

    t = numbers(names["t_s"])
    a = np.stack([numbers(c1) * f1, numbers(c2) * f2], axis=-1)
    front = _in_front(a, conv)
    if not front.all():
        i = int(np.argmin(front))
        raise InputError("the angles point behind the sensor (|angle| >= 90 deg)", path=path, line=int(lines[i]),
                         field=c1 if abs(a[i, 0]) >= 0.5 * math.pi * (1 - 1e-9) else c2)
    sig = []
    for c, f in ((c1, f1), (c2, f2)):
        sc = f"sigma_{c}"
        if sc in header:
            s = numbers(sc) * f
            if np.any(s <= 0):
                i = int(np.argmax(s <= 0))
                raise InputError(f"a sigma must be > 0, got {col[sc][i]!r}", path=path, line=int(lines[i]), field=sc)
        elif sigma_rad is not None:
            if not (math.isfinite(sigma_rad) and sigma_rad > 0):
                raise InputError(f"the default sigma must be a positive number, got {sigma_rad!r}", field="sigma")
            s = np.full(len(t), float(sigma_rad))
        else:
            raise InputError(f"missing column '{sc}' (or give one sigma for every row)", path=path, line=hline,
                             field=sc)
        sig.append(s)
    rho = np.zeros(len(t))
    if "corr" in header:
        rho = numbers("corr")
        if np.any(np.abs(rho) >= 1):
            i = int(np.argmax(np.abs(rho) >= 1))
            raise InputError(f"a correlation must lie in (-1, 1), got {col['corr'][i]!r}", path=path,
                             line=int(lines[i]), field="corr")
    keys = {}
    out_names = {}
    for k in ("sensor", "emitter"):
        v = np.array([s.strip() for s in col[names[k]]], dtype=object)
        empty = v == ""
        if empty.any():
            i = int(np.argmax(empty))
            raise InputError(f"empty {k} name", path=path, line=int(lines[i]), field=names[k])
        out_names[k] = v
    for i, key in enumerate(zip(t.tolist(), out_names["sensor"].tolist(), out_names["emitter"].tolist())):
        if key in keys:
            raise InputError(f"repeated observation (t_s {key[0]:g}, {names['sensor']} {key[1]!r}, "
                             f"{names['emitter']} {key[2]!r}); first on line {keys[key]}", path=path,
                             line=int(lines[i]), field=names["t_s"])
        keys[key] = int(lines[i])
    cov_a = np.empty((len(t), 2, 2))
    cov_a[:, 0, 0] = sig[0] ** 2
    cov_a[:, 1, 1] = sig[1] ** 2
    cov_a[:, 0, 1] = cov_a[:, 1, 0] = rho * sig[0] * sig[1]
    n, J = n_from_angles(a, conv)
    cov_n = J @ cov_a @ np.swapaxes(J, -1, -2)
    order = np.lexsort((out_names["emitter"].astype(str), out_names["sensor"].astype(str), t))
    return AnglesTable(t[order], out_names["sensor"][order], out_names["emitter"][order], n[order], cov_n[order],
                       conv, str(path), lines[order])


def _offset_pair(v, sensor):
    """A sensor's clock offset as (angle 1, angle 2), s."""
    if np.ndim(v) == 0:
        return float(v), float(v)
    v = [float(x) for x in v]
    if len(v) != 2 or not all(math.isfinite(x) for x in v):
        raise InputError(f"the time offset of sensor {sensor!r} must be one or two finite numbers of seconds",
                         field="offset")
    return v[0], v[1]


def _resample(table, T, max_gap_s, offsets):
    """Interpolated rows ``(t, sensor, emitter, n, cov)`` at the times ``T`` with one offset per sensor."""
    out = {k: [] for k in ("t", "s", "e", "n", "c")}
    keys = sorted(set(zip(table.sensor.tolist(), table.emitter.tolist())))
    for s, e in keys:
        m = np.flatnonzero((table.sensor == s) & (table.emitter == e))
        ts = table.t_s[m] + float(offsets.get(s, 0.0))
        o = np.argsort(ts, kind="stable")
        m, ts = m[o], ts[o]
        j = np.searchsorted(ts, T, side="right")  # ts[j-1] <= T < ts[j]
        ok = (j >= 1) & (j <= len(ts))
        jl = np.clip(j - 1, 0, len(ts) - 1)
        jr = np.clip(j, 0, len(ts) - 1)
        exact = ok & (ts[jl] == T)
        inner = ok & ~exact & (j < len(ts))
        inner &= (ts[jr] - ts[jl]) <= max_gap_s
        use = exact | inner
        if not use.any():
            continue
        w = np.where(exact, 0.0, (T - ts[jl]) / np.where(jr != jl, ts[jr] - ts[jl], 1.0))[use]
        il, ir = m[jl[use]], m[jr[use]]
        out["t"].append(T[use])
        out["s"].append(np.full(use.sum(), s, dtype=object))
        out["e"].append(np.full(use.sum(), e, dtype=object))
        out["n"].append((1 - w)[:, None] * table.n[il] + w[:, None] * table.n[ir])
        out["c"].append(((1 - w) ** 2)[:, None, None] * table.cov_n[il] + (w**2)[:, None, None] * table.cov_n[ir])
    if not out["t"]:
        return None
    return tuple(np.concatenate(out[k]) for k in ("t", "s", "e", "n", "c"))


def resample_angles(table: AnglesTable, times_s, *, max_gap_s: float, offsets_s: dict | None = None) -> AnglesTable:
    """Each (sensor, emitter) series interpolated linearly (in ``n``) at the given times.

    Sensors of a room rarely sample at the same instants (a Lighthouse's two
    stations alternate); a tag's pose at one time step needs every sensor's
    directions at that time. A time is kept for a series only where the
    series has samples on both sides at most ``max_gap_s`` apart (exact
    matches are kept as they are). The covariance of an interpolated value is
    ``(1 - w)^2 C0 + w^2 C1`` (independent noise of the two samples).

    Parameters
    ----------
    times_s : (T,) array_like
        The common time steps, s.
    max_gap_s : float
        Largest interval between two samples interpolated across, s.
    offsets_s : dict, optional
        A known clock offset per sensor, s: its samples were taken at
        ``t_s + offset``. A pair ``(offset_1, offset_2)`` gives each angle its
        own offset (a Lighthouse station's two sweeps, 1/120 s apart): each
        component of ``n`` is then interpolated at its own time, which is
        exact for the conventions whose angles each give one component
        (``psdcal``, ``tangent``); the correlation of the two components is
        kept.
    """
    T = np.unique(np.asarray(times_s, dtype=float))
    pairs = {s: _offset_pair(v, s) for s, v in (offsets_s or {}).items()}
    first = _resample(table, T, max_gap_s, {s: v[0] for s, v in pairs.items()})
    if first is None:
        raise InputError("no observation falls within the time steps (check max_gap_s and the offsets)")
    t, s, e, n, c = first
    if any(a != b for a, b in pairs.values()):
        second = _resample(table, T, max_gap_s, {s_: v[1] for s_, v in pairs.items()})
        if second is None:
            raise InputError("no observation falls within the time steps (check max_gap_s and the offsets)")
        where = {key: i for i, key in enumerate(zip(second[0].tolist(), second[1].tolist(), second[2].tolist()))}
        i2 = np.array([where.get(key, -1) for key in zip(t.tolist(), s.tolist(), e.tolist())], dtype=int)
        keep = i2 >= 0
        t, s, e, n, c, i2 = t[keep], s[keep], e[keep], n[keep].copy(), c[keep].copy(), i2[keep]
        n[:, 1] = second[3][i2, 1]
        ratio = np.sqrt(second[4][i2, 1, 1] / np.maximum(c[:, 1, 1], 1e-300))
        c[:, 0, 1] *= ratio
        c[:, 1, 0] *= ratio
        c[:, 1, 1] = second[4][i2, 1, 1]
        if len(t) == 0:
            raise InputError("no observation falls within the time steps (check max_gap_s and the offsets)")
    order = np.lexsort((e.astype(str), s.astype(str), t))
    return AnglesTable(t[order], s[order], e[order], n[order], c[order], table.convention, table.path,
                       np.zeros(len(t), dtype=int))


def align_to_sensor(table: AnglesTable, reference: str, *, max_gap_s: float, offsets_s: dict | None = None) -> AnglesTable:
    """:func:`resample_angles` at the times of one sensor's observations, shifted by its own offset (the
    second of a pair: with a Lighthouse's earlier first sweep given a negative offset, the steps are the
    times of the second sweeps)."""
    m = table.sensor == reference
    if not m.any():
        raise InputError(f"no observations of sensor {reference!r} (sensors: {', '.join(table.sensors)})",
                         field="sensor")
    own = _offset_pair((offsets_s or {}).get(reference, 0.0), reference)
    return resample_angles(table, table.t_s[m] + own[1], max_gap_s=max_gap_s, offsets_s=offsets_s)


__all__ = [
    "ALIASES",
    "CONVENTIONS",
    "R_CAMERA_FROM_XFWD",
    "AnglesTable",
    "align_to_sensor",
    "canonical_convention",
    "n_from_angles",
    "read_angles",
    "resample_angles",
]
