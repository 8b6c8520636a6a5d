"""Running the study: every case a table needs, through :func:`psdcal.study.montecarlo.run_trials`."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from psdcal.errors import InputError
from psdcal.study.montecarlo import run_trials
from psdcal.study.reproduce.cases import Case, PAPER_TRIALS, _lens_of, remedy_cases, required_cases, table_columns
from psdcal.study.reproduce.paper import compare_rows, paper_values
from psdcal.study.reproduce.trials import case_trial, initial_trial


@dataclass(frozen=True)
class CaseResult:
    """Summaries of one case: ``summaries[variant][param] -> ParameterSummary``."""

    case: Case | None
    lens: str
    n_trials: int
    summaries: dict
    values: dict = field(repr=False, default_factory=dict)


def _split(table) -> tuple[dict, dict]:
    summ: dict = {}
    vals: dict = {}
    for s in table.summary():
        variant, _, param = s.parameter.partition(".")
        summ.setdefault(variant, {})[param] = s
        vals.setdefault(variant, {})[param] = table.values(s.parameter)
    return summ, vals


def run_case(case: Case, n_trials: int, seed: int, *, executor=None, progress: bool = True) -> CaseResult:
    """Run one case's trials; the seed is derived from ``seed`` and the case key (reproducible alone)."""
    ss = np.random.SeedSequence([int(seed), *[ord(ch) for ch in case.key]])
    # no noise goes as None, not NaN: NaN setting columns would not group in the summaries
    snr = None if math.isnan(case.snr_db) else float(case.snr_db)
    table = run_trials(case_trial, n_trials, seed=ss, executor=executor, progress=progress, lens=case.lens,
                       snr_db=snr, imbalance=bool(case.imbalance), psd=bool(case.psd), kind=case.kind)
    summ, vals = _split(table)
    return CaseResult(case, case.lens, n_trials, summ, vals)


def run_initial(lens: str, n_trials: int, seed: int, *, executor=None, progress: bool = True) -> CaseResult:
    """Tables 1-2: the linear stage on noiseless sets."""
    ss = np.random.SeedSequence([int(seed), *[ord(ch) for ch in f"initial_{lens}"]])
    table = run_trials(initial_trial, n_trials, seed=ss, executor=executor, progress=progress, lens=lens)
    summ, vals = _split(table)
    return CaseResult(None, lens, n_trials, summ, vals)


@dataclass(frozen=True)
class Study:
    """Everything :func:`run_study` computed.

    Attributes
    ----------
    tables : tuple of int
    n_trials, gain_trials : int
        Trials per case of the tables, and per remedy case.
    seed : int
    results : dict
        Case key -> :class:`CaseResult` (tables and remedies).
    rows : dict
        Table -> list of :class:`ComparisonRow`.
    remedies : list of CaseResult
        The remedy cases (empty unless Table 5 or 6 was asked for).
    elapsed_s : float
    """

    tables: tuple
    n_trials: int
    gain_trials: int
    seed: int
    results: dict
    rows: dict
    remedies: list
    elapsed_s: float


def run_study(tables=tuple(range(1, 11)), n_trials: int = PAPER_TRIALS, seed: int = 0, *, gain_trials: int | None = None,
              workers: int | None = None, executor=None, progress: bool = True, log=None) -> Study:
    """Run the cases behind the requested tables, and the gain remedies, and compare with the paper.

    Parameters
    ----------
    tables : iterable of int (1-10)
    n_trials : int
        Trials per case (the paper: 200).
    seed : int
    gain_trials : int, optional
        Trials per remedy case (default ``max(4, n_trials // 4)``); the
        remedies run when Table 5 or 6 is asked for.
    workers : int, optional
        Processes (default: CPU count); 1 runs serially. Ignored with ``executor``.
    executor : concurrent.futures.Executor, optional
        Where the trials run instead of a local process pool (e.g. a Dask
        ``distributed.Client(address).get_executor()``); it is not shut down.
        The tables do not depend on it: every trial is seeded from the root
        seed and its index only.
    progress : bool
        Progress bar per case (stderr terminal only).
    log : callable, optional
        ``log(str)`` called before each case.
    """
    import concurrent.futures as cf
    import os
    import time

    tables = tuple(sorted({int(t) for t in tables}))
    for t in tables:
        table_columns(t)  # validates
    if int(n_trials) < 2:
        raise InputError("need at least 2 trials per case", field="trials")
    g_trials = max(4, int(n_trials) // 4) if gain_trials is None else int(gain_trials)
    t0 = time.perf_counter()
    own = executor is None
    if own:
        n_workers = workers or os.cpu_count() or 1
        executor = "serial" if n_workers == 1 else cf.ProcessPoolExecutor(max_workers=n_workers)
    results = {}
    todo = [(k, c, int(n_trials)) for k, c in required_cases(tables)]
    for lens in sorted({_lens_of(t) for t in tables if t in (5, 6)}):
        todo += [(c.key, c, g_trials) for c in remedy_cases(lens)]
    try:
        for key, case, n in todo:
            if log is not None:
                log(f"{key}: {n} trials")
            if case is None:
                results[key] = run_initial(key.split("_", 1)[1], n, seed, executor=executor, progress=progress)
            else:
                results[key] = run_case(case, n, seed, executor=executor, progress=progress)
    finally:
        if own and executor != "serial":
            executor.shutdown(wait=True, cancel_futures=True)
    paper = paper_values()
    rows = {t: compare_rows(t, results, paper) for t in tables}
    remedies = [results[c.key] for lens in ("lens1", "lens2") for c in remedy_cases(lens) if c.key in results]
    return Study(tables, int(n_trials), g_trials, int(seed), results, rows, remedies, time.perf_counter() - t0)
