#!/usr/bin/env python3
"""Taking calibration views: predicted AoA uncertainty against views, tilt, distance and coverage; guided vs random vs grid.

Predicted, not Monte Carlo: the calibration's own first-order covariance
(psdcal.study.capture; it equals the covariance `psdcal calibrate` reports)
at the true parameters of the paper's two lenses, 3 um noise per coordinate,
default model (f, C, k1, k2, p1, p2). Writes two Markdown tables to stdout (ids ``views`` and
``sweep``, the tables of docs/guide/capture.md) and docs/guide/capture_study.png.

    .venv/bin/python benchmarks/capture_study.py [--markdown]     (about a minute)
    .venv/bin/python benchmarks/capture_study.py --quick          (fewer seeds; no figure written)
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from psdcal.model.params import ModelSpec
from psdcal.report.compare import sensor_grid_mm
from psdcal.study.capture import (aoa_jacobian, candidate_views, grid_capture, guided_sequence, view_information,
                                  worst_sigma_deg)
from psdcal.study.simulate import LENSES, default_template, random_poses

NOISE_MM = 0.003
SPEC = ModelSpec()
N_MAX = 40
SEEDS = 10
TARGET_FRACTION = 0.7  # target: 70 % of the worst 1-sigma of a typical 9-view random capture (the paper uses 9 views)


def curve(S_views, Ja):
    """Worst 1-sigma (deg) after 1..n views of a sequence."""
    S = np.cumsum(S_views, axis=0)
    return worst_sigma_deg(S, Ja, NOISE_MM)


def needed(c, target):
    k = np.nonzero(np.asarray(c) <= target)[0]
    return int(k[0]) + 1 if k.size else None


def guided_refitted(lens, target, seed, n_max=N_MAX):
    """Guided capture as a user runs it: calibrate the views taken (noisy), ask next-view at the estimate, take it.

    Returns the number of views at which the calibration's own reported worst AoA 1-sigma (scaled to the nominal
    noise) reaches ``target`` (None if not within n_max), and the true worst AoA error over the sensor then (deg).
    """
    from psdcal import calibrate
    from psdcal.measure.aoa import angles_from_points
    from psdcal.measure.sensor_model import SensorModel
    from psdcal.report.compare import fov_uncertainty
    from psdcal.study.capture import information_of_calibration, next_view
    from psdcal.study.simulate import measured_points

    intr, dist = LENSES[lens]
    P = default_template()
    rng = np.random.default_rng(1000 + seed)
    rv, tv = random_poses(P, intr, dist, 3, rng)
    X = measured_points(P, intr, dist, rv, tv)
    X = X + rng.normal(0, NOISE_MM, X.shape)
    grid = sensor_grid_mm((9.0, 9.0), 11).reshape(-1, 2)
    truth = angles_from_points(grid, SensorModel(intrinsics=intr, distortion=dist)).alpha_rad
    while True:
        r = calibrate(P, X)
        worst = float(np.nanmax(fov_uncertainty(r, n=11).sigma_total_deg)) * NOISE_MM / r.sigma_mm
        if worst <= target or len(X) >= n_max:
            est = angles_from_points(grid, SensorModel(intrinsics=r.intrinsics, distortion=r.distortion)).alpha_rad
            err = float(np.degrees(np.linalg.norm(est - truth, axis=-1)).max())
            return (len(X) if worst <= target else None), err
        nv = next_view(P, r.intrinsics, r.distortion, r.model, information_of_calibration(r), NOISE_MM)
        c = nv.ranked[0][0]
        # the user sets up the instructed pose; the truth images it (the pose is the same physical pose)
        d = measured_points(P, intr, dist, [c.rvec], [c.tvec_mm])
        d = np.where(np.abs(d) <= 4.5, d, np.nan)
        X = np.concatenate([X, d + rng.normal(0, NOISE_MM, d.shape)])


def main(argv=None):
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--markdown", action="store_true", help="(the tables are Markdown in any case; accepted for tasks.py bench)")
    ap.add_argument("--quick", action="store_true", help="3 random sequences, 1 refitted run, 2 per sweep; no figure")
    a = ap.parse_args(argv)
    seeds, refits, sweeps = (3, 1, 2) if a.quick else (SEEDS, 4, 5)
    P = default_template()
    grid = sensor_grid_mm((9.0, 9.0), 11).reshape(-1, 2)
    rows_cmp, rows_sweep, curves = [], [], {}
    for lens in ("lens1", "lens2"):
        intr, dist = LENSES[lens]
        Ja = aoa_jacobian(intr, dist, SPEC.global_names, grid)
        info = lambda rv, tv: view_information(P, intr, dist, SPEC, rv, tv)  # noqa: E731
        rand = []
        for seed in range(seeds):
            rv, tv = random_poses(P, intr, dist, N_MAX, np.random.default_rng(seed))
            rand.append(curve(info(rv, tv), Ja))
        rand = np.array(rand)
        target = TARGET_FRACTION * float(np.median(rand[:, 8]))
        cands = candidate_views(P, intr, dist)
        gseq = grid_capture(cands, N_MAX)
        g_curve = curve(info([c.rvec for c in gseq], [c.tvec_mm for c in gseq]), Ja)
        S3 = info([c.rvec for c in gseq[:3]], [c.tvec_mm for c in gseq[:3]]).sum(0)
        _, guided = guided_sequence(P, intr, dist, SPEC, S3, NOISE_MM, N_MAX - 3, candidates=cands)
        guided = np.concatenate([g_curve[:3], guided])
        curves[lens] = (rand, g_curve, guided, target)
        n_rand = [needed(c, target) for c in rand]
        n_rand_ok = [n for n in n_rand if n is not None]
        refit = [guided_refitted(lens, target, seed) for seed in range(refits)]
        refit_n = [n for n, _ in refit if n is not None]
        rows_cmp.append((lens, target, needed(guided, target),
                         f"{min(refit_n)}-{max(refit_n)}" if refit_n else "-",
                         max(e for _, e in refit), float(np.median(n_rand_ok)) if n_rand_ok else None,
                         f"{min(n_rand_ok)}-{max(n_rand_ok)}" if n_rand_ok else "-", len(n_rand) - len(n_rand_ok),
                         needed(g_curve, target)))
        # sweeps with random captures: tilt, distance (fill), coverage
        for label, kw in [("tilt <= 10 deg", dict(max_tilt_deg=10.0)), ("tilt <= 20 deg", dict(max_tilt_deg=20.0)),
                          ("tilt <= 35 deg (default)", {}), ("tilt <= 50 deg", dict(max_tilt_deg=50.0)),
                          ("far: image 25-45 % of the sensor", dict(fill=(0.25, 0.45))),
                          ("near: image 65-90 % of the sensor", dict(fill=(0.65, 0.9)))]:
            vals = {n: [] for n in (6, 12, 24)}
            for seed in range(sweeps):
                rv, tv = random_poses(P, intr, dist, 24, np.random.default_rng(100 + seed), **kw)
                c = curve(info(rv, tv), Ja)
                for n in vals:
                    vals[n].append(c[n - 1])
            rows_sweep.append((lens, label, *[float(np.median(vals[n])) for n in (6, 12, 24)]))
        # coverage: candidates centred near the middle only vs over the whole sensor (35 deg tilts about random
        # axes, all at the distance where the template's image spans 35 % of the sensor)
        for label, rmax in [("coverage: centre spot within 1 mm of the middle", 1.0),
                            ("coverage: centre spot anywhere (corners too)", 9.0)]:
            far = max(c.distance_mm for c in cands)  # the distance where the template fits at every position
            pool = [c for c in cands if c.tilt_deg == 35.0 and c.distance_mm == far and np.hypot(*c.centre_mm) <= rmax]
            vals = {n: [] for n in (6, 12, 24)}
            for seed in range(sweeps):
                pick = np.random.default_rng(200 + seed).choice(len(pool), 24, replace=True)
                c = curve(info([pool[i].rvec for i in pick], [pool[i].tvec_mm for i in pick]), Ja)
                for n in vals:
                    vals[n].append(c[n - 1])
            rows_sweep.append((lens, label, *[float(np.median(vals[n])) for n in (6, 12, 24)]))
    print("<!-- table: views -->")
    print(f"| lens | target: worst 1-sigma AoA (deg) | guided | guided, refitted each view ({refits} runs) "
          "| its worst true error (deg) | random (median) | random (range) | random never | grid |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows_cmp:  # noqa
        r = tuple("not within %d" % N_MAX if v is None else v for v in r)
        print(f"| {r[0]} | {r[1]:.3g} | {r[2]} | {r[3]} | {r[4]:.3g} | {r[5]} | {r[6]} | {r[7]} of {seeds} | {r[8]} |")
    print()
    print("<!-- table: sweep -->")
    print(f"| lens | capture (median of {sweeps} random sequences) | worst 1-sigma AoA after 6 views (deg) | 12 views | 24 views |")
    print("|---|---|---|---|---|")
    for r in rows_sweep:
        print(f"| {r[0]} | {r[1]} | {r[2]:.3g} | {r[3]:.3g} | {r[4]:.3g} |")
    if a.quick:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 2, figsize=(10, 4))
    n = np.arange(1, N_MAX + 1)
    for ax, lens in zip(axs, ("lens1", "lens2")):
        rand, g, gd, target = curves[lens]
        ax.fill_between(n, np.percentile(rand, 10, 0), np.percentile(rand, 90, 0), alpha=0.3, label="random (10-90 %)")
        ax.plot(n, np.median(rand, 0), label="random (median)")
        ax.plot(n, g, label="grid")
        ax.plot(n, gd, label="guided (next-view)")
        ax.axhline(target, color="k", ls=":", label="target")
        ax.set_yscale("log")
        ax.set_ylim(target / 3, 20 * target)
        ax.set_xlabel("views")
        ax.set_ylabel("worst 1-sigma AoA over the sensor (deg)")
        ax.set_title(f"{lens}, noise {NOISE_MM * 1e3:g} um")
        ax.legend(fontsize=8)
    fig.tight_layout()
    out = Path(__file__).resolve().parent.parent / "docs" / "guide" / "capture_study.png"
    fig.savefig(out, dpi=90)
    print(f"\nwrote {out}", file=sys.stderr)


if __name__ == "__main__":
    main()
