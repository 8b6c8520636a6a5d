#!/usr/bin/env python3
"""Time one calibration of 12 views x 14 points (the default template, both lenses, 1 um noise).

Median over ``--sets`` sets of the median of ``--repeats`` calls (single-threaded BLAS),
for the default model and ``--no-tangential``; the time of the verdict
(:func:`psdcal.calibration.verdict.assess`) on the same fits is printed apart.

Usage::

    .venv/bin/python benchmarks/bench_verdict.py [--sets 10] [--repeats 3] [--markdown]
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--markdown", action="store_true", help="also print the results as a Markdown table")
    a = ap.parse_args(argv)
    from psdcal.calibration.core import calibrate
    from psdcal.study.simulate import simulate_set

    try:
        from psdcal.calibration.verdict import assess
    except ImportError:  # before the verdict existed
        assess = None
    table = []
    for tang in (True, False):
        times, vt = [], []
        for lens in ("lens1", "lens2"):
            for seed in range(a.sets):
                s = simulate_set(lens, n_images=12, noise_mm=1e-3, seed=seed)
                calibrate(s.template_mm, s.points_mm, tangential=tang)  # warm-up
                ts = []
                for _ in range(a.repeats):
                    t0 = time.perf_counter()
                    res = calibrate(s.template_mm, s.points_mm, tangential=tang)
                    ts.append(time.perf_counter() - t0)
                times.append(np.median(ts))
                if assess is not None:
                    t0 = time.perf_counter()
                    assess(res)
                    vt.append(time.perf_counter() - t0)
        line = f"tangential={tang}: calibrate median {np.median(times) * 1e3:.2f} ms"
        if vt:
            line += f"; verdict median {np.median(vt) * 1e3:.2f} ms"
        print(line)
        table.append(("default" if tang else "--no-tangential", f"{np.median(times) * 1e3:.2f}",
                      f"{np.median(vt) * 1e3:.2f}" if vt else "-"))
    if a.markdown:
        import sys

        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        from _table import print_table

        print_table(("model", "calibrate ms (median)", "verdict ms (median)"), table, markdown=True)


if __name__ == "__main__":
    main()
