#!/usr/bin/env python3
"""Self-calibration of a room from a moving tag (``psdcal.measure.selfcal``): NEES, false alarms, time.

Simulated rooms (the independent simulator of ``tests/test_selfcal.py``): 2-6
sensors on a ring 3 m out, a rigid tag (random 3D or a planar deck 120 x 60 mm)
moving along a smooth path of 10-60 s while turning, angles in the three
conventions with 1e-4 rad noise. Reported: the mean NEES of the sensor poses
(6 dof each, in the reference sensor's frame) with its Monte Carlo standard
error, by number of sensors; the chi2 check's false-alarm rate (design 0.1 %);
the time of one self-calibration of a 60 s path at 30 Hz; and, when the
Lighthouse data the tests read (``lighthouse-lh1``) is present, the deck centre's error with
self-calibrated stations against the Crazyflie's own estimate.

Usage::

    .venv/bin/python benchmarks/study_selfcal.py [--rooms 300] [--steps 15 60] [--markdown]
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import sys
import importlib.util
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))  # benchmarks/_table.py
from _table import print_skipped, print_table  # noqa: E402


def _sim():
    spec = importlib.util.spec_from_file_location("_selfcal_sim", REPO / "tests" / "test_selfcal.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def rooms(n_rooms: int, steps: tuple, tmp: Path) -> dict:
    from psdcal.measure.angles_table import read_angles
    from psdcal.measure.selfcal import self_calibrate
    from psdcal.measure.tagpose import read_tag

    sim = _sim()
    by_k = {k: [] for k in range(2, 7)}
    passed, times = 0, []
    for seed in range(n_rooms):
        rng = np.random.default_rng(50_000 + seed)
        K = int(rng.integers(2, 7))
        room = sim.simulate_room(rng, K, rng.uniform(10, 60), int(rng.integers(steps[0], steps[1] + 1)),
                                 convention=("psdcal", "tangent", "azel")[seed % 3], planar=seed % 2 == 0)
        table = read_angles(sim.write_angles(tmp / "a.csv", room))
        tag = read_tag(sim.write_tag(tmp / "t.csv", room["B"]))
        t0 = time.perf_counter()
        res = self_calibrate(table, tag)
        times.append(time.perf_counter() - t0)
        by_k[K] += sim.nees_in_reference(res, room)
        passed += bool(res.check.passed)
    return {"by_k": by_k, "passed": passed, "n": n_rooms, "times": times}


def timing_60s(tmp: Path, sensors: int = 2, rate_hz: float = 30.0) -> float:
    from psdcal.measure.angles_table import read_angles
    from psdcal.measure.selfcal import self_calibrate
    from psdcal.measure.tagpose import read_tag

    sim = _sim()
    rng = np.random.default_rng(7)
    room = sim.simulate_room(rng, sensors, 60.0, int(60 * rate_hz), planar=True)
    table = read_angles(sim.write_angles(tmp / "a.csv", room))
    tag = read_tag(sim.write_tag(tmp / "t.csv", room["B"]))
    t0 = time.perf_counter()
    self_calibrate(table, tag)
    return time.perf_counter() - t0


#: A Lighthouse V1 station sweeps its first angle 1/120 s before its second (the logged time is the second's).
SWEEPS = {"0": (-1 / 120, 0.0), "1": (-1 / 120, 0.0)}


def lighthouse(folder: str = "lh1_crossingBeam_flight_00", offsets: dict | None = None) -> dict | None:
    """Stations from the deck alone; the deck centre vs mocap (similarity fitted on alternate 10 s blocks)."""
    from psdcal.measure.angles_table import align_to_sensor
    from psdcal.measure.selfcal import self_calibrate
    from psdcal.measure.tagpose import KnownSensor, tag_poses

    sim = _sim()
    data = sim.DATA / folder  # where tests/test_selfcal.py finds the Lighthouse data
    if not (data / "angles.csv").exists():
        return None
    tab, deck = sim._lighthouse(folder)
    al = align_to_sensor(tab, "1", max_gap_s=0.05, offsets_s=offsets)
    t0 = time.perf_counter()
    res = self_calibrate(al, deck)
    dt = time.perf_counter() - t0
    tp = tag_poses(al, deck, [KnownSensor(nm, res.R[i], res.c_mm[i], res.cov[i]) for i, nm in enumerate(res.names)])
    mc, cf = sim._csv(data / "mocap.csv"), sim._csv(data / "crazyflie_estimate.csv")
    mt, M = mc["t_s"], np.c_[mc["X_m"], mc["Y_m"], mc["Z_m"]] * 1000

    def mocap_at(ts):
        j = np.clip(np.searchsorted(mt, ts), 1, len(mt) - 1)
        w = (ts - mt[j - 1]) / (mt[j] - mt[j - 1])
        return (1 - w)[:, None] * M[j - 1] + w[:, None] * M[j], (ts > mt[0]) & (ts < mt[-1]) & (mt[j] - mt[j - 1] < 0.02)

    truth, ok = mocap_at(tp.t_s)
    ct, C = cf["t_s"], np.c_[cf["X_m"], cf["Y_m"], cf["Z_m"]] * 1000
    i = np.clip(np.searchsorted(ct, tp.t_s), 1, len(ct) - 1)
    i = np.where(np.abs(ct[i - 1] - tp.t_s) < np.abs(ct[i] - tp.t_s), i - 1, i)
    ok &= (np.abs(ct[i] - tp.t_s) < 0.005) & (cf["delta_m"][i] < 0.1)
    out = {"folder": folder, "time_s": dt, "steps": res.n_steps, "chi2_per_dof": res.chi2 / res.dof, "halves": []}
    even = np.floor(tp.t_s / 10).astype(int) % 2 == 0
    for fit_even in (True, False):
        fit = ok & (even == fit_even)
        score = ok & (even != fit_even)
        s, R, t = sim._similarity(tp.p_mm[fit], truth[fit])
        e1 = np.linalg.norm(tp.p_mm[score] @ R.T * s + t - truth[score], axis=1)
        Rc, tc = sim._rigid(C[i][fit], truth[fit])
        e2 = np.linalg.norm(C[i][score] @ Rc.T + tc - truth[score], axis=1)
        # also a clock offset between the angles and the mocap, chosen on the fitting half only (2 ms grid)
        best = None
        for d in np.arange(-0.03, 0.0301, 0.002):
            tr, okd = mocap_at(tp.t_s + d)
            f = fit & okd
            sd, Rd, td = sim._similarity(tp.p_mm[f], tr[f])
            r = float(np.median(np.linalg.norm(tp.p_mm[f] @ Rd.T * sd + td - tr[f], axis=1)))
            if best is None or r < best[0]:
                best = (r, d, sd, Rd, td)
        _, d, sd, Rd, td = best
        tr, okd = mocap_at(tp.t_s + d)
        sc = score & okd
        e3 = np.linalg.norm(tp.p_mm[sc] @ Rd.T * sd + td - tr[sc], axis=1)
        out["halves"].append({"fit_on": "even blocks" if fit_even else "odd blocks", "n": int(score.sum()),
                              "scale": s, "median_mm": float(np.median(e1)), "p95_mm": float(np.percentile(e1, 95)),
                              "cf_median_mm": float(np.median(e2)), "cf_p95_mm": float(np.percentile(e2, 95)),
                              "clock_offset_s": float(d), "median_clock_mm": float(np.median(e3)),
                              "p95_clock_mm": float(np.percentile(e3, 95))})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rooms", type=int, default=300)
    ap.add_argument("--steps", type=int, nargs=2, default=(15, 60))
    ap.add_argument("--no-lighthouse", action="store_true")
    ap.add_argument("--no-timing", action="store_true", help="skip the 60 s paths' timing")
    ap.add_argument("--quick", action="store_true", help="a smoke run: 12 rooms, no timing")
    ap.add_argument("--markdown", action="store_true", help="the tables as Markdown (ids: sim, timing, lighthouse)")
    a = ap.parse_args(argv)
    if a.quick:
        a.rooms, a.no_timing = 12, True
    md = a.markdown
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        r = rooms(a.rooms, tuple(a.steps), tmp)
        all_nees = np.concatenate([np.array(v) for v in r["by_k"].values() if v])

        def cell(v):
            v = np.asarray(v)
            se = v.std(ddof=1) / np.sqrt(len(v)) if len(v) > 1 else float("nan")
            return [str(len(v)), f"{v.mean():.2f} +- {se:.2f}"]

        lines = [[f"{k}", *cell(v)] for k, v in r["by_k"].items() if v]
        lines.append(["all", *cell(all_nees)])
        print(f"{r['n']} rooms, {a.steps[0]}-{a.steps[1]} steps; the chi2 check passed in {r['passed']} of {r['n']} "
              f"rooms; median time {np.median(r['times']):.2f} s")
        print_table(["sensors", "sensor poses", "mean NEES (6 dof, ideal 6) +- its Monte Carlo standard error"],
                    lines, md, "sim")
        print()
        print_table(["rooms", "steps", "chi2 check passed (design false-alarm rate 0.1 %)"],
                    [[str(r["n"]), f"{a.steps[0]}-{a.steps[1]}", f"{r['passed']} of {r['n']}"]], md, "sim_check")
        print()
        if a.no_timing:
            print_skipped("timing", "run with --no-timing", md)
        else:
            print_table(["60 s path at 30 Hz", "self-calibration (s, wall)"],
                        [[f"{k} sensors", f"{timing_60s(tmp, k):.2f}"] for k in (2, 4)], md, "timing")
    runs = [(f, o) for f in ("lh1_crossingBeam_flight_00", "lh1_crossingBeam_flight_01") for o in (None, SWEEPS)]
    lines, missing = [], False
    for folder, offsets in () if a.no_lighthouse else runs:
        lh = lighthouse(folder, offsets)
        if lh is None:
            missing = True
            break
        how = "sweep times 1/120 s apart" if offsets else "one time per row"
        for h in lh["halves"]:
            lines.append([f"`{folder.replace('lh1_crossingBeam_', '')}`", how, f"{lh['chi2_per_dof']:.1f}",
                          h["fit_on"], str(h["n"]), f"{h['median_mm']:.2f} / {h['p95_mm']:.2f}", f"{h['scale']:.4f}",
                          f"{h['cf_median_mm']:.2f} / {h['cf_p95_mm']:.2f}", f"{h['median_mm'] / h['cf_median_mm']:.2f}",
                          f"{1000 * h['clock_offset_s']:+.0f} ms: {h['median_clock_mm']:.2f} / {h['p95_clock_mm']:.2f}"])
    print()
    if a.no_lighthouse:
        print_skipped("lighthouse", "run with --no-lighthouse", md)
    elif missing:
        print_skipped("lighthouse", "lighthouse-lh1 is not in the shared data folder", md)
    else:
        print_table(["flight", "angle times", "chi2/dof", "frame fitted on", "steps scored",
                     "psdcal selfcal: median / p95 (mm)", "scale of the fit", "Crazyflie's estimate: median / p95 (mm)",
                     "ratio of medians", "with a clock offset fitted on that half: median / p95 (mm)"], lines, md,
                    "lighthouse")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
