"""Angle tables in `locate`, `pose` and `bundle` (docs/guide/positioning.md#angles-in): the branches those
commands take with ``--angles`` (or, for ``pose``, an angles table as SOURCE); numerics in
:mod:`psdcal.measure.angles_locate`."""
from __future__ import annotations

from pathlib import Path

import click

#: Python names of the options :func:`psdcal.cli.selfcal_cmd._table_options` adds.
TABLE_KEYS = ("convention", "sensor_column", "emitter_column", "time_column", "sigma_rad", "sigma_deg", "align_to",
              "max_gap_s", "time_offsets")


def angles_option(f):
    """``--angles ANGLES.csv`` plus the options that read an angles table."""
    from psdcal.cli.selfcal_cmd import _table_options

    f = _table_options(f)
    return click.option(
        "--angles", "angles", type=click.Path(dir_okay=False, path_type=Path), default=None,
        help="An angles table from any angle-of-arrival front-end (t_s, sensor, emitter, two angles in the "
             "--convention, their sigma_ columns or --sigma-rad, optional corr) instead of recordings: no "
             "calibration needed (docs/guide/positioning.md#angles-in).")(f)


def table_options_except(*names):
    """A decorator adding the angles-table options but those named (a command's own option of that name wins)."""
    from psdcal.cli.selfcal_cmd import _table_options

    def dummy():  # pragma: no cover - never called
        pass

    params = [p for p in _table_options(dummy).__click_params__ if p.name not in names]

    def deco(f):
        if not hasattr(f, "__click_params__"):
            f.__click_params__ = []
        f.__click_params__.extend(params)
        return f

    return deco


def table_options(f):
    """All the angles-table options (:func:`psdcal.cli.selfcal_cmd._table_options`)."""
    from psdcal.cli.selfcal_cmd import _table_options

    return _table_options(f)


def read_table(angles, table_kw: dict):
    """The angles table, resampled when ``--align-to`` is given (:func:`psdcal.cli.selfcal_cmd._read_table`)."""
    from psdcal.cli.selfcal_cmd import _read_table

    kw = {k: table_kw.get(k) for k in TABLE_KEYS}
    kw["max_gap_s"] = kw["max_gap_s"] if kw["max_gap_s"] is not None else 0.05
    kw["time_offsets"] = kw["time_offsets"] or ()
    kw["sensor_column"] = kw["sensor_column"] or "sensor"
    kw["emitter_column"] = kw["emitter_column"] or "emitter"
    kw["time_column"] = kw["time_column"] or "t_s"
    return _read_table(angles, **kw)


def _warn(check) -> None:
    if check.passed is False:
        click.echo(f"psdcal: warning: {check.line()}" + (f" ({check.advice})" if check.advice else ""), err=True)


# --------------------------------------------------------------------------- locate
def locate_angles(angles, sensors, output, *, recordings=(), calib=None, carriers=(), output_format="csv",
                  track_path=None, track_q=None, table_kw=None) -> None:
    """``psdcal locate --angles ANGLES.csv --sensors SENSORS.json -o xyz.csv``."""
    from psdcal.errors import InputError
    from psdcal.measure.angles_locate import (
        load_angle_sensors,
        triangulate_table,
        write_positions_csv,
    )

    if sensors is None:
        raise InputError("--angles needs --sensors SENSORS.json (the sensors' poses)", field="sensors")
    if calib is not None:
        raise InputError("--angles needs no --calib: the table holds directions already", field="calib")
    if recordings or carriers:
        raise InputError("give RECORDINGS (with --carrier-hz) or --angles, not both", field="angles")
    if output_format != "csv":
        raise InputError("--format npy is not available with --angles: write CSV", field="format")
    table = read_table(angles, table_kw or {})
    if len(table.sensors) < 2:
        raise InputError(f"the angles table has one sensor ({', '.join(table.sensors)}): triangulation needs two or "
                         "more", path=angles, field="sensor")
    poses = load_angle_sensors(sensors)
    res = triangulate_table(table, poses, sensors_path=sensors)
    if len(res) == 0:
        raise InputError("no emitter is seen by two sensors at the same time step (sensors that do not sample "
                         "together: --align-to SENSOR)", path=angles, field="t_s")
    n = write_positions_csv(output, res)
    c = res.check
    click.echo(f"wrote {n} rows to {output} ({len(set(res.t_s.tolist()))} time steps, "
               f"{len(set(res.emitter.tolist()))} emitters, {res.n_skipped} seen by one sensor only; "
               f"convention {table.convention}; chi2 {c.statistic:.4g} for {c.dof:g} dof)")
    _warn(c)
    for w in res.warnings:  # a sensor left out as a reflection, or rays that cannot tell which
        click.echo(f"psdcal: warning: {w}", err=True)
    if track_path:
        from psdcal._atomic import staged
        from psdcal.measure.tracking import summary_line, track_csv

        info = track_csv(staged(output), track_path, q=track_q)
        click.echo(summary_line(info, track_path))
        for w in info["warnings"]:
            click.echo(f"psdcal: warning: {w}", err=True)


def track_angles(angles, sensors, output, table_kw, **kw) -> None:
    """``psdcal track ANGLES.csv --sensors SENSORS.json -o track.csv``: triangulated, then tracked (``kw``: the
    options of :func:`psdcal.measure.tracking.track_csv`)."""
    import tempfile

    from psdcal._atomic import immediate
    from psdcal.errors import InputError
    from psdcal.measure.angles_locate import (
        load_angle_sensors,
        triangulate_table,
        write_positions_csv,
    )
    from psdcal.measure.tracking import summary_line, track_csv

    table = read_table(angles, table_kw or {})
    res = triangulate_table(table, load_angle_sensors(sensors), sensors_path=sensors)
    if len(res) == 0:
        raise InputError("no emitter is seen by two sensors at the same time step (sensors that do not sample "
                         "together: --align-to SENSOR)", path=angles, field="t_s")
    _warn(res.check)
    for w in res.warnings:  # a sensor left out as a reflection, or rays that cannot tell which
        click.echo(f"psdcal: warning: {w}", err=True)
    with tempfile.TemporaryDirectory() as tmp:
        xyz = Path(tmp) / "xyz.csv"
        with immediate():  # a scratch file read back at once; the track joins the command's outputs
            write_positions_csv(xyz, res)
        info = track_csv(xyz, output, **kw)
    click.echo(summary_line(info, output))
    for w in info["warnings"]:
        click.echo(f"psdcal: warning: {w}", err=True)


# --------------------------------------------------------------------------- pose
def _header(path):
    """The header fields of a CSV (after '#' comment lines), or [] when it cannot be read."""
    try:
        with open(path, encoding="utf-8-sig") as fh:
            for line in fh:
                s = line.strip()
                if s and not s.startswith("#"):
                    return [h.strip() for h in s.split(",")]
    except (OSError, UnicodeDecodeError):
        return []
    return []


def is_front_end_table(source, table_kw: dict) -> bool:
    """Whether ``pose``'s SOURCE is read as an angles table of a front-end (:func:`read_table`).

    It is when a convention is declared (``--convention``, or a ``# convention:``
    line), or when the CSV has the sensor column and a known pair of angle columns.
    psdcal's own single-sensor angles (``alpha_x_deg``... without a sensor column)
    keep their older path.
    """
    from psdcal.measure.angles_table import CONVENTIONS

    if Path(source).suffix.lower() != ".csv" or not Path(source).exists():
        return False
    if table_kw.get("convention") is not None:
        return True
    try:
        head = Path(source).read_text(encoding="utf-8-sig")[:4096]
    except (OSError, UnicodeDecodeError):
        return False
    if any(ln.lstrip("#").strip().lower().startswith("convention") for ln in head.splitlines()
           if ln.strip().startswith("#")):
        return True
    header = set(_header(source))
    if (table_kw.get("sensor_column") or "sensor") not in header:
        return False
    return any(any(f"{a}_{u}" in header for u in ("deg", "rad")) and any(f"{b}_{u}" in header for u in ("deg", "rad"))
               for a, b in CONVENTIONS.values())


def pose_angles(source, names_w, points_w_mm, *, sensor, name, table_kw, **kw):
    """``(PoseResult, moving emitters)`` of ``pose`` from an angles table (``kw``: known_rvec, known_height_mm)."""
    from psdcal.measure.angles_locate import (
        moving_emitters,
        pose_from_table,
        table_sensor,
    )

    table = read_table(source, table_kw)
    s = table_sensor(table, sensor, fallback=name)
    res = pose_from_table(table, s, names_w, points_w_mm, **kw)
    return res, [e for e in moving_emitters(table, s) if e in set(names_w)]


# --------------------------------------------------------------------------- bundle
def bundle_angles(angles, *, located=(), calibs=(), known_csv, wands=(), points_out=None, output,
                  table_kw=None) -> None:
    """``psdcal bundle --angles ANGLES.csv --known known.csv [--wand NAME] -o sensors.json``."""
    import numpy as np

    from psdcal._consistency import chi2_check
    from psdcal.errors import InputError
    from psdcal.io import write_json
    from psdcal.measure.angles_locate import bundle_from_table
    from psdcal.measure.pose import POSE_COV_NAMES, read_emitters

    if located:
        raise InputError("give NAME=LOCATED.csv files or --angles, not both", field="angles")
    if calibs:
        raise InputError("--angles needs no --calib: the table holds directions already", field="calib")
    table = read_table(angles, table_kw or {})
    known_names, known_P, _ = read_emitters(known_csv)
    br = bundle_from_table(table, dict(zip(known_names, known_P)), wands)
    check = chi2_check(br.chi2, br.dof, name="bundle_chi2", inflate=False,
                       what=f"the directions of {len(br.points)} points seen by {len(br.sensors)} sensors",
                       advice="a wrong known position, a wand step seen at different times by the sensors "
                              "(--align-to), angle sigmas too small, or a mirrored start (use 4 or more known "
                              "emitters)")
    entries = []
    for j, nm in enumerate(br.sensors):
        cov = br.cov_poses[j]
        entries.append({
            "name": nm, "rvec": br.rvecs[j].tolist(), "tvec_mm": br.tvecs_mm[j].tolist(),
            "pose_covariance": {"names": list(POSE_COV_NAMES), "matrix": br.cov_omega_t(j).tolist()},
            "pose": {"center_w_mm": br.centers_mm[j].tolist(),
                     "sigma_center_mm": np.sqrt(np.clip(np.diag(cov)[3:], 0, None)).tolist(),
                     "sigma_rotation_deg": np.degrees(np.sqrt(np.clip(np.diag(cov)[:3], 0, None))).tolist(),
                     "method": "bundle", "source": "angles", "convention": table.convention,
                     "chi2": br.chi2, "dof": br.dof, "check": check.to_dict()},
        })
    write_json(output, {"sensors": entries})
    if points_out is not None:
        from psdcal.measure.bundle import write_points_csv

        write_points_csv(points_out, br)
    n_unknown = int((~br.known).sum())
    click.echo(f"bundle: {len(br.sensors)} sensors, {len(br.points)} points ({n_unknown} unknown), chi2 "
               f"{br.chi2:.4g} for {br.dof} dof, {br.iterations} iterations (angles, convention "
               f"{table.convention}); wrote {output}" + (f" and {points_out}" if points_out else ""))
    for e in entries:
        p = e["pose"]
        click.echo(f"  {e['name']}: centre +- {max(p['sigma_center_mm']):.3g} mm, rotation +- "
                   f"{max(p['sigma_rotation_deg']):.3g} deg")
    _warn(check)
