"""`psdcal selfcal` (sensor poses from a moving rigid tag) and `psdcal tag-pose` (the tag's pose over time)."""
from __future__ import annotations

from pathlib import Path

import click

from psdcal.cli import cli

_CONVENTIONS_HELP = (
    "Angle convention of the front-end: psdcal (alpha_x, alpha_y: n = tan alpha), azel (azimuth, elevation in a "
    "frame x forward, y left, z up), tangent or lighthouse (h, v: ray (1, tan h, tan v) in that frame). Default: "
    "a '# convention: NAME' line before the header, else recognised from the angle columns "
    "(docs/guide/selfcal.md#the-angles-table).")


def _table_options(f):
    """The options that read an angles table (shared by both commands)."""
    opts = [
        click.option("--convention", default=None, metavar="NAME", help=_CONVENTIONS_HELP),
        click.option("--sensor-column", default="sensor", show_default=True,
                     help="Column naming the sensor (a Lighthouse log: station)."),
        click.option("--emitter-column", default="emitter", show_default=True,
                     help="Column naming the emitter (a Lighthouse log: sensor, its photodiodes)."),
        click.option("--time-column", default="t_s", show_default=True, help="Column of the time, s."),
        click.option("--sigma-rad", type=click.FloatRange(min=0.0, min_open=True), default=None,
                     help="One angle sigma for every row, rad, where the table has no sigma_ columns."),
        click.option("--sigma-deg", type=click.FloatRange(min=0.0, min_open=True), default=None,
                     help="The same in degrees."),
        click.option("--align-to", default=None, metavar="SENSOR",
                     help="Resample every other sensor's directions (linear in time) at this sensor's times: "
                          "for sensors that do not sample together (a Lighthouse's two stations alternate)."),
        click.option("--max-gap-s", type=click.FloatRange(min=0.0, min_open=True), default=0.05, show_default=True,
                     help="With --align-to: the longest interval between two samples interpolated across, s."),
        click.option("--time-offset", "time_offsets", multiple=True, metavar="SENSOR=S[,S]",
                     help="With --align-to: a sensor's samples were taken at t_s + S (repeatable); two values give "
                          "each angle its own time (a Lighthouse V1 station's first sweep comes 1/120 s before "
                          "the second: SENSOR=-0.008333,0)."),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


def _parse_offsets(items):
    from psdcal.errors import InputError

    out = {}
    for it in items:
        name, sep, vals = str(it).partition("=")
        try:
            v = [float(x) for x in vals.split(",")]
        except ValueError:
            v = []
        if not sep or not name.strip() or len(v) not in (1, 2) or not all(abs(x) < 1e6 for x in v):
            raise InputError(f"--time-offset {it!r}: expected SENSOR=SECONDS or SENSOR=SECONDS,SECONDS",
                             field="time-offset")
        out[name.strip()] = v[0] if len(v) == 1 else tuple(v)
    return out


def _read_table(angles, convention, sensor_column, emitter_column, time_column, sigma_rad, sigma_deg, align_to,
                max_gap_s, time_offsets=()):
    import math

    from psdcal.errors import InputError
    from psdcal.measure.angles_table import align_to_sensor, read_angles

    if sigma_rad is not None and sigma_deg is not None:
        raise InputError("give --sigma-rad or --sigma-deg, not both")
    sigma = sigma_rad if sigma_deg is None else math.radians(sigma_deg)
    table = read_angles(angles, convention, sigma_rad=sigma,
                        columns={"sensor": sensor_column, "emitter": emitter_column, "t_s": time_column})
    offsets = _parse_offsets(time_offsets)
    if offsets and align_to is None:
        raise InputError("--time-offset needs --align-to (the offsets are applied when resampling)")
    unknown = sorted(set(offsets) - set(table.sensors))
    if unknown:
        raise InputError(f"--time-offset names sensors not in the table: {', '.join(unknown)}", field="time-offset")
    if align_to is not None:
        table = align_to_sensor(table, align_to, max_gap_s=max_gap_s, offsets_s=offsets)
    return table


@cli.command("selfcal")
@click.argument("angles", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--tag", "tag_path", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The tag: CSV emitter,X_mm,Y_mm,Z_mm (or X_m,Y_m,Z_m), its emitters in its own body frame.")
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Sensors file to write (JSON, the format `locate --sensors` and `tag-pose --sensors` read).")
@_table_options
@click.option("--reference", default=None, metavar="SENSOR",
              help="The sensor whose camera frame is the world frame (default: the first sensor name in sorted "
                   "order). Not used with --survey.")
@click.option("--survey", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Emitters at known world positions (emitter,X_m,Y_m,Z_m, as `pose` reads) also seen by the "
                   "sensors: they fix the world frame (at least three, each seen by two sensors).")
@click.option("--distance", "distances", type=(str, str, float), multiple=True, metavar="A B MM",
              help="A known distance between the centres of sensors A and B, mm (repeatable).")
@click.option("--distance-sigma-mm", type=click.FloatRange(min=0.0, min_open=True), default=1.0, show_default=True,
              help="The sigma of every --distance, mm.")
@click.option("--calib", "calibs", multiple=True, metavar="SENSOR=PATH",
              help="Calibration file of a PSD sensor, written as its entry's 'calib' (repeatable; `locate "
                   "--sensors` needs one per sensor for PSD recordings).")
@click.option("--tag-poses", "csv_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the tag's fitted pose at every step (CSV, the columns of `tag-pose`).")
@click.option("--quiet", "-q", is_flag=True, help="Print nothing but errors.")
def selfcal_command(angles, tag_path, output, convention, sensor_column, emitter_column, time_column, sigma_rad,
                    sigma_deg, align_to, max_gap_s, time_offsets, reference, survey, distances, distance_sigma_mm,
                    calibs, csv_path, quiet):
    """Calibrate the room: every sensor's pose from a tag waved through it.

    ANGLES is an angles table (one row per observation: t_s, sensor,
    emitter, two angles and their sigma_ columns, optional corr), from any
    angle-of-arrival front-end (--convention). The tag carries several
    emitters at known places (--tag); two or more sensors see it at each
    time step (one value of t_s; --align-to resamples sensors that do not
    sample together). The tag's geometry fixes the scale; the frame is the
    --reference sensor's camera frame (x right, y down, z forward), or the
    surveyed points' frame (--survey).

    Writes the sensors file with each pose's covariance (pose_covariance
    over omega, t) and a 'selfcal' summary with the chi2 check (the
    covariance is inflated when the directions disagree with their sigmas).

    \b
    Examples:
      psdcal selfcal angles.csv --tag tag.csv -o sensors.json
      psdcal selfcal angles.csv --tag deck.csv --convention lighthouse \\
        --sensor-column station --emitter-column sensor --sigma-rad 7e-5 \\
        --align-to 1 --time-offset 0=-0.008333,0 --time-offset 1=-0.008333,0 \\
        -o stations.json --tag-poses deck_poses.csv
    """
    from psdcal.errors import InputError
    from psdcal.io import write_json
    from psdcal.measure.pose import read_emitters
    from psdcal.measure.selfcal import self_calibrate
    from psdcal.measure.tagpose import KnownSensor, read_tag, tag_poses, write_tag_poses

    cal = {}
    for item in calibs:
        name, sep, path = str(item).partition("=")
        if not sep or not name.strip() or not path.strip():
            raise InputError(f"--calib {item!r}: expected SENSOR=PATH")
        cal[name.strip()] = path.strip()
    tag = read_tag(tag_path)
    table = _read_table(angles, convention, sensor_column, emitter_column, time_column, sigma_rad, sigma_deg,
                        align_to, max_gap_s, time_offsets)
    sv = None
    if survey is not None:
        names, pts, _ = read_emitters(survey)
        sv = (names, pts)
    res = self_calibrate(table, tag, reference=reference, survey=sv,
                         distances=[(a, b, d, distance_sigma_mm) for a, b, d in distances])
    unknown = sorted(set(cal) - set(res.names))
    if unknown:
        raise InputError(f"--calib names sensors not in the table: {', '.join(unknown)}", field="calib")
    obj = {"sensors": res.sensors_entries(cal), "selfcal": {**res.summary(), "angles": str(angles),
                                                           "tag": str(tag_path), "convention": table.convention}}
    tp = None
    if csv_path is not None:
        sens = [KnownSensor(nm, res.R[i], res.c_mm[i], res.cov[i]) for i, nm in enumerate(res.names)]
        tp = tag_poses(table, tag, sens, cov_joint=res.cov_full)
        write_tag_poses(csv_path, tp)
        obj["selfcal"]["tag_poses"] = tag_poses_summary(tp, csv_path)
    write_json(output, obj)
    if not quiet:
        frame = f"the camera frame of sensor {res.reference!r}" if res.gauge == "reference" else "the survey's frame"
        click.echo(f"{len(res.names)} sensors from {res.n_obs} directions at {res.n_steps} steps "
                   f"({res.iterations} iterations); world frame: {frame}")
        for d in obj["sensors"]:
            p = d["pose"]
            c, s, r = p["center_w_mm"], p["sigma_center_mm"], p["sigma_rotation_deg"]
            fixed = " (fixes the frame)" if p["fixed"] else ""
            click.echo(f"  {d['name']}: centre ({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f}) mm +- "
                       f"({s[0]:.2g}, {s[1]:.2g}, {s[2]:.2g}) mm, rotation +- ({r[0]:.2g}, {r[1]:.2g}, {r[2]:.2g}) "
                       f"deg{fixed}")
        click.echo(f"check {res.check.line()}")
        for w in res.warnings:
            if w != res.check.line():
                click.echo(f"warning: {w}", err=True)
        if tp is not None:
            for c in tp.checks:
                click.echo(f"tag poses: check {c.line()}")
        click.echo(f"wrote {output}" + (f" and {csv_path}" if csv_path is not None else ""))


@cli.command("tag-pose")
@click.argument("angles", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--tag", "tag_path", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The tag: CSV emitter,X_mm,Y_mm,Z_mm (or X_m,Y_m,Z_m) in its body frame.")
@click.option("--sensors", "sensors_path", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Sensors file with the poses (from `selfcal`, `pose --into`); calibrations are not needed.")
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="CSV to write: t_s, X_mm, Y_mm, Z_mm, rx_rad, ry_rad, rz_rad, their sigmas, chi2, dof, "
                   "n_sensors, ambiguous.")
@_table_options
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the checks (tag_pose_chi2, tag_pose_common_mode) and the shared error's sigma "
                   "as JSON.")
@click.option("--quiet", "-q", is_flag=True, help="Print nothing but errors.")
def tag_pose_command(angles, tag_path, sensors_path, output, convention, sensor_column, emitter_column, time_column,
                     sigma_rad, sigma_deg, align_to, max_gap_s, time_offsets, json_path, quiet):
    """The rigid tag's six-degree-of-freedom pose at every time step.

    From the directions of its emitters (ANGLES, an angles table as for
    `selfcal`) seen by one sensor or several with known poses (--sensors).
    The pose maps the tag's body frame into the world: Pw = R(r) B + (X, Y, Z),
    with r = (rx, ry, rz) a rotation vector, rad; its sigmas come from the
    angle noise and the sensors' pose covariances (with their correlations
    when the sensors file comes from `selfcal`). A planar tag seen by one
    sensor has a mirror pose that may fit as well: such rows have ambiguous = 1.

    Example: psdcal tag-pose angles.csv --tag tag.csv --sensors sensors.json -o tag_poses.csv
    """
    from psdcal.measure.tagpose import (
        load_joint_covariance,
        load_sensor_poses,
        read_tag,
        tag_poses,
        write_tag_poses,
    )

    tag = read_tag(tag_path)
    sensors = load_sensor_poses(sensors_path)
    joint = load_joint_covariance(sensors_path, sensors)
    table = _read_table(angles, convention, sensor_column, emitter_column, time_column, sigma_rad, sigma_deg,
                        align_to, max_gap_s, time_offsets)
    res = tag_poses(table, tag, sensors, cov_joint=joint)
    write_tag_poses(output, res)
    if json_path is not None:
        from psdcal.io import write_json

        write_json(json_path, tag_poses_summary(res, output))
    if not quiet:
        click.echo(f"{len(res.t_s)} tag poses from {int(res.n_obs.sum())} directions; median sigma of the position "
                   f"{float(np_median(res.sigma_p_mm)):.3g} mm; {int(res.ambiguous.sum())} ambiguous")
        lines = [c.line() for c in res.checks]
        for line in lines:
            click.echo(f"check {line}")
        for w in res.warnings:
            if w not in lines:
                click.echo(f"warning: {w}", err=True)
        click.echo(f"wrote {output}")


def np_median(a):
    import numpy as np

    return np.median(np.linalg.norm(a, axis=1))


def tag_poses_summary(res, csv_path) -> dict:
    """The JSON summary of a tag-pose fit: its checks, verdict and the shared error's sigma (rad)."""
    from psdcal._consistency import verdict_of

    return {"csv": str(csv_path), "n_steps": len(res.t_s), "verdict": verdict_of(res.checks),
            "checks": [c.to_dict() for c in res.checks],
            "common_mode_sigma_rad": float(res.common_mode_sigma_rad), "warnings": list(res.warnings)}
