"""``psdcal locate``, ``amplitudes``, ``aoa`` and ``errormap``: a thin layer over
:mod:`psdcal.measure.locate` and :mod:`psdcal.measure.positioning` (no numerics here)."""
from __future__ import annotations

import click

from psdcal.cli import _angles, cli

_PROGRESS_MIN_SAMPLES = 2_000_000


def _channels(value):
    if value is None:
        return None
    names = [v.strip() for v in value.split(",")]
    from psdcal.signal.module import is_module_spec

    if is_module_spec(value):
        raise click.BadParameter("x, y, sum recordings of a position module are read by 'psdcal module REC "
                                 f"--channels {value}' (LEDs found, positions, angles with --calib)")
    if len(names) != 4 or not all(names):
        raise click.BadParameter("give 4 comma-separated names (for vx1,vx2,vy1,vy2)")
    if len(set(names)) != 4:
        raise click.BadParameter(f"the 4 channel names must differ, got {','.join(names)}")
    return tuple(names)


def check_sensor(model, expect_sensor, allow_no_covariance) -> None:
    """The calibration is of the expected sensor (``--expect-sensor``) and carries an uncertainty."""
    from psdcal.errors import InputError

    if expect_sensor is not None and model.sensor_id != expect_sensor:
        got = "no sensor_id" if model.sensor_id is None else f"sensor_id {model.sensor_id!r}"
        raise InputError(f"the calibration has {got}, not the expected {expect_sensor!r}", path=model.source,
                         field="sensor_id")
    model.require_uncertainty(allow_no_covariance)
    if model.sensor_id is not None:
        click.echo(f"calibration of sensor {model.sensor_id} ({model.source})")


def _guard_window(config, recs) -> None:
    """Refuse a --window-s whose buffers would not fit in memory (before demodulating)."""
    from psdcal._limits import check_bytes

    if config.window_s is None:
        return
    for rec in recs:
        n = float(config.window_s) * rec.rate_hz
        check_bytes(n * 8 * 4 * (2 * max(len(config.carriers_hz), 1) + 6), f"--window-s {config.window_s:g} at "
                    f"{rec.rate_hz:g} Hz", "--window-s")


def _one_shot_mode(recs, config) -> None:
    """Files in, one run: the compiled kernels only if the whole output pays for loading them.

    ``psdcal._jit.set_mode_for`` of the rows the run writes (windows x emitters x
    recordings): a short recording takes the numpy path and never imports numba.
    """
    import os

    from psdcal import _jit

    windows = 0.0
    for r in recs:
        n = r.n_samples
        if n is None:  # a text recording: at least 8 bytes a sample row, so this over-counts
            try:
                n = os.path.getsize(r.path) // 8
            except (OSError, TypeError):
                return _jit.set_mode_for(None)
        rate = r.rate_hz or 0.0
        window_s = config.window_s or 0.001  # None: 0.01 s, or TDM on-times (longer than 1 ms)
        windows += n / max(window_s * rate, 1.0) if rate > 0 else n
    per_window = max(len(config.carriers_hz), config.n_emitters or 0, len(config.emitters or ()), 1)
    _jit.set_mode_for(int(windows * per_window))


def _aoa_one_shot_mode(points) -> None:
    """``psdcal aoa``: as :func:`_one_shot_mode`, the rows estimated from the file's size (>= 20 bytes a row)."""
    import os

    from psdcal import _jit

    try:
        _jit.set_mode_for(os.path.getsize(points) // 20)
    except (OSError, TypeError):
        _jit.set_mode_for(None)


def _demod_options(f):
    """Options shared by the commands that demodulate recordings (locate, amplitudes)."""
    opts = [
        click.option("--rate-hz", type=float, help="Sampling rate (when the file does not carry one)."),
        click.option("--carrier-hz", "carriers", type=float, multiple=True, required=True,
                     help="Carrier of an emitter; repeat for several emitters at once (frequency multiplexing)."),
        click.option("--emitter", "emitters", multiple=True, help="Name of each carrier's emitter (default '<f>Hz')."),
        click.option("--window-s", type=float, default=None,
                     help="Demodulation window, s: one output per window [default: 0.01; with --tdm chosen from "
                          "the on-times measured on the recording]."),
        click.option("--tdm", is_flag=True, help="Time multiplexing: one row per segment where one LED is on."),
        click.option("--schedule", type=click.Path(dir_okay=False),
                     help="TDM schedule CSV emitter,t_start_s,t_end_s (implies --tdm)."),
        click.option("--n-emitters", type=int,
                     help="TDM without schedule: emitters per cycle (names repeat); a segment count that is not "
                          "a multiple of it is refused."),
        click.option("--check-carriers/--no-check-carriers", default=True, show_default=True,
                     help="Measure the carriers on the start of the recording; warn when one asked is off."),
        click.option("--min-snr", type=float, default=10.0, show_default=True,
                     help="Drop a window/segment whose total amplitude is below this many sigma."),
        click.option("--channels",
                     help="Names of vx1,vx2,vy1,vy2 in the file (CSV columns, HDF5 datasets, TDMS channels)."),
        click.option("--dataset", help="HDF5: an (n, 4) dataset."),
        click.option("--group", help="HDF5 or TDMS group."),
        click.option("--chunk-samples", type=int, default=1 << 16, show_default=True,
                     help="Samples per channel read at once (bounds memory)."),
        click.option("--progress/--no-progress", default=None, help="Progress bar (default: on for long files)."),
        click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
                     help="Output file (CSV, or NumPy .npy with --format npy)."),
        click.option("--format", "output_format", type=click.Choice(["csv", "npy"]), default="csv", show_default=True,
                     help="Output format: CSV text, or one NumPy structured array (a field per column, full "
                          "precision; np.load(path)), no text formatting to write or parse."),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


@cli.command("locate")
@click.argument("recordings", nargs=-1, type=click.Path(dir_okay=False))
@click.option("--calib", type=click.Path(dir_okay=False), help="Calibration JSON of the sensor (one sensor).")
@click.option("--sensors", type=click.Path(dir_okay=False),
              help="SENSORS.json: several calibrated sensors with poses (3D triangulation).")
@click.option("--distance-mm", type=float, help="Plane distance S: also write X_mm, Y_mm on that plane.")
@click.option("--track", "track_path", type=click.Path(dir_okay=False),
              help="Also write TRACK.csv: each emitter filtered by a constant-velocity Kalman filter "
                   "(positions, velocities, sigmas, NIS, gated, restart, status); see `psdcal track --help`. "
                   "With live input, each tracked row is written right after its located row.")
@click.option("--track-q", type=float, default=None,
              help="Tracking process noise, mm^2/s^3 (deg^2/s^3 for angles) [default: 1e6, 10].")
@click.option("--raw-dtype", type=click.Choice(["float32", "float64", "int16"]), default="float64",
              show_default=True, help="Live input (RECORDING '-' or tcp://127.0.0.1:PORT): sample type of the "
                                      "interleaved vx1,vx2,vy1,vy2 frames (little-endian).")
@click.option("--raw-scale", type=float, default=1.0, show_default=True,
              help="Live input: factor applied to every sample (e.g. volts per int16 count).")
@click.option("--raw-order", default=None, metavar="ORDER",
              help="Live input: the frame's four channels in their order when not vx1,vx2,vy1,vy2 (e.g. "
                   "vx1,vy1,vx2,vy2). Whatever the order, the x and y channel sums are checked on the data "
                   "(they are equal in the right order) and a disagreement is a warning.")
@click.option("--gains", "gains_file", type=click.Path(dir_okay=False),
              help="Gains JSON from 'psdcal gains': channel gains (per carrier when it has them) replace the "
                   "calibration's, their covariance enters the sigmas.")
@click.option("--expect-sensor", "expect_sensor", default=None, metavar="ID",
              help="Refuse a calibration whose sensor_id is not ID (or has none): catches the calibration of "
                   "another sensor or lens.")
@click.option("--allow-no-covariance", is_flag=True, default=False,
              help="Accept a calibration without covariance or standard errors (its uncertainty is then left out "
                   "of every sigma); refused otherwise.")
@click.option("--offset-s", "offsets", multiple=True, metavar="NAME=SECONDS",
              help="Several sensors live: sensor NAME's first sample was taken SECONDS after the first sensor's "
                   "(repeat per sensor; the streams are aligned to the whole sample); 'auto': estimated for "
                   "every sensor from the arrival times of the first 0.5 s (sources sending at the real rate).")
@click.option("--replay", type=click.Path(dir_okay=False),
              help="With --sensors: play a session from `psdcal record` through the live path (no RECORDING).")
@click.option("--speed", type=click.FloatRange(0.0), default=1.0, show_default=True,
              help="--replay speed: 1 real time, 10 ten times faster, 0 as fast as possible.")
@click.option("--record", "record_path", type=click.Path(dir_okay=False),
              help="With --sensors and live sources: also record the session to this file (for --replay).")
@_demod_options
@_angles.angles_option
def locate_command(recordings, calib, sensors, gains_file, rate_hz, carriers, emitters, distance_mm, window_s, tdm,
                   schedule, n_emitters, check_carriers, min_snr, channels, dataset, group, chunk_samples, progress,
                   output, track_path=None, track_q=None, raw_dtype="float64", raw_scale=1.0, output_format="csv",
                   expect_sensor=None, allow_no_covariance=False, raw_order=None, angles=None, offsets=(),
                   replay=None, speed=1.0, record_path=None, **table_kw):
    """Demodulate RECORDING(s) and write angles of arrival and positions.

    \b
    One sensor:
      psdcal locate rec.npy --calib calib.json --rate-hz 125000 \\
          --carrier-hz 1000 --carrier-hz 1300 --distance-mm 5000 -o out.csv
    columns: t_s,emitter,x_mm,y_mm,alpha_x_deg,alpha_y_deg[,X_mm,Y_mm],
             sigma_x_mm,sigma_y_mm,sigma_alpha_x_deg,sigma_alpha_y_deg[,sigma_X_mm,sigma_Y_mm]
    \b
    Several sensors (recordings from SENSORS.json or given in its order):
      psdcal locate --sensors sensors.json --rate-hz 125000 --carrier-hz 1000 -o xyz.csv
    columns: t_s,emitter,X_mm,Y_mm,Z_mm,sigma_X_mm,sigma_Y_mm,sigma_Z_mm,n_sensors,chi2,dof,flagged

    \b
    Angles from any AoA front-end (no calibration, no recordings; docs/guide/positioning.md#angles-in):
      psdcal locate --angles angles.csv --sensors sensors.json -o xyz.csv \\
          [--convention tangent --align-to SENSOR --track track.csv]
    the same columns; every emitter at every time step seen by two or more sensors.

    Recordings: .npy (n, 4), .csv (header vx1,vx2,vy1,vy2[,t_s]), .h5/.hdf5, .tdms.
    Sigmas are 1-sigma, from the signal noise and the calibration covariance.
    Signs: seen from behind the sensor with the chip's +y edge up, alpha_x > 0
    is an emitter right of the optical axis, alpha_y > 0 one below it (the lens
    inverts the image; docs/model.md#hardware-conventions).

    \b
    Live input (one sensor): RECORDING '-' (stdin) or tcp://127.0.0.1:PORT (a local server
    sending interleaved frames, --raw-dtype, --raw-scale) or nidaqmx://Dev1/ai0:3 (psdcal[daq]);
    --rate-hz required; rows are written and flushed as windows complete.
    \b
    Several sensors live: --sensors with one live source per sensor, in its order (also
    file:PATH, raw frames from a file or named pipe); --offset-s NAME=SECONDS aligns a sensor
    that started later; --schedule for time multiplexing (one row per entry); --record SESSION
    keeps the session; --replay SESSION --speed X plays one back through the same path (see
    `psdcal record --help`).
    """
    from psdcal.errors import InputError
    from psdcal.measure.locate import LocateConfig, locate_multi_to_csv, locate_to_csv
    from psdcal.signal.recording import open_recording
    from psdcal.signal.stream import load_schedule

    if angles is not None:  # angles from any front-end: psdcal.cli._angles
        from psdcal.cli._angles import locate_angles

        return locate_angles(angles, sensors, output, recordings=recordings, calib=calib, carriers=carriers,
                             output_format=output_format, track_path=track_path, track_q=track_q, table_kw=table_kw)
    if not carriers:
        raise click.UsageError("Missing option '--carrier-hz' (or give --angles ANGLES.csv).")
    if (calib is None) == (sensors is None):
        raise InputError("give exactly one of --calib (one sensor) or --sensors (several)", field="calib")
    from psdcal.signal.live import is_stream_source
    from psdcal.signal.session import is_live_source

    if sensors is not None and (replay is not None or any(is_live_source(str(r)) for r in recordings)):
        from psdcal.cli.live_cmd import live_locate_multi  # several sensors live, or a replayed session

        if output_format != "csv":
            raise InputError("--format npy is not available with --sensors (several sensors): write CSV",
                             field="format")
        return live_locate_multi(recordings, sensors, rate_hz, carriers, emitters, window_s, tdm, schedule,
                                 n_emitters, min_snr, output, raw_dtype, raw_scale, track_path, track_q, offsets,
                                 replay, speed, record_path, allow_no_covariance)
    if replay is not None or record_path is not None or offsets:
        raise InputError("--replay, --record and --offset-s work with several sensors live (--sensors and live "
                         "sources)", field="replay")
    if any(is_stream_source(str(r)) for r in recordings):  # live input: see `psdcal.cli.system_cmd.live_locate`
        from psdcal.cli.system_cmd import live_locate

        if channels is not None:
            raise InputError("a live stream's frames carry no channel names: give their order with --raw-order "
                             "(e.g. vx1,vy1,vx2,vy2), not --channels", field="channels")
        if calib is not None:
            from psdcal.measure.sensor_model import SensorModel

            check_sensor(SensorModel.load(calib), expect_sensor, allow_no_covariance)

        return live_locate(recordings, calib, rate_hz, carriers, emitters, distance_mm, window_s, tdm, schedule,
                           n_emitters, min_snr, output, raw_dtype, raw_scale, track_path, track_q, raw_order)
    if raw_order is not None:
        raise InputError("--raw-order is for live input ('-', tcp://, nidaqmx://); name a file's channels with "
                         "--channels", field="raw_order")
    sched = load_schedule(schedule) if schedule else None
    config = LocateConfig(
        carriers_hz=tuple(carriers),
        window_s=window_s,
        distance_mm=distance_mm,
        emitters=tuple(emitters) or None,
        min_snr=min_snr,
        tdm=bool(tdm or sched is not None),
        schedule=sched,
        n_emitters=n_emitters,
        chunk_samples=chunk_samples,
        check_carriers=check_carriers,
        output_format=output_format,
    )
    opts = dict(channels=_channels(channels), dataset=dataset, group=group)
    if calib is not None:
        from psdcal.measure.sensor_model import SensorModel

        if len(recordings) != 1:
            raise InputError(f"give one RECORDING with --calib, got {len(recordings)}", field="RECORDING")
        model = SensorModel.load(calib)
        check_sensor(model, expect_sensor, allow_no_covariance)
        models = None
        if gains_file is not None:
            from psdcal.calibration.bench import load_gains, with_gains

            per = [with_gains(model, *load_gains(gains_file, f)) for f in carriers]
            model = per[0]
            models = dict(zip(config.emitter_names(), per)) if len(per) > 1 else None
        recs = [open_recording(recordings[0], rate_hz, **opts)]
    else:
        from psdcal.measure.positioning import load_sensors

        if gains_file is not None:
            raise InputError("--gains applies to one sensor (--calib); put the gains in each sensor's calibration",
                             field="gains")
        poses = load_sensors(sensors)
        for p in poses:  # every sensor's calibration carries its uncertainty (or the user said it need not)
            check_sensor(p.model, None, allow_no_covariance)
        paths = list(recordings) or [p.recording for p in poses]
        if len(paths) != len(poses) or any(p is None for p in paths):
            raise InputError(
                f"{len(poses)} sensors need {len(poses)} recordings (give them in order, or a 'recording' "
                "key per sensor)", path=sensors, field="recording")
        recs = [open_recording(p, rate_hz, **opts) for p in paths]
    _guard_window(config, recs)
    _one_shot_mode(recs, config)

    total = recs[0].n_samples
    show = progress if progress is not None else (total is not None and total >= _PROGRESS_MIN_SAMPLES)
    bar = _Bar(total, recs[0].path) if show else None
    try:
        cb = bar.update if bar else None
        if calib is not None:
            summary = locate_to_csv(recs[0], model, output, config, progress=cb, models=models)
        else:
            summary = locate_multi_to_csv(recs, poses, output, config, progress=cb)
    finally:
        if bar:
            bar.close()
    _report(summary, output)
    if track_path:
        from psdcal.measure.tracking import summary_line, track_csv

        from psdcal._atomic import staged

        info = track_csv(staged(output), track_path, q=track_q)
        click.echo(summary_line(info, track_path))
        for w in info["warnings"]:
            click.echo(f"psdcal: warning: {w}", err=True)


for _p in locate_command.params:  # --carrier-hz is not needed with --angles (checked in the command)
    if _p.name == "carriers":
        _p.required = False


def _report(summary, output) -> None:
    """The one-line summary (stdout) and the self-check warnings (stderr)."""
    for w in summary.warnings:
        click.echo(f"psdcal: warning: {w}", err=True)
    segs = "" if summary.n_segments is None else f", {summary.n_segments} TDM segments"
    flagged = "" if summary.n_flagged is None else f", {summary.n_flagged} flagged by their chi2"
    click.echo(
        f"wrote {summary.n_rows} rows to {output} ({summary.duration_s:.6g} s of signal, "
        f"{summary.n_windows} windows of {summary.window_s:g} s{segs}, {summary.n_skipped} below --min-snr{flagged})"
    )


class _Bar:
    """A rich progress bar over samples read (stderr)."""

    def __init__(self, total, name):
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

        self._p = Progress(TextColumn("[bold]locate[/] {task.description}"), BarColumn(),
                           TextColumn("{task.percentage:>5.1f}%"), TimeRemainingColumn(),
                           console=Console(stderr=True), transient=True)
        self._p.start()
        self._task = self._p.add_task(str(name)[-40:], total=total)

    def update(self, done):
        self._p.update(self._task, completed=done)

    def close(self):
        self._p.stop()


@cli.command("amplitudes")
@click.argument("recording", type=click.Path(dir_okay=False))
@click.option("--image-id", help="Write a calibration points CSV image_id,point_id,vx1,vx2,vy1,vy2 for this view.")
@_demod_options
def amplitudes_command(recording, rate_hz, carriers, emitters, window_s, tdm, schedule, n_emitters, check_carriers,
                       min_snr,
                       image_id, channels, dataset, group, chunk_samples, progress, output, output_format="csv"):
    """Demodulate RECORDING to carrier amplitudes (no calibration needed).

    \b
    Columns: t_s,emitter,vx1,vx2,vy1,vy2,sigma_vx1,sigma_vx2,sigma_vy1,sigma_vy2
    With --image-id: a calibration points CSV (one view of the LED template):
      psdcal amplitudes view3.tdms --carrier-hz 1000 --tdm --image-id 3 -o view3.csv
    """
    from psdcal.measure.locate import LocateConfig, amplitudes_to_csv
    from psdcal.signal.recording import open_recording
    from psdcal.signal.stream import load_schedule

    sched = load_schedule(schedule) if schedule else None
    config = LocateConfig(carriers_hz=tuple(carriers), window_s=window_s, emitters=tuple(emitters) or None,
                          min_snr=min_snr, tdm=bool(tdm or sched is not None), schedule=sched,
                          n_emitters=n_emitters, chunk_samples=chunk_samples, check_carriers=check_carriers,
                          output_format=output_format)
    rec = open_recording(recording, rate_hz, channels=_channels(channels), dataset=dataset, group=group)
    _guard_window(config, [rec])
    _one_shot_mode([rec], config)
    show = progress if progress is not None else (rec.n_samples is not None and rec.n_samples >= _PROGRESS_MIN_SAMPLES)
    bar = _Bar(rec.n_samples, rec.path) if show else None
    try:
        summary = amplitudes_to_csv(rec, output, config, image_id=image_id, progress=bar.update if bar else None)
    finally:
        if bar:
            bar.close()
    _report(summary, output)


@cli.command("aoa")
@click.argument("points", type=click.Path(dir_okay=False))
@click.option("--calib", required=True, type=click.Path(dir_okay=False), help="Calibration JSON.")
@click.option("--distance-mm", type=float, help="Plane distance S: also write X_mm, Y_mm.")
@click.option("--sigma-d-mm", type=float, default=0.0, show_default=True,
              help="1-sigma noise of the impact points, mm (added to the calibration covariance).")
@click.option("--gains", "gains_file", type=click.Path(dir_okay=False),
              help="Gains JSON from 'psdcal gains' (amplitude input): applied to the channels, covariance "
                   "in the sigmas.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Output CSV.")
@click.option("--expect-sensor", "expect_sensor", default=None, metavar="ID",
              help="Refuse a calibration whose sensor_id is not ID (or has none).")
@click.option("--allow-no-covariance", is_flag=True, default=False,
              help="Accept a calibration without covariance or standard errors (its uncertainty is then left out "
                   "of every sigma); refused otherwise.")
def aoa_command(points, calib, distance_mm, sigma_d_mm, gains_file, output, expect_sensor=None,
                allow_no_covariance=False):
    """Convert impact points (x_mm,y_mm) or amplitudes (vx1..vy2) in POINTS.csv to angles.

    Other columns (image_id, point_id, t_s, emitter, ...) are copied.  Output adds
    x_mm,y_mm,alpha_x_deg,alpha_y_deg[,X_mm,Y_mm],sigma_alpha_x_deg,sigma_alpha_y_deg[,sigma_X_mm,sigma_Y_mm]
    (replacing those columns when POINTS already has them, e.g. a `locate` output).  The input's
    sigma_x_mm,sigma_y_mm or sigma_vx1..sigma_vy2 columns enter the angle sigmas; a point off
    the sensor is an error; a sigma that cannot be computed is written empty.

    Signs: seen from behind the sensor with the chip's +y edge up, alpha_x > 0
    is an emitter right of the optical axis, alpha_y > 0 one below it (the lens
    inverts the image; docs/model.md#hardware-conventions).
    """
    from psdcal.measure.locate import aoa_csv
    from psdcal.measure.sensor_model import SensorModel

    model = SensorModel.load(calib)
    check_sensor(model, expect_sensor, allow_no_covariance)
    if distance_mm is not None and not distance_mm > 0:
        from psdcal.errors import InputError

        raise InputError(f"--distance-mm must be positive, got {distance_mm}", field="--distance-mm")
    if gains_file is not None:
        from psdcal.calibration.bench import load_gains, with_gains

        model = with_gains(model, *load_gains(gains_file))
    _aoa_one_shot_mode(points)
    n = aoa_csv(points, model, output, distance_mm=distance_mm, sigma_d_mm=sigma_d_mm)
    click.echo(f"wrote {n} rows to {output}")


@cli.command("errormap")
@click.option("--calib", required=True, type=click.Path(dir_okay=False), help="Calibration JSON (with covariance).")
@click.option("--distance-mm", type=float, default=5000.0, show_default=True, help="Plane distance S.")
@click.option("--mode", type=click.Choice(["sigma", "mean+2std"]), default="sigma", show_default=True,
              help="1-sigma from the covariance, or the paper's Figure 9: parameters at mean + 2 std.")
@click.option("--grid", type=int, default=61, show_default=True, help="Grid points per axis over the sensor.")
@click.option("--sigma-d-mm", type=float, default=0.0, show_default=True,
              help="Impact-point noise added in 'sigma' mode, mm.")
@click.option("--csv", "csv_path", type=click.Path(dir_okay=False), help="Also write the grid as CSV.")
@click.option("-o", "--output", default="errormap.png", show_default=True, type=click.Path(dir_okay=False),
              help="Output PNG.")
@click.option("--allow-no-covariance", is_flag=True, default=False,
              help="Draw a calibration without covariance or standard errors (its error is then zero "
                   "everywhere, only --sigma-d-mm is left); refused otherwise.")
def errormap_command(calib, distance_mm, mode, grid, sigma_d_mm, csv_path, output, allow_no_covariance=False):
    """Draw the AoA and position error over the field of view (the paper's Figure 9).

    Example: psdcal errormap --calib calib.json --distance-mm 5000 -o errormap.png
    """
    from psdcal.errors import InputError
    from psdcal.measure.positioning import error_map, plot_error_map, write_error_map_csv
    from psdcal.measure.sensor_model import SensorModel

    if grid < 3:
        raise InputError(f"--grid must be at least 3, got {grid}", field="grid")
    from psdcal import _jit

    _jit.set_mode_for(grid * grid)  # a map's angles: the numpy path unless the grid is very fine
    model = SensorModel.load(calib)
    model.require_uncertainty(allow_no_covariance)  # else a map of zeros, as if the calibration were exact
    from psdcal._limits import check_bytes

    check_bytes(float(grid) ** 2 * 8 * (8 * max(len(model.names), 1) + 64), f"--grid {grid}", "--grid")
    emap = error_map(model, distance_mm, mode=mode, grid=grid, sigma_d_mm=sigma_d_mm)
    plot_error_map(emap, output)
    if csv_path:
        write_error_map_csv(emap, csv_path)
    click.echo(
        f"wrote {output}: AoA error {emap.aoa_error_deg.min():.4g}..{emap.aoa_error_deg.max():.4g} deg, "
        f"position error {emap.position_error_mm.min():.4g}..{emap.position_error_mm.max():.4g} mm "
        f"at S = {emap.distance_mm:g} mm ({mode})"
    )
