"""``psdcal record`` and several sensors live in ``psdcal locate --sensors`` (a thin layer over
:mod:`psdcal.signal.session` and :mod:`psdcal.measure.live_multi`)."""
from __future__ import annotations

import click

from psdcal.cli import cli


def parse_offsets(items, names) -> list[float]:
    """``NAME=DT`` items (``--offset-s``) -> one offset per sensor name (0 for those not given)."""
    import math

    from psdcal.errors import InputError

    out = dict.fromkeys(names, 0.0)
    for item in items or ():
        name, sep, val = str(item).partition("=")
        name = name.strip()
        if not sep or name not in out:
            raise InputError(f"give NAME=SECONDS with NAME one of the sensors {list(names)}, got {item!r}",
                             field="offset_s")
        try:
            dt = float(val)
        except ValueError:
            dt = float("nan")
        if not math.isfinite(dt):
            raise InputError(f"not a number of seconds: {val!r}", field="offset_s")
        out[name] = dt
    return [out[n] for n in names]


def _summary(summary, output, rate_hz, what) -> str:
    return (f"wrote {summary.n_rows} rows to {output} ({summary.n_samples / rate_hz:.6g} s of {what} per sensor, "
            f"{summary.n_windows} windows, {summary.n_skipped} emitter-windows seen by fewer than two sensors); "
            f"{summary.latency_text()}")


def live_locate_multi(recordings, sensors_path, rate_hz, carriers, emitters, window_s, tdm, schedule, n_emitters,
                      min_snr, output, raw_dtype, raw_scale, track_path=None, track_q=None, offsets=(),
                      replay=None, speed=1.0, record_path=None, allow_no_covariance=False):
    """`psdcal locate --sensors` on live sources (one per sensor) or on a recorded session (``--replay``)."""
    from psdcal.cli.locate_cmd import check_sensor
    from psdcal.errors import InputError
    from psdcal.measure.live_multi import locate_live_multi, warm_up
    from psdcal.measure.locate import LocateConfig
    from psdcal.measure.positioning import load_sensors
    from psdcal.signal.session import (
        LiveSources,
        SessionWriter,
        SourceInfo,
        is_live_source,
        open_source,
        read_session_header,
        replay_events,
    )

    poses = load_sensors(sensors_path)
    for p in poses:
        check_sensor(p.model, None, allow_no_covariance)
    names = [p.name for p in poses]
    from psdcal.signal.stream import load_schedule

    sched = load_schedule(schedule) if schedule else None
    config = LocateConfig(carriers_hz=tuple(carriers), window_s=0.01 if window_s is None else window_s,
                          emitters=tuple(emitters) or None, min_snr=min_snr, n_emitters=n_emitters,
                          tdm=bool(tdm or sched is not None), schedule=sched)
    if config.tdm and sched is None:  # (checked again by locate_live_multi; here before connecting)
        raise InputError("time multiplexing with several sensors needs --schedule (the emitters' on-times, the "
                         "same for every sensor)", field="schedule")
    auto = [o for o in offsets or () if str(o).strip() == "auto"]
    if auto and len(offsets) > 1:
        raise InputError("--offset-s auto estimates every sensor's offset: give it alone", field="offset_s")
    offs = parse_offsets([] if auto else offsets, names)
    if replay is not None:
        if recordings:
            raise InputError("give either live sources or --replay SESSION, not both", field="replay")
        sources, _ = read_session_header(replay)
        if len(sources) != len(poses):
            raise InputError(f"the session has {len(sources)} sources for {len(poses)} sensors", path=replay,
                             field="sources")
        rates = sorted({s.rate_hz for s in sources})
        if len(rates) != 1:
            raise InputError(f"the sources have different sampling rates {rates}", path=replay, field="rate_hz")
        rate = rates[0]
        if rate_hz is not None and rate_hz != rate:
            raise InputError(f"--rate-hz {rate_hz:g} but the session was recorded at {rate:g} Hz", path=replay,
                             field="rate_hz")
        snames = [s.name for s in sources]
        if sorted(snames) == sorted(names) and snames != names:  # recorded in another order: by name
            order = [snames.index(n) for n in names]
            inv = {src: dst for dst, src in enumerate(order)}
            events = ((inv[i], b, at) for i, b, at in replay_events(replay, speed))
        else:
            events = replay_events(replay, speed)
        infos = [SourceInfo(n, f"replay:{replay}", rate) for n in names]
    else:
        srcs = [str(r) for r in recordings]
        if len(srcs) != len(poses):
            raise InputError(f"{len(poses)} sensors need {len(poses)} live sources, in the sensors' order (got "
                             f"{len(srcs)})", path=sensors_path, field="recording")
        bad = [s for s in srcs if not is_live_source(s)]
        if bad:
            raise InputError("every source must be live ('-', tcp://127.0.0.1:PORT, nidaqmx://..., file:PATH); "
                             "recorded files are read without live input", path=bad[0])
        if srcs.count("-") > 1:
            raise InputError("standard input ('-') can feed one sensor only", field="recording")
        if rate_hz is None:
            raise InputError("live streams need --rate-hz", field="rate_hz")
        rate = float(rate_hz)
        warm_up(poses, rate, config)  # before connecting: the kernels' start-up is not the first rows' latency
        streams = [open_source(s, rate, dtype=raw_dtype, scale=raw_scale) for s in srcs]
        events = LiveSources(streams).events()
        infos = [SourceInfo(n, s, rate, raw_dtype, raw_scale) for n, s in zip(names, srcs)]
    if auto:
        from psdcal.signal.session import estimate_offsets

        est, events = estimate_offsets(events, len(poses), rate)
        offs = [float(v) for v in est]
        click.echo("offsets estimated from the arrival times: "
                   + ", ".join(f"{n} {v:+.4f} s" for n, v in zip(names, offs)), err=True)
    from psdcal.cli.system_cmd import live_tracker, print_track_summary
    from psdcal.measure.locate import MULTI_COLUMNS

    tracker = live_tracker(track_path, MULTI_COLUMNS, track_q)  # the track row by row, with the rows
    recorder = SessionWriter(record_path, infos) if record_path else None
    try:
        summary = locate_live_multi(events, poses, rate, output, config, offsets_s=offs, recorder=recorder,
                                    check_rate=replay is None, on_rows=None if tracker is None else tracker.add)
    finally:
        if recorder is not None:
            recorder.close()
        info = None if tracker is None else tracker.close()
    click.echo(_summary(summary, output, rate, "replayed signal" if replay else "live signal"),
               err=str(output) == "-")
    got = summary.samples_per_source
    if got and max(got) - min(got) > config.window_s * rate:
        per = ", ".join(f"{n} {k / rate:.6g} s" for n, k in zip(names, got))
        click.echo(f"psdcal: warning: the sources ended at different times ({per}): rows up to the shortest",
                   err=True)
    print_track_summary(info, track_path, output)


@cli.command("record")
@click.argument("sources", nargs=-1, required=True)
@click.option("--rate-hz", type=float, required=True, help="Sampling rate of every source, Hz.")
@click.option("--names", help="Names of the sources (comma-separated, e.g. the sensors' names) [default: the "
                              "names in --sensors, or s1,s2,...].")
@click.option("--sensors", "sensors_path", type=click.Path(dir_okay=False),
              help="SENSORS.json: name the sources after its sensors, in order (what `locate --replay` matches).")
@click.option("--raw-dtype", type=click.Choice(["float32", "float64", "int16"]), default="float64",
              show_default=True, help="Sample type of the interleaved vx1,vx2,vy1,vy2 frames (little-endian).")
@click.option("--raw-scale", type=float, default=1.0, show_default=True,
              help="Factor applied to every sample (e.g. volts per int16 count).")
@click.option("--duration-s", type=float, default=None,
              help="Stop after this long (wall clock from the first data) [default: until every source ends, "
                   "or Ctrl-C].")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Session file to write (documented format: `psdcal.signal.session`).")
def record_command(sources, rate_hz, names, sensors_path, raw_dtype, raw_scale, duration_s, output):
    """Record live SOURCES (one per sensor) with their arrival times, for `locate --replay`.

    \b
    Sources: '-' (stdin), tcp://127.0.0.1:PORT, nidaqmx://Dev1/ai0:3, file:PATH (a raw file
    or a named pipe); frames vx1,vx2,vy1,vy2 interleaved (--raw-dtype, --raw-scale).
    Example:
      psdcal record tcp://127.0.0.1:5001 tcp://127.0.0.1:5002 --sensors sensors.json \\
          --rate-hz 20000 -o bench.psdsession
      psdcal locate --sensors sensors.json --replay bench.psdsession --speed 0 \\
          --carrier-hz 1000 -o xyz.csv
    The session keeps every block as received (scaled samples, float64) with its arrival time
    and the end of each source; a session cut short keeps what came before.
    """
    import time

    import numpy as np

    from psdcal.errors import InputError
    from psdcal.signal.session import (
        ENDED,
        LiveSources,
        SessionWriter,
        SourceInfo,
        open_source,
        parts,
    )

    srcs = [str(s) for s in sources]
    if names:
        nm = [n.strip() for n in names.split(",")]
    elif sensors_path:
        from psdcal.measure.positioning import load_sensors

        nm = [p.name for p in load_sensors(sensors_path)]
    else:
        nm = [f"s{i + 1}" for i in range(len(srcs))]
    if len(nm) != len(srcs) or len(set(nm)) != len(nm) or not all(nm):
        raise InputError(f"give {len(srcs)} different names, one per source (got {','.join(nm)})", field="names")
    if srcs.count("-") > 1:
        raise InputError("standard input ('-') can feed one source only", field="sources")
    if duration_s is not None and not duration_s > 0:
        raise InputError(f"--duration-s must be positive, got {duration_s}", field="duration_s")
    streams = [open_source(s, rate_hz, dtype=raw_dtype, scale=raw_scale) for s in srcs]
    writer = SessionWriter(output, [SourceInfo(n, s, float(rate_hz), raw_dtype, raw_scale) for n, s in zip(nm, srcs)])
    first = None
    try:
        for i, block, at in LiveSources(streams).events():
            last = float(at if np.ndim(at) == 0 else at[-1, 1])
            if first is None:
                first = float(at if np.ndim(at) == 0 else at[0, 1])
                writer.start(first)
            if block is ENDED:
                writer.end(i, last)
            else:
                for b, t_at in parts(block, at):
                    writer.write(i, b, t_at)
            if duration_s is not None and time.perf_counter() - first >= duration_s:
                break
    except KeyboardInterrupt:
        click.echo("psdcal: interrupted: the session so far is kept", err=True)
    finally:
        writer.close()
    per = ", ".join(f"{n}: {k / rate_hz:.6g} s" for n, k in zip(nm, writer.n_frames))
    click.echo(f"recorded {len(srcs)} sources to {output} ({writer.n_records} blocks; {per})")
