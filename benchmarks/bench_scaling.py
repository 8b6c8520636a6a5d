#!/usr/bin/env python3
"""Calibration time against the number of views and of points per view, with OpenCV and scipy.

(mrcal is not compared any more: the reference script failed with mrcal 2.5.2, and no mrcal
2.5 can be installed here to fix and check the call; see docs/guide/performance.md.)

Every row calibrates one synthetic set (Lens 2, noise 2 um) with psdcal
(``calibrate``, image cost, one f, k1, k2) and, in the same process on the
same points, with two references:

- OpenCV ``cv2.calibrateCamera`` (pixels at a 10 um pitch, flags
  ``FIX_ASPECT_RATIO | ZERO_TANGENT_DIST | FIX_K3``: one f, C, k1, k2);
- scipy ``least_squares`` (``trf``, ``tr_solver="lsmr"``) on psdcal's own
  residuals with its analytic Jacobian as a sparse CSR matrix, from psdcal's
  linear start (the linear start is included in its time): a generic sparse
  solver on the same model. Skipped above ``--scipy-max-views``.

Sizes: 5 ... 1000 views of the 14-point default template, and 20 views of a
square grid of 14 ... 1024 points. The last rows are real data: Zhang's five
views of 256 corners with fx, fy, k1, k2, p1, p2 (OpenCV: ``FIX_K3``) and,
when present, the chessboard sets of ``tests/data/chessboards``. Times are
the median of ``--repeats`` calls after a warm-up (at least 5 calls and
50 ms, for every library), one thread each. The growth exponent is the
slope of log(time) against log(views) from 30 views up.

Usage::

    .venv/bin/python benchmarks/bench_scaling.py [--repeats 5] [--markdown] [--quick]

Prints three tables: the calibrations, the real sets with the verdict, the growth exponent.
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import print_table  # noqa: E402
from _zhang import ZHANG, load_zhang  # noqa: E402
from _timing import median_seconds  # noqa: E402

from psdcal.calibration.core import calibrate  # noqa: E402
from psdcal.study.simulate import simulate_set  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CHESS = ROOT / "tests" / "data" / "chessboards"
PITCH_MM = 0.010


def grid_template(m: int) -> np.ndarray:
    """A square grid of about ``m`` points spanning 80 mm, (m, 2) mm."""
    k = int(round(np.sqrt(m)))
    a = np.linspace(-40.0, 40.0, k)
    X, Y = np.meshgrid(a, a)
    return np.stack([X.ravel(), Y.ravel()], axis=1)


_timed = median_seconds  # (the rule of benchmarks/_timing.py)


def _opencv_inputs(template, points, origin_px):
    obj = np.concatenate([template, np.zeros((len(template), 1))], axis=1).astype(np.float32)
    objs, imgs = [], []
    for p in points:
        ok = np.all(np.isfinite(p), axis=1)
        objs.append(obj[ok])
        imgs.append((p[ok] / PITCH_MM + origin_px).astype(np.float32).reshape(-1, 1, 2))
    return objs, imgs


def scipy_reference(template, points, *, general=False, sensor_mm=None):
    """psdcal's model and Jacobian solved by scipy's sparse trust-region least squares."""
    import scipy.sparse as sp
    from scipy.optimize import least_squares

    from psdcal.calibration._refine import Evaluator, Problem
    from psdcal.calibration.core import initial_estimate
    from psdcal.model.params import ModelSpec

    spec = ModelSpec(radial=2, tangential=general, aspect=general)
    start = initial_estimate(template, points, radial_terms=2, aspect=general)
    intr = start.intrinsics
    if general and intr.fy_mm is None:
        from dataclasses import replace

        intr = replace(intr, fy_mm=intr.f_mm)
    kw = {} if sensor_mm is None else {"sensor_mm": sensor_mm}
    prob = Problem(template, points, spec, **kw)
    ev = Evaluator(prob, intr, start.distortion(2), np.ones(4))
    z0 = prob.pack(intr, start.distortion(2), np.ones(4), start.rvecs, start.tvecs_mm)
    ng = prob.n_global
    rows = np.repeat(np.arange(2 * len(ev.img_idx)), ng + 6)
    pose_cols = ng + 6 * np.repeat(ev.img_idx, 2)[:, None] + np.arange(6)[None, :]
    cols = np.concatenate([np.broadcast_to(np.arange(ng), (pose_cols.shape[0], ng)), pose_cols], axis=1).ravel()

    def jac(z):
        return sp.csr_matrix((ev.jacobian_compact(z).ravel(), (rows, cols)), shape=(rows.size // (ng + 6), z.size))

    return least_squares(ev.residuals, z0, jac=jac, method="trf", tr_solver="lsmr", x_scale="jac",
                         ftol=1e-12, xtol=1e-12, gtol=1e-12)


def synthetic_rows(cv2, sizes, repeats, scipy_max_views):
    flags = cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    rows = []
    for n, m in sizes:
        s = simulate_set("lens2", n_images=n, noise_mm=0.002, seed=0, template_mm=None if m == 14 else grid_template(m))
        objs, imgs = _opencv_inputs(s.template_mm, s.points_mm, np.array([450.0, 450.0]))
        t_p = _timed(lambda: calibrate(s.template_mm, s.points_mm, cost="image", radial=2, tangential=False,
                                       verdict=False), repeats)
        t_o = _timed(lambda: cv2.calibrateCamera(objs, imgs, (900, 900), np.eye(3), np.zeros(5), flags=flags), repeats)
        t_s = _timed(lambda: scipy_reference(s.template_mm, s.points_mm), max(1, repeats // 2)) if n <= scipy_max_views and m <= 256 else None
        rows.append({"set": "synthetic", "views": n, "points": len(s.template_mm), "model": "f, C, k1, k2",
                     "psdcal": t_p, "opencv": t_o, "scipy": t_s})
    return rows


def zhang_row(cv2, repeats):

    T, pts, objs, imgs = load_zhang()
    kw = dict(cost="image", radial=2, tangential=True, aspect=True, sensor_mm=(6.4, 4.8))
    t_p = _timed(lambda: calibrate(T, pts, verdict=False, **kw), repeats)
    t_v = _timed(lambda: calibrate(T, pts, **kw), repeats)
    t_o = _timed(lambda: cv2.calibrateCamera(objs, imgs, (640, 480), np.eye(3), np.zeros(5), flags=cv2.CALIB_FIX_K3), repeats)
    t_s = _timed(lambda: scipy_reference(T, pts, general=True, sensor_mm=(6.4, 4.8)), max(1, repeats // 2))
    return {"set": "zhang1998 (real)", "views": len(objs), "points": len(T), "model": "fx, fy, C, k1, k2, p1, p2",
            "psdcal": t_p, "opencv": t_o, "scipy": t_s, "psdcal_verdict": t_v}


def chessboard_rows(cv2, repeats):
    """The real chessboard sets of tests/data/chessboards: one f, C, k1, k2, p1, p2 (OpenCV flags 130)."""
    import json

    from psdcal.io import read_points, read_template

    rows = []
    if not CHESS.exists():
        return rows
    for d in sorted(p for p in CHESS.iterdir() if p.is_dir()):
        meta = json.loads((d / "checks.json").read_text())
        ids, T = read_template(d / "template.csv")
        pts = read_points(d / "points.csv", ids)
        pid = {str(k): n for n, k in enumerate(ids)}
        obj = np.concatenate([T, np.zeros((len(T), 1))], axis=1).astype(np.float32)
        by_view: dict = {}
        with open(d / "points_px.csv") as fh:
            next(fh)
            for line in fh:
                img, p, u, v = line.strip().split(",")
                by_view.setdefault(img, []).append((pid[p], float(u), float(v)))
        objs = [obj[[r[0] for r in rr]] for rr in by_view.values()]
        imgs = [np.array([[r[1], r[2]] for r in rr], dtype=np.float32).reshape(-1, 1, 2) for rr in by_view.values()]
        size = tuple(meta["image_size_px"])
        flags = cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_K3
        t_p = _timed(lambda: calibrate(T, pts.points_mm, image_ids=pts.image_ids, verdict=False), repeats)
        t_v = _timed(lambda: calibrate(T, pts.points_mm, image_ids=pts.image_ids), repeats)
        t_o = _timed(lambda: cv2.calibrateCamera(objs, imgs, size, np.eye(3), np.zeros(5), flags=flags), repeats)
        rows.append({"set": d.name + " (real)", "views": len(objs), "points": len(T), "model": "f, C, k1, k2, p1, p2",
                     "psdcal": t_p, "opencv": t_o, "scipy": None, "psdcal_verdict": t_v})
    return rows


def growth_exponent(rows) -> float:
    sel = [r for r in rows if r["set"] == "synthetic" and r["points"] == 14 and r["views"] >= 30]
    if len(sel) < 2:
        return float("nan")
    x = np.log([r["views"] for r in sel])
    y = np.log([r["psdcal"] for r in sel])
    return float(np.polyfit(x, y, 1)[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="fewer sizes (up to 300 views, 256 points)")
    ap.add_argument("--scipy-max-views", type=int, default=100)
    ap.add_argument("--markdown", action="store_true")
    a = ap.parse_args(argv)
    import cv2

    cv2.setNumThreads(1)
    views = (5, 10, 30, 100, 300) if a.quick else (5, 10, 30, 100, 300, 1000)
    points = (64, 256) if a.quick else (64, 256, 1024)
    sizes = [(n, 14) for n in views] + [(20, m) for m in points]
    rows = synthetic_rows(cv2, sizes, a.repeats, a.scipy_max_views)
    if (ZHANG / "points_px.csv").exists():
        rows.append(zhang_row(cv2, a.repeats))
    rows += chessboard_rows(cv2, a.repeats)
    print(f"OpenCV {cv2.__version__}; one thread each; median of {a.repeats} calls; times in ms")
    head = ("set", "views", "points/view", "model", "psdcal ms", "OpenCV ms", "psdcal/OpenCV",
            "scipy ms", "psdcal/scipy")
    lines = [(r["set"], str(r["views"]), str(r["points"]), r["model"], f"{1e3 * r['psdcal']:.2f}", f"{1e3 * r['opencv']:.2f}",
              f"{r['psdcal'] / r['opencv']:.2f}",
              "-" if r["scipy"] is None else f"{1e3 * r['scipy']:.1f}",
              "-" if r["scipy"] is None else f"{r['psdcal'] / r['scipy']:.3f}") for r in rows]
    print_table(head, lines, a.markdown)
    print("\nwith the verdict (calibrate()'s default: the fit and its self-checks), real sets")
    print_table(("set", "views", "points/view", "psdcal + verdict ms", "OpenCV ms", "(psdcal + verdict)/OpenCV"),
                [(r["set"], str(r["views"]), str(r["points"]), f"{1e3 * r['psdcal_verdict']:.2f}",
                  f"{1e3 * r['opencv']:.2f}", f"{r['psdcal_verdict'] / r['opencv']:.2f}")
                 for r in rows if r.get("psdcal_verdict") is not None], a.markdown)
    views_used = [r["views"] for r in rows if r["set"] == "synthetic" and r["points"] == 14 and r["views"] >= 30]
    print("\ngrowth of psdcal's time in views (14 points; slope of log time against log views)")
    print_table(("views", "growth exponent"),
                [(f"{min(views_used)}-{max(views_used)}" if views_used else "-", f"{growth_exponent(rows):.2f}")],
                a.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
