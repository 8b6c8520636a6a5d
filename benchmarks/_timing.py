"""The timing rule of the benchmarks: a warm-up, then the median of timed calls."""
from __future__ import annotations

import time

import numpy as np

#: Warm-up before timing: at least this many calls and this long, so that every library is timed in its
#: steady state (CPython specialises a function's bytecode after its first calls; caches and branch
#: predictors settle), not in its first calls. ``_mrcal_reference.py`` (run under another Python) applies
#: the same rule.
WARMUP_CALLS = 5
WARMUP_S = 0.05


def median_seconds(fn, repeats: int) -> float:
    """Median wall time (s) of ``repeats`` calls of ``fn()`` after the warm-up."""
    t_end = time.perf_counter() + WARMUP_S
    for k in range(10_000):
        fn()
        if k + 1 >= WARMUP_CALLS and time.perf_counter() >= t_end:
            break
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))
