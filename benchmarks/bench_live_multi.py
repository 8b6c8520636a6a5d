#!/usr/bin/env python3
"""Benchmark of several sensors live: ``locate --sensors`` on four TCP sources at the real rate.

A room with four sensors (``psdcal simulate-recording room --sensors 4``,
20 kS/s, three emitters on 1000/1150/1300 Hz) is sent by a separate feeder
process through four localhost TCP sockets at the real-time rate (a block of
``--block-ms`` of frames per sensor every ``--block-ms``, float64, paced on the
clock, the way DAQs deliver).  The live path
(:func:`psdcal.measure.live_multi.locate_live_multi`, what ``psdcal locate
--sensors tcp://...`` runs) demodulates and triangulates and writes the rows.

Checks and figures:

* rows: the live CSV is compared with ``psdcal locate --sensors`` on the same
  recordings (byte-equal expected);
* latency "as a user sees it", per window, two ways: (a) from the arrival of
  the last block completing the window (read stamp in the reading thread) to
  its row flushed; (b) from the feeder's send time of the window's last sample
  (any sensor, ``time.perf_counter`` = CLOCK_MONOTONIC, shared by the two
  processes) to the row flushed.  Median and p99, over all windows (with the
  start-up) and without the first ``--startup-s`` of signal; the time from the
  first data to the first rows.
* the load average of the machine before and after (it is shared).

Run: ``.venv/bin/python benchmarks/bench_live_multi.py [--seconds 10] [--repeat 2] [--markdown]``
(also ``benchmarks/bench_live.py --sensors 4``).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

CARRIERS = (1000.0, 1150.0, 1300.0)

FEEDER = r"""
import socket, sys, time, numpy as np
files, rate, block_ms, log, nodelay = sys.argv[1].split(","), float(sys.argv[2]), float(sys.argv[3]), sys.argv[4], sys.argv[5] == "1"
data = [np.ascontiguousarray(np.load(f), dtype="<f8") for f in files]
srvs = []
for _ in files:
    s = socket.socket(); s.bind(("127.0.0.1", 0)); s.listen(1); srvs.append(s)
print(",".join(str(s.getsockname()[1]) for s in srvs), flush=True)
conns = [s.accept()[0] for s in srvs]
if nodelay:
    for c in conns:
        c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
per = max(1, int(round(block_ms * 1e-3 * rate)))
n = min(len(d) for d in data)
t0 = time.perf_counter()
rows = []
for k, start in enumerate(range(0, n, per)):
    wait = t0 + (start + per) / rate - time.perf_counter()   # a block is sent once its last sample exists
    if wait > 0:
        time.sleep(wait)
    for i, (c, d) in enumerate(zip(conns, data)):
        c.sendall(d[start:start + per].tobytes())
        rows.append((i, start, min(per, n - start), time.perf_counter()))
for c in conns:
    c.close()
np.save(log, np.array(rows, dtype=float))
"""


def _psdcal(*args, cwd):
    exe = Path(sys.executable).with_name("psdcal")
    p = subprocess.run([str(exe), *args], cwd=cwd, capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"psdcal {' '.join(args)} failed: {p.stderr.strip()}")
    return p


def run_once(tmp: Path, rate_hz: float, block_ms: float, startup_s: float, nodelay: bool = True):
    from psdcal.measure.live_multi import locate_live_multi, warm_up
    from psdcal.measure.locate import LocateConfig
    from psdcal.measure.positioning import load_sensors
    from psdcal.signal.session import LiveSources, open_source

    poses = load_sensors(tmp / "room" / "sensors.json")
    config = LocateConfig(carriers_hz=CARRIERS, window_s=0.01)
    warm_up(poses, rate_hz, config)  # as the CLI does, before connecting
    files = [str(tmp / "room" / f"s{i}.npy") for i in range(1, 5)]
    log = tmp / "send_log.npy"
    feeder = subprocess.Popen([sys.executable, "-c", FEEDER, ",".join(files), str(rate_hz), str(block_ms), str(log),
                               "1" if nodelay else "0"],
                              stdout=subprocess.PIPE, text=True)
    ports = feeder.stdout.readline().strip().split(",")
    load0 = os.getloadavg()
    streams = [open_source(f"tcp://127.0.0.1:{p}", rate_hz) for p in ports]
    out = tmp / "live.csv"
    import time

    cpu0 = time.process_time()
    s = locate_live_multi(LiveSources(streams).events(), poses, rate_hz, out, config, startup_s=startup_s)
    cpu_per_s = (time.process_time() - cpu0) / (s.n_samples / rate_hz)
    feeder.wait(timeout=60)
    load1 = os.getloadavg()
    send = np.load(log)
    n_win = int(round(0.01 * rate_hz))
    # send time of each window's last sample, latest over the sensors
    last = (np.arange(s.n_windows) + 1) * n_win - 1
    t_send = np.full(s.n_windows, -np.inf)
    for i in range(4):
        rows = send[send[:, 0] == i]
        k = np.searchsorted(rows[:, 1], last, side="right") - 1
        t_send = np.maximum(t_send, rows[k, 3])
    ext = s.written_s - t_send
    same = _compare(tmp / "file.csv", out)
    return s, ext, same, load0, load1, cpu_per_s


def _compare(a, b) -> str:
    """'bytes' when the files are equal, else the largest relative difference of the numbers (same rows)."""
    if a.read_bytes() == b.read_bytes():
        return "bytes"
    ra = [ln.split(",") for ln in a.read_text().splitlines()]
    rb = [ln.split(",") for ln in b.read_text().splitlines()]
    if len(ra) != len(rb) or ra[0] != rb[0] or [r[1] for r in ra] != [r[1] for r in rb]:
        return "NO"
    x = np.array([[float(v) for j, v in enumerate(r) if j != 1] for r in ra[1:]])
    y = np.array([[float(v) for j, v in enumerate(r) if j != 1] for r in rb[1:]])
    return f"{np.max(np.abs(x - y) / np.maximum(np.abs(y), 1e-9)):.1e}"


def _stats(ms):
    return float(np.median(ms)), float(np.percentile(ms, 99)), float(ms.max())


def run(seconds: float = 10.0, rate_hz: float = 20_000.0, block_ms: float = 5.0, startup_s: float = 1.0,
        repeat: int = 2, markdown: bool = False):
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        _psdcal("simulate-recording", "room", "--sensors", "4", "--anchors", "2", "--duration-s", str(seconds),
                "--rate-hz", str(rate_hz), "-o", "room", cwd=tmp)
        args = ["locate", "--sensors", "room/sensors.json", "--rate-hz", str(rate_hz), "--allow-no-covariance",
                "-o", "file.csv"]
        for f in CARRIERS:
            args += ["--carrier-hz", str(f)]
        _psdcal(*args, cwd=tmp)
        n_file = len((tmp / "file.csv").read_text().splitlines()) - 1
        lines = []
        for r in range(repeat):
            s, ext, same, l0, l1, cpu = run_once(tmp, rate_hz, block_ms, startup_s)
            keep = s.window_t_s - s.t_start_s >= startup_s
            a_all, a_run = _stats(s.latency_s * 1e3), _stats(s.latency_s[keep] * 1e3)
            e_all, e_run = _stats(ext * 1e3), _stats(ext[keep] * 1e3)
            lines.append((r + 1, s.n_rows, n_file, same, s.n_windows, a_all, a_run, e_all, e_run,
                          s.first_row_s * 1e3, l0[0], l1[0], cpu))
            (tmp / "live.csv").unlink()
    head = ("run | rows live/file | equal (bytes, or max rel. diff) | windows | arrival->row median/p99/max ms (all) | (after start-up) | "
            "send->row median/p99/max ms (all) | (after start-up) | first rows ms | load 1-min before/after | "
            "CPU s per s of signal")
    f3 = lambda t: "/".join(f"{v:.3g}" for v in t)
    body = [f"{r} | {nr}/{nf} | {eq} | {nw} | {f3(a)} | {f3(b)} | {f3(c)} | {f3(dd)} | "
            f"{fr:.4g} | {l0:.2f}/{l1:.2f} | {cpu:.2f}" for r, nr, nf, eq, nw, a, b, c, dd, fr, l0, l1, cpu in lines]
    title = (f"four sensors live at {rate_hz:g} S/s each over TCP ({seconds:g} s, blocks of {block_ms:g} ms, "
             f"10 ms windows, start-up = first {startup_s:g} s), {os.cpu_count()} CPUs")
    if markdown:
        print(f"{title}\n\n| {head} |\n|{'---|' * len(head.split('|'))}\n" + "\n".join(f"| {b} |" for b in body))
    else:
        print(title)
        print(head)
        print("\n".join(body))
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate-hz", type=float, default=20_000.0)
    ap.add_argument("--block-ms", type=float, default=5.0)
    ap.add_argument("--startup-s", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--switch-ms", type=float, default=None,
                    help="Python's thread switch interval, ms (sys.setswitchinterval) [default: Python's, 5 ms]")
    a = ap.parse_args(argv)
    if a.switch_ms is not None:
        sys.setswitchinterval(a.switch_ms * 1e-3)
    print(f"thread switch interval {sys.getswitchinterval() * 1e3:g} ms")
    run(a.seconds, a.rate_hz, a.block_ms, a.startup_s, a.repeat, a.markdown)


if __name__ == "__main__":
    main()
