"""`psdcal dashboard`: the room in the browser, live or replayed, and its static export."""
from __future__ import annotations

from pathlib import Path

import click

from psdcal.cli import OUTPUT_SUFFIXES, cli

OUTPUT_SUFFIXES[("dashboard", "output")] = (".html", ".htm")


def _sensor_rows(ctx, param, values):
    out = []
    for v in values:
        name, sep, path = v.partition("=")
        if not sep or not name or not path:
            raise click.BadParameter(f"{v!r}: expected NAME=FILE (the sensor's name in the sensors file)", ctx=ctx,
                                     param=param)
        out.append((name, Path(path)))
    return tuple(out)


@cli.command("dashboard")
@click.argument("rows", nargs=-1, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--sensor-rows", "sensor_rows", multiple=True, callback=_sensor_rows, metavar="NAME=FILE",
              help="One sensor's `locate` angles or `amplitudes` rows (its health: SNR, emitters seen, chi2 "
                   "against the others). Repeatable.")
@click.option("--sensors", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Sensors file (poses; `pose --into`, `bundle`): sensors and their fields of view.")
@click.option("--emitters", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Surveyed emitters CSV (emitter,X_m,Y_m,Z_m).")
@click.option("--plan", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="`psdcal plan --csv` output: the position-sigma map as an optional layer.")
@click.option("--events", "events", multiple=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Warnings log written by `psdcal --events FILE ...` (or $PSDCAL_EVENTS). Repeatable.")
@click.option("--replay", is_flag=True, default=False,
              help="Play finished rows files by their t_s (instead of following files being written).")
@click.option("--speed", type=click.FloatRange(min=0.0, min_open=True), default=1.0, show_default=True,
              help="Replay speed (1: real time).")
@click.option("--history-s", type=click.FloatRange(min=0.0, min_open=True), default=300.0, show_default=True,
              help="Seconds of rows kept for scrubbing back.")
@click.option("--trail-s", type=click.FloatRange(min=0.0), default=10.0, show_default=True,
              help="Seconds of track drawn behind each emitter.")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Interface to listen on; another than this machine's needs --allow-remote and --token.")
@click.option("--port", type=click.IntRange(0, 65535), default=8765, show_default=True, help="Port (0: any free one).")
@click.option("--allow-remote", is_flag=True, default=False, help="Allow a --host other machines can reach.")
@click.option("--token", envvar="PSDCAL_DASHBOARD_TOKEN", default=None,
              help="Secret every request must carry (?token=...); at least 16 characters. Default: "
                   "$PSDCAL_DASHBOARD_TOKEN.")
@click.option("--poll-ms", type=click.FloatRange(min=1.0, max=5000.0), default=20.0, show_default=True,
              help="How often the files are checked for new rows.")
@click.option("--title", default="psdcal dashboard", show_default=True, help="Title of the page.")
@click.option("--export", "output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write the static page (one self-contained HTML file of every row) and exit; no server.")
def dashboard_command(rows, sensor_rows, sensors, emitters, plan, events, replay, speed, history_s, trail_s, host,
                      port, allow_remote, token, poll_ms, title, output):
    """Show the room in a browser: sensors, emitters with their 3-sigma, tracks, health and warnings.

    Follows the files the commands write as they grow (the rows of `locate
    --sensors`, a track CSV, each sensor's rows, the `--events` log) and
    serves one page on http://127.0.0.1:PORT/ that updates as rows arrive.
    Read-only: the page changes nothing on disk. With --replay a finished
    recording plays at --speed times real time; with --export the same page
    is written as one HTML file that opens without a server.

    Example: psdcal dashboard xyz.csv track.csv --sensors sensors.json --emitters room/emitters.csv --replay
    """
    from psdcal.errors import InputError
    from psdcal.report.dashboard.hub import Hub, Options
    from psdcal.report.dashboard.server import check_bind, export_html, serve

    if not rows and not sensor_rows:
        raise InputError("give at least one rows file (`locate --sensors` rows or a track CSV) or --sensor-rows",
                         field="rows")
    if replay or output is not None:
        for p in (*rows, *(p for _, p in sensor_rows)):
            if not p.is_file():
                raise InputError("no such file (--replay and --export read finished files)", path=p)
    if output is None:
        check_bind(host, token, allow_remote)
    opts = Options(rows=tuple(rows), sensor_rows=sensor_rows, sensors=sensors, emitters=emitters, plan=plan,
                   events=tuple(events), replay=replay or output is not None, speed=speed,
                   history_s=float("inf") if output is not None else history_s, trail_s=trail_s, title=title)
    hub = Hub(opts)
    if replay or output is not None:
        # finished files: one that is empty or not a psdcal rows file is an error (a live file may still be starting)
        for src in hub.sources:
            if src.parser.kind is None:
                raise InputError("empty" if src.parser.header is None else
                                 "not a psdcal rows CSV (the header of `locate`, `locate --sensors`, `aoa`, "
                                 "`amplitudes` or a track)", path=src.follower.path, line=1, field="header")
    if output is not None:
        export_html(hub, output)
        for src in hub.sources:
            if src.parser.bad_lines:
                click.echo(f"psdcal: warning: {src.follower.path}: {src.parser.bad_lines} line(s) not read "
                           "(cells missing or not numbers)", err=True)
        click.echo(f"wrote {output}")
        return
    missing = [str(p) for p in (*rows, *(p for _, p in sensor_rows)) if not p.exists()]
    if missing:
        click.echo(f"waiting for {', '.join(missing)} (followed as they are written)", err=True)

    def ready(url):
        click.echo(f"psdcal dashboard: {url} (read-only; Ctrl-C stops)")
        import sys

        sys.stdout.flush()

    serve(hub, host=host, port=port, token=token, poll_s=poll_ms / 1000.0, ready=ready)
