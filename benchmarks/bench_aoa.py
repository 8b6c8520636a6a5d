#!/usr/bin/env python3
"""Impact points -> angles with their uncertainty: points per second on one core.

``angles_from_points`` (compiled kernel, angles + calibration and noise
covariances, with the derivatives dn/dp (the default) and without them,
``derivatives=False``) against its numpy reference, the bare
undistortion (``psdcal.model.distortion.undistort``) and OpenCV's
``cv2.undistortPoints`` (default, inexact iterations) on the same points.
"All points in one call" against the same points in calls of 65536 is
printed as a ratio (the library keeps a large call's output memory for the
next one and blocks its numpy paths itself, so one call costs no more than
many). "Angles only" runs the kernel with an empty parameter list (no covariance):
the covariance part's cost is the difference. The whole table is measured
``--runs`` times; the rates and the ratios (each taken within one run) are
medians over the runs.

Usage::

    .venv/bin/python benchmarks/bench_aoa.py [--points 1000000] [--runs 3] [--markdown]
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from _table import print_table  # noqa: E402


CHUNK = 65536  # points per call, as a streaming consumer (locate) passes them: buffers are reused


def _chunked(fn, d, *rest):
    """fn over ``d`` (and arrays ``rest``) in chunks of CHUNK points."""
    def run():
        for s in range(0, d.shape[0], CHUNK):
            fn(d[s:s + CHUNK], *(r[s:s + CHUNK] for r in rest))
    return run


def _rate(fn, n, repeats=3):
    fn()
    t = min(_once(fn) for _ in range(repeats))
    return n / t


def _once(fn):
    t0 = time.process_time()  # one thread: the process CPU time (not the waits of a shared machine)
    fn()
    return time.process_time() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--runs", type=int, default=3, help="repeats of the whole table (medians reported)")
    a = ap.parse_args(argv)
    import cv2

    from _locate_sim import model
    from psdcal.measure._aoa_kernel import angles_kernel
    from psdcal.measure.aoa import angles_from_points, angles_from_points_reference
    from psdcal.model.distortion import undistort

    cv2.setNumThreads(1)
    m = model(names=["f_mm", "cx_mm", "cy_mm", "k1", "k2", "p1", "p2", "l1"],
              std=[1e-2, 5e-3, 5e-3, 1e-4, 1e-6, 1e-5, 1e-5, 1e-4], fy=8.02)
    rng = np.random.default_rng(0)
    d = rng.uniform(-3.5, 3.5, (a.points, 2))
    cov = np.broadcast_to(np.diag([1e-6, 1e-6]), (a.points, 2, 2)).copy()
    intr = m.intrinsics
    K = np.array([[intr.f_mm / 0.01, 0, 450 + intr.cx_mm / 0.01], [0, intr.fy / 0.01, 450 + intr.cy_mm / 0.01], [0, 0, 1]])
    px = (d / 0.01 + 450).reshape(-1, 1, 2)
    coef = np.ascontiguousarray(m.distortion.as_array())
    vals = np.array([intr.f_mm, intr.cx_mm, intr.cy_mm, intr.skew, intr.fy])
    nref = min(a.points, 200_000)
    cases = [
        ("angles_from_points + both covariances + derivatives dn/dp (default)",
         _chunked(lambda dd, cc: angles_from_points(dd, m, cc), d, cov), a.points),
        ("angles_from_points + both covariances, derivatives=False",
         _chunked(lambda dd, cc: angles_from_points(dd, m, cc, derivatives=False), d, cov), a.points),
        ("angles only (kernel, no parameters)",
         _chunked(lambda dd: angles_kernel(dd, vals, True, coef, np.zeros(0, np.int64), np.zeros((0, 0)), True,
                                           np.zeros((0, 2, 2)), np.zeros((0, 2, 3)), False, np.zeros(0)), d), a.points),
        ("angles_from_points (default), all points in one call", lambda: angles_from_points(d, m, cov), a.points),
        ("angles_from_points, derivatives=False, all points in one call",
         lambda: angles_from_points(d, m, cov, derivatives=False), a.points),
        ("numpy reference (angles_from_points_reference)",
         lambda: angles_from_points_reference(d[:nref], m, cov[:nref]), nref),
        ("bare undistort (numpy)", lambda: undistort(d, m.distortion, intr.c), a.points),
        ("cv2.undistortPoints (default iterations)",
         lambda: cv2.undistortPoints(px, K, np.array([-0.1, 0.01, 0, 0, 0])), a.points),
    ]
    # whole table `runs` times; each ratio is taken within one run, then the medians are reported
    rates = np.array([[_rate(fn, npts) for _, fn, npts in cases] for _ in range(a.runs)])
    i_ang, i_cv = 2, len(cases) - 1
    med = np.median(rates, axis=0)
    vs_ang = np.median(rates / rates[:, i_ang:i_ang + 1], axis=0)
    vs_cv = np.median(rates / rates[:, i_cv:i_cv + 1], axis=0)
    print(f"{a.points} points in calls of {CHUNK} (unless stated), one core; model {', '.join(m.names)}; "
          f"median of {a.runs} runs")
    print_table(("what", "M points/s", "/ angles only", "/ cv2.undistortPoints"),
                [(w, f"{r / 1e6:.2f}", f"{x:.2f}", f"{y:.2f}") for (w, _, _), r, x, y in zip(cases, med, vs_ang, vs_cv)],
                a.markdown)
    # one call against calls of CHUNK points (the library blocks large inputs itself): ratios within a run
    one_default = np.median(rates[:, 3] / rates[:, 0])
    one_noderiv = np.median(rates[:, 4] / rates[:, 1])
    print(f"all {a.points} points in one call / in calls of {CHUNK} (rate ratio, median of {a.runs} runs, CPU "
          f"time): {one_default:.2f} with dn/dp (default), {one_noderiv:.2f} with derivatives=False")
    return 0


if __name__ == "__main__":
    sys.exit(main())
