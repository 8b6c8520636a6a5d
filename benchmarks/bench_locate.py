#!/usr/bin/env python3
"""Benchmark of ``psdcal locate``: recording -> angles throughput, against a bare lock-in, and memory.

Simulates recordings of the paper's DAQ set-up (PCI-6289: 4 channels at
125 kS/s each, 500 kS/s in all) with one emitter (1 kHz) and with two
(1 kHz and 1.3 kHz), writes them as ``(n, 4)`` float64 .npy, and streams each
through the whole pipeline (read chunks -> joint lock-in every 10 ms ->
impact point -> undistortion -> angles and positions with uncertainty ->
output), on ONE core (BLAS threads pinned to 1), with CSV output and with
``--format npy`` output.

Reference, measured in the same run on the same files: a bare numpy
lock-in (one matrix product of each 10 ms window with the carriers' sin/cos
tables, ``hypot`` of the pairs; no offset, no noise estimate, no finiteness
check, no angles, no output), the file read into one reused buffer or
memory-mapped, whichever is faster: the ceiling of a lock-in in numpy.

The same recordings also go through ``psdcal amplitudes`` (carrier
amplitudes only, CSV and npy) and through the live path (the recording's raw
frames read as a stream, as ``psdcal locate -`` reads standard input; rows
written and flushed as they come).

Each repeat runs the bare lock-in (both ways) and every case once, in turn;
a case's fraction of the bare lock-in is the median over the repeats of the
ratio within a repeat (runs made under the same load: the machine may be
shared).

Prints, per case (command x carriers x output format):
* throughput in samples per second per core (all 4 channels counted), as a
  multiple of real time for 4 x 125 kS/s, and as a fraction of the bare
  lock-in's speed (1.0 = as fast as the bare lock-in);
* the demodulation + AoA alone, from memory (no file reading);
* memory: peak traced working memory, its growth per second of signal
  (constant-memory streaming means ~0), and output bytes per second of signal.

Times are process CPU times (one core), the median of ``--repeats`` runs
after a warm-up.

Run: ``.venv/bin/python benchmarks/bench_locate.py [--seconds 60] [--repeats 5] [--markdown]`` (about 30 s).
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from psdcal.measure.aoa import angles_from_amplitudes  # noqa: E402
from psdcal.model.distortion import distort  # noqa: E402
from psdcal.measure.live import locate_stream  # noqa: E402
from psdcal.measure.locate import LocateConfig, amplitudes_to_csv, locate_to_csv  # noqa: E402
from psdcal.measure.positioning import plane_position  # noqa: E402
from psdcal.model.readout import photocurrents  # noqa: E402
from psdcal.signal.live import open_stream  # noqa: E402
from psdcal.signal.recording import DEFAULT_CHUNK, open_recording  # noqa: E402
from psdcal.measure.sensor_model import SensorModel  # noqa: E402
from psdcal.signal.stream import MultiCarrierLockin  # noqa: E402

RATE_HZ = 125_000.0  # per channel, PCI-6289 500 kS/s over 4 channels
CARRIERS_HZ = (1000.0, 1300.0)
WINDOW_S = 0.01
CALIB = {
    "intrinsics": {"f_mm": 8.0, "cx_mm": 0.5, "cy_mm": -0.7, "skew": 0.0},
    "distortion": {"k1": 1e-2, "k2": 3e-5, "l1": -1.3e-3},
    "covariance": {"names": ["f_mm", "cx_mm", "cy_mm", "k1", "k2"],
                   "matrix": np.diag([2.5e-5, 1.6e-5, 1.6e-5, 4e-10, 1e-12]).tolist()},
}


def make_recording(path: Path, seconds: float, model: SensorModel, carriers=CARRIERS_HZ) -> int:
    """A (n, 4) float64 .npy recording: one emitter per carrier (the first ``len(carriers)`` spots)."""
    n = int(seconds * RATE_HZ)
    d = distort(np.array([[2.0, -1.0], [-1.5, 2.5]]), model.distortion, model.intrinsics.c).d_mm
    amps = photocurrents(d, np.array([1.0, 0.6]))  # (2, 4)
    mm = np.lib.format.open_memmap(path, mode="w+", dtype=np.float64, shape=(n, 4))
    rng = np.random.default_rng(0)
    step = 1 << 18
    for i in range(0, n, step):
        m = min(step, n - i)
        t = (i + np.arange(m)) / RATE_HZ
        x = 0.05 + 1e-3 * rng.standard_normal((m, 4))
        for a, f, ph in zip(amps, carriers, (0.3, 1.2)):
            x += np.sin(2 * np.pi * f * t + ph)[:, None] * a[None]
        mm[i : i + m] = x
    mm.flush()
    del mm
    return n


def _cpu(fn, repeats: int) -> float:
    """Median process CPU time of ``fn()`` over ``repeats`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        c0 = time.process_time()
        fn()
        times.append(time.process_time() - c0)
    return float(np.median(times))


def bare_lockin(path: Path, carriers, read: str = "readinto") -> None:
    """The reference: one (2k, n) @ (n, 4) product per window, hypot of the (sin, cos) pairs.

    ``read``: ``"readinto"`` (the file read into one reused buffer, as psdcal does) or ``"mmap"``
    (a memory map: the pages faulted in).
    """
    n = int(round(WINDOW_S * RATE_HZ))
    tau = np.arange(n) / RATE_HZ
    ref = np.stack([g(2 * np.pi * f * tau) for f in carriers for g in (np.sin, np.cos)]) * (2.0 / n)  # (2k, n)
    x = np.load(path, mmap_mode="r")
    total, offset = x.shape[0], x.offset
    chunk = (DEFAULT_CHUNK // n) * n

    def lockin(w):
        w = w[: (w.shape[0] // n) * n].reshape(-1, n, 4)
        iq = np.matmul(ref, w)  # (nw, 2k, 4)
        np.hypot(iq[:, 0::2], iq[:, 1::2])

    if read == "mmap":
        for s in range(0, total - n + 1, chunk):
            lockin(x[s : s + chunk])
        return
    del x
    buf = np.empty((chunk, 4))
    with open(path, "rb") as fh:
        fh.seek(offset)
        for s in range(0, total - n + 1, chunk):
            m = min(chunk, total - s)
            fh.readinto(memoryview(buf[:m]).cast("B"))
            lockin(buf[:m])


def run_pipeline(path: Path, model: SensorModel, out: Path, carriers=CARRIERS_HZ, output_format: str = "csv"):
    rec = open_recording(path, RATE_HZ)
    cfg = LocateConfig(carriers_hz=tuple(carriers), window_s=WINDOW_S, distance_mm=5000.0, output_format=output_format)
    return locate_to_csv(rec, model, out, cfg)


def run_amplitudes(path: Path, out: Path, carriers=CARRIERS_HZ, output_format: str = "csv"):
    """``psdcal amplitudes``: the same recording to carrier amplitudes (no calibration)."""
    rec = open_recording(path, RATE_HZ)
    cfg = LocateConfig(carriers_hz=tuple(carriers), window_s=WINDOW_S, output_format=output_format)
    return amplitudes_to_csv(rec, out, cfg)


def run_live(path: Path, model: SensorModel, out: Path, carriers=CARRIERS_HZ):
    """The live path (``psdcal locate -`` / a live source): the recording's raw frames (the ``.npy``'s data
    after its header, little-endian float64) read as a stream, rows written and flushed as they come."""
    offset = np.load(path, mmap_mode="r").offset
    cfg = LocateConfig(carriers_hz=tuple(carriers), window_s=WINDOW_S, distance_mm=5000.0)
    with open(path, "rb") as fh:
        fh.seek(offset)
        return locate_stream(open_stream("-", RATE_HZ, stdin=fh), model, out, cfg)


def run_in_memory(model: SensorModel, seconds: float):
    n = int(seconds * RATE_HZ)
    rng = np.random.default_rng(1)
    x = 0.2 + 1e-3 * rng.standard_normal((4, n))
    t = np.arange(n) / RATE_HZ
    x += np.array([0.2, 0.3, 0.25, 0.15])[:, None] * np.sin(2 * np.pi * 1000.0 * t)
    x += np.array([0.1, 0.05, 0.1, 0.12])[:, None] * np.sin(2 * np.pi * 1300.0 * t)
    lk = MultiCarrierLockin(RATE_HZ, CARRIERS_HZ, WINDOW_S)
    chunk = 50 * lk.n_window
    c0 = time.process_time()
    for i in range(0, n, chunk):
        wb = lk.process(i / RATE_HZ, x[:, i : i + chunk])
        res = angles_from_amplitudes(wb.amplitude, model, wb.var_amplitude)
        plane_position(res, 5000.0)
    return n, time.process_time() - c0


def traced_peak(path: Path, model: SensorModel, out: Path) -> int:
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        locate_to_csv(open_recording(path, RATE_HZ), model, out,
                      LocateConfig(carriers_hz=CARRIERS_HZ, window_s=WINDOW_S, distance_mm=5000.0))
        return tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="recording length, s of signal (default 60)")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per case, median reported (default 5)")
    ap.add_argument("--markdown", action="store_true", help="also print the cases as a Markdown table")
    ap.add_argument("--json", action="store_true", help="also print the results as one JSON line")
    args = ap.parse_args(argv)
    model = SensorModel.from_dict(CALIB)
    reps = max(1, args.repeats)
    cases = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # the short run is longer than one batch of rows (1024 rows = 5 s of two carriers)
        long_s, short_s = args.seconds, max(min(10.0, args.seconds / 2), args.seconds / 4)
        n = 0
        for carriers in (CARRIERS_HZ[:1], CARRIERS_HZ):
            path = tmp / f"rec{len(carriers)}.npy"
            n = make_recording(path, long_s, model, carriers)
            runs = {("locate", fmt): (lambda fmt=fmt: run_pipeline(path, model, tmp / f"out.{fmt}", carriers, fmt))
                    for fmt in ("csv", "npy")}
            runs.update({("amplitudes", fmt): (lambda fmt=fmt: run_amplitudes(path, tmp / f"amp.{fmt}", carriers, fmt))
                         for fmt in ("csv", "npy")})
            runs[("live", "csv")] = lambda: run_live(path, model, tmp / "live.csv", carriers)
            bare = {"readinto": lambda: bare_lockin(path, carriers, "readinto"),
                    "mmap": lambda: bare_lockin(path, carriers, "mmap")}
            # paired: every repeat runs the bare lock-in (both ways) and each case once, in turn, so that the
            # ratios compare runs made under the same load (the machine may be shared); the medians are reported
            t = {k: [] for k in (*bare, *runs)}
            for f in (*bare.values(), *runs.values()):
                f()  # warm-up (compiled kernels loaded, file in the page cache)
            for _ in range(reps):
                for k, f in (*bare.items(), *runs.items()):
                    c0 = time.process_time()
                    f()
                    t[k].append(time.process_time() - c0)
            t = {k: np.array(v) for k, v in t.items()}
            bare_each = np.minimum(t["readinto"], t["mmap"])  # the faster of the two, each repeat
            bare_s = float(np.median(bare_each))
            for (what, fmt), f in runs.items():
                cpu_s = float(np.median(t[(what, fmt)]))
                w0 = time.perf_counter()
                summary = f()
                wall_s = time.perf_counter() - w0
                out = {"locate": tmp / f"out.{fmt}", "amplitudes": tmp / f"amp.{fmt}", "live": tmp / "live.csv"}[what]
                cases.append({
                    "what": what, "carriers": len(carriers), "format": fmt, "cpu_s": cpu_s, "wall_s": wall_s,
                    "samples_per_s_per_core": 4 * n / cpu_s, "x_real_time": (n / RATE_HZ) / cpu_s,
                    "x_real_time_wall": (n / RATE_HZ) / wall_s, "bare_lockin_cpu_s": bare_s,
                    "bare_lockin_x_real_time": (n / RATE_HZ) / bare_s,
                    "fraction_of_bare_lockin": float(np.median(bare_each / t[(what, fmt)])),
                    "bare_lockin_readinto_x_real_time": (n / RATE_HZ) / float(np.median(t["readinto"])),
                    "bare_lockin_mmap_x_real_time": (n / RATE_HZ) / float(np.median(t["mmap"])),
                    "rows": summary.n_rows, "output_bytes_per_signal_s": out.stat().st_size / (n / RATE_HZ),
                })
        make_recording(tmp / "short.npy", short_s, model)
        n_mem, cpu_mem = run_in_memory(model, min(long_s, 10.0))
        peak_short = traced_peak(tmp / "short.npy", model, tmp / "o1.csv")
        peak_long = traced_peak(tmp / "rec2.npy", model, tmp / "o2.csv")
    signal_s = n / RATE_HZ
    two_csv = next(c for c in cases if c["what"] == "locate" and c["carriers"] == 2 and c["format"] == "csv")
    res = {
        "signal_s": signal_s,
        "channels": 4,
        "rate_hz_per_channel": RATE_HZ,
        "carriers_hz": list(CARRIERS_HZ),
        "window_s": WINDOW_S,
        "repeats": reps,
        "cases": cases,
        # the two-carrier CSV case under the names of earlier versions of this script
        "pipeline_cpu_s": two_csv["cpu_s"],
        "pipeline_wall_s": two_csv["wall_s"],
        # single-threaded: the process CPU time (user + system, page faults included) is one core's time;
        # wall time is printed too (it also counts waiting for a busy machine or the disk)
        "pipeline_samples_per_s_per_core": two_csv["samples_per_s_per_core"],
        "pipeline_x_real_time": two_csv["x_real_time"],
        "pipeline_x_real_time_wall": two_csv["x_real_time_wall"],
        "min_x_real_time": min(c["x_real_time"] for c in cases),
        "min_fraction_of_bare_lockin": min(c["fraction_of_bare_lockin"] for c in cases),
        "demod_aoa_samples_per_s_per_core": 4 * n_mem / cpu_mem,
        "demod_aoa_x_real_time": (n_mem / RATE_HZ) / cpu_mem,
        "peak_working_memory_bytes": peak_long,
        "memory_growth_bytes_per_signal_s": (peak_long - peak_short) / (long_s - short_s),
        "output_bytes_per_signal_s": two_csv["output_bytes_per_signal_s"],
        "rows": two_csv["rows"],
    }
    print(f"psdcal locate benchmark: {signal_s:g} s of 4 x {RATE_HZ / 1e3:g} kS/s, {WINDOW_S * 1e3:g} ms windows, "
          f"1 core, CPU time, median of {reps}")
    for c in cases:
        print(f"  {c['what']:10s} {c['carriers']} carrier(s), -> {c['format']:3s}: {c['samples_per_s_per_core'] / 1e6:6.1f} MS/s "
              f"per core = {c['x_real_time']:5.0f} x real time = {c['fraction_of_bare_lockin']:.2f} x the bare "
              f"lock-in ({c['bare_lockin_x_real_time']:.0f} x real time; read {c['bare_lockin_readinto_x_real_time']:.0f}, "
              f"mmap {c['bare_lockin_mmap_x_real_time']:.0f}); wall {c['x_real_time_wall']:.0f} x")
    print(f"  demodulation + AoA only (2 carriers, from memory): {res['demod_aoa_samples_per_s_per_core'] / 1e6:6.1f} "
          f"MS/s per core = {res['demod_aoa_x_real_time']:5.0f} x real time")
    print(f"  peak working memory {peak_long / 1e6:.2f} MB (constant), growth "
          f"{res['memory_growth_bytes_per_signal_s']:.0f} B per s of signal; "
          f"output {res['output_bytes_per_signal_s'] / 1e3:.1f} kB per s of signal as CSV "
          f"(input {4 * 8 * RATE_HZ / 1e6:g} MB per s as float64)")
    if args.markdown:
        print()
        print("| command | carriers | output | x real time | / bare lock-in | bare lock-in x real time |")
        print("|---|---|---|---|---|---|")
        for c in cases:
            print(f"| {c['what']} | {c['carriers']} | {c['format']} | {c['x_real_time']:.0f} | "
                  f"{c['fraction_of_bare_lockin']:.2f} | {c['bare_lockin_x_real_time']:.0f} |")
    if args.json:
        print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
