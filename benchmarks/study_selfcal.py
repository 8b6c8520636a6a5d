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
self-calibrated stations against the Crazyflie's own estimate, and whether
the deck's stated covariance covers its difference from the motion capture
once the reference's own unknowns (frame, clock offset, the marker's lever
arm) are fitted on half of the flight (scored on the other half), without
and with the ``tag_pose_common_mode`` term; on simulated rooms, that check's
false-alarm rate and the positions' NEES, on correct data and with a shared
error put in.

Usage::

    .venv/bin/python benchmarks/study_selfcal.py [--rooms 300] [--steps 15 60] [--tag-rooms 200]
        [--common-sigma-rad 3e-4] [--no-lighthouse] [--no-coverage] [--markdown]
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


def _skew(v):
    Z = np.zeros(v.shape[:-1] + (3, 3))
    Z[..., 0, 1], Z[..., 0, 2], Z[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    Z[..., 1, 0], Z[..., 2, 0], Z[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return Z


def _reference_fit(sim, p, Q, truth, lever: bool):
    """The mocap point ~ s R (p + Q l) + t: similarity (s, R, t) and, with ``lever``, the marker's lever arm
    ``l`` (mm, deck frame) by alternating least squares; points off by > 5 x the median left out (3 rounds).
    Returns ``s, R, t, l, mean squared error of the points kept``."""
    use = np.ones(len(p), bool)
    ell = np.zeros(3)
    for _ in range(4):
        for _ in range(30 if lever else 1):
            s, R, t = sim._similarity((p + Q @ ell)[use], truth[use])
            if not lever:
                break
            A = s * np.einsum("ij,tjk->tik", R, Q[use]).reshape(-1, 3)
            new = np.linalg.lstsq(A, (truth[use] - t - s * p[use] @ R.T).reshape(-1), rcond=None)[0]
            done = np.linalg.norm(new - ell) < 1e-5
            ell = new
            if done:
                break
        s, R, t = sim._similarity((p + Q @ ell)[use], truth[use])
        err = np.linalg.norm((p + Q @ ell) @ R.T * s + t - truth, axis=1)
        use = err < 5 * np.median(err)
    return s, R, t, ell, float(np.mean(err[use] ** 2))


def score_against_mocap(sim, tp, mocap_at, ok, even, *, lever: bool, clock: bool) -> list:
    """Fit the reference's own unknowns on alternate 10 s blocks, score psdcal's deck on the others.

    Unknowns of the reference: the frame (similarity), and optionally the
    clock offset between the angles and the mocap (1 ms grid, +-30 ms) and
    the lever arm from the deck's origin to the mocap's marker point
    (3-vector in the deck's frame, turned by psdcal's attitude). Scored: the
    error of the marker point, and NEES (3 dof) of its covariance from
    psdcal's stated one (position and attitude, through the lever arm);
    NEES of step-to-step differences (the part of the error that changes
    between consecutive steps) and the rank correlation of consecutive errors.
    """
    from psdcal.model.projection import R_from_r

    Q = np.stack([R_from_r(r) for r in tp.rvec])
    out = []
    for fit_even in (True, False):
        fit = ok & (even == fit_even)
        best = None
        for d in (np.arange(-0.03, 0.03005, 0.001) if clock else [0.0]):
            tr, okd = mocap_at(tp.t_s + d)
            f = fit & okd
            r = _reference_fit(sim, tp.p_mm[f], Q[f], tr[f], lever)
            if best is None or r[-1] < best[0][-1]:
                best = (r, d)
        (s, R, t, ell, _), d = best
        tr, okd = mocap_at(tp.t_s + d)
        sc = ok & (even != fit_even) & okd
        Ql = Q[sc] @ ell
        e = (tp.p_mm[sc] + Ql) @ R.T * s + t - tr[sc]
        J = np.concatenate([-_skew(Ql), np.broadcast_to(np.eye(3), (len(Ql), 3, 3))], axis=2)
        C = s * s * R @ (J @ tp.cov[sc] @ np.swapaxes(J, 1, 2)) @ R.T
        nees = np.einsum("ti,ti->t", e, np.linalg.solve(C, e[..., None])[..., 0])
        nxt = np.flatnonzero(np.diff(np.flatnonzero(sc)) == 1)  # consecutive steps both scored
        de = e[nxt + 1] - e[nxt]
        dn = np.einsum("ti,ti->t", de, np.linalg.solve(C[nxt] + C[nxt + 1], de[..., None])[..., 0])
        rk = np.argsort(np.argsort(e, axis=0), axis=0).astype(float)
        rho = float(np.mean([np.corrcoef(rk[nxt, i], rk[nxt + 1, i])[0, 1] for i in range(3)]))
        en = np.linalg.norm(e, axis=1)
        out.append({"fit_on": "even blocks" if fit_even else "odd blocks", "n": int(sc.sum()), "scale": s,
                    "clock_offset_s": float(d), "lever_mm": ell.tolist(), "median_mm": float(np.median(en)),
                    "p95_mm": float(np.percentile(en, 95)), "nees_median": float(np.median(nees)),
                    "nees_mean": float(np.mean(nees)), "diff_nees_median": float(np.median(dn)),
                    "rank_corr_next": rho})
    return out


def roughness_mm(t_s, X, half: int = 4) -> np.ndarray:
    """Robust sd (mm, per axis) of each point about a cubic fitted to its ``2 half + 1`` neighbours in time
    (windows with a gap left out), corrected for the fit's own share: the white, step-to-step noise."""
    dt = float(np.median(np.diff(t_s)))
    out = []
    for i in range(half, len(t_s) - half):
        tt = t_s[i - half:i + half + 1] - t_s[i]
        if tt[-1] - tt[0] > (2 * half + 0.5) * dt:
            continue
        D = np.vander(tt, 4)
        out.append(X[i] - np.linalg.lstsq(D, X[i - half:i + half + 1], rcond=None)[0][-1])
    D = np.vander(np.arange(-half, half + 1.0), 4)
    h = (D @ np.linalg.pinv(D))[half, half]
    return 1.4826 * np.median(np.abs(np.array(out)), axis=0) / np.sqrt(1 - h)


def residual_time_correlation(al, deck, res, tp, max_lag: int = 60) -> tuple:
    """Lag-1 autocorrelation and integrated autocorrelation time (steps) of each sensor's mean whitened
    residual per step (its shared part), median over the sensors and the two direction coordinates."""
    from psdcal.measure._rigid import residuals_and_jacobians, whiteners
    from psdcal.measure.tagpose import observation_indices
    from psdcal.model.projection import R_from_r

    rows, k, e, t, times = observation_indices(al, deck, res.names)
    keep = np.isin(times[t], tp.t_s)
    rows, k, e, t = rows[keep], k[keep], e[keep], t[keep]
    t = np.searchsorted(tp.t_s, times[t])
    Q = np.stack([R_from_r(r) for r in tp.rvec])
    r = residuals_and_jacobians(res.R, res.c_mm, Q, tp.p_mm, deck.body_mm, k, t, e, al.n[rows],
                                whiteners(al.cov_n[rows]), jac=False)[0]
    T = len(tp.t_s)
    lag1, taus = [], []
    for kk in range(len(res.names)):
        m = k == kk
        cnt = np.bincount(t[m], minlength=T)
        for c in range(2):
            x = np.full(T, np.nan)
            x[cnt > 0] = np.bincount(t[m], r[m, c], minlength=T)[cnt > 0] / cnt[cnt > 0]
            x -= np.nanmean(x)
            ac = []
            for lag in range(1, max_lag):
                a, b = x[:-lag], x[lag:]
                g = np.isfinite(a) & np.isfinite(b)
                ac.append(np.sum(a[g] * b[g]) / np.sqrt(np.sum(a[g] ** 2) * np.sum(b[g] ** 2)))
            ac = np.array(ac)
            cut = int(np.argmax(ac < 0)) if np.any(ac < 0) else len(ac)
            lag1.append(ac[0])
            taus.append(1 + 2 * ac[:cut].sum())
    return float(np.median(lag1)), float(np.median(taus))


def lighthouse(folder: str = "lh1_crossingBeam_flight_00", offsets: dict | None = None,
               coverage: bool = True) -> dict | None:
    """Stations from the deck alone; the deck centre vs mocap (similarity fitted on alternate 10 s blocks).

    With ``coverage``, also :func:`score_against_mocap` of the deck's stated
    covariance, without (``common_mode=False``, as before the shared-error
    term) and with the ``tag_pose_common_mode`` term.
    """
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
    sens = [KnownSensor(nm, res.R[i], res.c_mm[i], res.cov[i]) for i, nm in enumerate(res.names)]
    tp = tag_poses(al, deck, sens)
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
    if coverage:
        before = tag_poses(al, deck, sens, cov_joint=res.cov_full, common_mode=False)
        after = tag_poses(al, deck, sens, cov_joint=res.cov_full)
        out["common_mode"] = after.common_mode
        out["shared_sigma_rad"] = after.common_mode_sigma_rad
        out["roughness_mm"] = roughness_mm(after.t_s, after.p_mm)
        # the shared error's time correlation, and the NEES if the stations' covariance were that much larger
        # (their fit averages over the steps as if they were independent)
        out["lag1"], out["tau_steps"] = residual_time_correlation(al, deck, res, after)
        wide = tag_poses(al, deck, sens, cov_joint=res.cov_full * out["tau_steps"])
        out["stations_widened"] = score_against_mocap(sim, wide, mocap_at, ok, even, lever=False, clock=True)
        out["mocap_roughness_mm"] = roughness_mm(mt[::10], M[::10])
        out["coverage"] = {}
        for name, tpx in (("before", before), ("after", after)):
            for lever, clock in ((False, False), (False, True), (True, True)):
                out["coverage"][(name, lever, clock)] = score_against_mocap(sim, tpx, mocap_at, ok, even,
                                                                            lever=lever, clock=clock)
    return out


def tag_rooms(n_rooms: int, tmp: Path, *, common_sigma_rad: float = 0.0) -> dict:
    """The deck's pose with self-calibrated sensors on simulated rooms: the common-mode check's alarms and NEES.

    Rooms of the tests' simulator (2-4 sensors, 30 s, 30-60 steps, 1e-4 rad);
    with ``common_sigma_rad`` every sensor's angles at each step are also
    shifted together (both angles, N(0, that^2)), written here, outside the
    code under test. NEES (3 dof) of the positions at steps seen by >= 2
    sensors, in the reference sensor's frame.
    """
    from psdcal.measure.angles_table import read_angles
    from psdcal.measure.selfcal import self_calibrate
    from psdcal.measure.tagpose import KnownSensor, read_tag, tag_poses

    sim = _sim()
    alarms, nees, tested, pvals = 0, [], 0, []
    for seed in range(n_rooms):
        rng = np.random.default_rng(70_000 + seed)
        room = sim.simulate_room(rng, int(rng.integers(2, 5)), 30.0, int(rng.integers(30, 61)),
                                 planar=seed % 2 == 0)
        if common_sigma_rad > 0:
            shift = {}
            rows = []
            for t, s_, e_, a, b in room["rows"]:
                d = shift.setdefault((t, s_), rng.normal(0, common_sigma_rad, 2))
                rows.append((t, s_, e_, a + d[0], b + d[1]))
            room = {**room, "rows": rows}
        table = read_angles(sim.write_angles(tmp / "a.csv", room))
        tag = read_tag(sim.write_tag(tmp / "t.csv", room["B"]))
        res = self_calibrate(table, tag)
        sens = [KnownSensor(nm, res.R[i], res.c_mm[i], res.cov[i]) for i, nm in enumerate(res.names)]
        tp = tag_poses(table, tag, sens, cov_joint=res.cov_full)
        tested += tp.common_mode.passed is not None
        alarms += tp.common_mode.passed is False
        if tp.common_mode.p_value is not None:
            pvals.append(tp.common_mode.p_value)
        R0, c0 = room["R"][0], room["c"][0]
        for i, t in enumerate(tp.t_s):
            if tp.n_sensors[i] >= 2:
                _, p = room["tag"][int(np.argmin(np.abs(room["t"] - t)))]
                err = R0 @ (p - c0) - tp.p_mm[i]
                nees.append(float(err @ np.linalg.solve(tp.cov[i][3:, 3:], err)))
    return {"n": n_rooms, "tested": tested, "alarms": alarms, "nees": np.array(nees), "p": np.array(pvals)}


def _pair(halves, key, fmt):
    return ", ".join(fmt.format(h[key]) for h in halves)


def _coverage_lines(folder, offsets, lh) -> list:
    """One row per reference model: both halves' figures, comma-separated (fitted on even, then odd blocks)."""
    out = []
    name = f"`{folder.replace('lh1_crossingBeam_', '')}`"
    for lever, clock in ((False, False), (False, True), (True, True)):
        b, a = lh["coverage"][("before", lever, clock)], lh["coverage"][("after", lever, clock)]
        ref = "similarity" + (" + clock" if clock else "") + (" + lever arm" if lever else "")
        out.append([name, "yes" if offsets else "no", ref,
                    ", ".join(f"{1000 * h['clock_offset_s']:+.0f}" for h in a),
                    "; ".join("(" + ", ".join(f"{x:.1f}" for x in h["lever_mm"]) + ")" for h in a) if lever else "-",
                    _pair(a, "n", "{}"), ", ".join(f"{h['median_mm']:.2f} / {h['p95_mm']:.2f}" for h in a),
                    _pair(b, "nees_median", "{:.1f}"), _pair(a, "nees_median", "{:.1f}"),
                    _pair(b, "nees_mean", "{:.1f}"), _pair(a, "nees_mean", "{:.1f}"),
                    _pair(a, "diff_nees_median", "{:.2f}"), _pair(a, "rank_corr_next", "{:.2f}")])
    return out


def _shared_line(folder, offsets, lh) -> list:
    cm = lh["common_mode"]
    sig = lh["shared_sigma_rad"]
    grow = "-" if cm.inflation is None else f"x{np.sqrt(cm.inflation):.2f}, x{1 + cm.effect_sigma:.2f}"
    return [f"`{folder.replace('lh1_crossingBeam_', '')}`", "yes" if offsets else "no", f"{1e6 * sig:.0f}",
            f"{cm.statistic:.3g} ({cm.dof:g})", grow, f"{lh['lag1']:.2f}", f"{lh['tau_steps']:.1f}",
            ", ".join(f"{x:.2f}" for x in lh["roughness_mm"]), ", ".join(f"{x:.2f}" for x in lh["mocap_roughness_mm"]),
            _pair(lh["stations_widened"], "nees_median", "{:.1f}")]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rooms", type=int, default=300)
    ap.add_argument("--steps", type=int, nargs=2, default=(15, 60))
    ap.add_argument("--no-lighthouse", action="store_true")
    ap.add_argument("--tag-rooms", type=int, default=200,
                    help="simulated rooms for the tag_pose_common_mode check (correct data and a shared error)")
    ap.add_argument("--common-sigma-rad", type=float, default=3e-4,
                    help="the shared error per sensor and step put into the second set of tag rooms")
    ap.add_argument("--no-coverage", action="store_true", help="skip the lighthouse coverage scoring")
    ap.add_argument("--no-timing", action="store_true", help="skip the 60 s paths' timing")
    ap.add_argument("--quick", action="store_true", help="a smoke run: 12 rooms, no timing")
    ap.add_argument("--markdown", action="store_true", help="the tables as Markdown (ids: sim, sim_check, timing, tag_rooms, lighthouse, shared_error, coverage)")
    a = ap.parse_args(argv)
    if a.quick:
        a.rooms, a.no_timing, a.tag_rooms = 12, True, min(a.tag_rooms, 6)
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
        print()
        if a.tag_rooms > 0:
            tlines = []
            for sig in (0.0, a.common_sigma_rad):
                tr = tag_rooms(a.tag_rooms, tmp, common_sigma_rad=sig)
                v = tr["nees"]
                tlines.append(["none (correct data)" if sig == 0 else f"{sig:g} rad per sensor and step",
                               str(tr["n"]), f"{tr['alarms']} of {tr['tested']}",
                               f"{np.mean(tr['p'] < 0.05):.3f} / {np.mean(tr['p'] < 0.01):.3f}", str(len(v)),
                               f"{v.mean():.3f} +- {v.std(ddof=1) / np.sqrt(len(v)):.3f}", f"{np.median(v):.2f}"])
            print_table(["shared error put in", "rooms", "tag_pose_common_mode failed (design 0.1 % on correct data)",
                         "p-values below 0.05 / 0.01", "steps",
                         ("position NEES mean (3 dof, ideal 3) +- its Monte Carlo standard error"),
                         "median (ideal 2.37)"], tlines, md, "tag_rooms")
        else:
            print_skipped("tag_rooms", "run with --tag-rooms 0", md)
    runs = [(f, o) for f in ("lh1_crossingBeam_flight_00", "lh1_crossingBeam_flight_01") for o in (None, SWEEPS)]
    lines, missing = [], False
    cov_lines, shared_lines = [], []
    for folder, offsets in () if a.no_lighthouse else runs:
        lh = lighthouse(folder, offsets, coverage=not a.no_coverage)
        if lh is None:
            missing = True
            break
        how = "sweep times 1/120 s apart" if offsets else "one time per row"
        if "coverage" in lh:
            cov_lines += _coverage_lines(folder, offsets, lh)
            shared_lines.append(_shared_line(folder, offsets, lh))
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
    print()
    if a.no_lighthouse or a.no_coverage or missing:
        why = "run with --no-lighthouse" if a.no_lighthouse else (
            "run with --no-coverage" if a.no_coverage else "lighthouse-lh1 is not in the shared data folder")
        print_skipped("shared_error", why, md)
        print()
        print_skipped("coverage", why, md)
    else:
        print_table(["flight", "sweep offsets", "shared error (urad)", "F (dof)",
                     "position sigmas grow (median, worst direction)", "lag-1 autocorrelation of the shared part", "its integrated time (steps)",
                     "step-to-step noise of psdcal's deck, per axis (mm)", "the same of the mocap at 30 Hz (mm)",
                     "NEES median with the stations' covariance x that time (clock fitted)"], shared_lines, md,
                    "shared_error")
        print()
        print_table(["flight", "sweep offsets", "reference fitted", "clock (ms)", "lever arm (mm)", "steps scored",
                     "median / p95 (mm)", "NEES median: before", "after", "NEES mean: before", "after",
                     "step-difference NEES median (after)", "rank correlation of consecutive errors"],
                    cov_lines, md, "coverage")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
