#!/usr/bin/env python3
"""False alarms and detections of the channel-sums check (:mod:`psdcal.measure.channel_order`).

Each run: 50 rows of amplitudes of spots uniform over +-3.5 mm of a 9 mm PSD
(the four corner currents ``I (1 -+ a -+ b) / 4`` written here from
docs/model.md, not taken from psdcal), channel noise at SNR 30-80 dB, channel
gains calibrated to 0.05-0.5 % (the true gains drawn from that covariance,
which the check is given).  A warning on the rows in the documented order is
a false alarm; on the same rows read as ``vx1, vy1, vx2, vy2`` it is a
detection, counted when that wiring's error (the impact point's y read as 0)
exceeds 3 sigmas of a row's y and the gains' own effect.

Usage::

    .venv/bin/python benchmarks/study_channel_sums.py [--runs 3000] [--seed 11]
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/_table.py
from _table import print_table  # noqa: E402

from psdcal.measure.channel_order import SumCheck


def corner_currents(xy_mm, l_mm=9.0):
    a, b = 2 * xy_mm[:, 0] / l_mm, 2 * xy_mm[:, 1] / l_mm
    return 0.25 * np.stack([1 - a - b, 1 + a + b, 1 + a - b, 1 - a + b], axis=-1)


def one_run(rng, label: str = "run") -> tuple[bool, bool, bool]:
    """One run: (false alarm on the documented order, wiring vx1,vy1,vx2,vy2 relevant, and caught)."""
    g_std = rng.uniform(5e-4, 5e-3)
    cov = np.eye(3) * g_std ** 2
    g_cal = np.r_[1.0, 1 + rng.uniform(-0.05, 0.05, 3)]
    g_true = g_cal.copy()
    g_true[1:] += g_std * rng.standard_normal(3)
    xy = rng.uniform(-3.5, 3.5, (50, 2))
    sigma = 0.25 * 10 ** (-rng.uniform(30, 80) / 20)
    amp = corner_currents(xy) * g_true + sigma * rng.standard_normal((50, 4))
    var = np.full_like(amp, sigma ** 2)
    ok = SumCheck(g_cal, 9.0, label, cov)
    ok.add(amp, var)
    bad = SumCheck(g_cal, 9.0, label, cov)
    bad.add(amp[:, [0, 2, 1, 3]], var)
    # the y error of that wiring, in sigmas of a row's y (sigma_y ~ 4.5 mm * sigma / (1/4 * 2))
    y_err = np.abs(xy[:, 1]).max()
    relevant = y_err / (4.5 * sigma * math.sqrt(2) / 0.5) > 3 and g_std * 9.0 < y_err
    return ok.warning() is not None, bool(relevant), bool(relevant) and bad.warning() is not None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--quick", action="store_true", help="a smoke run: 200 runs")
    ap.add_argument("--markdown", action="store_true", help="the result as a Markdown table")
    a = ap.parse_args(argv)
    if a.quick:
        a.runs = 200
    rng = np.random.default_rng(a.seed)
    alarms = relevant = caught = 0
    for _ in range(a.runs):
        alarm, rel, hit = one_run(rng)
        alarms += alarm
        relevant += rel
        caught += hit
    print_table(["runs of 50 rows", "false alarms (documented order)",
                 "`vx1,vy1,vx2,vy2` wiring caught (runs where its error exceeds 3 sigmas of a row)"],
                [[str(a.runs), f"{alarms} of {a.runs}", f"{caught} of {relevant}"]], a.markdown)


if __name__ == "__main__":
    main()
