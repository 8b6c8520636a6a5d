#!/usr/bin/env python3
"""The linear calibration stage on small sets: compiled kernels against their numpy reference.

``homographies``, ``intrinsics_from_homographies`` and ``poses_from_homographies``
(one compiled call each, :mod:`psdcal.calibration._linear_kernel`) against the
numpy code they replace (the same functions with the linear stage's dispatch
switched off), the per-view focal lengths (``focal_from_homographies`` against
``focal_from_homographies_kernel``), and a whole
``calibrate(..., cost="image", radial=2, tangential=False, verdict=False)``
with only the linear stage switched. Each number is the median of
``--repeats`` calls after a warm-up; both sides of a ratio come from the same
run, interleaved.

Usage::

    .venv/bin/python benchmarks/bench_linear.py [--repeats 300] [--markdown]
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import types  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import print_table  # noqa: E402
from _timing import median_seconds  # noqa: E402

import psdcal._jit  # noqa: E402
from psdcal.calibration import _closed_form, _homography  # noqa: E402
from psdcal.calibration.core import calibrate, focal_from_homographies  # noqa: E402
from psdcal.study.simulate import simulate_set  # noqa: E402

ZHANG = Path(__file__).resolve().parent.parent / "tests" / "data" / "zhang1998"


_median_s = median_seconds  # (the rule of benchmarks/_timing.py)


def _grid(nx: int, ny: int) -> np.ndarray:
    X, Y = np.meshgrid(np.linspace(-60.0, 60.0, nx), np.linspace(-40.0, 40.0, ny))
    return np.stack([X.ravel(), Y.ravel()], axis=1)


def _sets():
    s = simulate_set("lens2", n_images=5, noise_mm=0.002, seed=0)
    yield "synthetic", s.template_mm, s.points_mm, {}
    s = simulate_set("lens2", n_images=13, noise_mm=0.002, seed=0, template_mm=_grid(6, 4))
    yield "synthetic", s.template_mm, s.points_mm, {}
    if (ZHANG / "points.csv").exists():
        from psdcal.io import read_points, read_template

        ids, T = read_template(ZHANG / "template.csv")
        pts = read_points(ZHANG / "points.csv", ids, sensor_mm=(6.4, 4.8)).points_mm
        yield "zhang1998 (real)", T, pts, dict(aspect=True, sensor_mm=(6.4, 4.8))


def _linear_dispatch(compiled: bool) -> None:
    """Switch the linear stage (only) between the compiled kernels and the numpy code."""
    shim = psdcal._jit if compiled else types.SimpleNamespace(use_compiled=lambda n: False)
    _homography._jit = shim
    _closed_form._jit = shim


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=300, help="timed calls per number (median; default 300)")
    ap.add_argument("--markdown", action="store_true", help="print Markdown tables")
    a = ap.parse_args(argv)
    if not psdcal._jit.enabled():
        print("numba is missing or PSDCAL_JIT=0: nothing compiled to compare", file=sys.stderr)
        return 0
    from psdcal.calibration._homography import homographies, linear_kernels
    from psdcal.calibration._closed_form import intrinsics_from_homographies, poses_from_homographies

    lk = linear_kernels()
    rows = []
    for name, T, X, kw in _sets():
        Hs = homographies(T, X)
        intr = intrinsics_from_homographies(Hs)
        Hc = np.ascontiguousarray(Hs)
        steps = [
            ("homographies", lambda: homographies(T, X, normalize=True), None),
            ("poses_from_homographies", lambda: poses_from_homographies(Hs, intr), None),
            ("intrinsics_from_homographies", lambda: intrinsics_from_homographies(Hs), None),
            ("  skew=True, aspect=True", lambda: intrinsics_from_homographies(Hs, skew=True, aspect=True), None),
            ("focal_from_homographies", lambda: focal_from_homographies(Hs), lambda: lk.focal_from_homographies_kernel(Hc, 0.0, 0.0)),
            ("calibrate (verdict=False)", lambda: calibrate(T, X, cost="image", radial=2, tangential=False, verdict=False, **kw), None),
        ]
        for step, ref_fn, fast_fn in steps:
            t_ref, t_fast = [], []
            for _ in range(2):  # interleaved
                _linear_dispatch(False)
                t_ref.append(_median_s(ref_fn, a.repeats))
                _linear_dispatch(True)
                t_fast.append(_median_s(fast_fn or ref_fn, a.repeats))
            r, f = float(np.median(t_ref)), float(np.median(t_fast))
            rows.append((name, str(X.shape[0]), str(X.shape[1]), step, f"{1e3 * r:.4f}", f"{1e3 * f:.4f}", f"{f / r:.2f}"))
    print_table(("set", "views", "points/view", "step", "numpy ms", "compiled ms", "compiled/numpy"), rows, a.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
