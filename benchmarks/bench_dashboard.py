#!/usr/bin/env python3
"""Benchmark of `psdcal dashboard`: update latency, and the positioning's throughput with viewers connected.

1. Latency (needs Chromium): `psdcal dashboard` follows a rows CSV (live, not
   replay) that a writer appends to at 100 windows per second (two emitters
   per window, one ``write`` + flush per window, as live `locate` does). A
   headless Chromium shows the page; the page logs, after each redraw of the
   view from above has resolved and a frame has passed, the data time it
   shows and the wall clock. Latency of a window = the first redraw showing
   it minus the time its row was written (both on this machine's clock). The
   3-D view is WebGL; with no GPU it is software-rendered and is turned off
   here (``--webgl`` turns it on).
2. Throughput: `psdcal locate --sensors` on a simulated recording (3
   sensors, 20 s at 20 kS/s), its wall time, with (a) no dashboard, (b) the
   dashboard following a live rows feed (300 rows/s) and no viewer, (c) the
   same with ten viewers (WebSocket clients in another process, each parsing
   every update). The runs alternate; the median of ``--reps`` each is kept.
   The dashboard runs at ``nice 10`` and the viewers at ``nice 19`` (a viewer
   is usually another machine's browser); the positioning at normal priority.

Run: ``.venv/bin/python benchmarks/bench_dashboard.py [--seconds 10] [--reps 3] [--skip-throughput]``.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO / "src") + os.pathsep + env.get("PYTHONPATH", "")
    return env


def start_dashboard(args, nice=10):
    cmd = ["nice", "-n", str(nice), sys.executable, "-m", "psdcal.cli", "dashboard", *map(str, args), "--port", "0"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=_env())
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        m = re.search(r"(http://\S+)", proc.stdout.readline() or "")
        if m:
            return proc, m.group(1)
        if proc.poll() is not None:
            break
    proc.kill()
    raise RuntimeError("the dashboard did not start")


def stop(proc):
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def feed(path, stop_event, *, rate_hz=100.0, emitters=("a1", "tag"), log=None):
    """Append one window of rows (one write + flush) every 1/rate_hz s; log (t_s, wall) of each window."""
    from _dashboard_room import tag_position

    with open(path, "a", buffering=1) as fh:
        k = 0
        t0 = time.perf_counter()
        while not stop_event.is_set():
            t = 0.005 + k / rate_hz
            lines = []
            for i, em in enumerate(emitters):
                x, y, z = tag_position(t + i)
                lines.append(f"{t:.6f},{em},{x:.4f},{y:.4f},{z:.4f},2.0,2.0,3.0,3,1.5\n")
            fh.write("".join(lines))
            fh.flush()
            if log is not None:
                log.append((t, time.time()))
            k += 1
            wait = t0 + k / rate_hz - time.perf_counter()
            if wait > 0:
                time.sleep(wait)


def latency(seconds: float, webgl: bool):
    from browser import Chromium, find_chromium

    from _dashboard_room import ROWS_HEADER, write_room

    if find_chromium() is None:
        print("latency: skipped (no chromium; apt-get install chromium)")
        return None
    with tempfile.TemporaryDirectory() as d:
        room = write_room(d, duration_s=0.01)
        rows = Path(d) / "live.csv"
        rows.write_text(ROWS_HEADER + "\n")
        proc, url = start_dashboard([rows, "--sensors", room["sensors"], "--emitters", room["emitters"]], nice=0)
        flags = ("--enable-unsafe-swiftshader", "--use-angle=swiftshader") if webgl else ("--disable-3d-apis",)
        log: list = []
        halt = threading.Event()
        try:
            with Chromium(timeout_s=60, extra_flags=flags) as b:
                b.open_page(1400, 1100)
                b.load(url)
                deadline = time.monotonic() + 30
                while b.evaluate("psdDashboard.state.room ? 1 : 0") != 1 and time.monotonic() < deadline:
                    time.sleep(0.1)
                th = threading.Thread(target=feed, args=(rows, halt), kwargs={"log": log})
                th.start()
                time.sleep(seconds)
                halt.set()
                th.join()
                time.sleep(1.0)
                draws = json.loads(b.evaluate("JSON.stringify(psdDashboard.drawLog)"))
                errors = b.errors()
        finally:
            stop(proc)
    draws = [(d["t"], d["wall"] / 1000.0) for d in draws if d["t"] is not None]
    lat = []
    j = 0
    warm = log[int(len(log) * 0.1):]  # the first second: page and server warming up
    for t, wall in warm:
        while j < len(draws) and draws[j][0] < t - 1e-9:
            j += 1
        if j == len(draws):
            break
        lat.append(draws[j][1] - wall)
    lat.sort()
    if not lat:
        print("latency: no window was drawn")
        return None
    res = {"windows": len(lat), "draws": len(draws), "median_ms": 1e3 * statistics.median(lat),
           "p99_ms": 1e3 * lat[min(len(lat) - 1, int(0.99 * len(lat)))], "max_ms": 1e3 * lat[-1],
           "draws_per_s": len(draws) / seconds, "errors": errors}
    print(f"latency, row written -> drawn ({'with' if webgl else 'without'} the WebGL 3-D view): "
          f"median {res['median_ms']:.1f} ms, p99 {res['p99_ms']:.1f} ms, max {res['max_ms']:.1f} ms "
          f"over {res['windows']} windows ({res['draws_per_s']:.0f} redraws/s); page errors: {errors or 'none'}")
    return res


VIEWER = r"""
import asyncio, json, sys
import aiohttp
async def one(url, counts, i):
    async with aiohttp.ClientSession() as s:
        async with s.ws_connect(url) as ws:
            async for m in ws:
                json.loads(m.data); counts[i] += 1
async def main(url, n):
    counts = [0] * n
    tasks = [asyncio.ensure_future(one(url, counts, i)) for i in range(n)]
    print("connected", flush=True)
    await asyncio.gather(*tasks, return_exceptions=True)
asyncio.run(main(sys.argv[1], int(sys.argv[2])))
"""


def throughput(reps: int):
    from _dashboard_room import ROWS_HEADER, write_room

    psdcal = [sys.executable, "-m", "psdcal.cli"]
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        subprocess.run([*psdcal, "simulate-recording", "room", "--sensors", "3", "--anchors", "2", "--duration-s", "20",
                        "--seed", "3", "-o", str(d / "r")], check=True, env=_env(), capture_output=True)
        carriers = ["--carrier-hz", "1000", "--emitter", "a1", "--carrier-hz", "1150", "--emitter", "a2"]
        locate = [*psdcal, "locate", "--allow-no-covariance", "--sensors", str(d / "r" / "sensors.json"),
                  "--rate-hz", "20000", *carriers, "-o", str(d / "xyz.csv"), "--force"]
        subprocess.run(locate, check=True, env=_env(), capture_output=True)  # compile and warm the caches

        def timed():
            import resource

            c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            r = subprocess.run(locate, env=_env(), capture_output=True, text=True)
            wall = time.perf_counter() - t0
            if r.returncode:
                raise RuntimeError(f"locate failed: {r.stderr.strip()}")
            c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            return wall, (c1.ru_utime + c1.ru_stime) - (c0.ru_utime + c0.ru_stime)

        def cpu_s(pid):
            """CPU seconds (user + system) a running process has used."""
            f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")

        room = write_room(d, duration_s=0.01)
        rows = d / "live.csv"
        times = {"none": [], "dashboard, 0 viewers": [], "dashboard, 10 viewers": []}
        server_cpu = {0: [], 10: []}
        for _ in range(reps):
            times["none"].append(timed())
            for n in (0, 10):
                rows.write_text(ROWS_HEADER + "\n")
                proc, url = start_dashboard([rows, "--sensors", room["sensors"], "--emitters", room["emitters"]])
                halt = threading.Event()
                th = threading.Thread(target=feed, args=(rows, halt), kwargs={"rate_hz": 100.0,
                                                                             "emitters": ("a1", "a2", "tag")})
                viewers = None
                try:
                    if n:
                        ws = url.replace("http://", "ws://").split("?")[0] + "ws"
                        viewers = subprocess.Popen(["nice", "-n", "19", sys.executable, "-c", VIEWER, ws, str(n)],
                                                   stdout=subprocess.PIPE, text=True, env=_env())
                        viewers.stdout.readline()
                        time.sleep(0.5)
                    th.start()
                    time.sleep(0.5)
                    c0, t0 = cpu_s(proc.pid), time.perf_counter()
                    times[f"dashboard, {n} viewers"].append(timed())
                    server_cpu[n].append((cpu_s(proc.pid) - c0) / (time.perf_counter() - t0))
                finally:
                    halt.set()
                    if th.is_alive():
                        th.join()
                    if viewers is not None:
                        stop(viewers)
                    stop(proc)
    med = {k: statistics.median(w for w, _ in v) for k, v in times.items()}
    cpu = {k: statistics.median(c for _, c in v) for k, v in times.items()}
    for k, v in times.items():
        print(f"throughput: psdcal locate --sensors (3 sensors, 20 s at 20 kS/s), {k}: wall median {med[k]:.2f} s "
              f"({', '.join(f'{w:.2f}' for w, _ in v)}), CPU median {cpu[k]:.2f} s")
    # paired: each rep's 10-viewer run against the 0-viewer run just before it (slow drifts of the machine cancel)
    ratios = [w10 / w0 for (w0, _), (w10, _) in zip(times["dashboard, 0 viewers"], times["dashboard, 10 viewers"])]
    change = 100.0 * (statistics.median(ratios) - 1.0)
    print(f"throughput: ten viewers vs none (dashboard running), paired median: {change:+.1f} % wall time "
          f"(target within 5 %; runs {', '.join(f'{100 * (r - 1):+.1f}' for r in ratios)} %); "
          f"dashboard vs no dashboard: {100.0 * (med['dashboard, 0 viewers'] - med['none']) / med['none']:+.1f} %")
    for n, v in server_cpu.items():
        print(f"dashboard server CPU while following 300 rows/s with {n} viewers: median {100 * statistics.median(v):.1f} % "
              f"of one core ({', '.join(f'{100 * x:.1f}' for x in v)})")
    return {"median_s": med, "runs": times, "ten_vs_none_pct": change, "server_cpu": server_cpu}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="Seconds of rows for the latency (default 10).")
    ap.add_argument("--reps", type=int, default=3, help="Runs per condition for the throughput (default 3).")
    ap.add_argument("--webgl", action="store_true", help="Measure the latency with the 3-D view on (software GL).")
    ap.add_argument("--skip-throughput", action="store_true")
    ap.add_argument("--skip-latency", action="store_true")
    ap.add_argument("--markdown", action="store_true", help="also print the results as Markdown tables")
    a = ap.parse_args(argv)
    lat = thr = None
    if not a.skip_latency:
        lat = latency(a.seconds, a.webgl)
    if not a.skip_throughput:
        thr = throughput(a.reps)
    if a.markdown:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from _table import print_table

        if not a.skip_latency:
            print(f"\nlatency, row written -> drawn ({'with' if a.webgl else 'without'} the 3-D view), "
                  f"{a.seconds:g} s of rows")
            print_table(("windows", "median ms", "p99 ms", "max ms", "redraws/s", "page errors"),
                        [(str(lat["windows"]), f"{lat['median_ms']:.1f}", f"{lat['p99_ms']:.1f}", f"{lat['max_ms']:.1f}",
                          f"{lat['draws_per_s']:.0f}", str(len(lat["errors"] or [])))] if lat else
                        [("-", "-", "-", "-", "-", "not measured (no chromium, or no window drawn)")], markdown=True)
        if thr is not None:
            print(f"\npsdcal locate --sensors (3 sensors, 20 s at 20 kS/s), {a.reps} runs per case; "
                  "the dashboard following a live feed of 300 rows/s")
            rows = [(k, f"{thr['median_s'][k]:.2f}", f"{statistics.median(c for _, c in v):.2f}", "-")
                    for k, v in thr["runs"].items()]
            rows.append(("ten viewers against none, paired median", "-", "-", f"{thr['ten_vs_none_pct']:+.1f} %"))
            for n, v in thr["server_cpu"].items():
                rows.append((f"dashboard server CPU, {n} viewers", "-", "-",
                             f"{100 * statistics.median(v):.1f} % of one core"))
            print_table(("case", "locate wall s (median)", "locate CPU s (median)", "change or share"), rows,
                        markdown=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
