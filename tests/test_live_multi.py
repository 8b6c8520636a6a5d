"""Several sensors live (`locate --sensors` on TCP sockets, files, named pipes), `record` and `--replay`:
the rows are those of `locate --sensors` on the same recordings; offsets align a late sensor; a source that
dies, lags or has another rate is one line, exit 2."""
from __future__ import annotations

import json
import os
import re
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from psdcal.cli import main

RATE = 20_000.0
CARRIERS = ("1000", "1150")
ALLOW = "--allow-no-covariance"


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """Three sensors, two fixed emitters (1000, 1150 Hz), 1.5 s at 20 kS/s, and the file path's rows."""
    d = tmp_path_factory.mktemp("room")
    assert main(["simulate-recording", "room", "--sensors", "3", "--anchors", "2", "--moving", "none",
                 "--duration-s", "1.5", "--rate-hz", str(RATE), "-o", str(d / "room")]) == 0
    assert main(_loc(d / "room" / "sensors.json", d / "file.csv")) == 0
    data = [np.load(d / "room" / f"s{i}.npy") for i in (1, 2, 3)]
    return d, data


def _loc(sensors, out, *sources, extra=()):
    a = ["locate", *map(str, sources), "--sensors", str(sensors), "--rate-hz", str(RATE), ALLOW, "-o", str(out),
         *extra]
    for f in CARRIERS:
        a += ["--carrier-hz", f]
    return a


def _server(x: np.ndarray, block: int = 200, pace_s: float = 0.0, stop_after: int | None = None):
    """A localhost server sending frames ``x`` (n, 4) float64 in blocks; returns (url, thread)."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    payload = np.ascontiguousarray(x, dtype="<f8")
    n = len(payload) if stop_after is None else stop_after

    def serve():
        conn, _ = srv.accept()
        try:
            for start in range(0, n, block):
                conn.sendall(payload[start:min(start + block, n)].tobytes())
                if pace_s:
                    time.sleep(pace_s)
        finally:
            conn.close()
            srv.close()

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    return f"tcp://127.0.0.1:{srv.getsockname()[1]}", th


def _rows(path):
    lines = Path(path).read_text().splitlines()
    return lines[0], [ln.split(",") for ln in lines[1:]]


def _same(a, b, dt_s=0.0):
    """The rows of CSV ``a`` are those of ``b`` (times shifted by ``dt_s``): same header, emitters and sensor
    counts, numbers to 1e-9 relative (the windows are demodulated in other batches: the last bits may differ)."""
    ha, ra = _rows(a)
    hb, rb = _rows(b)
    assert ha == hb and len(ra) == len(rb) > 0
    assert [r[1] for r in ra] == [r[1] for r in rb]
    i_n = ha.split(",").index("n_sensors")
    assert [r[i_n] for r in ra] == [r[i_n] for r in rb]
    # the text columns (emitter; left_out and reflection, docs/guide/positioning.md#reflections) equal as text
    text = [j for j, h in enumerate(ha.split(",")) if h in ("emitter", "left_out", "reflection")]
    assert [[r[j] for j in text] for r in ra] == [[r[j] for j in text] for r in rb]
    x = np.array([[float(v) for j, v in enumerate(r) if j not in text] for r in ra])
    y = np.array([[float(v) for j, v in enumerate(r) if j not in text] for r in rb])
    y[:, 0] += dt_s
    np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9)


def test_tcp_sources_equal_file_rows(room, tmp_path, capsys):
    d, data = room
    urls = [_server(x)[0] for x in data]
    assert main(_loc(d / "room" / "sensors.json", tmp_path / "live.csv", *urls)) == 0
    _, rows = _rows(d / "file.csv")
    assert len(rows) > 200  # both emitters, 150 windows
    _same(tmp_path / "live.csv", d / "file.csv")
    out = capsys.readouterr().out
    assert "latency per window (arrival to row)" in out and "p99" in out and "after the first 1 s" in out


def test_file_and_named_pipe_sources_equal_file_rows(room, tmp_path):
    d, data = room
    (tmp_path / "s1.raw").write_bytes(np.ascontiguousarray(data[0], dtype="<f8").tobytes())
    fifo = tmp_path / "s2.fifo"
    os.mkfifo(fifo)

    def feed():
        with open(fifo, "wb") as fh:
            fh.writelines(np.ascontiguousarray(data[1][start:start + 300], dtype="<f8").tobytes() for start in range(0, len(data[1]), 300))

    th = threading.Thread(target=feed, daemon=True)
    th.start()
    url, _ = _server(data[2])
    assert main(_loc(d / "room" / "sensors.json", tmp_path / "live.csv", f"file:{tmp_path / 's1.raw'}",
                     f"file:{fifo}", url)) == 0
    th.join(5)
    _same(tmp_path / "live.csv", d / "file.csv")


def test_record_then_replay_same_rows_at_speed(room, tmp_path, capsys):
    d, data = room
    urls = [_server(x)[0] for x in data]
    sensors = d / "room" / "sensors.json"
    assert main(["record", *urls, "--sensors", str(sensors), "--rate-hz", str(RATE), "-o",
                 str(tmp_path / "s.psdsession")]) == 0
    assert "recorded 3 sources" in capsys.readouterr().out
    assert main(_loc(sensors, tmp_path / "rep.csv", extra=["--replay", str(tmp_path / "s.psdsession"),
                                                           "--speed", "0"])) == 0
    _same(tmp_path / "rep.csv", d / "file.csv")
    # --record while locating live, then replay at real speed: the same rows again, taking the session's time
    urls = [_server(x, block=400, pace_s=0.02)[0] for x in data]  # 20 ms of signal every 20 ms
    t0 = time.perf_counter()
    assert main(_loc(sensors, tmp_path / "live.csv", *urls, extra=["--record", str(tmp_path / "b.psdsession")])) == 0
    live_s = time.perf_counter() - t0
    _same(tmp_path / "live.csv", d / "file.csv")
    t0 = time.perf_counter()
    a = _loc(sensors, tmp_path / "rep1.csv", extra=["--replay", str(tmp_path / "b.psdsession"), "--speed", "1"])
    assert main(a) == 0
    real_s = time.perf_counter() - t0
    _same(tmp_path / "rep1.csv", d / "file.csv")
    a = _loc(sensors, tmp_path / "rep8.csv", extra=["--replay", str(tmp_path / "b.psdsession"), "--speed", "8"])
    assert main(a) == 0
    _same(tmp_path / "rep8.csv", d / "file.csv")
    # the session lasted >= 1.4 s (75 blocks of 20 ms); a real-speed replay takes that long
    assert live_s >= 1.4 and real_s >= 1.35
    # the replay's own pace (no processing): 8x faster releases the last block after ~1/8 of the session
    from psdcal.signal.session import replay_events

    t0 = time.perf_counter()
    ats = [at for _, _, at in replay_events(tmp_path / "b.psdsession", 8.0)]
    took = ats[-1] - t0
    assert 1.4 / 8 - 0.01 <= took < 1.4 / 2, took


def test_offset_aligns_a_late_sensor(room, tmp_path):
    d, data = room
    k = 37  # sensor s2 started 37 samples (1.85 ms) after the others: its stream lacks their first 37 samples
    trimmed = [x[k:] for x in data]
    for i, x in enumerate(trimmed, start=1):
        np.save(tmp_path / f"t{i}.npy", x)
    assert main(_loc(d / "room" / "sensors.json", tmp_path / "file_t.csv",
                     *[tmp_path / f"t{i}.npy" for i in (1, 2, 3)])) == 0
    urls = [_server(data[0])[0], _server(trimmed[1])[0], _server(data[2])[0]]
    assert main(_loc(d / "room" / "sensors.json", tmp_path / "live.csv", *urls,
                     extra=["--offset-s", f"s2={k / RATE!r}"])) == 0
    # the live rows are stamped on the first sensor's clock: the file's times + 37 samples
    _same(tmp_path / "live.csv", tmp_path / "file_t.csv", dt_s=k / RATE)
    _, rf = _rows(tmp_path / "file_t.csv")
    # without the offset, the misaligned windows give other rows
    urls = [_server(data[0])[0], _server(trimmed[1])[0], _server(data[2])[0]]
    assert main(_loc(d / "room" / "sensors.json", tmp_path / "live0.csv", *urls)) == 0
    _, r0 = _rows(tmp_path / "live0.csv")
    x0 = np.array([[float(v) for v in r[2:5]] for r in r0[: len(rf)]])
    xf = np.array([[float(v) for v in r[2:5]] for r in rf])
    assert np.abs(x0 - xf).max() > 1e-3  # mm: misaligned by 1.85 ms, the positions move


def _one_line_error(capsys, *words):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("psdcal: error:"), err
    for w in words:
        assert w in err[0], err[0]


def test_source_dying_mid_way_is_exit_2(room, tmp_path, capsys):
    d, data = room
    urls = [_server(data[0])[0], _server(data[1], stop_after=4000)[0], _server(data[2])[0]]  # s2 dies at 0.2 s
    assert main(_loc(d / "room" / "sensors.json", tmp_path / "live.csv", *urls)) == 2
    _one_line_error(capsys, "sensor s2 ended after 0.2 s")


def test_unequal_rates_and_lagging_source(room, tmp_path, capsys):
    from psdcal.errors import InputError
    from psdcal.measure.live_multi import locate_live_multi
    from psdcal.measure.locate import LocateConfig
    from psdcal.measure.positioning import load_sensors
    from psdcal.signal.session import SessionWriter, SourceInfo

    d, data = room
    # a session whose sources have different rates
    w = SessionWriter(tmp_path / "u.psdsession", [SourceInfo("s1", "x", RATE), SourceInfo("s2", "y", RATE / 2),
                                                  SourceInfo("s3", "z", RATE)])
    w.write(0, data[0][:100].T, 0.0)
    w.close()
    args = _loc(d / "room" / "sensors.json", tmp_path / "u.csv", extra=["--replay", str(tmp_path / "u.psdsession")])
    assert main(args) == 2
    _one_line_error(capsys, "different sampling rates")
    # live: s3 delivers at half the rate (arrival stamps 2 blocks of signal time apart): refused once 1 s behind
    poses = load_sensors(d / "room" / "sensors.json")

    x = [np.concatenate([v] * 3) for v in data]  # 4.5 s

    def events():
        for j in range(0, len(x[0]), 500):
            t = j / RATE
            yield 0, x[0][j:j + 500].T, t
            yield 1, x[1][j:j + 500].T, t
            if j % 1000 == 0:
                yield 2, x[2][j // 2:j // 2 + 500].T, t
    with pytest.raises(InputError, match=r"sensor s3 is 1\.\d* s of signal behind .* delivers 10000 samples/s"):
        locate_live_multi(events(), poses, RATE, tmp_path / "h.csv",
                          LocateConfig(carriers_hz=(1000.0, 1150.0), min_snr=10.0))


@pytest.mark.parametrize("extra,words", [
    (["--offset-s", "s9=0.1"], ["NAME=SECONDS", "s9=0.1"]),
    (["--offset-s", "s2=abc"], ["not a number of seconds"]),
    (["--tdm"], ["time multiplexing with several sensors needs --schedule"]),
])
def test_bad_options_one_line(room, tmp_path, capsys, extra, words):
    d, data = room
    url, _ = _server(data[0][:10])
    args = _loc(d / "room" / "sensors.json", tmp_path / "x.csv", url, "tcp://127.0.0.1:1", "-", extra=extra)
    assert main(args) == 2
    _one_line_error(capsys, *words)


def test_mismatched_sources_one_line(room, tmp_path, capsys):
    d, _ = room
    sensors = d / "room" / "sensors.json"
    assert main(_loc(sensors, tmp_path / "a.csv", "-", "-", "-")) == 2
    _one_line_error(capsys, "standard input")
    assert main(_loc(sensors, tmp_path / "b.csv", "-", "tcp://127.0.0.1:1")) == 2
    _one_line_error(capsys, "3 sensors need 3 live sources")
    (tmp_path / "bad.psdsession").write_text("hello\n")
    assert main(_loc(sensors, tmp_path / "c.csv", extra=["--replay", str(tmp_path / "bad.psdsession")])) == 2
    _one_line_error(capsys, "not a psdcal session file")
    cal = json.loads(sensors.read_text())["sensors"][0]["calib"]
    assert main(["locate", "--calib", str(d / "room" / cal), "--replay", str(tmp_path / "bad.psdsession"),
                 "--carrier-hz", "1000", "-o", str(tmp_path / "d.csv"), ALLOW]) == 2
    _one_line_error(capsys, "--replay")


def test_truncated_session_replays_what_came(room, tmp_path, capsys):
    d, data = room
    urls = [_server(x)[0] for x in data]
    p = tmp_path / "s.psdsession"
    assert main(["record", *urls, "--names", "s1,s2,s3", "--rate-hz", str(RATE), "-o", str(p)]) == 0
    capsys.readouterr()
    p.write_bytes(p.read_bytes()[:-1000])  # cut inside the last record
    assert main(_loc(d / "room" / "sensors.json", tmp_path / "r.csv", extra=["--replay", str(p), "--speed", "0"])) == 0
    assert "ends inside a record" in capsys.readouterr().err
    _, rows = _rows(tmp_path / "r.csv")
    _, full = _rows(d / "file.csv")
    assert 0 < len(rows) < len(full)
    # the numbers (the last two columns, left_out and reflection, are text)
    np.testing.assert_allclose(np.array([[float(v) for v in r[2:-2]] for r in rows]),
                               np.array([[float(v) for v in r[2:-2]] for r in full[: len(rows)]]), rtol=1e-9, atol=1e-9)
    assert [r[-2:] for r in rows] == [r[-2:] for r in full[: len(rows)]]


def test_help_texts():
    from click.testing import CliRunner

    from psdcal.cli import cli

    r = CliRunner().invoke(cli, ["record", "--help"])
    assert r.exit_code == 0
    for w in ("tcp://127.0.0.1:PORT", "file:PATH", "--replay", "Example", "--duration-s", "arrival"):
        assert w in r.output, w
    r = CliRunner().invoke(cli, ["locate", "--help"])
    for w in ("--offset-s", "NAME=SECONDS", "--replay", "--speed", "--record", "Several sensors live"):
        assert w in r.output, w


def test_each_window_keeps_the_arrival_of_its_last_sample(room, tmp_path):
    """Blocks of 150 samples (windows of 200), some joined as LiveSources joins them: a window's latency is
    counted from the arrival of the block holding its last sample, latest over the sensors."""
    from psdcal.measure.live_multi import locate_live_multi
    from psdcal.measure.locate import LocateConfig
    from psdcal.measure.positioning import load_sensors

    d, data = room
    poses = load_sensors(d / "room" / "sensors.json")
    n = 150

    def arrival(i, start):
        return 1000.0 + start / RATE + 0.001 * i  # sensor i's block starting at `start`

    def events():
        for j in range(0, 30000, 2 * n):
            for i in range(3):
                a, b = data[i][j:j + n].T, data[i][j + n:j + 2 * n].T
                if i == 1:  # two blocks joined: (ends, arrivals)
                    stamps = np.array([[a.shape[1], arrival(i, j)], [a.shape[1] + b.shape[1], arrival(i, j + n)]])
                    yield i, np.concatenate([a, b], axis=1), stamps
                else:
                    yield i, a, arrival(i, j)
                    yield i, b, arrival(i, j + n)

    s = locate_live_multi(events(), poses, RATE, tmp_path / "a.csv",
                          LocateConfig(carriers_hz=(1000.0, 1150.0), window_s=0.01))
    last = (np.arange(s.n_windows) + 1) * 200 - 1
    expected = np.max([[arrival(i, (q // n) * n) for q in last] for i in range(3)], axis=0)
    np.testing.assert_allclose(s.written_s - s.latency_s, expected, rtol=0, atol=1e-9)
    _same(tmp_path / "a.csv", d / "file.csv")


def test_sources_ending_apart_warn(room, tmp_path, capsys):
    d, data = room
    urls = [_server(data[0])[0], _server(data[1], stop_after=22000)[0], _server(data[2])[0]]  # s2 0.4 s short
    assert main(_loc(d / "room" / "sensors.json", tmp_path / "live.csv", *urls)) == 0
    err = capsys.readouterr().err
    assert "ended at different times (s1 1.5 s, s2 1.1 s, s3 1.5 s)" in err
    _, rows = _rows(tmp_path / "live.csv")
    assert len(rows) == 2 * 110


def test_tdm_with_schedule_across_sensors(tmp_path):
    """Three sensors, three emitters taking turns (20 ms each): one row per schedule entry, at the truth
    within 5 of its sigmas on every axis; a recorded session replays to the same rows."""
    d = tmp_path
    assert main(["simulate-recording", "room", "--sensors", "3", "--anchors", "3", "--moving", "none", "--mux", "tdm",
                 "--duration-s", "1", "--rate-hz", str(RATE), "-o", str(d / "tdm")]) == 0
    truth = {e["name"]: np.array(e["p0_mm"]) for e in json.loads((d / "tdm" / "truth.json").read_text())["emitters"]}
    urls = [_server(np.load(d / "tdm" / f"s{i}.npy"))[0] for i in (1, 2, 3)]
    a = ["locate", *urls, "--sensors", str(d / "tdm" / "sensors.json"), "--rate-hz", str(RATE), ALLOW,
         "--carrier-hz", "1000", "--schedule", str(d / "tdm" / "schedule.csv"), "-o", str(d / "live.csv"),
         "--record", str(d / "tdm.psdsession")]
    assert main(a) == 0
    sched = (d / "tdm" / "schedule.csv").read_text().splitlines()[1:]
    head, rows = _rows(d / "live.csv")
    assert len(rows) == len(sched) == 50
    for r, e in zip(rows, sched):
        name, t0, t1 = e.split(",")
        assert r[1] == name and abs(float(r[0]) - 0.5 * (float(t0) + float(t1))) < 1e-9
        err = (np.array([float(v) for v in r[2:5]]) - truth[name]) / np.array([float(v) for v in r[5:8]])
        assert np.all(np.abs(err) < 5), (r, err)
    a = ["locate", "--sensors", str(d / "tdm" / "sensors.json"), ALLOW, "--carrier-hz", "1000", "--schedule",
         str(d / "tdm" / "schedule.csv"), "--replay", str(d / "tdm.psdsession"), "--speed", "0", "-o",
         str(d / "rep.csv")]
    assert main(a) == 0
    _same(d / "rep.csv", d / "live.csv")


def test_an_existing_session_is_not_replaced(room, tmp_path, capsys):
    d, data = room
    (tmp_path / "s.psdsession").write_bytes(b"keep")
    urls = [_server(x)[0] for x in data]
    assert main(_loc(d / "room" / "sensors.json", tmp_path / "live.csv", *urls,
                     extra=["--record", str(tmp_path / "s.psdsession")])) == 2
    _one_line_error(capsys, "--record")
    assert (tmp_path / "s.psdsession").read_bytes() == b"keep"
    assert main(["record", *urls, "--rate-hz", str(RATE), "-o", str(tmp_path / "s.psdsession")]) == 2
    _one_line_error(capsys, "--output")
    assert (tmp_path / "s.psdsession").read_bytes() == b"keep"


def test_offsets_estimated_from_arrival_times(room, tmp_path, capsys):
    """Senders at the real rate (20 ms blocks sent once sampled); sensor s2 started 0.3 s after the others:
    --offset-s auto finds 0.3 s (to 5 ms) and s3 0 s, and the rows are those of the aligned recordings."""
    d, data = room
    late_s, blk = 0.3, 400
    k = int(late_s * RATE)
    streams = [data[0], data[1][k:], data[2]]
    starts = [0.0, late_s, 0.0]
    barrier = threading.Barrier(3)
    urls = []
    for x, st in zip(streams, starts):
        srv = socket.socket()
        srv.bind(("127.0.0.1", 0))
        srv.listen(1)
        urls.append(f"tcp://127.0.0.1:{srv.getsockname()[1]}")

        def serve(srv=srv, x=x, st=st):
            conn, _ = srv.accept()
            barrier.wait()
            t0 = time.perf_counter() + st
            payload = np.ascontiguousarray(x, dtype="<f8")
            for j in range(0, len(payload), blk):
                wait = t0 + (j + blk) / RATE - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
                conn.sendall(payload[j:j + blk].tobytes())
            conn.close()
            srv.close()

        threading.Thread(target=serve, daemon=True).start()
    assert main(_loc(d / "room" / "sensors.json", tmp_path / "live.csv", *urls, extra=["--offset-s", "auto"])) == 0
    err = capsys.readouterr().err
    line = [ln for ln in err.splitlines() if "offsets estimated" in ln][0]
    est = {n: float(v) for n, v in re.findall(r"(s\d) ([+-][\d.]+) s", line)}
    assert est["s1"] == 0.0 and abs(est["s2"] - late_s) < 0.005 and abs(est["s3"]) < 0.005, line
    # the aligned recordings through the file path: the same emitters and windows
    for i, x in enumerate([data[0][k:], data[1][k:], data[2][k:]], start=1):
        np.save(tmp_path / f"a{i}.npy", x)
    assert main(_loc(d / "room" / "sensors.json", tmp_path / "file_a.csv",
                     *[tmp_path / f"a{i}.npy" for i in (1, 2, 3)])) == 0
    _, rl = _rows(tmp_path / "live.csv")
    _, rf = _rows(tmp_path / "file_a.csv")
    assert abs(len(rl) - len(rf)) <= 4 and [r[1] for r in rl[:200]] == [r[1] for r in rf[:200]]
    xl = np.array([[float(v) for j, v in enumerate(r[:5]) if j != 1] for r in rl[:200]])
    xf = np.array([[float(v) for j, v in enumerate(r[:5]) if j != 1] for r in rf[:200]])
    sig = np.array([[float(v) for v in r[5:8]] for r in rf[:200]])
    # stamped on s1's clock: the aligned file's times + the estimated start; the windows hold nearly the same
    # samples (a few misaligned of 200): positions within a fraction of their sigma
    assert np.abs(xl[:, 0] - xf[:, 0] - est["s2"]).max() < 1e-4  # (est is printed to 0.1 ms)
    assert np.abs((xl[:, 1:] - xf[:, 1:]) / sig).max() < 1.5


def test_format_npy_refused_and_a_silent_source_stalls(room, tmp_path, capsys):
    from psdcal.errors import InputError
    from psdcal.signal.session import LiveSources, open_source

    d, _ = room
    assert main(_loc(d / "room" / "sensors.json", tmp_path / "x.npy", "-", "-", "-", extra=["--format", "npy"])) == 2
    _one_line_error(capsys, "--format npy")
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    src = open_source(f"tcp://127.0.0.1:{srv.getsockname()[1]}", RATE)
    conn, _ = srv.accept()  # connected, but nothing is sent
    t0 = time.perf_counter()
    with pytest.raises(InputError, match="no data from any source for 0.3 s"):
        list(LiveSources([src]).events(stall_s=0.3))
    assert 0.25 < time.perf_counter() - t0 < 5
    conn.close()
    srv.close()
