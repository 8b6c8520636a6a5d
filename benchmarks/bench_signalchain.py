#!/usr/bin/env python3
"""Throughput of the simulated signal chain: spots per second per core.

Default chain settings (50 kHz, 20 ms records = 1000 samples x 4 channels,
1 kHz carrier), 40 dB SNR.  One thread (BLAS pinned to one core), best of
three repeats.  Rows:

* ``simulate``: spot -> currents -> gains -> carrier + noise (the records);
* ``demodulate``: records -> amplitudes (lock-in or band-pass);
* ``chain``: the whole :func:`psdcal.signal.chain.measure_points`, blocks included.

Run: ``.venv/bin/python benchmarks/bench_signalchain.py [--points N] [--markdown]`` (about 15 s).
"""
from __future__ import annotations

import os

# one core: set before numpy is imported
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402


def _best_of(fn, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=4000, help="spots per timed call (default 4000)")
    parser.add_argument("--markdown", action="store_true", help="print the table in Markdown")
    args, _ = parser.parse_known_args(argv)

    from psdcal.signal import chain as sc

    n = max(1, args.points)
    xy = np.random.default_rng(0).uniform(-4.5, 4.5, (n, 2))
    rows = []
    for method in sc.METHODS:
        s = sc.ChainSettings(method=method, snr_db=40.0)
        block = xy[: min(n, 500)]  # one block of records: the memory the chain itself uses
        recs = sc.simulate_signals(block, s, rng=1)
        t_sim = _best_of(lambda: sc.simulate_signals(block, s, rng=1)) / len(block)
        t_dem = _best_of(lambda: sc.estimate_amplitudes(recs, s)) / len(block)
        t_all = _best_of(lambda: sc.measure_points(xy, s, rng=1)) / n
        rows += [(method, "simulate", t_sim), (method, "demodulate", t_dem), (method, "chain", t_all)]
    noiseless = replace(sc.ChainSettings(), snr_db=None)
    t_clean = _best_of(lambda: sc.measure_points(xy, noiseless)) / n
    rows.append(("lockin", "chain, noiseless", t_clean))

    s0 = sc.ChainSettings()
    print(f"signal chain throughput, one core: {s0.rate_hz:g} Hz x {s0.duration_s * 1e3:g} ms "
          f"({s0.n_samples} samples x 4 channels), carrier {s0.carrier_hz:g} Hz, SNR 40 dB, {n} spots")
    if args.markdown:
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        from _table import print_table

        print_table(("method", "stage", "us/spot", "spots/s per core"),
                    [(m, st, f"{t * 1e6:.1f}", f"{1.0 / t:,.0f}") for m, st, t in rows], markdown=True)
        return 0
    print(f"{'method':<10}{'stage':<20}{'us/spot':>10}{'spots/s/core':>15}")
    for method, stage, t in rows:
        print(f"{method:<10}{stage:<20}{t * 1e6:>10.1f}{1.0 / t:>15,.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
