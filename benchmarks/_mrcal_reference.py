"""mrcal's optimizer on one calibration set: the second reference of ``bench_scaling.py``.

Runs under a Python that has mrcal (e.g. Debian's ``python3-mrcal`` with
``/usr/bin/python3``), not necessarily the project's own: ``bench_scaling.py``
writes the set to an ``.npz`` file and runs this script in a subprocess::

    /usr/bin/python3 benchmarks/_mrcal_reference.py set.npz

The ``.npz`` holds ``template_mm`` (M, 2) (the plate, Z = 0), ``points_px``
(n, M, 2) (NaN where missing), ``seed_px`` (fx, fy, cx, cy), ``rvecs`` and
``tvecs_mm`` (n, 3) (the seed poses, plate to camera), ``imagersize`` (w, h)
and ``repeats``. The plate points are mrcal *discrete points*, all fixed
(``Npoints_fixed``), seen by one camera whose pose per view is an
``extrinsics_rt_fromref`` entry: a plate of any layout works (mrcal's board
observations need a regular grid). Model ``LENSMODEL_OPENCV4`` (fx, fy, cx,
cy, k1, k2, p1, p2); no outlier rejection; mrcal's default regularisation.
Only ``mrcal.optimize`` is timed (the seed is given), median of ``repeats``
calls after a warm-up (at least 5 calls and 50 ms), on one thread. Prints one JSON line: ``ms``,
``intrinsics`` (the solution) and ``rms_px``.
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402


def solve(d):
    import mrcal

    T = np.asarray(d["template_mm"], dtype=float)
    X = np.asarray(d["points_px"], dtype=float)
    n, M = X.shape[:2]
    points = np.concatenate([T, np.zeros((M, 1))], axis=1)
    ok = np.all(np.isfinite(X), axis=-1)
    iv, ip = np.nonzero(ok)
    obs = np.concatenate([X[iv, ip], np.ones((iv.size, 1))], axis=1)
    idx = np.stack([ip, np.zeros_like(ip), iv], axis=1).astype(np.int32)
    fx, fy, cx, cy = (float(v) for v in d["seed_px"])
    intr0 = np.array([[fx, fy, cx, cy, 0.0, 0.0, 0.0, 0.0]])
    ext0 = np.concatenate([d["rvecs"], d["tvecs_mm"]], axis=1).astype(float)
    size = np.array([[int(v) for v in d["imagersize"]]], dtype=np.int32)

    def run():
        intr = intr0.copy()
        ext = ext0.copy()
        pts = points.copy()
        o = obs.copy()
        stats = mrcal.optimize(
            intr, ext, None, pts, None, None, o, idx,
            lensmodel="LENSMODEL_OPENCV4", imagersizes=size, Npoints_fixed=M,
            point_min_range=1e-6, point_max_range=1e12,
            do_optimize_intrinsics_core=True, do_optimize_intrinsics_distortions=True,
            do_optimize_extrinsics=True, do_optimize_frames=False, do_optimize_calobject_warp=False,
            do_apply_outlier_rejection=False, do_apply_regularization=True, verbose=False,
        )
        return intr, stats

    t_end = time.perf_counter() + 0.05  # warm-up: at least 5 calls and 50 ms, the rule of _timing.py
    for k in range(10_000):
        run()
        if k + 1 >= 5 and time.perf_counter() >= t_end:
            break
    times = []
    for _ in range(int(d["repeats"])):
        t0 = time.perf_counter()
        intr, stats = run()
        times.append(time.perf_counter() - t0)
    return {"ms": 1e3 * float(np.median(times)), "intrinsics": intr[0].tolist(), "rms_px": float(stats["rms_reproj_error__pixels"])}


def main(argv) -> int:
    d = dict(np.load(argv[1]))
    print(json.dumps(solve(d)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
