"""`psdcal dashboard`: the file follower, the rows it reads, its safety rules, the --events log, and the page
in a real headless Chromium (replayed recording, positions to the pixel, a warning, pause/resume, static export)."""
from __future__ import annotations

import asyncio
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from _dashboard_room import BAD_T, REFLECTION, read_rows, write_room
from psdcal.cli import main
from psdcal.errors import InputError
from psdcal.report.dashboard.follow import FileFollower

REPO = Path(__file__).resolve().parents[1]


# ---- the file follower ---------------------------------------------------------------------------------------------
def test_follower_returns_complete_lines_only(tmp_path):
    p = tmp_path / "rows.csv"
    f = FileFollower(p)
    assert f.poll().lines == ()  # not there yet: empty, no error
    p.write_bytes(b"t_s,emitter\n0.1,a")
    assert f.poll().lines == ("t_s,emitter",)
    assert f.poll().lines == ()  # nothing new: no read
    with open(p, "ab") as fh:
        fh.write(b"1\r\n0.2,a1\n0.3")
    c = f.poll()
    assert c.lines == ("0.1,a1", "0.2,a1") and not c.reset
    with open(p, "ab") as fh:
        fh.write(b",b\xff\n")
    assert f.poll().lines == ("0.3,b\ufffd",)  # a bad byte does not stop the follower


def test_follower_notices_truncation_and_rotation(tmp_path):
    p = tmp_path / "rows.csv"
    p.write_text("h\n1\n2\n")
    f = FileFollower(p)
    assert f.poll().lines == ("h", "1", "2")
    p.write_text("h\n")  # truncated (rewritten shorter in place)
    c = f.poll()
    assert c.reset and c.lines == ("h",)
    new = tmp_path / "new.csv"
    new.write_text("h2\n9\n")
    os.replace(new, p)  # rotated: another file at the same path
    c = f.poll()
    assert c.reset and c.lines == ("h2", "9")
    with open(p, "a") as fh:
        fh.write("10\n")
    c = f.poll()
    assert c.lines == ("10",) and not c.reset


# ---- rows ----------------------------------------------------------------------------------------------------------
def test_rows_flag_chi2_and_warn_only_on_a_run():
    from psdcal.report.dashboard.data import RUN, RowParser

    from scipy.stats import chi2 as chi2_dist

    lim = chi2_dist.isf(1e-3, 3)  # 3 sensors: 2*3 - 3 dof
    p = RowParser("rows", source="xyz.csv")
    head = "t_s,emitter,X_mm,Y_mm,Z_mm,sigma_X_mm,sigma_Y_mm,sigma_Z_mm,n_sensors,chi2"
    rows = [f"{0.01 * i:.2f},a1,1,2,3,0.1,0.1,0.1,3,{c}" for i, c in
            enumerate([1.0, lim * 1.01, 2.0, lim * 1.01, lim * 1.01, lim * 2, lim * 3, 1.0])]
    out = p.feed([head, *rows, "0.5,a1,1,2", "x,a1,1,2,3,1,1,1,3,1"])
    assert [r[-1] for r in out["positions"]] == [0, 1, 0, 1, 1, 1, 1, 0]
    assert len(out["warnings"]) == 1 and RUN == 3 and out["warnings"][0][0] == pytest.approx(0.05)
    assert "a1" in out["warnings"][0][4] and p.bad_lines == 2


def test_track_rows_warn_on_gating_and_restart():
    from psdcal.report.dashboard.data import RowParser

    p = RowParser("rows", source="track.csv")
    head = ("t_s,emitter,X_mm,Y_mm,Z_mm,vX_mm_s,vY_mm_s,vZ_mm_s,sigma_X_mm,sigma_Y_mm,sigma_Z_mm,"
            "sigma_vX_mm_s,sigma_vY_mm_s,sigma_vZ_mm_s,nis,gated")
    gated = [0, 1, 0, 1, 1, 1, 1, 1, 0]
    out = p.feed([head] + [f"{i},tag,1,2,3,0,0,0,1,1,1,1,1,1,2,{g}" for i, g in enumerate(gated)])
    assert p.kind == "tracks" and len(out["tracks"]) == 9
    texts = [w[4] for w in out["warnings"]]
    assert sum("gated by the tracker" in t for t in texts) == 2 and sum("restarts" in t for t in texts) == 1


def test_sensor_chi2_against_the_located_position():
    """A sensor's angles, computed here from its pose, against the position: 0 when they agree, (d/sigma)^2 when not."""
    import math

    import numpy as np

    from psdcal.report.dashboard.data import SensorChi2

    s = SensorChi2()
    R = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # looking down
    t = -R @ np.array([1000.0, 2000.0, 3000.0])
    s.poses["s1"] = (R, t)
    P = np.array([1500.0, 1800.0, 1000.0])
    pc = R @ P + t
    ax, ay = math.degrees(math.atan(pc[0] / pc[2])), math.degrees(math.atan(pc[1] / pc[2]))
    good = [0.5, "s1", "tag", None, None, [ax, ay, 0.01, 0.02]]
    bad = [0.6, "s1", "tag", None, None, [ax + 0.03, ay, 0.01, 0.02]]
    s.add_sensor([good])  # before its position: waits
    done = s.add_positions([[0.5, "tag", *P], [0.6, "tag", *P]])
    assert len(done) == 1 and done[0][4] == pytest.approx(0.0, abs=1e-9)
    s.add_sensor([bad])  # after it: at once
    assert bad[4] == pytest.approx(9.0, rel=1e-6)


def test_one_sensor_room(tmp_path):
    """Live input is one sensor: a sensors file of one sensor is drawn (its rays come from its angle rows)."""
    from psdcal.report.dashboard.data import read_sensors

    room = write_room(tmp_path, duration_s=0.1)
    data = json.loads(room["sensors"].read_text())
    one = tmp_path / "one.json"
    one.write_text(json.dumps({"sensors": data["sensors"][:1]}))
    (s,) = read_sensors(one)
    assert s["name"] == "s1" and s["verdict"] == "good"
    assert s["center_mm"] == pytest.approx([5800.0, 3800.0, 2800.0], abs=1e-6)  # the test's own pose
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([{"calib": "calib.json", "rvec": [0, 0], "tvec_mm": [0, 0, 1]}]))
    with pytest.raises(InputError, match="rvec"):
        read_sensors(bad)


def test_sensor_warning_per_emitter_run(tmp_path):
    """A reflection into one sensor for one emitter warns once, although the sensor's other emitter is fine between."""
    from psdcal.report.dashboard.hub import Hub, Options

    from _dashboard_room import REFLECTION

    room = write_room(tmp_path, duration_s=3.0, sensor_rows=True)
    hub = Hub(Options(rows=(room["rows"],), sensors=room["sensors"],
                      sensor_rows=tuple((s, room[f"{s}_angles"]) for s in ("s1", "s2", "s3"))))
    snap = hub.drain()
    texts = [w[4] for w in snap["warnings"] if w[4].startswith("sensor ")]
    assert len(texts) == 1 and texts[0].startswith(f"sensor {REFLECTION[0]}:") and REFLECTION[1] in texts[0]
    chi2 = [r[4] for r in snap["sensor"] if r[4] is not None]
    assert len(chi2) > 0.9 * 3 * 2 * 300  # nearly every (window, emitter, sensor) matched its position
    import numpy as np

    assert 0.2 < np.median(chi2) / 2 < 1.0  # angle noise 0.05 deg stated as 0.1 deg, plus the position's own noise


# ---- safety --------------------------------------------------------------------------------------------------------
def test_bind_rules():
    from psdcal.report.dashboard.server import check_bind

    check_bind("127.0.0.1", None, False)
    check_bind("::1", None, False)
    check_bind("localhost", "x" * 16, False)
    with pytest.raises(InputError, match="--allow-remote"):
        check_bind("0.0.0.0", "x" * 32, False)
    with pytest.raises(InputError, match="needs --token"):
        check_bind("0.0.0.0", None, True)
    with pytest.raises(InputError, match="at least 16"):
        check_bind("0.0.0.0", "short", True)
    check_bind("192.168.1.5", "x" * 16, True)


def test_cli_refuses_a_remote_bind_without_token(tmp_path, capsys):
    room = write_room(tmp_path, duration_s=0.1)
    assert main(["dashboard", str(room["rows"]), "--host", "0.0.0.0", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--allow-remote" in err
    assert main(["dashboard", str(room["rows"]), "--host", "0.0.0.0", "--allow-remote", "--port", "0"]) == 2
    assert "--token" in capsys.readouterr().err


def test_token_host_origin_and_read_only(tmp_path):
    """Every request needs the token (constant-time check); a foreign Host or Origin is refused; GET only."""
    pytest.importorskip("aiohttp")
    from aiohttp.test_utils import TestClient, TestServer

    from psdcal.report.dashboard.hub import Hub, Options
    from psdcal.report.dashboard.server import make_app

    room = write_room(tmp_path, duration_s=0.2)
    token = "t0ken-" + "x" * 20

    async def run():
        hub = Hub(Options(rows=(room["rows"],), sensors=room["sensors"]))
        async with TestClient(TestServer(make_app(hub, token=token, poll_s=0.01))) as c:
            assert (await c.get("/")).status == 403
            assert (await c.get("/?token=wrong-token-xxxxxxxxxx")).status == 403
            r = await c.get(f"/?token={token}")
            assert r.status == 200 and "psd-config" in await r.text()
            assert "psdcal_token" in r.cookies  # the page's own requests carry it from now on
            assert (await c.get("/snapshot.json", headers={"Authorization": f"Bearer {token}"})).status == 200
            assert (await c.post(f"/?token={token}")).status == 405
            assert (await c.get(f"/snapshot.json?token={token}", headers={"Host": "evil.example:80"})).status == 403
            r = await c.get(f"/ws?token={token}", headers={"Origin": "http://evil.example"})
            assert r.status == 403
            ws = await c.ws_connect(f"/ws?token={token}")
            snap = json.loads((await ws.receive()).data)
            assert snap["type"] == "snapshot" and [s["name"] for s in snap["room"]["sensors"]] == ["s1", "s2", "s3"]
            await ws.close()

    asyncio.run(run())


def test_dashboard_imports_stay_out_of_the_other_commands():
    code = ("import sys; from psdcal.cli import main; main(['--help']); "
            "print('LOADED', [m for m in ('aiohttp', 'plotly') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(), timeout=60)
    assert "LOADED []" in out.stdout


# ---- the --events log ------------------------------------------------------------------------------------------------
def test_events_log_records_warning_lines(tmp_path, capsys):
    import click

    from psdcal.cli._events import logging_warnings

    log = tmp_path / "ev.jsonl"
    with logging_warnings(log, "locate"):
        click.echo("psdcal: warning: reflection suspected", err=True)
        click.echo("wrote 3 rows")
        print("warning: partial", end="")
        print(" line", file=sys.stdout)
    out = capsys.readouterr()
    assert "reflection suspected" in out.err and "wrote 3 rows" in out.out  # printed unchanged
    ev = [json.loads(line) for line in log.read_text().splitlines()]
    assert [e["text"] for e in ev] == ["reflection suspected", "partial line"]
    assert ev[0]["command"] == "locate" and ev[0]["stream"] == "stderr" and ev[1]["stream"] == "stdout"
    assert all(isinstance(e["t_unix"], float) for e in ev)


def test_events_option_logs_a_command_warning(tmp_path, capsys):
    """`psdcal --events FILE CMD`: the warning CMD prints is in the log, with the command's name."""
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,emitter,X_mm,Y_mm,Z_mm,sigma_X_mm,sigma_Y_mm,sigma_Z_mm,n_sensors,chi2\n"
                   "0.1,tag,1,2,3,1,1,1,2,0.5\n0.2,tag,1,2\n")
    log = tmp_path / "ev.jsonl"
    assert main(["--events", str(log), "dashboard", str(bad), "--export", str(tmp_path / "o.html")]) == 0
    assert "1 line(s) not read" in capsys.readouterr().err
    ev = [json.loads(line) for line in log.read_text().splitlines()]
    assert len(ev) == 1 and ev[0]["command"] == "dashboard" and "1 line(s) not read" in ev[0]["text"]


def test_a_finished_file_that_is_not_rows_is_an_error(tmp_path, capsys):
    """--export / --replay read finished files: an empty file or another CSV is one line, exit 2, no page."""
    for name, text, what in (("empty.csv", "", "empty"), ("other.csv", "a,b\n1,2\n", "not a psdcal rows CSV")):
        p = tmp_path / name
        p.write_text(text)
        assert main(["dashboard", str(p), "--export", str(tmp_path / "o.html")]) == 2
        err = capsys.readouterr().err
        assert what in err and str(p) in err and "header" in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "o.html").exists()


def test_events_from_the_environment(tmp_path, monkeypatch, capsys):
    bad = tmp_path / "short.csv"
    bad.write_text("t_s,emitter,X_mm,Y_mm,Z_mm,sigma_X_mm,sigma_Y_mm,sigma_Z_mm,n_sensors,chi2\n0.2,tag,1\n")
    log = tmp_path / "env.jsonl"
    monkeypatch.setenv("PSDCAL_EVENTS", str(log))
    assert main(["dashboard", str(bad), "--export", str(tmp_path / "o.html")]) == 0
    capsys.readouterr()
    ev = [json.loads(line) for line in log.read_text().splitlines()]
    assert [e["text"] for e in ev] == [f"{bad}: 1 line(s) not read (cells missing or not numbers)"]


def test_a_new_run_starts_the_rows_over(tmp_path):
    """A rows file replaced by a new run (t_s from 0 again): the pages get a snapshot of the new rows only."""
    from psdcal.report.dashboard.hub import Hub, Options

    room = write_room(tmp_path, duration_s=1.0)
    hub = Hub(Options(rows=(room["rows"],)))
    first = hub.poll()
    assert first["type"] == "update" and len(first["positions"]) == 200
    head, *lines = room["rows"].read_text().splitlines()
    new = tmp_path / "new.csv"
    new.write_text("\n".join([head, *lines[:10]]) + "\n")
    os.replace(new, room["rows"])
    msg = hub.poll()
    assert msg["type"] == "snapshot" and len(msg["positions"]) == 10 and hub.poll() is None
    assert len(hub.snapshot()["positions"]) == 10


def test_hub_replays_by_time(tmp_path):
    from psdcal.report.dashboard.hub import Hub, Options

    room = write_room(tmp_path, duration_s=2.0)
    now = [0.0]
    hub = Hub(Options(rows=(room["rows"],), replay=True, speed=2.0), clock=lambda: now[0])
    first = hub.poll()
    assert {r[0] for r in first["positions"]} == {0.005}
    now[0] = 0.25  # 0.5 s of data at speed 2
    upd = hub.poll()
    assert max(r[0] for r in upd["positions"]) == pytest.approx(0.505) and min(r[0] for r in upd["positions"]) > 0.005
    assert hub.poll() is None
    now[0] = 10.0
    hub.poll()
    assert hub.replay_done() and len(hub.snapshot()["positions"]) == 400


def test_follows_a_running_live_locate(tmp_path):
    """`psdcal locate -` flushes each window's row: the dashboard has rows before the stream ends."""
    import numpy as np

    from psdcal.measure.sensor_model import SensorModel
    from psdcal.report.dashboard.hub import Hub, Options
    from psdcal.study.recordings import amplitudes, calib_dict, signals, spot_for_angles

    calib = calib_dict()
    (tmp_path / "c.json").write_text(json.dumps(calib))
    m = SensorModel.from_dict(calib)
    rate = 20000.0
    x = signals(rate, int(rate * 1.0), [(amplitudes(m, spot_for_angles(m, np.radians([3.0, -2.0]))), 1000.0, 0.3)],
                noise=1e-3, rng=np.random.default_rng(0))
    payload = np.ascontiguousarray(x.T).astype("<f4").tobytes()
    out = tmp_path / "live.csv"
    proc = subprocess.Popen([sys.executable, "-m", "psdcal.cli", "locate", "-", "--calib", str(tmp_path / "c.json"),
                             "--allow-no-covariance", "--rate-hz", str(rate), "--carrier-hz", "1000", "--emitter", "led",
                             "--raw-dtype", "float32", "-o", str(out)],
                            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=_env())
    hub = Hub(Options(sensor_rows=(("s1", out),)))
    half = len(payload) // 2 // 16 * 16
    proc.stdin.write(payload[:half])
    proc.stdin.flush()
    got = []
    deadline = time.monotonic() + 60
    while not got and time.monotonic() < deadline:  # the stream is still open: rows of the first half only
        upd = hub.poll()
        got += upd["sensor"] if upd else []
        time.sleep(0.05)
    assert got and proc.poll() is None
    assert all(r[2] == "led" and r[5] is not None for r in got)
    assert abs(np.median([r[5][0] for r in got]) - 3.0) < 0.1 and abs(np.median([r[5][1] for r in got]) + 2.0) < 0.1
    proc.stdin.write(payload[half:])
    proc.stdin.close()
    assert proc.wait(timeout=60) == 0, proc.stderr.read()
    while hub.poll():
        pass
    assert len(hub.snapshot()["sensor"]) == 100  # 1 s of 10 ms windows


# ---- the page in a real browser --------------------------------------------------------------------------------------
def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO / "src") + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _chromium():
    from browser import find_chromium

    return find_chromium()


def test_chromium_present_on_ci():
    if os.environ.get("CI", "").lower() not in ("true", "1", "yes"):
        pytest.skip("only enforced on CI (CI=true)")
    assert _chromium() is not None, "CI must install chromium so that the dashboard's browser test runs"


def start_server(args, timeout_s=60.0):
    """Start `psdcal dashboard ARGS --port 0`; return (process, url)."""
    proc = subprocess.Popen([sys.executable, "-m", "psdcal.cli", "dashboard", *map(str, args), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        m = re.search(r"(http://\S+)", line or "")
        if m:
            return proc, m.group(1)
        if proc.poll() is not None:
            raise AssertionError("the dashboard stopped: " + proc.stderr.read())
    proc.kill()
    raise AssertionError("the dashboard did not start")


def wait_for(b, expr, timeout_s=30.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        v = b.evaluate(expr)
        if v:
            return v
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {expr}")


WEBGL = ("--enable-unsafe-swiftshader", "--use-angle=swiftshader")
LOCATED_JS = """JSON.stringify(Array.from(document.querySelectorAll('#top .scatterlayer .trace.tracelocated path.point'))
  .map(function (p) { var m = /translate\\(([-\\d.e]+),\\s*([-\\d.e]+)\\)/.exec(p.getAttribute('transform')); return [+m[1], +m[2]]; }))"""
AXES_JS = """(function () { var L = document.getElementById('top')._fullLayout;
  return JSON.stringify({x: L.xaxis.range, y: L.yaxis.range, w: L.xaxis._length, h: L.yaxis._length}); })()"""


def expected_latest(rows, T):
    """The latest row of each emitter at or before T (from the CSV, read by the test)."""
    out = {}
    for t, em, x, y in rows:
        if t <= T + 1e-9:
            out[em] = (t, x, y)
    return out


def drawn_positions(b, rows, zoom=True):
    """Compare each emitter's marker in the view from above with its row, in pixels.

    With ``zoom`` the view is first zoomed onto the emitter's expected position
    (300 mm across: a pixel is about half a millimetre).
    """
    wait_for(b, "!psdDashboard.state.busy && !psdDashboard.state.dirty")
    T = float(b.evaluate("document.body.dataset.viewT"))
    exp = expected_latest(rows, T)
    worst = 0.0
    for em, (_, x, y) in sorted(exp.items()):
        if zoom:
            b.evaluate(f"Plotly.relayout('top', {{'xaxis.range': [{x - 150}, {x + 150}], 'yaxis.range': [{y - 150}, {y + 150}]}}); 1")
            ax = json.loads(wait_for(b, f"(function () {{ var a = {AXES_JS}; var r = JSON.parse(a).x; "
                                        f"return r[1] - r[0] < 1000 ? a : ''; }})()", 10))
            assert (ax["x"][1] - ax["x"][0]) / ax["w"] < 1.0  # the test's zoom: a pixel is less than a millimetre
        else:
            ax = json.loads(b.evaluate(AXES_JS))
        px = (x - ax["x"][0]) / (ax["x"][1] - ax["x"][0]) * ax["w"]
        py = (ax["y"][1] - y) / (ax["y"][1] - ax["y"][0]) * ax["h"]
        pts = json.loads(b.evaluate(LOCATED_JS))
        assert len(pts) == len(exp)
        worst = max(worst, min(((p[0] - px) ** 2 + (p[1] - py) ** 2) ** 0.5 for p in pts))
    return T, exp, worst


@pytest.mark.slow
@pytest.mark.skipif(_chromium() is None, reason="no chromium on this machine (apt-get install chromium); CI installs it")
def test_dashboard_in_a_browser(tmp_path):
    """Replay a recording: emitters appear where the rows put them (to a pixel), the chi2 warning and an event-log
    warning appear, pause holds the view while rows arrive, resume follows again; the static export opens from disk."""
    from browser import Chromium

    room = write_room(tmp_path, duration_s=60.0, sensor_rows=True)
    rows = read_rows(room["rows"])
    events = tmp_path / "events.jsonl"
    events.write_text("")
    per_sensor = [a for s in ("s1", "s2", "s3") for a in ("--sensor-rows", f"{s}={room[s + '_angles']}",
                                                         "--sensor-rows", f"{s}={room[s + '_amp']}")]
    proc, url = start_server([room["rows"], "--sensors", room["sensors"], "--emitters", room["emitters"],
                              "--events", events, "--replay", "--speed", "1", *per_sensor])
    try:
        # WebGL off here: the software-rendered 3-D view would share two CPU cores with the replay (the static
        # export below checks it); the view from above is SVG and is what is measured to the pixel
        with Chromium(timeout_s=60, extra_flags=("--disable-3d-apis",)) as b:
            b.open_page(1400, 1100)
            b.load(url)
            # the emitters appear
            wait_for(b, "document.querySelectorAll('#top .tracelocated path.point').length === 2")
            assert b.evaluate("document.querySelectorAll('#top .tracesensors path.point').length") == 3
            assert b.evaluate("document.querySelectorAll('#top .tracesurveyed path.point').length") == 3
            # the chi2 run of a1 at t = 1.0..1.02 s becomes one warning, with its time
            wait_for(b, "parseFloat(document.body.dataset.viewT) > 1.2")
            text = b.evaluate("document.getElementById('warnings').textContent")
            assert "a1: chi2" in text and f"t = {BAD_T[-1] + 0.005:.3f} s" in text
            # each sensor's health: its calibration's verdict, the emitters it sees, its SNR, its chi2 against the others
            view_t, health = json.loads(b.evaluate(
                "JSON.stringify([parseFloat(document.body.dataset.viewT), "
                "Array.from(document.querySelectorAll('#sensors tbody tr')).map(function (r) {"
                " return Array.from(r.cells).map(function (c) { return c.textContent; }); })])"))
            assert [h[0] for h in health] == ["s1", "s2", "s3"] and all(h[1] == "good" for h in health)
            assert all(h[2] == "a1 tag" for h in health)
            snr = [float(h[3]) for h in health]  # written as 4 / (2 * noise): 400, 250, 80
            assert 360 < snr[0] < 440 and 225 < snr[1] < 275 and 70 < snr[2] < 90
            # chi2 against the others near its correct-data value; s2's only before its reflection (t >= 2.0 s),
            # which a slow machine may have reached by now
            clean = [h for h in health if h[0] != REFLECTION[0] or view_t < REFLECTION[2]]
            assert all(0.1 < float(h[4]) < 1.5 for h in clean), (view_t, health)
            wait_for(b, "parseFloat(document.body.dataset.viewT) > 2.2")
            assert "sensor s2: its angles disagree" in b.evaluate("document.getElementById('warnings').textContent")
            # a warning a command prints (the --events log) appears too
            from psdcal.cli._events import append_event, event

            append_event(events, event("the stream ended inside a frame (12 bytes dropped)", command="locate"))
            wait_for(b, "document.getElementById('warnings').textContent.indexOf('12 bytes dropped') >= 0", 10)
            # pause: the view holds while rows keep arriving
            b.evaluate("document.getElementById('pause').click()")
            n0 = b.evaluate("psdDashboard.state.pos.length")
            T, exp, worst = drawn_positions(b, rows)
            assert worst < 1.0, f"a marker is {worst:.2f} px from its row"
            assert set(exp) == {"a1", "tag"}
            time.sleep(0.8)
            assert float(b.evaluate("document.body.dataset.viewT")) == T
            assert b.evaluate("psdDashboard.state.pos.length") > n0  # rows arrived meanwhile
            assert "paused" in b.evaluate("document.getElementById('status').textContent")
            # the CSV export is the rows on screen: the trail behind T, as written
            csv_text = b.evaluate("psdDashboard.csv()")
            lines = csv_text.strip().split("\n")
            assert lines[0].startswith("t_s,emitter,X_mm") and float(lines[-1].split(",")[0]) == pytest.approx(T)
            # resume: the view follows the rows again
            b.evaluate("document.getElementById('pause').click()")
            wait_for(b, f"parseFloat(document.body.dataset.viewT) > {T + 0.3}", 10)
            assert b.errors() == []
    finally:
        proc.terminate()
        proc.wait(timeout=10)

    # the static export: one file, no server, no network
    out = tmp_path / "room.html"
    short = tmp_path / "short.csv"
    short.write_text("".join(room["rows"].read_text().splitlines(keepends=True)[:401]))  # 2 s
    assert main(["dashboard", str(short), "--sensors", str(room["sensors"]), "--emitters", str(room["emitters"]),
                 "--export", str(out)]) == 0
    html_text = out.read_text(encoding="utf-8")
    outside = re.sub(r"<script>.*?</script>", "", html_text, flags=re.DOTALL)  # the markup, not the inlined code
    assert "<script src" not in outside and not re.search(r"""(src|href)\s*=\s*["']?(https?:|//)""", outside)
    assert html_text.count("<script>") == 2 and "plotly.js v" in html_text  # plotly.js and the page's script
    with Chromium(timeout_s=60, extra_flags=WEBGL) as b:
        b.open_page(1400, 1100)
        b.load(out.resolve().as_uri())
        wait_for(b, "document.querySelectorAll('#top .tracelocated path.point').length === 2")
        T, exp, worst = drawn_positions(b, read_rows(short), zoom=False)  # at the page's own zoom (~25 mm/px)
        assert T == pytest.approx(1.995) and worst < 1.0
        assert "static export" in b.evaluate("document.getElementById('status').textContent")
        assert "a1: chi2" in b.evaluate("document.getElementById('warnings').textContent")
        # the 3-D view (WebGL, software-rendered here): the same located points
        pts3d = json.loads(wait_for(b, "(function () { var d = document.getElementById('room3d')._fullData;"
                                       " var t = d && d.filter(function (t) { return t.name === 'located'; })[0];"
                                       " return t ? JSON.stringify([t.x, t.y, t.z]) : ''; })()"))
        got = {(round(x, 3), round(y, 3)) for x, y in zip(pts3d[0], pts3d[1])}
        assert got == {(round(x, 3), round(y, 3)) for _, x, y in exp.values()}
        assert b.evaluate("document.querySelectorAll('#room3d canvas').length") > 0
        # scrub back: the slider's middle shows the rows of the middle of the recording
        b.evaluate("var s = document.getElementById('scrub'); s.value = '0.5'; s.dispatchEvent(new Event('input')); 1")
        wait_for(b, "Math.abs(parseFloat(document.body.dataset.viewT) - 1.0) < 0.01", 10)
        T2, _, worst2 = drawn_positions(b, read_rows(short), zoom=False)
        assert T2 == pytest.approx(0.005 + 0.5 * (1.995 - 0.005)) and worst2 < 1.0
        # PNG export: the image the PNG button saves (plotly's own rendering of the view from above)
        png = b.evaluate("Plotly.toImage('top', {format: 'png'}).then(function (u) { return u; })")
        assert png.startswith("data:image/png;base64,") and len(png) > 5000
        # Play replays the recording from its start
        b.evaluate("document.getElementById('play').click()")
        t_play = float(wait_for(b, "parseFloat(document.body.dataset.viewT) < 0.5 && document.body.dataset.viewT", 10))
        wait_for(b, f"parseFloat(document.body.dataset.viewT) > {t_play + 0.2}", 10)
        assert b.errors() == []
