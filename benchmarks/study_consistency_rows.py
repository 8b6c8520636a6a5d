#!/usr/bin/env python3
"""False-alarm rates of the triangulation rule (per-point flags and the pooled file rule) at the design rate 1e-3.

Rooms of 2-4 sensors, rays and anisotropic noise drawn with numpy alone (the generator of
tests/test_consistency_rows.py, independent of psdcal's simulator).  ``--files`` files of
``--points`` points each: the fraction of points flagged and the fraction of files whose pooled
test fails (and so get the extra ray noise), with their binomial standard errors; then the
Lighthouse numbers of docs/guide/positioning.md#sigmas-that-cover-the-error when
``lighthouse-lh1`` of the shared data folder beside the repository is there.

Usage::

    .venv/bin/python benchmarks/study_consistency_rows.py [--files 20000] [--points 20]
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))
sys.path.insert(0, str(HERE))  # benchmarks/_table.py
from _table import print_skipped, print_table  # noqa: E402


def rates(files: int, points: int, seed: int = 0):
    from test_consistency_rows import _points, _rays, _room

    from psdcal.measure.positioning import pooled_check, triangulate

    rng = np.random.default_rng(seed)
    flagged = total = alarms = 0
    per_room = 200  # files sharing one room (drawn anew every 200 files)
    for start in range(0, files, per_room):
        m = min(per_room, files - start)
        R, t = _room(rng, int(rng.integers(2, 5)))
        P = _points(rng, m * points)
        n, cov = _rays(rng, R, t, P)
        tri = triangulate(n, cov, R, t, inflate=False)
        flagged += int(tri.flagged.sum())
        total += len(P)
        chi2 = tri.chi2.reshape(m, points)
        dof = tri.dof.reshape(m, points)
        for c, d in zip(chi2, dof):
            alarms += pooled_check(float(c.sum()), float(d.sum()), points).passed is False
    return flagged / total, total, alarms / files, files


def lighthouse(md: bool = False):
    import _lighthouse as lh

    from psdcal.measure.positioning import triangulate
    from psdcal.measure.tracking import track

    if not lh.available():
        print_skipped("lighthouse", "lighthouse-lh1 is not in the shared data folder", md)
        return
    g = lh.geometry()
    lines = []
    for name in lh.FLIGHTS:
        log = lh.load(name)
        t, n, _, est = lh.steps(log)
        E = len(t)
        rays = n.reshape(2, E * 4, 2)
        tri = triangulate(rays, lh.station_directions(rays), g.R_w2c, g.t_mm)
        p = tri.p_w_mm.reshape(E, 4, 3)
        centre = p.mean(1)
        truth = lh.mocap_at(log, t)
        fit, score = lh.halves(t)
        same = np.all(np.isfinite(p), (1, 2)) & np.all(np.isfinite(truth), 1)
        e_psd, R, tt, rows = lh.scored_errors(t, centre, truth, fit & same, score & same)
        e_cf, *_ = lh.scored_errors(t, est * 1000, truth, fit & same, score & same)
        err = centre[rows] @ R.T + tt - truth[rows]
        before, after = (lh.nees(err, np.einsum("ij,njk,lk->nil", R, C.reshape(E, 4, 3, 3).mean(1)[rows], R))
                         for C in (tri.cov_p_stated_mm2, tri.cov_p_mm2))
        c = tri.chi2[np.isfinite(tri.chi2)]
        cov = tri.cov_p_mm2.reshape(E, 4, 3, 3).mean(1)
        ok = same & np.all(np.isfinite(cov), (1, 2))
        tr = track(t[ok], np.array(["deck"] * int(ok.sum()), dtype=object), centre[ok], cov[ok])
        pt = np.full(centre.shape, np.nan)
        pt[ok] = tr.p
        e_tr = np.linalg.norm(pt[rows] @ R.T + tt - truth[rows], axis=1)
        lines.append([f"`{name.replace('lh1_crossingBeam_', '')}`", str(len(rows)),
                      f"{np.median(e_psd):.2f} / {np.percentile(e_psd, 95):.2f}",
                      f"{np.median(e_cf):.2f} / {np.percentile(e_cf, 95):.2f}",
                      f"{np.nanmedian(e_tr):.2f} / {np.nanpercentile(e_tr, 95):.2f}",
                      f"{np.median(c):.0f} / {c.mean():.0f}", f"{tri.flagged[np.isfinite(tri.chi2)].mean():.1%}",
                      f"{1e3 * math.sqrt(tri.extra_var_n):.1f} mrad", f"{before.mean():.0f} / {after.mean():.2f}"])
    print_table(["flight", "scored steps", "psdcal median / p95 (mm)", "Crazyflie median / p95 (mm)",
                 "tracking median / p95 (mm)", "chi2 per point (1 dof), median / mean", "rows flagged",
                 "extra ray noise", "NEES (3 dof) stated / inflated"], lines, md, "lighthouse")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=20000)
    ap.add_argument("--points", type=int, default=20)
    ap.add_argument("--quick", action="store_true", help="a smoke run: 1000 files")
    ap.add_argument("--no-lighthouse", action="store_true")
    ap.add_argument("--markdown", action="store_true", help="the tables as Markdown (ids: rates, lighthouse)")
    a = ap.parse_args(argv)
    if a.quick:
        a.files = 1000
    fr, npts, ar, nf = rates(a.files, a.points)
    print_table(["rule (design false-alarm rate 0.001)", "sample", "measured rate +- its binomial standard error"],
                [["per-point flags", f"{npts} points", f"{fr:.5f} +- {math.sqrt(1e-3 * (1 - 1e-3) / npts):.5f}"],
                 ["pooled rule (the file's extra ray noise)", f"{nf} files of {a.points} points",
                  f"{ar:.5f} +- {math.sqrt(1e-3 * (1 - 1e-3) / nf):.5f}"]], a.markdown, "rates")
    print()
    if a.no_lighthouse:
        print_skipped("lighthouse", "run with --no-lighthouse", a.markdown)
    else:
        lighthouse(a.markdown)


if __name__ == "__main__":
    main()
