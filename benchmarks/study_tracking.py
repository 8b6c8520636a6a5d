#!/usr/bin/env python3
"""The tracker's checks and sigmas, on an independent simulator and on the Lighthouse flights.

Part 1 (simulation): scenes of 3 emitters x 200 measurements (d = 3, 5-20 ms
apart, measurement covariances of a few mm^2), each path a continuous
white-noise acceleration of density q = 1e6 mm^2/s^3 integrated here on a
0.25 ms grid (not with the filter's matrices).  For the filter given q,
4 q and q / 4: the mean state NEES (6 expected) with its standard error over
scenes, the mean NIS of the used rows (3 expected), and how often each check
(``track_nis``, ``track_gated``) fails: the false-alarm rate with the right
q, the detection rate with the wrong ones.

Part 2 (real data, with ``--lighthouse DIR``: the ``lighthouse-lh1`` folder of
the shared data, which is not redistributed with the project): the
Crazyflie's own position estimate of the two flights as measurements
(sigma: its scatter at rest in the five stationary logs), tracked with
``--q auto``'s factor; the error against motion capture after a rigid
transform fitted on alternate 10 s blocks and scored on the others, raw and
tracked, with the statuses and restarts.

Usage::

    .venv/bin/python benchmarks/study_tracking.py [--scenes 200] [--seed0 0] [--lighthouse DIR] [--markdown]

Without ``--lighthouse`` the flights are read from ``lighthouse-lh1`` of the shared data folder beside the
repository when it is there (``--no-lighthouse``: never); otherwise that table is skipped.
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/_table.py
from _table import print_skipped  # noqa: E402

H_S = 2.5e-4
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import _lighthouse  # noqa: E402

#: the Lighthouse data where the tests look for it: the shared data folder beside the repository
LIGHTHOUSE = _lighthouse.ROOT


def scene(rng, *, n_emitters=3, n=200, d=3, q=1e6, sigma_v=500.0):
    ts, ems, zs, Rs, truth = [], [], [], [], []
    for e in range(n_emitters):
        steps = np.cumsum(rng.integers(20, 81, n))
        v = rng.normal(0.0, sigma_v, d) + np.vstack(
            [np.zeros((1, d)), np.cumsum(rng.normal(0.0, np.sqrt(q * H_S), (steps[-1], d)), 0)])
        p = rng.uniform(0, 3000, d) + np.vstack([np.zeros((1, d)), np.cumsum(0.5 * (v[1:] + v[:-1]) * H_S, 0)])
        A = rng.normal(size=(n, d, d))
        R = A @ A.transpose(0, 2, 1) * rng.uniform(0.5, 4.0, (n, 1, 1)) + 0.2 * np.eye(d)
        ts.append(steps * H_S)
        ems += [f"e{e}"] * n
        zs.append(p[steps] + np.einsum("nij,nj->ni", np.linalg.cholesky(R), rng.normal(size=(n, d))))
        Rs.append(R)
        truth.append(np.hstack([p[steps], v[steps]]))
    t = np.concatenate(ts)
    o = np.argsort(t, kind="stable")
    return t[o], np.array(ems, dtype=object)[o], np.concatenate(zs)[o], np.concatenate(Rs)[o], np.concatenate(truth)[o]


def simulation(n_scenes: int, seed0: int) -> None:
    from psdcal.measure.tracking import TrackConfig, track

    q = 1e6
    rows = {f: {"nees": [], "nis": [], "nis_fail": 0, "gated_fail": 0} for f in (1.0, 4.0, 0.25)}
    for k in range(n_scenes):
        t, em, z, R, truth = scene(np.random.default_rng(seed0 + k), q=q)
        for f, acc in rows.items():
            res = track(t, em, z, R, TrackConfig(q=q * f, init_sigma_v=500.0))
            u = res.used
            err = np.hstack([res.p, res.v])[u] - truth[u]
            acc["nees"].append(np.mean(np.einsum("ni,nij,nj->n", err, np.linalg.inv(res.cov[u]), err)))
            acc["nis"].append(np.mean(res.nis[res.status == "ok"]))
            c = {c.name: c.passed for c in res.checks}
            acc["nis_fail"] += c["track_nis"] is False
            acc["gated_fail"] += c["track_gated"] is False
    print(f"simulation: {n_scenes} scenes x 3 emitters x 200 measurements (d = 3, q = {q:g} mm^2/s^3)")
    print("<!-- table: sim -->")
    print("| filter q | mean NEES (6) | mean NIS (3) | track_nis fails | track_gated fails |")
    print("|---|---|---|---|---|")
    for f, acc in rows.items():
        ne, ni = np.array(acc["nees"]), np.array(acc["nis"])
        se = lambda a: a.std(ddof=1) / np.sqrt(len(a))  # noqa: E731
        print(f"| {f:g} q | {ne.mean():.3f} +- {se(ne):.3f} | {ni.mean():.3f} +- {se(ni):.3f} | "
              f"{acc['nis_fail']}/{n_scenes} | {acc['gated_fail']}/{n_scenes} |")


def _kabsch(A, B):
    ca, cb = A.mean(0), B.mean(0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    Rm = Vt.T @ D @ U.T
    return Rm, cb - Rm @ ca


def lighthouse(folder: Path) -> None:
    from dataclasses import replace

    from psdcal.measure.tracking import TrackConfig, estimate_q_factor, track

    if not folder.is_dir():
        raise SystemExit(f"lighthouse: {folder} is not a folder")

    def load(f):
        return np.loadtxt(f, delimiter=",", skiprows=1)

    rest = []
    for k in range(5):
        a = load(folder / f"lh1_crossingBeam_jitter_0{k}" / "crazyflie_estimate.csv")
        a = a[(a[:, 0] > 0) & (a[:, 0] < 11.9)]
        rest.append(a[:, 1:4].std(0) * 1000.0)
    sigma = float(np.sqrt(np.mean(np.square(rest))))
    print(f"lighthouse: measurement sigma {sigma:.3f} mm per axis (the estimate's scatter at rest, 5 logs)")
    print()
    print("<!-- table: lighthouse -->")
    print(f"| flight (sigma {sigma:.2f} mm per axis) | rows | q auto (mm^2/s^3) | gaps re-acquired | jumps | gated | raw p95 / median (mm) | "
          "tracked p95 / median (mm) | max raw / tracked (mm) | scored rows (tracked / all) | restart distances (mm) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for flight in ("lh1_crossingBeam_flight_00", "lh1_crossingBeam_flight_01"):
        e, m = load(folder / flight / "crazyflie_estimate.csv"), load(folder / flight / "mocap.csv")
        t, z = e[:, 0], e[:, 1:4] * 1000.0
        n = len(t)
        R = np.broadcast_to(sigma**2 * np.eye(3), (n, 3, 3)).copy()
        cfg = TrackConfig(q=1e6)
        cfg = replace(cfg, q=cfg.q * estimate_q_factor(t, ["cf"] * n, z, R, cfg))
        res = track(t, ["cf"] * n, z, R, cfg)
        inm = (t > m[0, 0]) & (t < m[-1, 0])
        truth = np.stack([np.interp(t, m[:, 0], m[:, k]) for k in (1, 2, 3)], -1) * 1000.0
        blk = np.floor(t / 10) % 2 == 0
        Rm, tm = _kabsch(z[inm & blk], truth[inm & blk])
        score = inm & ~blk
        er = np.linalg.norm(z @ Rm.T + tm - truth, axis=1)[score]
        su = score & res.used
        et = np.linalg.norm(res.p @ Rm.T + tm - truth, axis=1)[su]
        st = res.status
        print(f"| {flight} | {n} | {cfg.q:.3g} | {(st == 'gap').sum()} | {(st == 'jump').sum()} | "
              f"{(st == 'gated').sum()} | {np.percentile(er, 95):.1f} / {np.median(er):.1f} | "
              f"{np.percentile(et, 95):.1f} / {np.median(et):.1f} | {er.max():.1f} / {et.max():.1f} | "
              f"{su.sum()} / {score.sum()} | {np.nanmin(res.restart_distance):.0f} to "
              f"{np.nanmax(res.restart_distance):.0f} |")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=200)
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--lighthouse", type=Path, default=None, help="the lighthouse-lh1 data folder")
    ap.add_argument("--no-lighthouse", action="store_true", help="skip the flights even when the data are there")
    ap.add_argument("--quick", action="store_true", help="a smoke run: 10 scenes")
    ap.add_argument("--markdown", action="store_true", help="(the tables are Markdown; ids sim, lighthouse)")
    args = ap.parse_args(argv)
    if args.quick:
        args.scenes = 10
    if args.scenes > 1:
        simulation(args.scenes, args.seed0)
    print()
    folder = args.lighthouse if args.lighthouse is not None else LIGHTHOUSE
    if args.no_lighthouse:
        print_skipped("lighthouse", "run with --no-lighthouse", True)
    elif args.lighthouse is None and not folder.is_dir():
        print_skipped("lighthouse", "lighthouse-lh1 is not in the shared data folder", True)
    else:
        lighthouse(folder)


if __name__ == "__main__":
    main()
