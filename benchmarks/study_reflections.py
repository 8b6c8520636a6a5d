#!/usr/bin/env python3
"""How often a reflection is found and left out, and how often a correct row is flagged (issue 20, item 4).

Each room: a box of 4-8 x 3-6 x 2.5-3.5 m, 2-6 sensors (``psdcal.study.recordings.room_sensors``,
Lens 2), ``--points`` emitter positions at random in the room's lower half, one mirror (the floor,
or a wall) with a power attenuation drawn log-uniform in 0.05-0.5 (``--att-min/--att-max``) applied to ONE sensor (a specular path seen from
one place). Rays are simulated at the ray level: the direct ray, plus for the reflected sensor the
image source's ray, combined as a PSD does (the power-weighted centroid, ``--mode centroid``) or
reported outright (a ghost, ``--mode ghost``); Gaussian noise ``--sigma-n`` on every ray.
Each row is screened by :func:`psdcal.measure.reflections.screen_rays` twice: with the reflection,
and with the direct rays only (the false alarms).

A reflection *counts* (is a trial) where the reflected sensor sees both the emitter and its image.
Rates are split by the number of sensors that see the emitter (2, and 3 or more), and by the bias of
the reflected ray in its own sigmas.

Usage::

    .venv/bin/python benchmarks/study_reflections.py [--rooms 400] [--points 30] [--mode centroid] [--att-min 0.05 --att-max 0.5]
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/_table.py
from _table import print_table  # noqa: E402


def one_room(seed: int, points: int, sigma_n: float, mode: str, alpha: float, att=(0.05, 0.5)):
    from psdcal.measure._geometry import project_world
    from psdcal.measure.positioning import triangulate
    from psdcal.measure.reflections import screen_rays
    from psdcal.model.projection import R_from_r
    from psdcal.study.recordings import _in_view, model, room_sensors
    from psdcal.study.reflections import Reflector, observed_rays, sensor_centre_mm

    rng = np.random.default_rng(seed)
    room = np.array([rng.uniform(4000, 8000), rng.uniform(3000, 6000), rng.uniform(2500, 3500)])
    k = int(rng.integers(2, 7))
    m = model()
    sensors = room_sensors(k, room, m)
    # the mirror: the floor half the time, else one of the four walls
    if rng.uniform() < 0.5:
        ax, v = 2, 0.0
    else:
        ax = int(rng.integers(0, 2))
        v = 0.0 if rng.uniform() < 0.5 else room[ax]
    normal = np.zeros(3)
    normal[ax] = 1.0 if room[ax] / 2 > v else -1.0
    point = np.zeros(3)
    point[ax] = v
    j_ref = int(rng.integers(0, k))
    mirror = Reflector(tuple(point), tuple(normal), float(math.exp(rng.uniform(math.log(att[0]), math.log(att[1])))), (sensors[j_ref].name,))
    P = np.stack([rng.uniform(0.1, 0.9, points) * room[0], rng.uniform(0.1, 0.9, points) * room[1],
                  rng.uniform(0.1, 0.5, points) * room[2]], -1)
    R = np.stack([R_from_r(s.rvec) for s in sensors])
    t = np.stack([np.asarray(s.tvec_mm, float) for s in sensors])
    n_dir = np.full((k, points, 2), np.nan)
    n_obs = np.full((k, points, 2), np.nan)
    bias = np.zeros(points)
    counts = np.zeros(points, bool)
    for j, s in enumerate(sensors):
        seen = _in_view(s.model, P, s.rvec, s.tvec_mm, 1.0)
        nd, _ = project_world(P, s.rvec, s.tvec_mm)
        nd = np.where(seen[:, None], nd, np.nan)
        n_dir[j] = nd
        n_obs[j] = nd
        if j == j_ref:
            Pi = mirror.mirror(P)
            seen_i = _in_view(s.model, Pi, s.rvec, s.tvec_mm, 1.0)
            ni, _ = project_world(Pi, s.rvec, s.tvec_mm)
            w = mirror.weight(P, sensor_centre_mm(s.rvec, s.tvec_mm)) * seen_i * seen
            n_obs[j] = observed_rays(nd, np.where(seen_i[:, None], ni, np.nan), w, mode)
            counts = seen & (w > 0)
            bias = np.where(counts, np.linalg.norm(n_obs[j] - nd, axis=-1) / sigma_n, 0.0)
    noise = sigma_n * rng.standard_normal(n_dir.shape)
    cov = np.broadcast_to(sigma_n ** 2 * np.eye(2), (k, points, 2, 2)).copy()
    m_seen = np.sum(np.all(np.isfinite(n_dir), -1), 0)
    clean = screen_rays(n_dir + noise, cov, R, t, alpha=alpha)
    dirty = screen_rays(n_obs + noise, cov, R, t, alpha=alpha)
    err = np.linalg.norm(dirty.tri.p_w_mm - P, axis=-1)
    err_all = np.linalg.norm(triangulate(n_obs + noise, cov, R, t).p_w_mm - P, axis=-1)
    return dict(m=m_seen, counts=counts, bias=bias, j_ref=j_ref, clean_flag=clean.flag, clean_left=clean.left_out,
                flag=dirty.flag, left=dirty.left_out, err=err, err_kept=err_all)


def rate(x):
    x = np.asarray(x, bool)
    n = len(x)
    if n == 0:
        return {"n": 0}
    p = float(x.mean())
    return {"n": n, "rate": p, "se": math.sqrt(max(p * (1 - p), 1.0 / n) / n)}


def study(a, mode: str, att: tuple) -> dict:
    """The rates of ``--rooms`` rooms for one reflection model (``centroid``/``ghost``) and attenuation range."""
    t0 = time.time()
    rows = [one_room(a.seed0 + i, a.points, a.sigma_n, mode, a.alpha, att) for i in range(a.rooms)]
    cat = {key: np.concatenate([np.atleast_1d(r[key]) if np.ndim(r[key]) else np.full(len(r["m"]), r[key])
                                for r in rows]) for key in rows[0]}
    m, c = cat["m"], cat["counts"]
    found = cat["left"] == cat["j_ref"]
    flagged = cat["clean_flag"] != ""
    big = cat["bias"] >= 10
    out = {
        "rooms": a.rooms, "points_per_room": a.points, "sigma_n": a.sigma_n, "mode": mode, "att": list(att), "alpha": a.alpha,
        "rooms_with_a_counted_reflection": int(sum(bool(np.any(r["counts"] & (r["m"] >= 2))) for r in rows)),
        "k>=3: reflected sensor left out": rate(found[c & (m >= 3)]),
        "k>=3, bias >= 10 sigma: reflected sensor left out": rate(found[c & (m >= 3) & big]),
        "k>=4, bias >= 10 sigma: reflected sensor left out": rate(found[c & (m >= 4) & big]),
        "k==3, bias >= 10 sigma: reflected sensor left out": rate(found[c & (m == 3) & big]),
        "k>=3: another sensor left out (wrong)": rate(((cat["left"] >= 0) & ~found)[c & (m >= 3)]),
        "k>=3: ambiguous": rate((cat["flag"] == "ambiguous")[c & (m >= 3)]),
        "k>=3: unresolved": rate((cat["flag"] == "unresolved")[c & (m >= 3)]),
        "k>=3: nothing found": rate((cat["flag"] == "")[c & (m >= 3)]),
        "k>=3, nothing found: median bias (sigma)": float(np.median(cat["bias"][c & (m >= 3) & (cat["flag"] == "")]))
        if np.any(c & (m >= 3) & (cat["flag"] == "")) else None,
        "k==2: flagged ambiguous": rate((cat["flag"] == "ambiguous")[c & (m == 2)]),
        "k==2, bias >= 10 sigma: flagged ambiguous": rate((cat["flag"] == "ambiguous")[c & (m == 2) & big]),
        "k==2: a sensor left out (must be 0)": int(((cat["left"] >= 0) & c & (m == 2)).sum()),
        "no reflection: any flag (false alarm), k>=3": rate(flagged[m >= 3]),
        "no reflection: any flag (false alarm), k==2": rate(flagged[m == 2]),
        "no reflection: a sensor left out, k>=3": rate((cat["clean_left"] >= 0)[m >= 3]),
        "k>=3, left out: median position error mm (screened / every ray kept)":
            [float(np.median(cat["err"][c & (m >= 3) & found])), float(np.median(cat["err_kept"][c & (m >= 3) & found]))]
            if np.any(c & (m >= 3) & found) else None,
        "k>=3: reflected sensor left out, by bias (sigma) bins": {
            f"[{lo:g}, {hi:g})": rate(found[c & (m >= 3) & (cat["bias"] >= lo) & (cat["bias"] < hi)])
            for lo, hi in ((0, 3), (3, 5), (5, 10), (10, 30), (30, math.inf))},
        "k==2: flagged ambiguous, by bias (sigma) bins": {
            f"[{lo:g}, {hi:g})": rate((cat["flag"] == "ambiguous")[c & (m == 2) & (cat["bias"] >= lo) & (cat["bias"] < hi)])
            for lo, hi in ((0, 3), (3, 5), (5, 10), (10, 30), (30, math.inf))},
        "seconds": round(time.time() - t0, 1),
    }
    return out


def _pct(r) -> str:
    if not r["n"]:
        return "-"
    rate, se = 100 * r["rate"], 100 * r["se"]
    return f"{rate:.{2 if rate < 1 else 1}f} +- {se:.{2 if se < 0.1 else 1}f} %"


def markdown(a) -> None:
    """The two tables of docs/guide/positioning.md#reflections: strong reflections (centroid and ghost), weak ones by bias."""
    strong = {mode: study(a, mode, (a.att_min, a.att_max)) for mode in ("centroid", "ghost")}
    c, g = strong["centroid"], strong["ghost"]
    print(f"{a.rooms} rooms; rooms with a reflection that the sensor sees: {c['rooms_with_a_counted_reflection']}")

    def both(key, fmt=_pct):
        return [fmt(c[key]), fmt(g[key])]

    n3, n4, n33 = (c[k]["n"] for k in ("k>=3: reflected sensor left out", "k>=4, bias >= 10 sigma: reflected sensor left out",
                                        "k==3, bias >= 10 sigma: reflected sensor left out"))
    e = c["k>=3, left out: median position error mm (screened / every ray kept)"]
    eg = g["k>=3, left out: median position error mm (screened / every ray kept)"]
    lines = [
        [f"reflected sensor left out, 3 or more sensors see the emitter ({n3} rows)", *both("k>=3: reflected sensor left out")],
        [f"the same, bias >= 10 sigma, 4 or more sensors ({n4} rows)", *both("k>=4, bias >= 10 sigma: reflected sensor left out")],
        [f"the same, bias >= 10 sigma, exactly 3 sensors ({n33} rows)", *both("k==3, bias >= 10 sigma: reflected sensor left out")],
        ["3 or more sensors: `ambiguous`", *both("k>=3: ambiguous")],
        ["another sensor left out instead", *both("k>=3: another sensor left out (wrong)")],
        [f"two sensors: flagged `ambiguous` ({c['k==2: flagged ambiguous']['n']} rows)", *both("k==2: flagged ambiguous")],
        ["two sensors: a sensor left out (chosen)", str(c["k==2: a sensor left out (must be 0)"]),
         str(g["k==2: a sensor left out (must be 0)"])],
        [f"no reflection: any flag, 3 or more sensors ({c['no reflection: any flag (false alarm), k>=3']['n']} rows)",
         _pct(c["no reflection: any flag (false alarm), k>=3"]), ""],
        [f"no reflection: any flag, two sensors ({c['no reflection: any flag (false alarm), k==2']['n']} rows)",
         _pct(c["no reflection: any flag (false alarm), k==2"]), ""],
        ["median position error of the rows left out: screened / every ray kept",
         f"{e[0]:.2f} mm / {e[1]:.0f} mm" if e else "-", f"{eg[0]:.2f} mm / {eg[1]:.0f} mm" if eg else "-"],
    ]
    print_table(["", "centroid (a PSD)", "ghost"], lines, True, "strong")
    weak = study(a, "centroid", (a.weak_min, a.weak_max))
    bins3 = weak["k>=3: reflected sensor left out, by bias (sigma) bins"]
    bins2 = weak["k==2: flagged ambiguous, by bias (sigma) bins"]
    label = {"[0, 3)": "< 3 sigma", "[3, 5)": "3-5 sigma", "[5, 10)": "5-10 sigma", "[10, 30)": "10-30 sigma",
             "[30, inf)": "> 30 sigma"}
    print()
    print(f"weak reflections (attenuation {a.weak_min:g}-{a.weak_max:g}): another sensor left out "
          f"{_pct(weak['k>=3: another sensor left out (wrong)'])}; nothing found: median bias "
          f"{weak['k>=3, nothing found: median bias (sigma)']}")
    print_table([f"bias of the ray (attenuation {a.weak_min:g}-{a.weak_max:g})", "rows (3 or more sensors)",
                 "reflected sensor left out", "two sensors: `ambiguous`"],
                [[label[b], str(bins3[b]["n"]), _pct(bins3[b]), _pct(bins2[b])] for b in label], True, "weak")
    print()
    print_table(["weak reflections, 3 or more sensors", "rate"],
                [["another sensor left out", _pct(weak["k>=3: another sensor left out (wrong)"])],
                 ["nothing found: median bias of the ray (sigma)",
                  f"{weak['k>=3, nothing found: median bias (sigma)']:.2g}"
                  if weak["k>=3, nothing found: median bias (sigma)"] is not None else "-"]], True, "weak_other")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rooms", type=int, default=400)
    ap.add_argument("--points", type=int, default=30)
    ap.add_argument("--sigma-n", type=float, default=2e-4, help="ray noise, normalised units (~rad)")
    ap.add_argument("--mode", choices=("centroid", "ghost"), default="centroid")
    ap.add_argument("--alpha", type=float, default=1e-3)
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--att-min", type=float, default=0.05, help="attenuation drawn log-uniform in [min, max]")
    ap.add_argument("--att-max", type=float, default=0.5)
    ap.add_argument("--weak-min", type=float, default=0.0002, help="--markdown: the weak reflections' attenuation range")
    ap.add_argument("--weak-max", type=float, default=0.02)
    ap.add_argument("--json", default=None, help="write the rates here")
    ap.add_argument("--quick", action="store_true", help="a smoke run: 20 rooms")
    ap.add_argument("--markdown", action="store_true",
                    help="the tables of the docs (both modes, then weak reflections by bias; ids strong, weak, weak_other)")
    a = ap.parse_args()
    if a.quick:
        a.rooms = 20
    if a.markdown:
        markdown(a)
        return
    out = study(a, a.mode, (a.att_min, a.att_max))
    print(json.dumps(out, indent=1))
    if a.json:
        with open(a.json, "w", encoding="utf-8") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
