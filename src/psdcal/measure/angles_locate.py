"""Positions, poses and bundles from angle tables of any AoA front-end (docs/guide/positioning.md#angles-in).

An angles table (:mod:`psdcal.measure.angles_table`: ``t_s, sensor,
emitter``, two angles in a declared convention, their sigmas or covariance)
holds directions already: no calibration is needed. With a sensors file
(only each entry's ``name``, ``rvec``, ``tvec_mm`` and optional
``pose_covariance`` are read):

* :func:`triangulate_table`: every emitter at every time step from the
  sensors that see it, by :func:`psdcal.measure.positioning.triangulate`;
  the rows of ``locate --sensors`` (:data:`ANGLES_LOCATE_COLUMNS`);
* :func:`pose_from_table`: one sensor's pose from emitters at known places;
* :func:`bundle_from_table`: every sensor's pose and the unknown emitters in
  one bundle adjustment (:func:`psdcal.measure.bundle.bundle_adjust`).

A time step is one value of ``t_s``: sensors that do not sample together
are first brought to common times by
:func:`psdcal.measure.angles_table.align_to_sensor` (the CLI's ``--align-to``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from psdcal._consistency import Check
from psdcal.errors import InputError
from psdcal.measure.angles_table import AnglesTable

#: Columns of the positions written from an angles table: the first ten of ``locate --sensors``
#: (:data:`psdcal.measure.locate.MULTI_COLUMNS`), so that ``track`` and the dashboard read them alike.
ANGLES_LOCATE_COLUMNS = ("t_s", "emitter", "X_mm", "Y_mm", "Z_mm", "sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm",
                         "n_sensors", "chi2")
#: Appended: the sensor left out as a reflection and the flag (:mod:`psdcal.measure.reflections`), as ``locate``.
ANGLES_LOCATE_COLUMNS = ANGLES_LOCATE_COLUMNS + ("left_out", "reflection")
#: What a failed check of the table's rays points to.
ANGLES_ADVICE = ("the stated angle sigmas are too small, the sensors' poses are off, the sensors do not sample "
                 "together (--align-to, --time-offset), or a ray is a reflection")
#: Time steps triangulated at once (bounds memory on long tables).
CHUNK_STEPS = 65536


@dataclass(frozen=True)
class AngleSensor:
    """A sensor placed in the world: ``Pc = R Pw + t_mm``; ``cov_pose`` (6, 6) over ``(omega_rad, t_mm)`` or None."""

    name: str
    R: np.ndarray
    t_mm: np.ndarray
    cov_pose: np.ndarray | None = None

    @property
    def center_w_mm(self) -> np.ndarray:
        """Projection centre in the world frame (3,), mm."""
        return -self.R.T @ self.t_mm


def load_angle_sensors(path) -> list[AngleSensor]:
    """The poses of a sensors file, no calibration needed (``name``, ``rvec``, ``tvec_mm``, ``pose_covariance``).

    Raises
    ------
    InputError
        Naming the file and the key (as :func:`psdcal.measure.tagpose.load_sensor_poses`).
    """
    from psdcal.measure.tagpose import load_sensor_poses, omega_t_to_omega_c

    out = []
    for ks in load_sensor_poses(path):
        t = -ks.R @ ks.c_mm
        cov = None
        if ks.cov is not None:
            Ti = np.linalg.inv(omega_t_to_omega_c(ks.R, ks.c_mm))  # (omega, c) -> (omega, t)
            cov = Ti @ ks.cov @ Ti.T
            cov = 0.5 * (cov + cov.T)
        out.append(AngleSensor(ks.name, ks.R, t, cov))
    return out


def check_sensors_known(table: AnglesTable, sensors, sensors_path=None) -> None:
    """InputError naming the table's sensors that the sensors file lacks."""
    have = {s.name for s in sensors}
    missing = [s for s in table.sensors if s not in have]
    if missing:
        raise InputError(f"sensor(s) {', '.join(repr(m) for m in missing)} of the angles table "
                         f"{'' if table.path is None else table.path + ' '}are not in the sensors file "
                         f"(it has {', '.join(repr(s.name) for s in sensors)})", path=sensors_path, field="name")


# --------------------------------------------------------------------------- triangulation
@dataclass(frozen=True)
class AnglePositions:
    """Emitters triangulated from an angles table, one row per (time step, emitter) seen by >= 2 sensors.

    Attributes
    ----------
    t_s : (M,) ndarray
    emitter : (M,) ndarray of str
    p_w_mm : (M, 3) ndarray
        Position in the world frame, mm.
    cov_p_mm2 : (M, 3, 3) ndarray
        Its covariance (angle noise and, when the sensors file has them, the sensors' pose covariances).
    chi2 : (M,) ndarray
        Weighted residual of the rays, ``2 n_sensors - 3`` degrees of freedom.
    n_sensors : (M,) int ndarray
    n_skipped : int
        (time step, emitter) pairs seen by one sensor only (not written).
    check : Check
        ``locate_angles_chi2``: the sum of ``chi2`` against the sum of the degrees of freedom.
    """

    t_s: np.ndarray
    emitter: np.ndarray
    p_w_mm: np.ndarray
    cov_p_mm2: np.ndarray
    chi2: np.ndarray
    n_sensors: np.ndarray
    n_skipped: int
    check: Check
    left_out: np.ndarray | None = None
    reflection: np.ndarray | None = None
    warnings: tuple = ()

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def sigma_p_mm(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diagonal(self.cov_p_mm2, axis1=-2, axis2=-1), 0.0, None))

    def columns(self) -> dict:
        """The output columns (:data:`ANGLES_LOCATE_COLUMNS`) as arrays."""
        s = self.sigma_p_mm
        return {"t_s": self.t_s, "emitter": self.emitter, "X_mm": self.p_w_mm[:, 0], "Y_mm": self.p_w_mm[:, 1],
                "Z_mm": self.p_w_mm[:, 2], "sigma_X_mm": s[:, 0], "sigma_Y_mm": s[:, 1], "sigma_Z_mm": s[:, 2],
                "n_sensors": self.n_sensors, "chi2": self.chi2,
                "left_out": np.full(len(self), "", dtype=object) if self.left_out is None else self.left_out,
                "reflection": np.full(len(self), "", dtype=object) if self.reflection is None else self.reflection}


def triangulate_table(table: AnglesTable, sensors, *, sensors_path=None, chunk_steps: int = CHUNK_STEPS,
                      alpha: float | None = None) -> AnglePositions:
    """Triangulate every emitter at every time step of an angles table from the sensors that see it.

    Parameters
    ----------
    table : AnglesTable
        Rows with the same ``t_s`` form one time step (resample first when the
        sensors do not sample together).
    sensors : sequence of AngleSensor (or anything with ``name``, ``R``, ``t_mm``, ``cov_pose``)
    sensors_path : path, optional
        For the error message naming a sensor the file lacks.

    Returns
    -------
    AnglePositions
        Sorted by time, then emitter name.
    """
    from psdcal.measure.locate_multi import _RowPool
    from psdcal.measure.positioning import extra_noise_check, triangulate
    from psdcal.measure.reflections import (
        left_out_names,
        reflection_warnings,
        noise_scale,
        screen_rays,
        screen_with_noise_scale,
    )

    check_sensors_known(table, sensors, sensors_path)
    used = [s for s in sensors if s.name in set(table.sensors)]
    k = len(used)
    names = [s.name for s in used]
    sidx = {s.name: j for j, s in enumerate(used)}
    si = np.array([sidx[s] for s in table.sensor.tolist()], dtype=int)
    tu, ti = np.unique(table.t_s, return_inverse=True)
    eu, ei = np.unique(table.emitter.astype(str), return_inverse=True)
    gid = ti.astype(np.int64) * len(eu) + ei
    groups, gi = np.unique(gid, return_inverse=True)
    R = np.stack([np.asarray(s.R, float) for s in used])
    t = np.stack([np.asarray(s.t_mm, float) for s in used])
    cp = None
    if any(s.cov_pose is not None for s in used):
        cp = np.stack([np.zeros((6, 6)) if s.cov_pose is None else np.asarray(s.cov_pose, float) for s in used])
    parts, tris, refl, rays = [], [], [], []
    pool = _RowPool() if alpha is None else _RowPool(alpha)
    order = np.argsort(gi, kind="stable")
    bounds = np.searchsorted(gi[order], np.arange(0, len(groups) + chunk_steps, chunk_steps))
    for a in range(0, len(groups), chunk_steps):
        G = min(chunk_steps, len(groups) - a)
        rows = order[bounds[a // chunk_steps]:bounds[a // chunk_steps + 1]]
        n = np.full((k, G, 2), np.nan)
        cov = np.full((k, G, 2, 2), np.nan)
        n[si[rows], gi[rows] - a] = table.n[rows]
        cov[si[rows], gi[rows] - a] = table.cov_n[rows]
        tri0 = triangulate(n, cov, R, t, cov_pose=cp, inflate=False)  # the file's rule below, as locate's
        scr = screen_rays(n, cov, R, t, tri0, cov_pose=cp, inflate=False,
                          **({} if alpha is None else {"alpha": alpha}))
        tri = scr.tri  # a sensor whose ray disagrees with the others left out
        refl.append((left_out_names(scr, names), scr.flag))
        pool.add(tri)
        tris.append(tri)
        rays.append((n, cov, tri0.chi2, tri0.dof))
    check, s2 = pool.result()
    if s2 > 0:  # rays noisier than stated: screen again against that noise, then the file's rule as before
        # every ray's chi2 (before any was left out): its median is robust to a minority of reflections
        scale = noise_scale(np.concatenate([x[2] for x in rays]), np.concatenate([x[3] for x in rays]))
        pool = _RowPool() if alpha is None else _RowPool(alpha)
        tris, refl = [], []
        for n, cov, _, _ in rays:
            scr, tri = screen_with_noise_scale(n, cov, R, t, scale, cov_pose=cp,
                                               **({} if alpha is None else {"alpha": alpha}))
            refl.append((left_out_names(scr, names), scr.flag))
            pool.add(tri)
            tris.append(tri)
        check, s2 = pool.result()
    for tri in tris:
        parts.append((tri.p_w_mm, tri.cov_p_stated_mm2 + s2 * tri.dcov_dextra_mm2, tri.chi2, tri.n_sensors))
    if s2 > 0:  # the check's message and inflation: the extra noise and the sigmas' growth over all points
        C0 = np.concatenate([tri.cov_p_stated_mm2 for tri in tris])
        C1 = np.concatenate([x[1] for x in parts])
        check = extra_noise_check(check, s2, np.trace(C0, axis1=-2, axis2=-1), np.trace(C1, axis1=-2, axis2=-1))
    check = replace(check, name="locate_angles_chi2", advice=ANGLES_ADVICE)
    p = np.concatenate([x[0] for x in parts])
    C = np.concatenate([x[1] for x in parts])
    chi2 = np.concatenate([x[2] for x in parts])
    ns = np.concatenate([x[3] for x in parts])
    lo = np.concatenate([x[0] for x in refl])
    fl = np.concatenate([x[1] for x in refl])
    ok = ns >= 2
    g = groups[ok]
    tt = tu[g // len(eu)]
    ee = eu[g % len(eu)].astype(object)
    kw = {} if alpha is None else {"alpha": alpha}
    return AnglePositions(tt, ee, p[ok], C[ok], chi2[ok], ns[ok].astype(int), int((~ok).sum()), check,
                          lo[ok], fl[ok], tuple(reflection_warnings(lo[ok], fl[ok], **kw)))


def write_positions_csv(path, res: AnglePositions) -> int:
    """Write :data:`ANGLES_LOCATE_COLUMNS` rows (10 significant digits, as ``locate``), atomically; rows written."""
    from psdcal._atomic import atomic_path
    from psdcal.measure.locate import _write_rows

    with atomic_path(path, suffix=".csv") as tmp, open(tmp, "w", encoding="utf-8", newline="") as fh:
        fh.write(",".join(ANGLES_LOCATE_COLUMNS) + "\n")
        n = _write_rows(fh, res.columns(), ANGLES_LOCATE_COLUMNS) if len(res) else 0
    return n


# --------------------------------------------------------------------------- pose and bundle
def mean_directions(table: AnglesTable, mask=None):
    """Per emitter, the inverse-covariance weighted mean of its directions and the covariance of the mean.

    Returns
    -------
    names : list of str (first-seen order), n : (k, 2), cov_n : (k, 2, 2)
    """
    sub = table if mask is None else table.subset(mask)
    names = list(dict.fromkeys(sub.emitter.tolist()))
    W = np.linalg.inv(sub.cov_n)
    n_out, c_out = [], []
    for nm in names:
        m = sub.emitter == nm
        Ws = W[m].sum(0)
        C = np.linalg.inv(Ws)
        n_out.append(C @ np.einsum("nij,nj->i", W[m], sub.n[m]))
        c_out.append(0.5 * (C + C.T))
    return names, np.array(n_out).reshape(-1, 2), np.array(c_out).reshape(-1, 2, 2)


def moving_emitters(table: AnglesTable, sensor: str, alpha: float = 1e-3) -> list:
    """Emitters whose directions, seen by ``sensor``, scatter about their mean more than their covariance allows.

    Per emitter ``sum_i (n_i - mean)^T C_i^-1 (n_i - mean)`` against chi2 with
    ``2 (m - 1)`` degrees of freedom; named when its p-value is below ``alpha``
    (the emitter moved, or the sigmas are too small): averaging them for a pose
    is then wrong.
    """
    from scipy.stats import chi2 as chi2_dist

    sub = table.subset(table.sensor == sensor)
    names, n, _ = mean_directions(sub)
    W = np.linalg.inv(sub.cov_n)
    out = []
    for nm, mu in zip(names, n):
        m = sub.emitter == nm
        if m.sum() < 2:
            continue
        r = sub.n[m] - mu
        q = float(np.einsum("ni,nij,nj->", r, W[m], r))
        if chi2_dist.sf(q, 2 * (int(m.sum()) - 1)) < alpha:
            out.append(nm)
    return out


def table_sensor(table: AnglesTable, sensor: str | None, fallback: str | None = None) -> str:
    """The sensor whose rows to use: ``sensor``, else ``fallback`` when in the table, else the only one."""
    names = table.sensors
    if sensor is not None:
        if sensor not in names:
            raise InputError(f"no rows of sensor {sensor!r} in the angles table (sensors: {', '.join(names)})",
                             path=table.path, field="sensor")
        return sensor
    if fallback is not None and fallback in names:
        return fallback
    if len(names) == 1:
        return names[0]
    raise InputError(f"the angles table has several sensors ({', '.join(names)}): say which (--sensor)",
                     path=table.path, field="sensor")


def pose_from_table(table: AnglesTable, sensor: str, names_w, points_w_mm, **kw):
    """:func:`psdcal.measure.pose.estimate_pose` of one sensor from its rows of an angles table.

    The rows of each emitter are averaged (inverse-covariance weights, the
    emitters are still); emitters not in ``names_w`` are left out. ``kw`` goes
    to ``estimate_pose`` (``known_rvec``, ``known_height_mm``).
    """
    from psdcal.measure.pose import estimate_pose

    names, n, cov = mean_directions(table, table.sensor == sensor)
    idx = {nm: i for i, nm in enumerate(names_w)}
    use = [j for j, nm in enumerate(names) if nm in idx]
    if not use:
        raise InputError(f"none of the emitters sensor {sensor!r} sees is in the emitters file ({list(names_w)})",
                         path=table.path, field="emitter")
    P = np.asarray(points_w_mm, dtype=float)[[idx[names[j]] for j in use]]
    return estimate_pose(n[use], cov[use], P, **kw)


@dataclass(frozen=True)
class BundleInputs:
    """The observations of an angles table for :func:`psdcal.measure.bundle.bundle_adjust`."""

    sensors: list
    points: list
    obs_sensor: np.ndarray
    obs_point: np.ndarray
    n: np.ndarray
    cov_n: np.ndarray
    init_rvecs: np.ndarray
    init_centers_mm: np.ndarray


def bundle_inputs(table: AnglesTable, known_mm: dict, wands=()) -> BundleInputs:
    """Observations, points and starting poses for a bundle adjustment from an angles table.

    Emitters not in ``wands`` are still: their rows are averaged per sensor;
    a wand emitter gives one point per time step (``emitter@t_s``), matched
    between sensors by ``t_s``. Each sensor's start is its pose from the known
    emitters it sees (>= 3); unknown points seen by one sensor only are left out.
    """
    from psdcal.measure.pose import estimate_pose

    sensors = table.sensors
    if len(sensors) < 2:
        raise InputError(f"a bundle needs at least two sensors, the angles table has {len(sensors)}",
                         path=table.path, field="sensor")
    wand_set = set(wands)
    points, pidx = [], {}
    js, ii, ns, covs, r0, c0 = [], [], [], [], [], []
    for j, s in enumerate(sensors):
        mine = table.sensor == s
        wand = mine & np.isin(table.emitter, list(wand_set))
        still = mine & ~wand
        names, n, cov = mean_directions(table, still) if still.any() else ([], np.zeros((0, 2)), np.zeros((0, 2, 2)))
        wn = [f"{e}@{t:.6f}" for e, t in zip(table.emitter[wand], table.t_s[wand])]
        names = list(names) + wn
        n = np.concatenate([n, table.n[wand]])
        cov = np.concatenate([cov, table.cov_n[wand]])
        kn = [i for i, nm in enumerate(names) if nm in known_mm]
        if len(kn) < 3:
            raise InputError(f"sensor {s!r} sees {len(kn)} known emitter(s); its start needs 3", path=table.path,
                             field="emitter")
        st = estimate_pose(n[kn], cov[kn], np.array([known_mm[names[i]] for i in kn]))
        r0.append(st.rvec)
        c0.append(st.center_w_mm)
        for i, nm in enumerate(names):
            if nm not in pidx:
                pidx[nm] = len(points)
                points.append(nm)
            js.append(j)
            ii.append(pidx[nm])
            ns.append(n[i])
            covs.append(cov[i])
    ii_a, js_a = np.array(ii), np.array(js)
    counts = np.bincount(ii_a, minlength=len(points))
    keep_pt = np.array([counts[k] >= 2 or points[k] in known_mm for k in range(len(points))])
    keep = keep_pt[ii_a]
    remap = -np.ones(len(points), int)
    remap[keep_pt] = np.arange(int(keep_pt.sum()))
    return BundleInputs(list(sensors), [p for p, k in zip(points, keep_pt) if k], js_a[keep], remap[ii_a[keep]],
                        np.array(ns)[keep], np.array(covs)[keep], np.array(r0), np.array(c0))


def bundle_from_table(table: AnglesTable, known_mm: dict, wands=()):
    """:func:`psdcal.measure.bundle.bundle_adjust` of every sensor of an angles table; returns BundleResult."""
    from psdcal.measure.bundle import bundle_adjust

    b = bundle_inputs(table, known_mm, wands)
    return bundle_adjust(b.sensors, b.points, b.obs_sensor, b.obs_point, b.n, b.cov_n, known_mm,
                         init_rvecs=b.init_rvecs, init_centers_mm=b.init_centers_mm)


def sensors_entry_xfwd(name: str, rotation_sensor_to_world, origin_mm) -> dict:
    """A sensors-file entry for a sensor whose own frame is x forward, y left, z up (a Lighthouse base station).

    ``rotation_sensor_to_world`` (3, 3) maps the sensor's frame into the world
    and ``origin_mm`` is its centre: the camera frame is
    ``Pc = M R^T (Pw - origin)`` with ``M`` =
    :data:`psdcal.measure.angles_table.R_CAMERA_FROM_XFWD`.
    """
    from psdcal.measure.angles_table import R_CAMERA_FROM_XFWD
    from psdcal.model.projection import r_from_R

    Rw = np.asarray(rotation_sensor_to_world, dtype=float)
    c = np.asarray(origin_mm, dtype=float)
    Rc = R_CAMERA_FROM_XFWD @ Rw.T
    return {"name": str(name), "rvec": np.asarray(r_from_R(Rc), float).tolist(), "tvec_mm": (-Rc @ c).tolist()}


__all__ = [
    "ANGLES_LOCATE_COLUMNS",
    "AnglePositions",
    "AngleSensor",
    "BundleInputs",
    "bundle_from_table",
    "bundle_inputs",
    "check_sensors_known",
    "load_angle_sensors",
    "mean_directions",
    "moving_emitters",
    "pose_from_table",
    "sensors_entry_xfwd",
    "table_sensor",
    "triangulate_table",
    "write_positions_csv",
]
