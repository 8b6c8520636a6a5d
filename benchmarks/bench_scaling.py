#!/usr/bin/env python3
"""Calibration time against the number of views and of points per view, with OpenCV and scipy.

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
from _timing import median_seconds  # noqa: E402

from psdcal.calibration.core import calibrate  # noqa: E402
from psdcal.study.simulate import simulate_set  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
ZHANG = ROOT / "tests" / "data" / "zhang1998"
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


MRCAL_SCRIPT = Path(__file__).resolve().parent / "_mrcal_reference.py"


def find_mrcal_python(given: str | None) -> str | None:
    """A Python that can import mrcal: ``given``, else the system's ``/usr/bin/python3`` when it can; None."""
    import subprocess

    for exe in ([given] if given else ["/usr/bin/python3"]):
        if exe and Path(exe).exists():
            ok = subprocess.run([exe, "-c", "import mrcal"], capture_output=True).returncode == 0
            if ok:
                return exe
    return None


def refine_seconds(template_mm, points_mm, sensor_mm, repeats):
    """Median time (s) of psdcal's optimizer alone (``refine``, image cost) from its closed-form seed,
    with mrcal's LENSMODEL_OPENCV4 parameters: fx, fy, cx, cy, k1, k2, p1, p2 (like for like with mrcal)."""
    from dataclasses import replace

    from psdcal.calibration._refine import Problem, refine
    from psdcal.calibration.core import initial_estimate
    from psdcal.model.params import ModelSpec

    est = initial_estimate(template_mm, points_mm, aspect=True)
    spec = ModelSpec(radial=2, tangential=True, aspect=True)
    prob = Problem(np.asarray(template_mm, float), np.asarray(points_mm, float), spec, sensor_mm=tuple(sensor_mm))
    i0 = est.intrinsics if est.intrinsics.fy_mm is not None else replace(est.intrinsics, fy_mm=est.intrinsics.f_mm)
    return _timed(lambda: refine(prob, i0, est.distortion(2), np.ones(4), est.rvecs, est.tvecs_mm), repeats)


def mrcal_seconds(python, template_mm, points_mm, to_px, imagersize, repeats):
    """Median time (s) of mrcal's optimizer on the set, seeded by psdcal's linear stage (None without mrcal).

    ``to_px`` (sx, sy, ox, oy) maps sensor mm to pixels: ``u = sx x + ox``. The
    seed (closed-form intrinsics and poses) is not timed; see ``_mrcal_reference.py``.
    """
    import json
    import subprocess
    import tempfile

    from psdcal.calibration.core import initial_estimate

    if python is None:
        return None
    est = initial_estimate(template_mm, points_mm, aspect=True)
    sx, sy, ox, oy = to_px
    i = est.intrinsics
    X = np.asarray(points_mm, dtype=float)
    px = np.stack([X[..., 0] * sx + ox, X[..., 1] * sy + oy], axis=-1)
    with tempfile.TemporaryDirectory() as tmp:
        f = Path(tmp) / "set.npz"
        np.savez(f, template_mm=np.asarray(template_mm, dtype=float), points_px=px,
                 seed_px=np.array([i.f_mm * sx, i.fy * sy, i.cx_mm * sx + ox, i.cy_mm * sy + oy]),
                 rvecs=est.rvecs, tvecs_mm=est.tvecs_mm, imagersize=np.asarray(imagersize), repeats=repeats)
        out = subprocess.run([python, str(MRCAL_SCRIPT), str(f)], capture_output=True, text=True)
    if out.returncode != 0:
        print(f"mrcal failed: {out.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
        return None
    return json.loads(out.stdout)["ms"] / 1e3


def _to_px_fit(points_mm, px_list):
    """(sx, sy, ox, oy) of ``px = s mm + o`` from matching points (least squares per axis)."""
    mm = np.concatenate([p for p in points_mm]).reshape(-1, 2)
    px = np.concatenate([p for p in px_list]).reshape(-1, 2)
    ok = np.all(np.isfinite(mm), axis=1) & np.all(np.isfinite(px), axis=1)
    out = []
    for k in range(2):
        a, b = np.polyfit(mm[ok, k], px[ok, k], 1)
        out.append((a, b))
    return out[0][0], out[1][0], out[0][1], out[1][1]


def synthetic_rows(cv2, sizes, repeats, scipy_max_views, mrcal_python=None):
    flags = cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    rows = []
    for n, m in sizes:
        s = simulate_set("lens2", n_images=n, noise_mm=0.002, seed=0, template_mm=None if m == 14 else grid_template(m))
        objs, imgs = _opencv_inputs(s.template_mm, s.points_mm, np.array([450.0, 450.0]))
        t_p = _timed(lambda: calibrate(s.template_mm, s.points_mm, cost="image", radial=2, tangential=False,
                                       verdict=False), repeats)
        t_o = _timed(lambda: cv2.calibrateCamera(objs, imgs, (900, 900), np.eye(3), np.zeros(5), flags=flags), repeats)
        t_s = _timed(lambda: scipy_reference(s.template_mm, s.points_mm), max(1, repeats // 2)) if n <= scipy_max_views and m <= 256 else None
        t_m = mrcal_seconds(mrcal_python, s.template_mm, s.points_mm, (1 / PITCH_MM, 1 / PITCH_MM, 450.0, 450.0),
                            (900, 900), repeats)
        t_r = refine_seconds(s.template_mm, s.points_mm, (9.0, 9.0), repeats) if t_m is not None else None
        rows.append({"set": "synthetic", "views": n, "points": len(s.template_mm), "model": "f, C, k1, k2",
                     "psdcal": t_p, "opencv": t_o, "scipy": t_s, "mrcal": t_m, "refine": t_r})
    return rows


def zhang_row(cv2, repeats, mrcal_python=None):
    from psdcal.io import read_points, read_template

    ids, T = read_template(ZHANG / "template.csv")
    pts = read_points(ZHANG / "points.csv", ids, sensor_mm=(6.4, 4.8)).points_mm
    px = np.loadtxt(ZHANG / "points_px.csv", delimiter=",", skiprows=1)
    obj = np.concatenate([T, np.zeros((len(T), 1))], axis=1).astype(np.float32)
    objs, imgs = [], []
    for i in np.unique(px[:, 0]):
        sel = px[px[:, 0] == i]
        objs.append(obj[sel[:, 1].astype(int)])
        imgs.append(sel[:, 2:4].astype(np.float32).reshape(-1, 1, 2))
    kw = dict(cost="image", radial=2, tangential=True, aspect=True, sensor_mm=(6.4, 4.8))
    t_p = _timed(lambda: calibrate(T, pts, verdict=False, **kw), repeats)
    t_v = _timed(lambda: calibrate(T, pts, **kw), repeats)
    t_o = _timed(lambda: cv2.calibrateCamera(objs, imgs, (640, 480), np.eye(3), np.zeros(5), flags=cv2.CALIB_FIX_K3), repeats)
    t_s = _timed(lambda: scipy_reference(T, pts, general=True, sensor_mm=(6.4, 4.8)), max(1, repeats // 2))
    px_views = np.full(pts.shape, np.nan)
    for row in px:
        px_views[int(row[0]), int(row[1])] = row[2:4]
    t_m = mrcal_seconds(mrcal_python, T, pts, _to_px_fit(pts, px_views), (640, 480), repeats)
    t_r = refine_seconds(T, pts, (6.4, 4.8), repeats) if t_m is not None else None
    return {"set": "zhang1998 (real)", "views": len(objs), "points": len(T), "model": "fx, fy, C, k1, k2, p1, p2",
            "psdcal": t_p, "opencv": t_o, "scipy": t_s, "psdcal_verdict": t_v, "mrcal": t_m, "refine": t_r}


def chessboard_rows(cv2, repeats, mrcal_python=None):
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
        px_views = np.full(pts.points_mm.shape, np.nan)
        for k, rr in enumerate(by_view.values()):
            for j, u, v in rr:
                px_views[k, j] = (u, v)
        t_m = mrcal_seconds(mrcal_python, T, pts.points_mm, _to_px_fit(pts.points_mm, px_views), size, repeats)
        t_r = refine_seconds(T, pts.points_mm, (9.0, 9.0), repeats) if t_m is not None else None
        rows.append({"set": d.name + " (real)", "views": len(objs), "points": len(T), "model": "f, C, k1, k2, p1, p2",
                     "psdcal": t_p, "opencv": t_o, "scipy": None, "psdcal_verdict": t_v, "mrcal": t_m, "refine": t_r})
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
    ap.add_argument("--mrcal-python", default=None,
                    help="a Python that can import mrcal (default: /usr/bin/python3 when it can; else no mrcal column)")
    a = ap.parse_args(argv)
    mpy = find_mrcal_python(a.mrcal_python)
    import cv2

    cv2.setNumThreads(1)
    views = (5, 10, 30, 100, 300) if a.quick else (5, 10, 30, 100, 300, 1000)
    points = (64, 256) if a.quick else (64, 256, 1024)
    sizes = [(n, 14) for n in views] + [(20, m) for m in points]
    rows = synthetic_rows(cv2, sizes, a.repeats, a.scipy_max_views, mpy)
    if (ZHANG / "points_px.csv").exists():
        rows.append(zhang_row(cv2, a.repeats, mpy))
    rows += chessboard_rows(cv2, a.repeats, mpy)
    mver = "no mrcal" if mpy is None else f"mrcal via {mpy} (LENSMODEL_OPENCV4, optimizer only, seeded)"
    print(f"OpenCV {cv2.__version__}; {mver}; one thread each; median of {a.repeats} calls; times in ms")
    head = ("set", "views", "points/view", "model", "psdcal ms", "OpenCV ms", "psdcal/OpenCV", "mrcal ms", "psdcal/mrcal",
            "scipy ms", "psdcal/scipy")
    lines = [(r["set"], str(r["views"]), str(r["points"]), r["model"], f"{1e3 * r['psdcal']:.2f}", f"{1e3 * r['opencv']:.2f}",
              f"{r['psdcal'] / r['opencv']:.2f}",
              "-" if r.get("mrcal") is None else f"{1e3 * r['mrcal']:.2f}",
              "-" if r.get("mrcal") is None else f"{r['psdcal'] / r['mrcal']:.2f}",
              "-" if r["scipy"] is None else f"{1e3 * r['scipy']:.1f}",
              "-" if r["scipy"] is None else f"{r['psdcal'] / r['scipy']:.3f}") for r in rows]
    print_table(head, lines, a.markdown)
    opt = [r for r in rows if r.get("refine") is not None and r.get("mrcal") is not None]
    if opt:
        print("\noptimizers alone, like for like: psdcal refine() and mrcal.optimize() from the same closed-form seed, "
              "fx, fy, cx, cy, k1, k2, p1, p2 (LENSMODEL_OPENCV4)")
        print_table(("set", "views", "points/view", "psdcal refine ms", "mrcal ms", "refine/mrcal"),
                    [(r["set"], str(r["views"]), str(r["points"]), f"{1e3 * r['refine']:.2f}", f"{1e3 * r['mrcal']:.2f}",
                      f"{r['refine'] / r['mrcal']:.2f}") for r in opt], a.markdown)
    for r in rows:
        if r.get("psdcal_verdict") is not None:
            print(f"{r['set']}: with the verdict (its self-checks) {1e3 * r['psdcal_verdict']:.2f} ms = "
                  f"{r['psdcal_verdict'] / r['opencv']:.2f} x OpenCV")
    print(f"\ngrowth exponent of psdcal's time in views (14 points, 30 views and up): {growth_exponent(rows):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
