#!/usr/bin/env python3
"""Benchmark of live `locate`: latency from a window's end to its row written.

A local server sends a simulated recording (4 channels, float32 frames, two
emitters on 1 and 1.3 kHz, 10 ms windows) through a localhost TCP socket at
the real-time rate (one window of samples every window length, the way a DAQ
delivers them); `psdcal.measure.live.locate_stream` demodulates it and writes
the rows.  Latency per window = time from the arrival of the bytes that
complete the window to its row being written and flushed.  Target: <= 2 ms.

Run: ``.venv/bin/python benchmarks/bench_live.py [--seconds 3] [--rate-hz 125000]``.
"""
from __future__ import annotations

import argparse
import socket
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def run(seconds: float = 3.0, rate_hz: float = 125_000.0, window_s: float = 0.01, markdown: bool = False):
    from psdcal.measure.live import locate_stream
    from psdcal.measure.locate import LocateConfig
    from psdcal.measure.sensor_model import SensorModel
    from psdcal.signal.live import open_stream
    from psdcal.study.recordings import amplitudes, calib_dict, signals, spot_for_angles

    m = SensorModel.from_dict(calib_dict())
    n = int(seconds * rate_hz)
    em = [(amplitudes(m, spot_for_angles(m, np.radians([3.0, -2.0]))), 1000.0, 0.3),
          (amplitudes(m, spot_for_angles(m, np.radians([-5.0, 4.0]))), 1300.0, 1.1)]
    x = signals(rate_hz, n, em, noise=1e-3, rng=np.random.default_rng(0))
    payload = np.ascontiguousarray(x.T).astype("<f4").tobytes()
    per = int(round(window_s * rate_hz)) * 16
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    port = srv.getsockname()[1]

    def serve():
        conn, _ = srv.accept()
        t0 = time.perf_counter()
        for k, start in enumerate(range(0, len(payload), per)):
            wait = t0 + k * window_s - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            conn.sendall(payload[start : start + per])
        conn.close()

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    stream = open_stream(f"tcp://127.0.0.1:{port}", rate_hz, dtype="float32")
    with tempfile.TemporaryDirectory() as tmp:
        s = locate_stream(stream, m, Path(tmp) / "live.csv", LocateConfig(carriers_hz=(1000.0, 1300.0),
                                                                            window_s=window_s, distance_mm=3000.0))
    th.join()
    srv.close()
    ms = s.latency_s[5:] * 1e3  # the first windows include the start-up (imports, compilation)
    from _table import print_table

    head = ["windows", "rate (S/s/ch)", "median (ms)", "p99 (ms)", "max (ms)", "target"]
    print_table(head, [[str(len(ms)), f"{rate_hz:g}", f"{np.median(ms):.3f}", f"{np.percentile(ms, 99):.3f}",
                        f"{ms.max():.3f}", "<= 2 ms"]], markdown)
    return ms


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--rate-hz", type=float, default=125_000.0)
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--sensors", type=int, default=1,
                    help="4: several sensors live over TCP (benchmarks/bench_live_multi.py, 20 kS/s each)")
    a, rest = ap.parse_known_args()
    if a.sensors > 1:
        import bench_live_multi

        return bench_live_multi.main(rest + ["--seconds", str(a.seconds)] + (["--markdown"] if a.markdown else []))
    run(a.seconds, a.rate_hz, markdown=a.markdown)


if __name__ == "__main__":
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
