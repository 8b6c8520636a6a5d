#!/usr/bin/env python3
"""False alarms and detections of the carrier check on time-multiplexed records.

Each record: 8 LEDs on one at a time (on-time 10-50 ms, dark gap 0-8 ms, each
slot with its own random carrier phase and channel amplitudes), 50 kHz,
SNR 30-70 dB, the demodulation window a quarter of the on-time (at most 5 ms),
as ``psdcal simulate-recording template`` and the tutorial make them.  The
records are drawn here, independently of psdcal's simulator.  For each: the
check at the right carrier (a warning is a false alarm) and, on a second record,
at a carrier 0.2-1 % off (a warning is a detection), with the spectral peak
(:func:`psdcal.signal.inspect.carrier_near`, the old check) and the phase slope
in the bursts (:func:`psdcal.signal.inspect.carrier_in_bursts`, now used for TDM).

Usage::

    .venv/bin/python benchmarks/study_tdm_carrier.py [--records 400] [--seed 1]
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
import time

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/_table.py
from _table import print_table  # noqa: E402

from psdcal.signal.inspect import carrier_in_bursts, carrier_near, check_carrier

RATE_HZ = 50_000.0
CARRIER_HZ = 1000.0


def tdm_record(rng, *, n_led=8, on_s=0.02, gap_s=0.004, snr_db=60.0, f_hz=CARRIER_HZ, rate_hz=RATE_HZ):
    """(4, n) samples: ``n_led`` slots of ``on_s`` after ``gap_s`` of dark each, random phase per slot."""
    n_on, n_gap = round(on_s * rate_hz), round(gap_s * rate_hz)
    n = n_gap + n_led * (n_on + n_gap)
    t = np.arange(n) / rate_hz
    x = np.zeros((4, n)) + rng.uniform(0.05, 0.15, (4, 1))
    for j in range(n_led):
        a0 = n_gap + j * (n_on + n_gap)
        amp = rng.uniform(0.1, 0.4, 4)
        x[:, a0:a0 + n_on] += amp[:, None] * np.sin(2 * np.pi * f_hz * t[a0:a0 + n_on] + rng.uniform(0, 2 * np.pi))
    sigma = 0.25 / 4 / math.sqrt(2) / 10 ** (snr_db / 20)
    return x + sigma * rng.standard_normal(x.shape)


def draw(rng):
    """Random record settings: (snr_db, on_s, gap_s, window_s)."""
    snr, on, gap = rng.uniform(30, 70), rng.uniform(0.01, 0.05), rng.uniform(0.0, 0.008)
    return snr, on, gap, min(on / 4, 0.005)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--records", type=int, default=400)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="a smoke run: 20 records")
    ap.add_argument("--markdown", action="store_true", help="the result as a Markdown table")
    a = ap.parse_args(argv)
    if a.quick:
        a.records = 20
    rng = np.random.default_rng(a.seed)
    counts = {"spectral": [0, 0], "bursts": [0, 0]}
    t0 = time.perf_counter()
    for _ in range(a.records):
        snr, on, gap, w = draw(rng)
        x = tdm_record(rng, snr_db=snr, on_s=on, gap_s=gap)
        f_off = CARRIER_HZ * (1 + rng.choice([-1, 1]) * rng.uniform(0.002, 0.01))
        xo = tdm_record(rng, snr_db=snr, on_s=on, gap_s=gap, f_hz=f_off)
        for name, fn in (("spectral", carrier_near), ("bursts", carrier_in_bursts)):
            counts[name][0] += not check_carrier(CARRIER_HZ, fn(x, RATE_HZ, CARRIER_HZ), w, tdm=True).ok
            counts[name][1] += not check_carrier(CARRIER_HZ, fn(xo, RATE_HZ, CARRIER_HZ), w, tdm=True).ok
    print(f"{a.records} records ({time.perf_counter() - t0:.1f} s)")
    label = {"spectral": "the spectral peak (before)", "bursts": "the bursts' phase slope (`--tdm`, now)"}
    print_table(["carrier estimator", "false alarms (right carrier)", "detections (carrier 0.2-1 % off)"],
                [[label[name], f"{fa} of {a.records}", f"{det} of {a.records}"] for name, (fa, det) in counts.items()],
                a.markdown)


if __name__ == "__main__":
    main()
