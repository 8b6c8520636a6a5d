#!/usr/bin/env python3
"""Start-up: fresh processes for ``psdcal --help`` and ``psdcal calibrate`` against an OpenCV script.

Each command runs ``--repeats`` times in a new interpreter; the table gives
the median wall-clock seconds and the ratio to the OpenCV script, which
reads the same bundled CSV files, calls ``cv2.calibrateCamera`` (one f, C,
k1, k2, p1, p2) and writes a JSON file. ``psdcal calibrate`` runs on the
bundled default data (12 views x 14 points), where the command line keeps
to the numpy path (loading numba and the compiled kernels would cost more
than the calibration; see ``psdcal._jit``). A last row forces the compiled
kernels (``psdcal._jit`` mode "always", warm disk cache) for comparison.

Usage::

    .venv/bin/python benchmarks/bench_startup.py [--repeats 5] [--markdown]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import print_table  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "src" / "psdcal" / "data"
BIN = Path(sys.executable).parent

_OPENCV = r"""
import json, sys
import numpy as np, cv2
T = np.loadtxt(sys.argv[1], delimiter=",", skiprows=1, usecols=(1, 2))
P = np.loadtxt(sys.argv[2], delimiter=",", skiprows=1)
obj = np.concatenate([T, np.zeros((len(T), 1))], 1).astype(np.float32)
imgs = [(P[P[:, 0] == i][:, 2:4] / 0.01 + 450).astype(np.float32).reshape(-1, 1, 2) for i in np.unique(P[:, 0])]
rms, K, dist, rv, tv = cv2.calibrateCamera([obj] * len(imgs), imgs, (900, 900), np.eye(3), np.zeros(5),
                                           flags=cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_K3)
json.dump({"K": K.tolist(), "dist": dist.ravel().tolist(), "rms": rms}, open(sys.argv[3], "w"))
"""

_FORCED = r"""
import sys
from psdcal import _jit
from psdcal.cli import calibrate_cmd
calibrate_cmd._kernels_for = lambda *a: None  # keep mode "always": compiled kernels from the disk cache
from psdcal.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _median_seconds(cmd, repeats, env=None) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True, env=env)
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--markdown", action="store_true")
    a = ap.parse_args(argv)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    psdcal = str(BIN / "psdcal")
    pts, tpl = str(DATA / "default_points.csv"), str(DATA / "default_template.csv")
    subprocess.run([sys.executable, "-c", "from psdcal.study.warmup import warm_up; warm_up(False)"], check=True, env=env)
    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "c.json")
        t_cv = _median_seconds([sys.executable, "-c", _OPENCV, tpl, pts, out], a.repeats, env)
        rows = [
            ("psdcal --help", _median_seconds([psdcal, "--help"], a.repeats, env)),
            ("psdcal calibrate (bundled data)", _median_seconds([psdcal, "calibrate", pts, "-t", tpl, "-o", out, "-q", "--force"], a.repeats, env)),
            ("psdcal calibrate, compiled kernels forced", _median_seconds(
                [sys.executable, "-c", _FORCED, "calibrate", pts, "-t", tpl, "-o", out, "-q", "--force"], a.repeats, env)),
            ("OpenCV script (same data, reads CSV, writes JSON)", t_cv),
        ]
    print(f"fresh processes, median of {a.repeats}; ratio to the OpenCV script")
    print_table(("command", "seconds", "ratio to OpenCV"), [(n, f"{t:.3f}", f"{t / t_cv:.2f}") for n, t in rows], a.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
