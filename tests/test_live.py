"""Live input to `locate`: a simulated recording streamed through stdin and a localhost socket gives the
rows of the file-based locate (to 1e-9), written as the windows complete."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from psdcal.cli import main
from psdcal.study.recordings import amplitudes, calib_dict, model, signals, spot_for_angles, write_recording

RATE = 20_000.0
CARRIERS = (1000.0, 1300.0)


def _setup(tmp_path, n=12_000, seed=0):
    m = model()
    (tmp_path / "calib.json").write_text(json.dumps(calib_dict()))
    rng = np.random.default_rng(seed)
    d1 = spot_for_angles(m, np.radians([3.0, -2.0]))
    d2 = spot_for_angles(m, np.radians([-5.0, 4.0]))
    x = signals(RATE, n, [(amplitudes(m, d1), CARRIERS[0], 0.3), (amplitudes(m, d2), CARRIERS[1], 1.1)],
                noise=1e-3, rng=rng)
    return x


def _args(src, out, extra=()):
    a = ["locate", str(src), "--calib", "calib.json", "--rate-hz", str(RATE), "--distance-mm", "3000",
         "-o", str(out), *extra]
    for f in CARRIERS:
        a += ["--carrier-hz", str(f)]
    return a


def _rows(path):
    lines = Path(path).read_text().splitlines()
    head = lines[0]
    body = [ln.split(",") for ln in lines[1:]]
    return head, body


def _assert_same(a, b):
    ha, ra = _rows(a)
    hb, rb = _rows(b)
    assert ha == hb and len(ra) == len(rb) > 0
    for x, y in zip(ra, rb):
        assert x[1] == y[1]
        np.testing.assert_allclose(np.array([x[0], *x[2:]], float), np.array([y[0], *y[2:]], float),
                                   rtol=1e-9, atol=1e-12)


@pytest.fixture
def cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_stdin_equals_file(cwd):
    x = _setup(cwd)
    write_recording(cwd / "rec.npy", x, RATE)
    assert main(_args("rec.npy", "file.csv")) == 0
    exe = Path(sys.executable).with_name("psdcal")
    p = subprocess.run([str(exe), *_args("-", "live.csv")], input=np.ascontiguousarray(x.T).astype("<f8").tobytes(),
                       capture_output=True, cwd=cwd, timeout=120)
    assert p.returncode == 0, p.stderr.decode()
    assert b"latency per window" in p.stdout
    _assert_same("file.csv", "live.csv")


def test_int16_stdin_with_scale_equals_file(cwd):
    x = _setup(cwd, seed=1)
    scale = 1e-4
    q = np.clip(np.round(x / scale), -32768, 32767).astype("<i2")
    write_recording(cwd / "rec.npy", q.astype(float) * scale, RATE)
    assert main(_args("rec.npy", "file.csv")) == 0
    exe = Path(sys.executable).with_name("psdcal")
    p = subprocess.run([str(exe), *_args("-", "live.csv", ["--raw-dtype", "int16", "--raw-scale", str(scale)])],
                       input=np.ascontiguousarray(q.T).tobytes(), capture_output=True, cwd=cwd, timeout=120)
    assert p.returncode == 0, p.stderr.decode()
    _assert_same("file.csv", "live.csv")


def test_tcp_equals_file_and_rows_come_while_streaming(cwd):
    x = _setup(cwd, seed=2)
    write_recording(cwd / "rec.npy", x.astype("<f4").astype(float), RATE)
    assert main(_args("rec.npy", "file.csv")) == 0
    payload = np.ascontiguousarray(x.T).astype("<f4").tobytes()
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    port = srv.getsockname()[1]
    seen_early = []

    def serve():
        conn, _ = srv.accept()
        half = len(payload) // 2 // 16 * 16
        for k in range(0, half, 4000):  # odd-sized pieces: frames split across reads
            conn.sendall(payload[k : min(k + 4000, half)])
        deadline = time.time() + 20
        while time.time() < deadline:  # rows of the first half appear before the second half is sent
            if (cwd / "live.csv").exists() and len((cwd / "live.csv").read_text().splitlines()) > 5:
                seen_early.append(True)
                break
            time.sleep(0.01)
        conn.sendall(payload[half:])
        conn.close()

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    assert main(_args(f"tcp://127.0.0.1:{port}", "live.csv", ["--raw-dtype", "float32"])) == 0
    th.join(5)
    srv.close()
    assert seen_early
    _assert_same("file.csv", "live.csv")


def test_refuses_remote_hosts_and_missing_daq(cwd, capsys):
    _setup(cwd)
    assert main(_args("tcp://192.0.2.1:9000", "o.csv")) == 2
    assert "localhost" in capsys.readouterr().err
    try:
        import nidaqmx  # noqa: F401
    except ImportError:
        assert main(_args("nidaqmx://Dev1/ai0:3", "o.csv")) == 2
        err = capsys.readouterr().err.strip()
        assert "nidaqmx" in err and len(err.splitlines()) == 1
    assert not os.path.exists(cwd / "o.csv")


def test_bench_live_runs(capsys):
    import importlib.util

    bench = Path(__file__).resolve().parents[1] / "benchmarks"
    sys.path.insert(0, str(bench))
    try:
        spec = importlib.util.spec_from_file_location("_bench_live", bench / "bench_live.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        ms = mod.run(seconds=0.2, rate_hz=20_000.0)
    finally:
        sys.path.remove(str(bench))
    assert len(ms) >= 10 and np.all(ms > 0)
    assert "median (ms)" in capsys.readouterr().out


def test_backlog_read_in_pieces_and_batched_equals_file(cwd, monkeypatch):
    """A backlog (a stream whose reads fill the buffer) is read in small pieces whose windows are gathered
    before they become rows: the same rows as the file; a bad sample late in the stream still names the
    sample, and the rows of the pieces before it are written."""
    import psdcal.measure.live as live
    from psdcal.measure.locate import LocateConfig, locate_to_csv
    from psdcal.signal.live import open_stream
    from psdcal.signal.recording import open_recording

    monkeypatch.setattr(live, "LIVE_READ_BYTES", 1 << 12)  # 128 frames a read: many pieces a window batch
    monkeypatch.setattr(live, "BATCH_WINDOWS", 7)
    n = 40_000
    x = _setup(cwd, n=n, seed=3)
    write_recording(cwd / "rec.npy", x, RATE)
    m = model()
    cfg = LocateConfig(carriers_hz=CARRIERS, window_s=0.01, distance_mm=3000.0, check_carriers=False)
    locate_to_csv(open_recording(cwd / "rec.npy", RATE), m, cwd / "file.csv", cfg)
    raw = np.ascontiguousarray(x.T).astype("<f8")
    (cwd / "raw.bin").write_bytes(raw.tobytes())
    with open(cwd / "raw.bin", "rb") as fh:
        s = live.locate_stream(open_stream("-", RATE, stdin=fh), m, cwd / "live.csv", cfg)
    assert s.n_windows == n // 200 and len(s.latency_s) == s.n_windows
    _assert_same("file.csv", "live.csv")
    with open(cwd / "file.csv") as fh:
        n_file = len(fh.read().splitlines()) - 1
    bad = 31_234  # in window 156 (200 samples a window)
    raw[bad, 2] = np.nan
    (cwd / "raw.bin").write_bytes(raw.tobytes())
    from psdcal.errors import InputError

    with open(cwd / "raw.bin", "rb") as fh, pytest.raises(InputError, match=f"sample {bad} of channel 3"):
        live.locate_stream(open_stream("-", RATE, stdin=fh), m, cwd / "bad.csv", cfg)
    _, rows = _rows(cwd / "bad.csv")
    t_last = max(float(r[0]) for r in rows)
    # every window of the pieces before the bad one (128 frames each) was written, none at or after it
    assert (bad // 128 * 128) / RATE - 0.01 - 1e-9 <= t_last < bad / RATE
    assert 0 < len(rows) < n_file


def test_stdin_from_a_regular_file_is_read_in_the_pieces_asked_for(cwd, monkeypatch, capsys):
    """Standard input redirected from a regular file is read into one reused buffer, like a pipe (a memory
    map would spare the copy, but the compiled sums read a map's pages slower than the kernel copies them):
    blocks of the size asked for, the file's rows, the file left after the last frame, the partial last frame
    warned about, and a bad sample named with its index, the rows of the pieces before it written."""
    import psdcal.measure.live as live
    from psdcal.errors import InputError
    from psdcal.signal.live import open_stream

    n = 9_000
    x = _setup(cwd, n=n, seed=4)
    raw = np.ascontiguousarray(x.T).astype("<f8")
    head = b"0123456789"  # the stream starts where the file is positioned (a header read past first)
    (cwd / "raw.bin").write_bytes(head + raw.tobytes() + b"\x00" * 7)  # and ends inside a frame
    with open(cwd / "raw.bin", "rb") as fh:
        fh.read(len(head))
        s = open_stream("-", RATE, stdin=fh)
        got = [(t0, np.array(b), s.backlog) for t0, b in s.chunks(rows=True, read_bytes=32 * 1000)]
        pos = fh.tell()
    assert "ended inside a frame (7 bytes dropped)" in capsys.readouterr().err
    assert [b.shape[0] for _, b, _ in got] == [1000] * 9
    assert [t0 for t0, _, _ in got] == [1000 * i / RATE for i in range(9)]
    assert all(bl for _, _, bl in got)  # (each read filled the buffer: more may be waiting)
    np.testing.assert_array_equal(np.concatenate([b for _, b, _ in got]), raw)
    assert pos == len(head) + raw.nbytes + 7  # at the end (the partial frame taken and dropped)
    assert [a[0] for a in s.arrivals] == list(range(1000, n + 1, 1000))

    # the whole live path on the file: the rows of the file's locate (to 1e-9)
    from psdcal.measure.locate import LocateConfig, locate_to_csv
    from psdcal.signal.recording import open_recording

    write_recording(cwd / "rec.npy", x, RATE)
    m = model()
    cfg = LocateConfig(carriers_hz=CARRIERS, window_s=0.01, distance_mm=3000.0, check_carriers=False)
    locate_to_csv(open_recording(cwd / "rec.npy", RATE), m, cwd / "file.csv", cfg)
    (cwd / "raw.bin").write_bytes(raw.tobytes())
    with open(cwd / "raw.bin", "rb") as fh:
        s = live.locate_stream(open_stream("-", RATE, stdin=fh), m, cwd / "live.csv", cfg)
    assert s.n_windows == n // 200
    _assert_same("file.csv", "live.csv")
    bad = 5_555
    raw[bad, 1] = np.inf
    (cwd / "raw.bin").write_bytes(raw.tobytes())
    monkeypatch.setattr(live, "LIVE_READ_BYTES", 32 * 1000)
    with open(cwd / "raw.bin", "rb") as fh, pytest.raises(InputError, match=f"sample {bad} of channel 2"):
        live.locate_stream(open_stream("-", RATE, stdin=fh), m, cwd / "bad.csv", cfg)
    _, rows = _rows(cwd / "bad.csv")
    assert (bad // 1000 * 1000) / RATE - 0.01 - 1e-9 <= max(float(r[0]) for r in rows) < bad / RATE


def test_stdin_follows_a_file_that_grows(cwd):
    """Frames appended to the file while it is read (a capture still being written) are read too: the
    blocks are the file's frames in order."""
    from psdcal.signal.live import open_stream

    rng = np.random.default_rng(6)
    first, more = rng.standard_normal((3000, 4)), rng.standard_normal((2500, 4))
    (cwd / "grow.bin").write_bytes(first.astype("<f8").tobytes())
    got = []
    with open(cwd / "grow.bin", "rb") as fh:
        s = open_stream("-", RATE, stdin=fh)
        for i, (_, b) in enumerate(s.chunks(rows=True, read_bytes=32 * 1000)):
            got.append(np.array(b))
            if i == 0:
                with open(cwd / "grow.bin", "ab") as app:
                    app.write(more.astype("<f8").tobytes())
    assert [g.shape[0] for g in got] == [1000] * 5 + [500]
    np.testing.assert_array_equal(np.concatenate(got), np.concatenate([first, more]))


def test_stdin_with_track_writes_the_track_of_the_rows(cwd):
    """`locate - --track`: the track is written row by row with the rows; it equals `psdcal track` of them."""
    x = _setup(cwd, seed=4)
    exe = Path(sys.executable).with_name("psdcal")
    p = subprocess.run([str(exe), *_args("-", "live.csv", ["--track", "live_track.csv", "--track-q", "1e4"])],
                       input=np.ascontiguousarray(x.T).astype("<f8").tobytes(), capture_output=True, cwd=cwd,
                       timeout=120)
    assert p.returncode == 0, p.stderr.decode()
    assert b"tracked rows to live_track.csv" in p.stdout
    assert main(["track", "live.csv", "-o", "track.csv", "--q", "1e4"]) == 0
    assert (cwd / "live_track.csv").read_bytes() == (cwd / "track.csv").read_bytes()
    assert len((cwd / "track.csv").read_text().splitlines()) > 10
