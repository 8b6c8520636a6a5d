"""The timing rule of the benchmarks: a warm-up, then the median of timed calls."""
from __future__ import annotations

import time

import numpy as np

#: Warm-up before timing: at least this many calls and this long, so that every library is timed in its
#: steady state (CPython specialises a function's bytecode after its first calls; caches and branch
#: predictors settle), not in its first calls.
WARMUP_CALLS = 5
WARMUP_S = 0.05


def _median_time(fn, repeats: int, clock) -> float:
    t_end = clock() + WARMUP_S
    for k in range(10_000):
        fn()
        if k + 1 >= WARMUP_CALLS and clock() >= t_end:
            break
    ts = []
    for _ in range(repeats):
        t0 = clock()
        fn()
        ts.append(clock() - t0)
    return float(np.median(ts)) if ts else float("nan")


def median_seconds(fn, repeats: int) -> float:
    """Median wall time (s) of ``repeats`` calls of ``fn()`` after the warm-up."""
    return _median_time(fn, repeats, time.perf_counter)


def median_cpu_seconds(fn, repeats: int) -> float:
    """Median process CPU time (s) of ``repeats`` calls of ``fn()`` after the warm-up."""
    return _median_time(fn, repeats, time.process_time)


def interleaved_cpu_seconds(fns, repeats: int) -> list[float]:
    """Median process CPU time (s) of each of ``fns``, timed in turns: each one warmed up, then ``repeats``
    rounds that call every function once, in order.

    A ratio of two of these medians compares the functions under the same conditions: a machine whose speed
    drifts during the run (another tenant, the clock) slows every function of a round alike, where timing
    one function's repeats after the other's would put the drift into the ratio.
    """
    for fn in fns:
        _median_time(fn, 0, time.process_time)  # the warm-up only
    ts = [[] for _ in fns]
    for _ in range(repeats):
        for k, fn in enumerate(fns):
            t0 = time.process_time()
            fn()
            ts[k].append(time.process_time() - t0)
    return [float(np.median(t)) for t in ts]
