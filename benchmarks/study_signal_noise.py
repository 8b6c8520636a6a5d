#!/usr/bin/env python3
"""Impact-point noise against SNR, measured through the simulated chain and predicted (the table of docs/guide/signal-chain.md).

For each SNR, method (lock-in, band-pass) and spot (centre (0, 0), corner (4.5, 4.5) mm): ``--records``
noisy records (defaults: 50 kHz x 20 ms, 1 kHz carrier) through ``psdcal.signal.chain.point_noise_vs_snr``;
the measured std of x / y in um beside the first-order prediction of x, and the largest deviation of
measured from predicted in units of the measured std's standard error.

    .venv/bin/python benchmarks/study_signal_noise.py [--records 4000] [--markdown]
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/_table.py
from _table import print_table  # noqa: E402

SNRS_DB = (30, 40, 50, 60)
SPOTS = (("centre", (0.0, 0.0)), ("corner", (4.5, 4.5)))


def main(argv=None) -> int:
    from psdcal.signal.chain import ChainSettings, point_noise_vs_snr

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", type=int, default=4000)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--quick", action="store_true", help="200 records per cell")
    ap.add_argument("--markdown", action="store_true")
    a = ap.parse_args(argv)
    if a.quick:
        a.records = 200
    cells, worst = {}, 0.0
    for method in ("lockin", "bandpass"):
        settings = replace(ChainSettings(), method=method)
        for name, xy in SPOTS:
            r = point_noise_vs_snr(SNRS_DB, settings, n=a.records, rng=a.seed, xy_mm=xy)
            worst = max(worst, float(np.max(np.abs(r.measured_std_mm - r.predicted_std_mm) / r.measured_std_se_mm)))
            for k, snr in enumerate(SNRS_DB):
                m, p = r.measured_std_mm[k] * 1e3, r.predicted_std_mm[k, 0] * 1e3
                cells[(snr, method, name)] = f"{m[0]:.3g} / {m[1]:.3g} ({p:.3g})"
    lines = [[str(snr)] + [cells[(snr, me, sp)] for me in ("lockin", "bandpass") for sp, _ in SPOTS] for snr in SNRS_DB]
    print(f"{a.records} records per cell, seed {a.seed}; largest |measured - predicted| = {worst:.1f} standard errors")
    print_table(["SNR (dB)", "lock-in, centre", "lock-in, corner", "band-pass, centre", "band-pass, corner"], lines,
                a.markdown)
    print()
    print_table(["records per cell", "largest deviation of measured from predicted std"],
                [[str(a.records), f"{worst:.1f} standard errors of the measured std"]], a.markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
