#!/usr/bin/env python3
"""The default calibration (fit + verdict) against ``cv2.calibrateCamera`` on the same points: CPU-time ratios.

What a user and the Monte Carlo trials run is ``psdcal.calibrate(template,
points)`` with its verdict attached (the default ``verdict=True``; no
diagnosis). Three sets, each timed in the same process for psdcal with the
verdict, psdcal without it (the fit alone) and OpenCV:

- Zhang's five views of 256 corners (``tests/data/zhang1998``), the general
  model: fx, fy, C, k1, k2, p1, p2 (OpenCV ``CALIB_FIX_K3`` on the published
  pixels);
- 20 views of a 32 x 32 grid (1024 points), Lens 2, 2 um noise;
- 12 views of the 14-point default template, Lens 2, 2 um noise;

the synthetic sets with psdcal's default model (one f, C, k1, k2, p1, p2) and
OpenCV's ``CALIB_FIX_ASPECT_RATIO | CALIB_FIX_K3`` (the same parameters), the
points in pixels at a 10 um pitch. Time: process CPU time
(``time.process_time``), one thread (BLAS and OpenCV), the median of
``--repeats`` calls after a warm-up (benchmarks/_timing.py's rule), the three
calls of a set timed in turns (``interleaved_cpu_seconds``: a machine whose
speed drifts during the run slows all three alike). The ratio
is psdcal's time over OpenCV's (the issue 22 target: <= 0.5 with the verdict).

A second table (skipped with ``--no-cli``) runs ``psdcal calibrate`` on each
real set of ``tests/data`` (Zhang's and the five chessboard sets, whatever
their verdict: the diagnosis of a failed check included) in fresh processes,
and gives the CPU time of each (the children's user + system time,
``resource.getrusage``) above that of ``psdcal --help``, the median of
``--cli-repeats`` runs (issue 22 target: <= 0.3 s). The interpreter writes its
bytecode cache (a first run of each command is not counted).

Usage::

    .venv/bin/python benchmarks/bench_default.py [--repeats 7] [--cli-repeats 5] [--no-cli] [--markdown]
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import print_table  # noqa: E402
from _timing import interleaved_cpu_seconds  # noqa: E402
from _zhang import ZHANG, load_zhang  # noqa: E402
from bench_scaling import _opencv_inputs, grid_template  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
PITCH_MM = 0.010



def cases(cv2):
    """[(name, psdcal call with the verdict, psdcal call without, OpenCV call)]."""
    from psdcal.calibration.core import calibrate
    from psdcal.study.simulate import simulate_set

    out = []
    T, pts, objs, imgs = load_zhang()
    kw = dict(aspect=True, sensor_mm=(6.4, 4.8))
    out.append(("zhang1998 (real), 5 x 256, general model",
                lambda: calibrate(T, pts, **kw), lambda: calibrate(T, pts, verdict=False, **kw),
                lambda: cv2.calibrateCamera(objs, imgs, (640, 480), np.eye(3), np.zeros(5), flags=cv2.CALIB_FIX_K3)))
    flags = cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_K3
    for n, m in ((20, 1024), (12, 14)):
        s = simulate_set("lens2", n_images=n, noise_mm=0.002, seed=0, template_mm=None if m == 14 else grid_template(m))
        o, i_ = _opencv_inputs(s.template_mm, s.points_mm, np.array([450.0, 450.0]))
        out.append((f"synthetic, {n} x {len(s.template_mm)}, default model",
                    (lambda s=s: calibrate(s.template_mm, s.points_mm)),
                    (lambda s=s: calibrate(s.template_mm, s.points_mm, verdict=False)),
                    (lambda o=o, i_=i_: cv2.calibrateCamera(o, i_, (900, 900), np.eye(3), np.zeros(5), flags=flags))))
    return out


def real_sets() -> list[Path]:
    """The folders (template.csv, points.csv) of the real sets in tests/data."""
    chess = ROOT / "tests" / "data" / "chessboards"
    return [ZHANG] + sorted(d for d in chess.iterdir() if (d / "points.csv").exists())


def _children_cpu(cmd, env) -> float:
    """CPU seconds (user + system) of one fresh process running ``cmd``."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def cli_rows(repeats: int) -> tuple[float, list[list[str]]]:
    """``psdcal --help`` CPU seconds, and per real set: the median CPU seconds of ``psdcal calibrate`` above it."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    script = Path(sys.executable).parent / "psdcal"  # the console script, as a user runs it
    exe = [str(script)] if script.exists() else [sys.executable, "-m", "psdcal.cli"]
    out = Path(tempfile.mkdtemp()) / "calib.json"
    cmds = {d.name: exe + ["calibrate", str(d / "points.csv"), "-t", str(d / "template.csv"), "-o", str(out),
                           "--force"] for d in real_sets()}
    for cmd in [exe + ["--help"], *cmds.values()]:  # the bytecode cache written, not counted
        _children_cpu(cmd, env)
    helps, runs = [], {n: [] for n in cmds}
    for _ in range(repeats):
        helps.append(_children_cpu(exe + ["--help"], env))
        for n, cmd in cmds.items():
            runs[n].append(_children_cpu(cmd, env))
    h = float(np.median(helps))
    return h, [[n, f"{np.median(t):.3f}", f"{np.median(t) - h:.3f}"] for n, t in runs.items()]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--cli-repeats", type=int, default=5)
    ap.add_argument("--no-cli", dest="cli", action="store_false", help="skip the command-line table")
    ap.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    a = ap.parse_args(argv)
    import cv2

    cv2.setNumThreads(1)
    lines = []
    for name, with_v, fit, ocv in cases(cv2):
        # in turns (fit + verdict, fit, OpenCV, then again): a drift of the machine's speed hits the three alike
        t_v, t_f, t_o = interleaved_cpu_seconds((with_v, fit, ocv), a.repeats)
        lines.append([name, f"{t_f * 1e3:.2f}", f"{t_v * 1e3:.2f}", f"{t_o * 1e3:.2f}", f"{t_f / t_o:.2f}x",
                      f"{t_v / t_o:.2f}x"])
    print_table(["set", "fit (ms)", "fit + verdict (ms)", "OpenCV (ms)", "fit / OpenCV", "fit + verdict / OpenCV"],
                lines, a.markdown)
    if not a.markdown:
        print(f"(process CPU time, one thread, median of {a.repeats}; load {os.getloadavg()[0]:.2f})")
    if a.cli:
        h, rows = cli_rows(a.cli_repeats)
        print()
        print_table(["psdcal calibrate on", "CPU (s)", "above psdcal --help (s)"], rows, a.markdown)
        if not a.markdown:
            print(f"(psdcal --help: {h:.3f} s CPU; fresh processes, median of {a.cli_repeats}; "
                  f"load {os.getloadavg()[0]:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
