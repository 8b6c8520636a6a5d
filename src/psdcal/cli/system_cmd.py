"""System-level commands: ``pose``, ``track``, ``bundle``, ``plan`` and one-sensor live input.

A thin layer over :mod:`psdcal.measure.pose`, :mod:`psdcal.measure.tracking`,
:mod:`psdcal.measure.bundle` and :mod:`psdcal.measure.planning` (no numerics here);
``simulate-recording`` is in :mod:`psdcal.cli.simrec_cmd`.
"""
from __future__ import annotations

from pathlib import Path

import click

from psdcal.cli import _angles, cli

def _merge_sensors_file(path: Path, entry: dict) -> None:
    """Add ``entry`` to the sensors file ``path`` (replacing one of the same name); create it if missing."""
    import json

    from psdcal.errors import InputError
    from psdcal.io import write_json

    sensors = []
    if path.exists():
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise InputError(f"not valid JSON: {exc.msg}", path=path, line=exc.lineno) from None
        sensors = data.get("sensors") if isinstance(data, dict) else data
        if not isinstance(sensors, list):
            raise InputError("expected a list of sensors", path=path, field="sensors")
    sensors = [s for s in sensors if not (isinstance(s, dict) and s.get("name") == entry["name"])] + [entry]
    write_json(path, {"sensors": sensors})


def _read_table(path):
    """(header, rows) of a CSV whose header names 'emitter' (a locate or amplitudes output), else None."""

    from psdcal.io import csv_rows

    rows = csv_rows(path, "table")
    if not rows or "emitter" not in [h.strip() for h in rows[0]]:
        return None
    return [h.strip() for h in rows[0]], [r for r in rows[1:] if r and any(c.strip() for c in r)]


def _table_means(path, header, rows, model):
    import numpy as np

    from psdcal.errors import InputError
    from psdcal.measure.pose import mean_amplitudes, mean_points

    def column(name):
        i = header.index(name)
        out = []
        for lineno, r in enumerate(rows, start=2):
            try:
                out.append(float(r[i]))
            except (ValueError, IndexError):
                raise InputError(f"not a number: {r[i] if i < len(r) else ''!r}", path=path, line=lineno,
                                 field=name) from None
        return np.array(out)

    names = [r[header.index("emitter")].strip() for r in rows]
    amp = ("vx1", "vx2", "vy1", "vy2")
    if all(c in header for c in amp):
        a = np.stack([column(c) for c in amp], -1)
        if all(f"sigma_{c}" in header for c in amp):
            v = np.stack([column(f"sigma_{c}") for c in amp], -1) ** 2
        else:
            v = np.ones_like(a)
        return mean_amplitudes(names, a, v, model)
    if all(c in header for c in ("x_mm", "y_mm")):
        d = np.stack([column("x_mm"), column("y_mm")], -1)
        if all(c in header for c in ("sigma_x_mm", "sigma_y_mm")):
            s = np.stack([column("sigma_x_mm"), column("sigma_y_mm")], -1)
        else:
            s = np.full_like(d, 1e-3)
        return mean_points(names, d, s)
    raise InputError("the table must have x_mm,y_mm (a locate output) or vx1,vx2,vy1,vy2 (amplitudes)",
                     path=path, line=1)


def _table_angles(path, header, rows):
    """(names, alpha_deg (N, 2), sigma_alpha_deg (N, 2)) of an angles table."""
    import numpy as np

    from psdcal.errors import InputError

    cols = ["alpha_x_deg", "alpha_y_deg", "sigma_alpha_x_deg", "sigma_alpha_y_deg"]
    missing = [c for c in cols[2:] if c not in header]
    if missing:
        raise InputError(f"an angles table needs the sigma columns too (missing {missing})", path=path, line=1,
                         field=missing[0])
    vals = np.empty((len(rows), 4))
    for lineno, r in enumerate(rows, start=2):
        for k, c in enumerate(cols):
            try:
                vals[lineno - 2, k] = float(r[header.index(c)])
            except (ValueError, IndexError):
                raise InputError("not a number", path=path, line=lineno, field=c) from None
    names = [r[header.index("emitter")].strip() for r in rows]
    return names, vals[:, :2], vals[:, 2:]


@cli.command("pose")
@click.argument("source", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--calib", required=False, type=click.Path(dir_okay=False, path_type=Path),
              help="Calibration JSON of the sensor (its covariance enters the pose's); not needed for angles.")
@click.option("--emitters", "emitters_csv", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="CSV emitter,X_m,Y_m,Z_m[,carrier_hz]: the known emitters in the room frame (metres).")
@click.option("--rate-hz", type=float, help="Sampling rate (when the recording does not carry one).")
@click.option("--carrier-hz", "carriers", type=float, multiple=True,
              help="Carrier of an emitter, repeat (default: the emitters file's carrier_hz column).")
@click.option("--emitter", "emitter_names", multiple=True, help="Name of each --carrier-hz's emitter.")
@click.option("--also-carrier-hz", "also", type=float, multiple=True,
              help="Other carriers in the recording (emitters not in the file, e.g. a moving tag): fitted "
                   "jointly so they do not leak into the known emitters' amplitudes; repeat.")
@click.option("--window-s", type=float, default=0.01, show_default=True, help="Demodulation window.")
@click.option("--schedule", type=click.Path(dir_okay=False), help="TDM schedule CSV (implies --tdm).")
@click.option("--tdm", is_flag=True, help="Time multiplexing (one carrier; names from --schedule).")
@click.option("--min-snr", type=float, default=10.0, show_default=True, help="Drop windows below this many sigma.")
@click.option("--known-rvec", type=(float, float, float), default=None,
              help="Known orientation (rotation vector world -> camera, rad): only the position is estimated.")
@click.option("--known-height-m", type=float, default=None, help="Known height of the sensor's centre, m.")
@click.option("--side-point", "side_point", type=(float, float, float), default=None,
              help="A point (X Y Z, m) on the sensor's side of the emitters' plane, for (nearly) coplanar emitters "
                   "whose mirror image fits as well (default: the side rule, see the docs).")
@click.option("--max-extent-m", type=float, default=100.0, show_default=True,
              help="Largest plausible extent of the emitters, m (beyond: a unit error, exit 2).")
@click.option("--name", default="s1", show_default=True, help="Sensor name in the sensors file.")
@click.option("--recording", "rec_key", type=click.Path(dir_okay=False, path_type=Path),
              help="Recording the sensors-file entry names (default: SOURCE when it is a recording).")
@click.option("--into", type=click.Path(dir_okay=False, path_type=Path),
              help="Add (or replace, by name) the entry in this sensors file (created if missing).")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the entry alone as JSON.")
@click.option("--sensor", "table_sensor", default=None, metavar="SENSOR",
              help="An angles table of several sensors: the sensor whose rows to use (default: --name when the "
                   "table has it, else the table's only sensor).")
@_angles.table_options
def pose_command(source, calib, emitters_csv, rate_hz, carriers, emitter_names, also, window_s, schedule, tdm, min_snr,
                 known_rvec, known_height_m, side_point, max_extent_m, name, rec_key, into, output,
                 table_sensor=None, **table_kw):
    """Estimate a calibrated sensor's rotation and position in the room (PnP + maximum likelihood).

    SOURCE is the sensor's recording of >= 3 emitters at known positions
    (2 with --known-rvec, 1 with --known-rvec and --known-height-m), or a table
    with an 'emitter' column: a `locate` output (x_mm,y_mm,sigma_x_mm,sigma_y_mm),
    an `amplitudes` output, or angles (alpha_x_deg,alpha_y_deg and their sigma_
    columns: taken as independent, so the calibration's correlated part is not
    separated).  The windows of each emitter are averaged.
    An angles table of any front-end (t_s, sensor, emitter, two angles in the --convention and
    their sigmas; docs/guide/positioning.md#angles-in) needs no --calib: its rows of --sensor
    (default --name, or its only sensor) are averaged per emitter; the entry then has no calib.

    \b
    Writes the sensors-file entry `locate --sensors` reads: name, calib, rvec, tvec_mm,
    recording, plus pose_covariance (6x6 over omega_x,y,z rad and tx,ty,tz mm, the angle
    noise and the calibration covariance), pose_calibration (the pose's derivative by the
    calibration parameters and its noise-only covariance: `locate --sensors` then propagates
    the rays' and the pose's calibration error together) and pose (centre, 1-sigma, chi2,
    warnings).
    \b
    Example:
      psdcal pose room/s1.npy --rate-hz 20000 --calib calib.json --emitters room/emitters.csv \\
          --name s1 --into sensors.json
    Collinear or too few emitters: an error; a poor layout or angles that do not fit
    the coordinates (chi2, 0.1 % false alarms; the covariance is then inflated by
    chi2/dof): a warning on stderr and in the entry.  A survey that looks mirrored
    (x/y swapped, a left-handed frame), a sensor on the unexpected side of coplanar
    emitters (--side-point to state it), or emitters spread over more than
    --max-extent-m (a unit error): one line, exit 2, nothing written.
    """
    import os
    import tempfile

    import numpy as np

    from psdcal.errors import InputError
    from psdcal.io import write_json
    from psdcal.measure.pose import pose_from_means, read_emitters
    from psdcal.measure.sensor_model import SensorModel

    if into is None and output is None:
        raise InputError("give --into SENSORS.json and/or -o ENTRY.json", field="output")
    from psdcal import _jit

    _jit.set_mode("auto")  # a pose's angles are a few emitters' means: the numpy path, numba never imported
    from psdcal.cli._angles import is_front_end_table

    front_end = is_front_end_table(source, table_kw)  # angles of any front-end: no calibration
    if calib is None and not front_end and not (source.suffix.lower() == ".csv" and source.exists()):
        raise InputError("give --calib (a recording needs the sensor's calibration)", field="calib")
    model = None if calib is None else SensorModel.load(calib)
    names_w, P, carriers_w = read_emitters(emitters_csv, max_extent_m=max_extent_m)
    table = _read_table(source) if source.suffix.lower() == ".csv" and source.exists() and not front_end else None
    angles = None
    if front_end:
        angles = "front-end"
        recording = rec_key
    elif table is not None:
        header, rows = table
        has = set(header)
        if not ({"x_mm", "y_mm"} <= has or {"vx1", "vx2", "vy1", "vy2"} <= has) and \
                {"alpha_x_deg", "alpha_y_deg"} <= has:
            angles = _table_angles(source, header, rows)
        else:
            if model is None:
                raise InputError("give --calib (impact points or amplitudes need the sensor's calibration)",
                                 field="calib")
            means = _table_means(source, *table, model)
        recording = rec_key
    else:
        from psdcal.measure.locate import LocateConfig, amplitudes_to_csv
        from psdcal.signal.recording import open_recording
        from psdcal.signal.stream import load_schedule

        sched = load_schedule(schedule) if schedule else None
        is_tdm = bool(tdm or sched is not None)
        if carriers:
            cs, ems = tuple(carriers), tuple(emitter_names) or None
        elif is_tdm:
            raise InputError("time multiplexing: give the --carrier-hz", field="carrier_hz")
        elif carriers_w is None:
            raise InputError("give --carrier-hz (or a carrier_hz column in the emitters file)", path=emitters_csv,
                             field="carrier_hz")
        else:
            cs, ems = tuple(float(f) for f in carriers_w), tuple(names_w)
        if also:
            if is_tdm:
                raise InputError("--also-carrier-hz is for frequency multiplexing", field="also_carrier_hz")
            ems = (ems or tuple(f"{f:g}Hz" for f in cs)) + tuple(f"other{j + 1}" for j in range(len(also)))
            cs = cs + tuple(also)
        config = LocateConfig(carriers_hz=cs, window_s=window_s, emitters=ems, min_snr=min_snr, tdm=is_tdm,
                              schedule=sched)
        rec = open_recording(source, rate_hz)
        from psdcal._atomic import immediate

        with tempfile.TemporaryDirectory() as tmp, immediate():
            amp = Path(tmp) / "amp.csv"
            amplitudes_to_csv(rec, amp, config)
            header, rows = _read_table(amp)
            means = _table_means(amp, header, rows, model)
        recording = rec_key or source
    kw = dict(known_rvec=known_rvec, known_height_mm=None if known_height_m is None else known_height_m * 1000.0,
              side_point_mm=None if side_point is None else np.array(side_point) * 1000.0,
              max_extent_mm=max_extent_m * 1000.0)
    if angles == "front-end":
        from psdcal.cli._angles import pose_angles

        res, moved = pose_angles(source, names_w, P, sensor=table_sensor, name=name, table_kw=table_kw, **kw)
    elif angles is not None:
        from psdcal.measure.pose import pose_from_angles

        moved = []
        res = pose_from_angles(*angles, names_w, P, **kw)
    else:
        moved = [nm for nm, p in zip(means.names, means.scatter_p) if nm in names_w and np.isfinite(p) and p < 1e-6]
        res = pose_from_means(means, model, names_w, P, **kw)
    if not res.usable:  # a mirrored survey, the sensor on the unexpected side, a unit error: nothing written
        bad = [c for c in res.checks if c.passed is False and c.severe]
        raise InputError(f"{bad[0].message}; nothing written", path=emitters_csv)
    base = (into or output).resolve().parent

    def rel(p):
        return None if p is None else os.path.relpath(Path(p).resolve(), base)

    entry = res.sensors_entry(name, rel(calib), rel(recording), calib_names=model.names if angles is None else None)
    if calib is None:  # angles: no calibration (`locate --angles` and `tag-pose` read the pose alone)
        entry.pop("calib", None)
    if moved:
        entry["pose"]["warnings"].append(f"emitter(s) {moved} scatter more than their noise between windows "
                                         "(moving, or a changing signal)")
    if output is not None:
        write_json(output, entry)
    if into is not None:
        _merge_sensors_file(into, entry)
    c = res.center_w_mm / 1000.0
    sc = res.sigma_center_mm
    click.echo(f"{name}: centre ({c[0]:.4f}, {c[1]:.4f}, {c[2]:.4f}) m +- ({sc[0]:.3g}, {sc[1]:.3g}, {sc[2]:.3g}) mm, "
               f"rotation +- {res.sigma_rotation_deg.max():.3g} deg, {res.n_emitters} emitters, chi2 {res.chi2:.3g} "
               f"for {res.dof} dof; wrote {', '.join(str(p) for p in (output, into) if p is not None)}")
    for w in entry["pose"]["warnings"]:
        click.echo(f"warning: {w}", err=True)


# --------------------------------------------------------------------------- track
@cli.command("track")
@click.argument("located", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--q", "q", type=str, default=None, metavar="Q|auto",
              help="Process noise: spectral density of the white acceleration, mm^2/s^3 (deg^2/s^3 for angles) "
                   "[default: 1e6 mm^2/s^3, 10 deg^2/s^3]; 'auto': the default times the factor that makes the "
                   "NIS's 99 % point chi2's.")
@click.option("--gate-p", type=click.FloatRange(0.5, 1.0, max_open=True), default=0.999, show_default=True,
              help="Chi2 gate probability: a measurement whose NIS exceeds this quantile is not used.")
@click.option("--max-gated", type=click.IntRange(1, 1000), default=5, show_default=True,
              help="Consecutive gated measurements, consistent with each other, after which the track jumps "
                   "to them (restart=1, a warning).")
@click.option("--max-gap-s", type=float, default=None,
              help="A longer time without a used measurement is a gap: the track is re-acquired from the next "
                   "measurement (restart=1) [default: 10 x the emitter's median interval].")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path), help="Output CSV.")
@click.option("--sensors", "angle_sensors", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="LOCATED is an angles table of any front-end: triangulate it with these sensors' poses first "
                   "(as `locate --angles`; docs/guide/positioning.md#angles-in).")
@_angles.table_options_except("max_gap_s")  # --max-gap-s stays the track's gap
def track_command(located, q, gate_p, max_gated, max_gap_s, output, angle_sensors=None, **table_kw):
    """Filter a `locate` output (LOCATED.csv) per emitter with a constant-velocity Kalman filter.

    \b
    Tracks X_mm,Y_mm,Z_mm (several sensors), else X_mm,Y_mm (--distance-mm), else the angles,
    with the measurement covariance from their sigma_ columns; each emitter has its own
    track, updated at its own times (time multiplexing needs nothing special).
    Columns: t_s,emitter,<pos>,v<pos>_s,sigma_<pos>,sigma_v<pos>_s,nis,gated,restart,status
    (e.g. X_mm, vX_mm_s, sigma_X_mm, sigma_vX_mm_s).
    \b
    status: start, ok, gated (NIS beyond the gate: not used), gap (re-acquired after a gap),
    jump (max-gated consistent measurements that did not fit the track: a reflection, or
    motion faster than q allows), invalid (empty or non-finite input).  Gated and invalid
    rows have EMPTY state columns: the filter's prediction is never written as a position.
    restart is 1 on gap and jump rows, each also a warning.
    NIS should average the number of tracked coordinates: the summary counts every row,
    and a two-sided chi2 test of the NIS (and of the number gated) warns with the factor
    q looks off by ('q looks 4x too small').
    Example: psdcal track xyz.csv -o track.csv     (same as: psdcal locate ... --track track.csv)
    Angles of any front-end: psdcal track angles.csv --sensors sensors.json -o track.csv
    (triangulated first, as `locate --angles`; the table options as there).
    """
    from psdcal.errors import InputError
    from psdcal.measure.tracking import summary_line, track_csv

    if q is not None and q.strip().lower() != "auto":
        try:
            q = float(q)
        except ValueError:
            raise InputError(f"--q must be a number or 'auto', got {q!r}", field="q") from None
    if max_gap_s is not None and not max_gap_s > 0:
        raise InputError(f"--max-gap-s must be positive, got {max_gap_s}", field="max_gap_s")
    if angle_sensors is not None:  # angles in: triangulated first (psdcal.cli._angles)
        from psdcal.cli._angles import track_angles

        return track_angles(located, angle_sensors, output, table_kw, q=q, gate_p=gate_p, max_gated=max_gated,
                            max_gap_s=max_gap_s)
    info = track_csv(located, output, q=q, gate_p=gate_p, max_gated=max_gated, max_gap_s=max_gap_s)
    click.echo(summary_line(info, output))
    for w in info["warnings"]:
        click.echo(f"psdcal: warning: {w}", err=True)


# --------------------------------------------------------------------------- bundle
def _name_value(items, what):
    from psdcal.errors import InputError

    out = {}
    for it in items:
        if "=" not in it:
            raise InputError(f"{what} must be NAME=PATH, got {it!r}", field=what)
        k, v = it.split("=", 1)
        if not k or not v:
            raise InputError(f"{what} must be NAME=PATH, got {it!r}", field=what)
        if k in out:
            raise InputError(f"sensor {k!r} given twice", field=what)
        out[k] = v
    return out


def _calib_blocks(dns, cal_covs, keep):
    """``(dn_dcalib (N, 2, m), cov_calib (S, m, m))`` zero-padded to the largest calibration, or None."""
    import numpy as np

    m = max((c.shape[0] for c in cal_covs), default=0)
    if m == 0:
        return None
    D = np.zeros((len(dns), 2, m))
    for o, d in enumerate(dns):
        D[o, :, : d.shape[-1]] = d
    Sc = np.zeros((len(cal_covs), m, m))
    for j, c in enumerate(cal_covs):
        Sc[j, : c.shape[0], : c.shape[0]] = c
    return D[keep], Sc


@cli.command("bundle")
@click.argument("located", nargs=-1, required=False)
@click.option("--calib", "calibs", multiple=True, required=False,
              help="Calibration JSON: one for every sensor, or NAME=CALIB.json per sensor (repeat).")
@click.option("--known", "known_csv", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="CSV emitter,X_m,Y_m,Z_m of the emitters at known positions (>= 3, not collinear): they fix "
                   "the world frame.")
@click.option("--wand", "wands", multiple=True,
              help="An emitter moved through the room: every window is a new point (repeat for several).")
@click.option("--points-out", type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the estimated emitter positions: emitter,X_m,Y_m,Z_m,sigma_X_mm,sigma_Y_mm,sigma_Z_mm.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Sensors file (JSON) with every pose and its pose_covariance.")
@_angles.angles_option
def bundle_command(located, calibs, known_csv, wands, points_out, output, angles=None, **table_kw):
    """Calibrate several sensors together: all poses and emitter positions in one bundle adjustment.

    LOCATED are NAME=FILE.csv, one per sensor: `psdcal locate REC --calib ...` outputs (columns
    t_s,emitter,x_mm,y_mm,sigma_x_mm,sigma_y_mm) of recordings made together (the same
    windows).  Fixed emitters (known or not) are averaged over their windows; a --wand
    emitter gives a point per window, matched between sensors by t_s.  Each sensor
    must see >= 3 known emitters (its starting pose); every unknown point >= 2 sensors.
    Or --angles ANGLES.csv: one angles table of every sensor from any front-end (no LOCATED,
    no --calib; docs/guide/positioning.md#angles-in); a --wand emitter's rows are matched by t_s.

    \b
    Example:
      psdcal bundle s1=s1.csv s2=s2.csv s3=s3.csv --calib calib.json --known known.csv \\
          --wand tag -o sensors.json --points-out emitters_est.csv
    The observations are weighted by their angle noise; each sensor's calibration
    covariance, common to all its observations, is propagated through the solution
    and added to the pose and point covariances (inverse Schur complement + that).
    """
    import os

    import numpy as np

    from psdcal.errors import InputError
    from psdcal.io import write_json
    from psdcal.measure.aoa import angles_from_points
    from psdcal.measure.bundle import bundle_adjust
    from psdcal.measure.pose import estimate_pose, mean_points, read_emitters
    from psdcal.measure.sensor_model import SensorModel

    if angles is not None:  # angles from any front-end, no calibration: psdcal.cli._angles
        from psdcal.cli._angles import bundle_angles

        return bundle_angles(angles, located=located, calibs=calibs, known_csv=known_csv, wands=wands,
                             points_out=points_out, output=output, table_kw=table_kw)
    if not located or not calibs:
        raise click.UsageError("Missing " + ("argument 'LOCATED...'" if not located else "option '--calib'")
                               + " (or give --angles ANGLES.csv).")
    files = _name_value(located, "LOCATED")
    if len(files) < 2:
        raise InputError("give at least two sensors NAME=LOCATED.csv", field="LOCATED")
    if len(calibs) == 1 and "=" not in calibs[0]:
        calib_paths = {k: calibs[0] for k in files}
    else:
        calib_paths = _name_value(calibs, "calib")
        missing = [k for k in files if k not in calib_paths]
        if missing:
            raise InputError(f"no --calib for sensor(s) {missing}", field="calib")
    # the NAME=PATH inputs are plain text to click: the output policy's input check, for them
    from psdcal._atomic import guard_outputs

    guard_outputs([("LOCATED", Path(v)) for v in files.values()] + [("--calib", Path(v)) for v in calib_paths.values()],
                  [("--output", output), ("--points-out", points_out)], force=True)
    known_names, known_P, _ = read_emitters(known_csv)
    known = dict(zip(known_names, known_P))
    sensors = sorted(files)  # the answer does not depend on the order; keep the file's stable
    points: list = []
    pidx: dict = {}
    js, ii, ns, covs, dns, cal_covs = [], [], [], [], [], []
    starts_r, starts_c = [], []
    for j, name in enumerate(sensors):
        path = Path(files[name])
        model = SensorModel.load(calib_paths[name])
        cal_covs.append(model.covariance)
        table = _read_table(path)
        if table is None:
            raise InputError("expected a locate output with an 'emitter' column", path=path, line=1)
        header, rows = table
        for c in ("t_s", "x_mm", "y_mm", "sigma_x_mm", "sigma_y_mm"):
            if c not in header:
                raise InputError(f"missing column '{c}' (a `locate --calib` output)", path=path, line=1, field=c)
        col = {c: header.index(c) for c in ("t_s", "emitter", "x_mm", "y_mm", "sigma_x_mm", "sigma_y_mm")}
        try:
            data = np.array([[float(r[col[c]]) for c in ("t_s", "x_mm", "y_mm", "sigma_x_mm", "sigma_y_mm")]
                             for r in rows])
        except (ValueError, IndexError):
            raise InputError("a row is not numbers", path=path) from None
        em = np.array([r[col["emitter"]] for r in rows], dtype=object)
        wand = np.isin(em, list(wands))
        fixed = mean_points(em[~wand], data[~wand, 1:3], data[~wand, 3:5]) if (~wand).any() else None
        obs_names, d, cov_d = [], [], []
        if fixed is not None:
            obs_names += list(fixed.names)
            d.append(fixed.d_mm)
            cov_d.append(fixed.cov_d_mm2)
        if wand.any():
            obs_names += [f"{e}@{t:.6f}" for e, t in zip(em[wand], data[wand, 0])]
            d.append(data[wand, 1:3])
            cov_d.append(np.einsum("ni,ij->nij", data[wand, 3:5] ** 2, np.eye(2)))
        res = angles_from_points(np.concatenate(d), model, np.concatenate(cov_d))
        kn = [k for k, nm in enumerate(obs_names) if nm in known]
        if len(kn) < 3:
            raise InputError(f"sensor {name!r} sees {len(kn)} known emitter(s); its start needs 3", path=path)
        st = estimate_pose(res.n[kn], res.cov_n_noise[kn] + res.cov_n_calib[kn],
                           np.array([known[obs_names[k]] for k in kn]))
        starts_r.append(st.rvec)
        starts_c.append(st.center_w_mm)
        for k, nm in enumerate(obs_names):
            if nm not in pidx:
                pidx[nm] = len(points)
                points.append(nm)
            js.append(j)
            ii.append(pidx[nm])
            ns.append(res.n[k])
            covs.append(res.cov_n_noise[k])
            dns.append(res.dn_dp[k])
    # points seen by one sensor only (a wand window another sensor missed) carry no information: drop them
    ii_a, js_a = np.array(ii), np.array(js)
    counts = np.bincount(ii_a, minlength=len(points))
    keep_pt = np.array([counts[k] >= 2 or points[k] in known for k in range(len(points))])
    keep_obs = keep_pt[ii_a]
    remap = -np.ones(len(points), int)
    remap[keep_pt] = np.arange(keep_pt.sum())
    points = [p for p, k in zip(points, keep_pt) if k]
    br = bundle_adjust(sensors, points, js_a[keep_obs], remap[ii_a[keep_obs]], np.array(ns)[keep_obs],
                       np.array(covs)[keep_obs], known, init_rvecs=np.array(starts_r),
                       init_centers_mm=np.array(starts_c), calib=_calib_blocks(dns, cal_covs, keep_obs))
    base = output.resolve().parent
    entries = []
    for j, name in enumerate(sensors):
        c = br.centers_mm[j]
        sig_c = np.sqrt(np.clip(np.diag(br.cov_poses[j])[3:], 0, None))
        sig_r = np.degrees(np.sqrt(np.clip(np.diag(br.cov_poses[j])[:3], 0, None)))
        entries.append({
            "name": name, "calib": os.path.relpath(Path(calib_paths[name]).resolve(), base),
            "rvec": br.rvecs[j].tolist(), "tvec_mm": br.tvecs_mm[j].tolist(),
            "pose_covariance": {"names": ["omega_x_rad", "omega_y_rad", "omega_z_rad", "tx_mm", "ty_mm", "tz_mm"],
                                "matrix": br.cov_omega_t(j).tolist()},
            "pose": {"center_w_mm": c.tolist(), "sigma_center_mm": sig_c.tolist(),
                     "sigma_rotation_deg": sig_r.tolist(), "method": "bundle", "chi2": br.chi2, "dof": br.dof,
                     "checks": [br.check.to_dict()] if br.check is not None else []},
        })
    write_json(output, {"sensors": entries})
    if points_out is not None:
        from psdcal.measure.bundle import write_points_csv

        write_points_csv(points_out, br)
    n_unknown = int((~br.known).sum())
    click.echo(f"bundle: {len(sensors)} sensors, {len(br.points)} points ({n_unknown} unknown), chi2 {br.chi2:.4g} "
               f"for {br.dof} dof, {br.iterations} iterations; wrote {output}"
               + (f" and {points_out}" if points_out else ""))
    for e in entries:
        p = e["pose"]
        click.echo(f"  {e['name']}: centre +- {max(p['sigma_center_mm']):.3g} mm, rotation +- "
                   f"{max(p['sigma_rotation_deg']):.3g} deg")
    if br.check is not None and br.check.passed is False:
        click.echo(f"warning: the observations do not fit: {br.check.line()} ({br.check.advice})", err=True)


# --------------------------------------------------------------------------- plan
def _read_candidates(path, calib):
    """Sensors from a CSV ``name,X_m,Y_m,Z_m,aim_X_m,aim_Y_m,aim_Z_m`` (centre and aim point) and one calibration."""
    import math

    import numpy as np

    from psdcal.errors import InputError
    from psdcal.measure.positioning import SensorPose
    from psdcal.measure.sensor_model import SensorModel
    from psdcal.study.recordings import look_at

    if calib is None:
        raise InputError("--candidates needs --calib (the sensors' calibration)", field="calib")
    model = SensorModel.load(calib)
    cols = ["X_m", "Y_m", "Z_m", "aim_X_m", "aim_Y_m", "aim_Z_m"]
    from psdcal.io import csv_rows

    rows = csv_rows(path, "candidates file")
    header = [h.strip() for h in rows[0]] if rows else []
    for c in ["name"] + cols:
        if c not in header:
            raise InputError(f"missing column '{c}' (header name,{','.join(cols)})", path=path, line=1, field=c)
    out = []
    for lineno, r in enumerate(rows[1:], start=2):
        if not r or not any(x.strip() for x in r):
            continue
        try:
            v = np.array([float(r[header.index(c)]) for c in cols]) * 1000.0
        except (ValueError, IndexError):
            raise InputError("not a number", path=path, line=lineno) from None
        if not all(math.isfinite(x) for x in v) or np.linalg.norm(v[3:] - v[:3]) == 0:
            raise InputError("the aim point must differ from the centre (finite numbers)", path=path, line=lineno)
        rvec, tvec = look_at(v[:3], v[3:])
        out.append(SensorPose(r[header.index("name")].strip(), model, rvec, tvec))
    if len(out) < 2:
        raise InputError("give at least two candidate sensors", path=path)
    return out


@cli.command("plan")
@click.option("--sensors", "sensors_json", type=click.Path(dir_okay=False, path_type=Path),
              help="Sensors file with the candidate poses (the format of `locate --sensors`; recordings not needed).")
@click.option("--candidates", type=click.Path(dir_okay=False, path_type=Path),
              help="Or a CSV name,X_m,Y_m,Z_m,aim_X_m,aim_Y_m,aim_Z_m: each sensor's centre and the point it "
                   "looks at (with --calib).")
@click.option("--calib", type=click.Path(dir_okay=False, path_type=Path),
              help="With --candidates: the calibration JSON of the sensors.")
@click.option("--room-m", type=(float, float, float), required=True, help="Room size X Y Z in metres.")
@click.option("--height-m", type=float, default=1.0, show_default=True, help="Height of the mapped plane, m.")
@click.option("--grid-mm", type=float, default=100.0, show_default=True, help="Grid spacing, mm.")
@click.option("--sigma-d-mm", type=click.FloatRange(0.0), default=1e-3, show_default=True,
              help="Impact-point noise, mm (added to each sensor's calibration covariance).")
@click.option("--csv", "csv_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the maps: X_m,Y_m,Z_m,n_sensors,sigma_mm,sigma_X_mm,sigma_Y_mm,sigma_Z_mm.")
@click.option("-o", "--output", default="plan.png", show_default=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Output PNG.")
def plan_command(sensors_json, candidates, calib, room_m, height_m, grid_mm, sigma_d_mm, csv_path, output):
    """Plan an installation: coverage and position uncertainty over a plane of the room.

    \b
    For the candidate sensor poses in SENSORS.json, at every grid point of the plane
    Z = --height-m: how many sensors see it, and the 1-sigma of the triangulated position
    (dilution of precision from each sensor's calibrated angle covariance, the impact-point
    noise and, when present, its pose_covariance).
    Example: psdcal plan --sensors sensors.json --room-m 6 4 3 --height-m 1 -o plan.png --csv plan.csv
    \b
    Candidate positions without poses yet: a CSV name,X_m,Y_m,Z_m,aim_X_m,aim_Y_m,aim_Z_m
    (centre and aim point) and the calibration:
      psdcal plan --candidates layout.csv --calib calib.json --room-m 6 4 3 -o plan.png
    """
    import numpy as np

    from psdcal.measure.planning import plan_map, plot_plan, write_plan_csv
    from psdcal.measure.positioning import load_sensors

    from psdcal.errors import InputError

    if (sensors_json is None) == (candidates is None):
        raise InputError("give exactly one of --sensors or --candidates", field="sensors")
    sensors = load_sensors(sensors_json) if sensors_json is not None else _read_candidates(candidates, calib)
    name = (sensors_json or candidates).name
    from psdcal._limits import check_bytes

    if not grid_mm > 0:
        raise InputError(f"--grid-mm must be positive, got {grid_mm}", field="--grid-mm")
    n_cells = (room_m[0] * 1000.0 / grid_mm + 1) * (room_m[1] * 1000.0 / grid_mm + 1)
    check_bytes(n_cells * 8 * (64 + 16 * len(sensors)), f"--grid-mm {grid_mm:g} over the room", "--grid-mm")
    pm = plan_map(sensors, np.array(room_m) * 1000.0, z_mm=height_m * 1000.0, grid_mm=grid_mm, sigma_d_mm=sigma_d_mm)
    plot_plan(pm, output, title=f"{name}: {len(sensors)} sensors, plane Z = {height_m:g} m")
    if csv_path:
        write_plan_csv(pm, csv_path)
    cov2 = np.mean(pm.count >= 2) * 100
    s = pm.sigma_mm[np.isfinite(pm.sigma_mm)]
    rng = f"{s.min():.3g}..{s.max():.3g} mm (median {np.median(s):.3g})" if s.size else "none (no point seen twice)"
    click.echo(f"wrote {output}" + (f" and {csv_path}" if csv_path else "")
               + f": {cov2:.1f} % of the plane seen by >= 2 sensors; position 1-sigma {rng}")


# --------------------------------------------------------------------------- live locate (called by `locate`)
def live_locate(recordings, calib, rate_hz, carriers, emitters, distance_mm, window_s, tdm, schedule, n_emitters,
                min_snr, output, raw_dtype, raw_scale, track_path=None, track_q=None, raw_order=None):
    """`psdcal locate` on a live source ('-', tcp://127.0.0.1:PORT, nidaqmx://...): one sensor, rows as they come."""
    from psdcal.errors import InputError
    from psdcal.measure.live import locate_stream
    from psdcal.measure.locate import LocateConfig
    from psdcal.measure.sensor_model import SensorModel
    from psdcal.signal.live import open_stream
    from psdcal.signal.stream import load_schedule

    if calib is None or len(recordings) != 1:
        raise InputError("live input works with one sensor: one source and --calib", field="calib")
    if distance_mm is not None and not distance_mm > 0:
        raise InputError(f"--distance-mm must be positive, got {distance_mm}", field="distance_mm")
    sched = load_schedule(schedule) if schedule else None
    # a live stream cannot be pre-scanned for the on-times: the window is --window-s or 10 ms
    config = LocateConfig(carriers_hz=tuple(carriers), window_s=0.01 if window_s is None else window_s,
                          distance_mm=distance_mm, emitters=tuple(emitters) or None, min_snr=min_snr,
                          tdm=bool(tdm or sched is not None), schedule=sched, n_emitters=n_emitters)
    model = SensorModel.load(calib)
    stream = open_stream(str(recordings[0]), rate_hz, dtype=raw_dtype, scale=raw_scale, order=raw_order)
    from psdcal.measure.locate import single_columns

    tracker = live_tracker(track_path, single_columns(distance_mm is not None), track_q)
    try:
        summary = locate_stream(stream, model, output, config, on_rows=None if tracker is None else tracker.add)
    finally:
        info = None if tracker is None else tracker.close()
    msg = (f"wrote {summary.n_rows} rows to {output} ({summary.n_samples / stream.rate_hz:.6g} s of live signal, "
           f"{summary.n_windows} windows, {summary.n_skipped} below --min-snr); {summary.latency_text()}")
    click.echo(msg, err=str(output) == "-")
    print_track_summary(info, track_path, output)


def live_tracker(track_path, columns, track_q):
    """``--track`` with live input: the track written row by row with the located rows (None without --track)."""
    if not track_path:
        return None
    from psdcal.measure.track_live import LiveTrackWriter

    return LiveTrackWriter(track_path, columns, q=track_q)


def print_track_summary(info, track_path, output) -> None:
    """The live track's summary line and warnings, once the sources ended (nothing without --track)."""
    if info is None:
        return
    from psdcal.measure.tracking import summary_line

    click.echo(summary_line(info, track_path), err=str(output) == "-")
    for w in info["warnings"]:
        click.echo(f"psdcal: warning: {w}", err=True)
