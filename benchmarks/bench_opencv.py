#!/usr/bin/env python3
"""Time ``psdcal.calibrate`` against ``cv2.calibrateCamera`` on the same synthetic sets.

For each of the paper's lenses (docs/model.md#paper-simulation-setup) and 9 and 12 views of the
14-point default template, ``--sets`` synthetic sets (seeds 0, 1, ...) with
Gaussian noise of ``--noise-mm`` on the impact points are calibrated by both
libraries in the same process:

- psdcal: ``calibrate(template, points, cost="image", radial=2, tangential=False)``
  (one focal length, no skew, k1, k2 of the undistortion model, docs/model.md#distortion);
- OpenCV: ``cv2.calibrateCamera`` on the same points in pixel units (pitch
  ``--pitch-um``, pixel (W/2, H/2) at the sensor's electrical centre, a
  900 x 900 image for the 9 mm PSD), template points float32 with Z = 0,
  flags ``CALIB_FIX_ASPECT_RATIO | CALIB_ZERO_TANGENT_DIST | CALIB_FIX_K3``
  (one focal length, no tangential terms, k1, k2 of OpenCV's *forward*
  model; OpenCV has no skew, as ours here).

A last row does the same on real data, Zhang's five views of 256 corners
(``tests/data/zhang1998``: psdcal on ``points.csv`` in mm, OpenCV on the
published pixels ``points_px.csv``, 640 x 480, 10 um nominal pitch); its
errors are the distances to Zhang's published f and C, not to a truth.

Time: the median over all sets of the median of ``--repeats`` calls per set,
after a warm-up call per method that is not timed; ``cv2.setNumThreads(1)``
and single-threaded BLAS (environment set before numpy loads), so both run
on one core. Accuracy: the RMS over the sets of the error of f and of the
distance |C - C_true| in mm. The two distortion models differ (the truth is
generated with ours), so only the intrinsics are compared.

Start-up (skipped with ``--no-startup``): seconds from a fresh interpreter
to the end of its first calibration, imports included, for psdcal with an
empty numba cache (its compiled kernels are built: once per machine and
version), psdcal with the cache filled (every later process), and OpenCV.

Usage::

    .venv/bin/python benchmarks/bench_opencv.py [--sets 20] [--repeats 3] [--markdown]
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/_table.py, also when imported by the tests
from _table import print_table  # noqa: E402
from _zhang import ZHANG, load_zhang  # noqa: E402

import psdcal  # noqa: E402
from psdcal.calibration.core import calibrate  # noqa: E402
from psdcal.model.readout import LX_MM, LY_MM  # noqa: E402
from psdcal.study.simulate import simulate_set  # noqa: E402

CONFIGS = (("lens1", 9), ("lens1", 12), ("lens2", 9), ("lens2", 12))
#: Zhang's published alpha, beta, u0, v0 (pixels) of these data
ZHANG_PUBLISHED_PX = (832.5, 832.53, 303.959, 206.585)


def to_opencv(sset, pitch_mm: float):
    """The set in OpenCV's terms.

    Returns
    -------
    object_points : list of (M, 3) float32, template points with Z = 0
    image_points : list of (M, 1, 2) float32, pixels
    image_size : (width, height) pixels
    """
    size = (int(round(LX_MM / pitch_mm)), int(round(LY_MM / pitch_mm)))
    centre = np.array(size, dtype=float) / 2
    obj = np.concatenate([sset.template_mm, np.zeros((len(sset.template_mm), 1))], axis=1).astype(np.float32)
    objs, imgs = [], []
    for pts in sset.points_mm:
        ok = np.all(np.isfinite(pts), axis=1)
        objs.append(obj[ok])
        imgs.append((pts[ok] / pitch_mm + centre).astype(np.float32).reshape(-1, 1, 2))
    return objs, imgs, size


def opencv_calibrate(cv2, objs, imgs, size, pitch_mm: float):
    """f and C in mm from ``cv2.calibrateCamera`` (one focal length, k1, k2)."""
    flags = cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    K0 = np.eye(3)
    _, K, _, _, _ = cv2.calibrateCamera(objs, imgs, size, K0, np.zeros(5), flags=flags)
    centre = np.array(size, dtype=float) / 2
    f = 0.5 * (K[0, 0] + K[1, 1]) * pitch_mm
    c = (np.array([K[0, 2], K[1, 2]]) - centre) * pitch_mm
    return f, c


def psdcal_calibrate(sset):
    """f and C in mm from ``psdcal.calibrate`` (image cost, k1, k2, no tangential)."""
    res = calibrate(sset.template_mm, sset.points_mm, cost="image", radial=2, tangential=False)
    return res.intrinsics.f_mm, res.intrinsics.c


def zhang_row(cv2, repeats: int) -> dict:
    """Both libraries on Zhang's real data; errors against his published f and C (mm)."""

    pitch, origin, size = 0.010, np.array([320.0, 240.0]), (640, 480)
    template, pts, objs, imgs = load_zhang()
    a, b, u0, v0 = ZHANG_PUBLISHED_PX
    f_ref = 0.5 * (a + b) * pitch
    c_ref = (np.array([u0, v0]) - origin) * pitch

    def ours():
        res = calibrate(template, pts, cost="image", radial=2, tangential=False, sensor_mm=(6.4, 4.8))
        return res.intrinsics.f_mm, res.intrinsics.c

    def theirs():
        flags = cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
        _, K, _, _, _ = cv2.calibrateCamera(objs, imgs, size, np.eye(3), np.zeros(5), flags=flags)
        return 0.5 * (K[0, 0] + K[1, 1]) * pitch, (np.array([K[0, 2], K[1, 2]]) - origin) * pitch

    ours()
    theirs()
    (f_p, c_p), t_p = _timed(ours, repeats)
    (f_o, c_o), t_o = _timed(theirs, repeats)
    return {
        "lens": "zhang1998 (real)",
        "n_images": len(objs),
        "t_psdcal_ms": 1e3 * t_p,
        "t_opencv_ms": 1e3 * t_o,
        "f_err_psdcal": abs(f_p - f_ref),
        "f_err_opencv": abs(f_o - f_ref),
        "c_err_psdcal": float(np.linalg.norm(c_p - c_ref)),
        "c_err_opencv": float(np.linalg.norm(c_o - c_ref)),
    }


def _timed(fn, repeats: int):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, float(np.median(times))


def run(n_sets: int, repeats: int, noise_mm: float, pitch_mm: float) -> list[dict]:
    """One row per (lens, n_images): median times and RMS intrinsic errors of both libraries."""
    import cv2

    cv2.setNumThreads(1)
    rows = []
    for lens, n_images in CONFIGS:
        sets = [simulate_set(lens, n_images=n_images, noise_mm=noise_mm, seed=s) for s in range(n_sets)]
        cvdata = [to_opencv(s, pitch_mm) for s in sets]
        psdcal_calibrate(sets[0])  # warm-up, not timed
        opencv_calibrate(cv2, *cvdata[0], pitch_mm)
        t_p, t_o, ef_p, ef_o, ec_p, ec_o = [], [], [], [], [], []
        for s, cvd in zip(sets, cvdata):
            (f, c), t = _timed(lambda: psdcal_calibrate(s), repeats)
            t_p.append(t)
            ef_p.append(f - s.intrinsics.f_mm)
            ec_p.append(np.linalg.norm(c - s.intrinsics.c))
            (f, c), t = _timed(lambda: opencv_calibrate(cv2, *cvd, pitch_mm), repeats)
            t_o.append(t)
            ef_o.append(f - s.intrinsics.f_mm)
            ec_o.append(np.linalg.norm(c - s.intrinsics.c))
        rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
        rows.append(
            {
                "lens": lens,
                "n_images": n_images,
                "t_psdcal_ms": 1e3 * float(np.median(t_p)),
                "t_opencv_ms": 1e3 * float(np.median(t_o)),
                "f_err_psdcal": rms(ef_p),
                "f_err_opencv": rms(ef_o),
                "c_err_psdcal": rms(ec_p),
                "c_err_opencv": rms(ec_o),
            }
        )
    if (ZHANG / "points_px.csv").exists():
        rows.append(zhang_row(cv2, repeats))
    return rows


_FIRST_CALL = r"""
import os, sys, time
for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[v] = "1"
import numpy as np
data = np.load(sys.argv[2])
t0 = time.perf_counter()
if sys.argv[1] == "psdcal":
    from psdcal.calibration.core import calibrate
    calibrate(data["template"], data["points"], cost="image", radial=2, tangential=False)
else:
    import cv2
    cv2.setNumThreads(1)
    obj = np.concatenate([data["template"], np.zeros((len(data["template"]), 1))], axis=1).astype(np.float32)
    imgs = [(p / 0.01 + 450.0).astype(np.float32).reshape(-1, 1, 2) for p in data["points"]]
    flags = cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    cv2.calibrateCamera([obj] * len(imgs), imgs, (900, 900), np.eye(3), np.zeros(5), flags=flags)
print(time.perf_counter() - t0)
"""


def first_call_seconds(repeats: int = 3, cold: bool = True) -> dict:
    """Seconds from a fresh interpreter to the end of its first calibration (imports included).

    psdcal is measured twice: with an empty numba cache (``NUMBA_CACHE_DIR``
    pointing at a new folder, so its kernels are compiled: once per machine
    and psdcal version) and with that cache filled (every later process).
    OpenCV has nothing to compile. Median of ``repeats`` processes each.
    With ``cold=False`` only the warm case is run, on numba's default cache.
    """
    import subprocess
    import tempfile

    sset = simulate_set("lens2", n_images=12, noise_mm=0.002, seed=0)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "set.npz"
        np.savez(data, template=sset.template_mm, points=sset.points_mm)

        def once(which, cache):
            env = dict(os.environ)
            if cache is not None:
                env["NUMBA_CACHE_DIR"] = str(cache)
            res = subprocess.run([sys.executable, "-c", _FIRST_CALL, which, str(data)], env=env,
                                 capture_output=True, text=True, check=True)
            return float(res.stdout.strip().splitlines()[-1])

        cache = None
        if cold:
            out["psdcal, kernels compiled (first use on a machine)"] = float(
                np.median([once("psdcal", Path(tmp) / f"cold{k}") for k in range(repeats)]))
            cache = Path(tmp) / "cold0"
        out["psdcal, kernels from the disk cache"] = float(np.median([once("psdcal", cache) for _ in range(repeats)]))
        out["OpenCV"] = float(np.median([once("opencv", cache) for _ in range(repeats)]))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sets", type=int, default=20, help="synthetic sets per configuration")
    ap.add_argument("--repeats", type=int, default=3, help="timed calls per set and library (median)")
    ap.add_argument("--noise-mm", type=float, default=0.002)
    ap.add_argument("--pitch-um", type=float, default=10.0, help="pixel pitch given to OpenCV")
    ap.add_argument("--markdown", action="store_true", help="print a Markdown table (for docs/benchmarks.md)")
    ap.add_argument("--no-startup", action="store_true", help="skip the fresh-process (start-up) timing")
    a = ap.parse_args(argv)
    import cv2

    rows = run(a.sets, a.repeats, a.noise_mm, a.pitch_um * 1e-3)
    print(
        f"psdcal {psdcal.__version__} vs OpenCV {cv2.__version__}; Python {platform.python_version()}, "
        f"numpy {np.__version__}, {platform.machine()}, one thread each; {a.sets} sets per row, "
        f"14 points per image, noise {a.noise_mm * 1e3:g} um, pitch {a.pitch_um:g} um/px; "
        "times: median per calibration; errors: RMS over the sets"
    )
    head = ("lens", "images", "psdcal ms", "OpenCV ms", "ratio psdcal/OpenCV",
            "psdcal |f err| mm", "OpenCV |f err| mm", "psdcal |C err| mm", "OpenCV |C err| mm")
    lines = [
        (
            r["lens"],
            str(r["n_images"]),
            f"{r['t_psdcal_ms']:.2f}",
            f"{r['t_opencv_ms']:.2f}",
            f"{r['t_psdcal_ms'] / r['t_opencv_ms']:.2f}",
            f"{r['f_err_psdcal']:.4f}",
            f"{r['f_err_opencv']:.4f}",
            f"{r['c_err_psdcal']:.4f}",
            f"{r['c_err_opencv']:.4f}",
        )
        for r in rows
    ]
    print_table(head, lines, a.markdown)
    if not a.no_startup:
        print()
        print("start-up: a fresh process to the end of its first calibration (lens2, 12 views), imports included; "
              "median of 3 processes")
        print_table(("what", "seconds"), [(k, f"{v:.2f}") for k, v in first_call_seconds().items()], a.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
