"""``simulate-recording template|room``: simulated raw recordings of template views and of a room.

A thin layer over :mod:`psdcal.study.recordings` (no numerics here).
"""
from __future__ import annotations

from pathlib import Path

import click

from psdcal.cli import cli

_FORMATS = ("npy", "csv", "hdf5", "tdms")


def _lens_model(lens, psd_l1=0.0):
    from dataclasses import replace

    from psdcal.measure.sensor_model import SensorModel
    from psdcal.study.simulate import LENSES

    intr, dist = LENSES[lens]
    return SensorModel(intrinsics=intr, distortion=replace(dist, l1=dist.l1 + psd_l1))


def _write_schedule(path, sched):
    from psdcal._atomic import write_text_atomic

    lines = ["emitter,t_start_s,t_end_s"] + [f"{e},{a:.9g},{b:.9g}" for e, a, b in sched]
    write_text_atomic(path, "\n".join(lines) + "\n")


@cli.group("simulate-recording")
def simulate_recording_group():
    """Simulate four-channel recordings with known truth (template views, or a room).

    \b
    psdcal simulate-recording template -o cal/      # recordings for amplitudes + calibrate
    psdcal simulate-recording room -o room/         # recordings for pose + locate
    Run each with --help for the files it writes.
    """


@simulate_recording_group.command("template")
@click.option("--lens", type=click.Choice(["lens1", "lens2"]), default="lens2", show_default=True,
              help="The truth: one of the paper's lens presets.")
@click.option("--psd-l1", type=float, default=0.0, show_default=True, help="PSD radial distortion l1 added, mm^-2.")
@click.option("--views", type=click.IntRange(3, 1000), default=12, show_default=True, help="Template views.")
@click.option("--mux", type=click.Choice(["tdm", "fdm"]), default="tdm", show_default=True,
              help="tdm: one LED on at a time (a schedule is written); fdm: all LEDs at once on their own carriers.")
@click.option("--format", "fmt", type=click.Choice(_FORMATS), default="npy", show_default=True,
              help="Recording file format.")
@click.option("--rate-hz", type=float, default=50_000.0, show_default=True, help="Sampling rate.")
@click.option("--carrier-hz", type=float, default=1000.0, show_default=True,
              help="Carrier (tdm), or the first LED's carrier (fdm).")
@click.option("--carrier-step-hz", type=float, default=100.0, show_default=True,
              help="fdm: carrier spacing between consecutive LEDs.")
@click.option("--on-s", type=float, default=0.02, show_default=True,
              help="tdm: time each LED is on; fdm: length of each recording (one window).")
@click.option("--gap-s", type=float, default=0.004, show_default=True, help="tdm: dark time between LEDs.")
@click.option("--snr-db", type=float, default=60.0, show_default=True,
              help="SNR against the mean channel signal power (same noise sigma on every channel).")
@click.option("--no-noise", is_flag=True, help="Noiseless recordings (overrides --snr-db).")
@click.option("--gain-imbalance", type=click.FloatRange(0.0, 0.5), default=0.0, show_default=True,
              help="Channel gains drawn in 1 +- this (calibrate with --fit-gains to estimate them).")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (same seed, same files).")
@click.option("-o", "--out-dir", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Folder for the recordings, template.csv, schedule.csv (tdm) and truth.json.")
def simulate_template_command(lens, psd_l1, views, mux, fmt, rate_hz, carrier_hz, carrier_step_hz, on_s, gap_s,
                              snr_db, no_noise, gain_imbalance, seed, out_dir):
    """Recordings of the calibration template's LEDs in several poses.

    \b
    Writes OUT_DIR/view_00.npy ... (one recording per view, channels vx1,vx2,vy1,vy2),
    OUT_DIR/template.csv (point_id,X_mm,Y_mm), OUT_DIR/schedule.csv (tdm: emitter,t_start_s,t_end_s,
    the LED = the template's point_id), OUT_DIR/truth.json (intrinsics, distortion, gains, poses,
    the demodulation settings) and OUT_DIR/amplitudes.sh (the amplitudes commands for every view).
    \b
    Example (tdm):
      psdcal simulate-recording template --views 8 -o cal
      psdcal amplitudes cal/view_00.npy --rate-hz 50000 --carrier-hz 1000 --window-s 0.005 \\
          --schedule cal/schedule.csv --image-id 0 -o cal/amp_00.csv
    """
    from psdcal.io import write_json, write_template
    from psdcal.study.recordings import FORMATS, simulate_template_views, write_recording
    from psdcal.study.simulate import LENSES

    intr, dist = LENSES[lens]
    from psdcal._limits import check_bytes

    check_bytes(views * 14 * max(on_s + gap_s, 0.0) * rate_hz * 8 * 4 * 4, f"--on-s {on_s:g} x --views {views}",
                "--on-s")
    tv = simulate_template_views((intr, dist), n_views=views, mux=mux, rate_hz=rate_hz, carrier_hz=carrier_hz,
                                 carrier_step_hz=carrier_step_hz, on_s=on_s, gap_s=gap_s,
                                 snr_db=None if no_noise else snr_db, gain_imbalance=gain_imbalance,
                                 psd_l1=psd_l1, seed=seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_template(out_dir / "template.csv", tv.point_ids, tv.template_mm)
    files = []
    for v, x in enumerate(tv.x):
        p = out_dir / f"view_{v:02d}{FORMATS[fmt]}"
        write_recording(p, x, tv.rate_hz)
        files.append(p.name)
    if tv.schedule is not None:
        _write_schedule(out_dir / "schedule.csv", tv.schedule)
        demod = f"--carrier-hz {tv.carriers_hz[0]:g} --window-s {tv.window_s:g} --schedule {out_dir / 'schedule.csv'}"
    else:
        demod = " ".join(f"--carrier-hz {f:g} --emitter {pid}" for f, pid in zip(tv.carriers_hz, tv.point_ids))
        demod += f" --window-s {tv.window_s:g}"
    rate_opt = "" if fmt in ("csv", "hdf5", "tdms") else f" --rate-hz {tv.rate_hz:g}"
    cmds = [f"psdcal amplitudes {out_dir / f}{rate_opt} {demod} --image-id {v} -o {out_dir / f'amp_{v:02d}.csv'}"
            for v, f in enumerate(files)]
    from psdcal._atomic import write_text_atomic

    write_text_atomic(out_dir / "amplitudes.sh", "\n".join(cmds) + "\n")
    truth = dict(tv.truth, lens=lens, recordings=files, format=fmt,
                 amplitudes_options=f"{rate_opt.strip()} {demod}".strip())
    write_json(out_dir / "truth.json", truth)
    click.echo(f"wrote {len(files)} {fmt} recordings ({mux}, {len(tv.point_ids)} LEDs, "
               f"{tv.x[0].shape[1] / tv.rate_hz:.4g} s each), template.csv, truth.json, amplitudes.sh to {out_dir}")


@simulate_recording_group.command("room")
@click.option("--lens", type=click.Choice(["lens1", "lens2"]), default="lens2", show_default=True,
              help="The sensors' true intrinsics: one of the paper's lens presets.")
@click.option("--psd-l1", type=float, default=0.0, show_default=True, help="PSD radial distortion l1 added, mm^-2.")
@click.option("--calib", type=click.Path(dir_okay=False, path_type=Path),
              help="Calibration JSON the sensors file refers to (default: write calib_truth.json, the exact truth).")
@click.option("--room-m", type=(float, float, float), default=(6.0, 4.0, 3.0), show_default=True,
              help="Room size X Y Z in metres (the world frame: floor corner at the origin, Z up).")
@click.option("--sensors", "n_sensors", type=click.IntRange(1, 16), default=2, show_default=True,
              help="Sensors near the ceiling around the room, looking at its centre.")
@click.option("--anchors", type=click.IntRange(0, 40), default=5, show_default=True,
              help="Fixed emitters at known positions (written to emitters.csv, for psdcal pose).")
@click.option("--sensors-in", type=click.Path(dir_okay=False, path_type=Path),
              help="Use these sensor poses (a sensors file; names, rvec, tvec_mm) instead of the default ring "
                   "(their calibrations are ignored: the truth is --lens).")
@click.option("--emitters-in", type=click.Path(dir_okay=False, path_type=Path),
              help="Fixed emitters at these positions (CSV emitter,X_m,Y_m,Z_m) instead of random --anchors.")
@click.option("--moving", type=click.Choice(["circle", "line", "none"]), default="circle", show_default=True,
              help="A moving emitter 'tag' and its trajectory.")
@click.option("--speed-mm-s", type=float, default=500.0, show_default=True, help="Speed of the moving emitter.")
@click.option("--radius-mm", type=float, default=600.0, show_default=True, help="Radius of the circle.")
@click.option("--duration-s", type=float, default=1.0, show_default=True, help="Recording length.")
@click.option("--survey-s", type=float, default=0.0, show_default=True,
              help="Light the fixed emitters during the first SURVEY_S seconds only and the moving one after "
                   "(a survey for `pose`, then the tracking); 0: all lit all the time.")
@click.option("--mux", type=click.Choice(["fdm", "tdm"]), default="fdm", show_default=True,
              help="fdm: every emitter on its own carrier; tdm: the emitters take turns (schedule.csv).")
@click.option("--slot-s", type=float, default=0.02, show_default=True, help="tdm: time each emitter is on.")
@click.option("--format", "fmt", type=click.Choice(_FORMATS), default="npy", show_default=True,
              help="Recording file format.")
@click.option("--rate-hz", type=float, default=20_000.0, show_default=True, help="Sampling rate.")
@click.option("--carrier-hz", type=float, default=1000.0, show_default=True, help="First emitter's carrier.")
@click.option("--carrier-step-hz", type=float, default=150.0, show_default=True,
              help="fdm: carrier spacing between emitters.")
@click.option("--snr-db", type=float, default=60.0, show_default=True,
              help="SNR against the mean channel signal power (docs/model.md#snr-definition).")
@click.option("--gain-imbalance", type=click.FloatRange(0.0, 0.5), default=0.0, show_default=True,
              help="Each sensor's channel gains drawn in 1 +- this.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@click.option("--reflection", "reflections", multiple=True, metavar="AXIS=V:ATT[:SENSORS[:EMITTERS]]",
              help="Add a reflected path off the plane AXIS=V (metres; e.g. z=0, the floor) with power attenuation "
                   "ATT, for the comma-separated SENSORS and EMITTERS (default all); repeatable. The PSD sees the "
                   "power-weighted centroid of the direct and reflected spots.")
@click.option("-o", "--out-dir", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output folder.")
def simulate_room_command(lens, psd_l1, calib, room_m, n_sensors, anchors, sensors_in, emitters_in, moving, speed_mm_s, radius_mm, duration_s,
                          survey_s, mux, slot_s, fmt, rate_hz, carrier_hz, carrier_step_hz, snr_db, gain_imbalance, seed,
                          reflections, out_dir):
    """Recordings of emitters (fixed and moving) seen by sensors placed in a room.

    \b
    Writes to OUT_DIR:
      s1.npy, s2.npy ...   one recording per sensor
      sensors.json         the sensors file of `locate --sensors` with the TRUE poses
      emitters.csv         emitter,X_m,Y_m,Z_m,carrier_hz of the fixed emitters (for `pose`)
      truth.json           emitters, sensors, signal settings
      truth_track.csv      t_s,emitter,X_mm,Y_mm,Z_mm of every emitter every millisecond
      schedule.csv         (tdm) emitter,t_start_s,t_end_s
      calib_truth.json     (without --calib) the sensors' exact calibration
    Example:
      psdcal simulate-recording room --sensors 2 --anchors 5 -o room
    """
    import numpy as np

    from psdcal._atomic import write_text_atomic
    from psdcal.errors import InputError
    from psdcal.io import write_json
    from psdcal.study.recordings import FORMATS, room_layout, simulate_room, write_recording

    truth_model = _lens_model(lens, psd_l1)
    given_sensors = anchors_mm = anchor_names = None
    if sensors_in is not None:
        import json

        from psdcal.study.recordings import RoomSensor

        try:
            data = json.loads(Path(sensors_in).read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError("sensors file not found", path=sensors_in) from None
        except json.JSONDecodeError as exc:
            raise InputError(f"not valid JSON: {exc.msg}", path=sensors_in, line=exc.lineno) from None
        items = data.get("sensors") if isinstance(data, dict) else data
        if not isinstance(items, list) or not items:
            raise InputError("expected a list of sensors", path=sensors_in, field="sensors")
        given_sensors = []
        for i, it in enumerate(items):
            try:
                rv = np.asarray(it["rvec"], dtype=float)
                tv = np.asarray(it["tvec_mm"], dtype=float)
                assert rv.shape == (3,) and tv.shape == (3,) and np.all(np.isfinite(rv)) and np.all(np.isfinite(tv))
            except (KeyError, TypeError, ValueError, AssertionError):
                raise InputError("each sensor needs 'rvec' and 'tvec_mm' (3 numbers each)", path=sensors_in,
                                 field=f"sensors[{i}]") from None
            given_sensors.append(RoomSensor(str(it.get("name", f"s{i + 1}")), truth_model, rv, tv))
    if emitters_in is not None:
        from psdcal.measure.pose import read_emitters

        anchor_names, anchors_mm, _ = read_emitters(emitters_in)
    sensors, emitters = room_layout(truth_model, room_mm=np.array(room_m) * 1000.0, n_sensors=n_sensors,
                                    sensors=given_sensors, anchors_mm=anchors_mm, anchor_names=anchor_names,
                                    n_anchors=anchors, moving=None if moving == "none" else moving,
                                    speed_mm_s=speed_mm_s, radius_mm=radius_mm, carrier_hz=carrier_hz,
                                    carrier_step_hz=carrier_step_hz, seed=seed, survey_s=survey_s)
    if not emitters:
        raise InputError("no emitters: give --anchors > 0 or a --moving trajectory", field="anchors")
    from psdcal._limits import check_bytes

    check_bytes(max(duration_s, 0.0) * rate_hz * 8 * 4 * 4 * max(len(sensors), 1), f"--duration-s {duration_s:g}",
                "--duration-s")
    from psdcal.study.reflections import parse_reflection

    mirrors = [parse_reflection(r, np.array(room_m) * 1000.0) for r in reflections]
    rr = simulate_room(sensors, emitters, duration_s=duration_s, rate_hz=rate_hz, snr_db=snr_db, mux=mux,
                       slot_s=slot_s, gain_imbalance=gain_imbalance, seed=seed, reflections=mirrors)
    out_dir.mkdir(parents=True, exist_ok=True)
    if calib is None:
        calib_name = "calib_truth.json"
        d = truth_model.to_dict()
        d.pop("covariance")  # the exact truth: no parameter uncertainty
        write_json(out_dir / calib_name, d)
    else:
        import os

        calib_name = os.path.relpath(Path(calib).resolve(), out_dir.resolve())
    entries = []
    for s, x in zip(sensors, rr.x):
        name = f"{s.name}{FORMATS[fmt]}"
        write_recording(out_dir / name, x, rr.rate_hz)
        entries.append({"name": s.name, "calib": calib_name, "rvec": np.asarray(s.rvec).tolist(),
                        "tvec_mm": np.asarray(s.tvec_mm).tolist(), "recording": name})
    write_json(out_dir / "sensors.json", {"sensors": entries})
    lines = ["emitter,X_m,Y_m,Z_m,carrier_hz"]
    for e in emitters:
        if e.kind == "static":
            p = np.asarray(e.p0_mm) / 1000.0
            lines.append(f"{e.name},{p[0]:.9g},{p[1]:.9g},{p[2]:.9g},{e.carrier_hz:g}")
    write_text_atomic(out_dir / "emitters.csv", "\n".join(lines) + "\n")
    tg = np.arange(0.0, duration_s + 1e-12, 1e-3)
    rows = ["t_s,emitter,X_mm,Y_mm,Z_mm"]
    for e in emitters:
        P = e.position(tg)
        rows += [f"{t:.6f},{e.name},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f}" for t, p in zip(tg, P)]
    write_text_atomic(out_dir / "truth_track.csv", "\n".join(rows) + "\n")
    if rr.schedule is not None:
        _write_schedule(out_dir / "schedule.csv", rr.schedule)
    write_json(out_dir / "truth.json", dict(rr.truth, lens=lens, format=fmt, room_m=list(room_m)))
    hidden = [(s.name, e.name) for i, s in enumerate(sensors) for j, e in enumerate(emitters) if not rr.visible[i, j]]
    click.echo(f"wrote {len(sensors)} {fmt} recordings of {len(emitters)} emitters ({mux}, {duration_s:g} s), "
               f"sensors.json, emitters.csv, truth.json, truth_track.csv to {out_dir}")
    if hidden:
        click.echo(f"warning: not always in view: {', '.join(f'{e} from {s}' for s, e in hidden)}", err=True)


# --------------------------------------------------------------------------- pose
