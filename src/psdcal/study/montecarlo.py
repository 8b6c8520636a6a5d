"""Seeded, executor-agnostic Monte Carlo runner with a tidy result table.

A *trial* is a picklable top-level function ``trial_fn(rng, **kwargs) ->
dict[str, float]``.  :func:`run_trials` calls it ``n_trials`` times, trial
``i`` with its own generator ``numpy.random.default_rng(children[i])`` where
``children = numpy.random.SeedSequence(seed).spawn(n_trials)``: the results
depend only on ``seed`` and the trial index, never on the executor, the
number of workers, the chunk size or the completion order.

The result is a :class:`TrialTable` in tidy (long) form: one row per trial
and parameter with columns ``trial, parameter, value, error`` plus one
constant column per scalar keyword argument given to the trials (the
settings of the run).  A failing trial does not stop the run: it gets a row
per parameter (the parameters the other trials returned) with ``value`` NaN
and ``error`` the exception's type and message (``error`` is ``""`` for a
good row); :func:`run_trials` then warns with the number of failures and the
first failing trial's index.  ``on_error="raise"`` raises
:class:`TrialError` naming the trial instead.

Examples
--------
>>> from psdcal.study.montecarlo import run_trials
>>> from psdcal.signal.chain import measure_point_trial
>>> table = run_trials(measure_point_trial, 200, seed=1, executor="serial",
...                    progress=False, snr_db=40.0)
>>> [s.parameter for s in table.summary()]
['x_mm', 'y_mm']
"""
from __future__ import annotations

import concurrent.futures as cf
import csv
import io
import math
import os
import pickle
import sys
import warnings
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from psdcal._atomic import write_text_atomic
from psdcal._stats import std_standard_error  # noqa: F401  (re-exported)
from psdcal.errors import PsdcalError

#: Columns every :class:`TrialTable` has, in this order.
BASE_COLUMNS = ("trial", "parameter", "value", "error")


class TrialError(PsdcalError, RuntimeError):
    """A Monte Carlo trial failed (``on_error="raise"``). ``trial`` is its index."""

    def __init__(self, message: str, trial: int):
        super().__init__(message)
        self.trial = trial


class TrialFailureWarning(UserWarning):
    """Some trials failed; their rows hold NaN and the error message."""


# ---------------------------------------------------------------------------
# Statistics
# ---------------------------------------------------------------------------



@dataclass(frozen=True)
class ParameterSummary:
    """Summary of one parameter over the trials of one setting.

    Attributes
    ----------
    parameter : str
    n : int
        Trials with a finite value.
    n_failed : int
        Trials without one (NaN value: failed trial or a NaN result).
    mean, std : float
        Sample mean and standard deviation (``ddof=1``).
    sem : float
        Standard error of the mean, ``std / sqrt(n)``.
    se_std : float
        Standard error of ``std`` (:func:`std_standard_error`).
    settings : Mapping[str, object]
        Values of the setting columns of this group.
    """

    parameter: str
    n: int
    n_failed: int
    mean: float
    std: float
    sem: float
    se_std: float
    settings: Mapping = field(default_factory=dict)

    def as_dict(self) -> dict:
        d = dict(self.settings)
        d.update(parameter=self.parameter, n=self.n, n_failed=self.n_failed, mean=self.mean, std=self.std,
                 sem=self.sem, se_std=self.se_std)
        return d


def _summarise_values(parameter: str, values: np.ndarray, settings: Mapping) -> ParameterSummary:
    finite = values[np.isfinite(values)]
    n = int(finite.size)
    mean = float(finite.mean()) if n else float("nan")
    std = float(finite.std(ddof=1)) if n >= 2 else float("nan")
    sem = std / math.sqrt(n) if n >= 2 else float("nan")
    return ParameterSummary(parameter, n, int(values.size - n), mean, std, sem, std_standard_error(finite),
                            MappingProxyType(dict(settings)))


# ---------------------------------------------------------------------------
# The table
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class TrialTable:
    """Tidy Monte Carlo results: one row per trial and parameter.

    Attributes
    ----------
    columns : Mapping[str, ndarray]
        Equal-length 1-D arrays: ``trial`` (int), ``parameter`` (str),
        ``value`` (float), ``error`` (str, ``""`` when the trial succeeded),
        then the setting columns.
    seed_entropy : int or None
        Entropy of the root :class:`numpy.random.SeedSequence` (re-run with
        ``seed=seed_entropy`` when the run was seeded from fresh entropy).
    """

    columns: Mapping
    seed_entropy: int | None = None

    def __post_init__(self):
        cols = {k: np.asarray(v) for k, v in self.columns.items()}
        missing = [c for c in BASE_COLUMNS if c not in cols]
        if missing:
            raise ValueError(f"a trial table needs the columns {', '.join(missing)}")
        lengths = {v.shape for v in cols.values()}
        if len(lengths) != 1 or len(next(iter(lengths))) != 1:
            raise ValueError("columns of a trial table must be 1-D arrays of one length")
        for v in cols.values():
            v.setflags(write=False)
        order = list(BASE_COLUMNS) + [k for k in cols if k not in BASE_COLUMNS]
        object.__setattr__(self, "columns", MappingProxyType({k: cols[k] for k in order}))

    def __len__(self) -> int:
        return int(self.columns["trial"].size)

    @property
    def setting_names(self) -> tuple[str, ...]:
        """Names of the setting columns (all but ``trial, parameter, value, error``)."""
        return tuple(k for k in self.columns if k not in BASE_COLUMNS)

    @property
    def parameters(self) -> tuple[str, ...]:
        """Parameter names in order of first appearance."""
        return tuple(dict.fromkeys(self.columns["parameter"].tolist()))

    @property
    def failed_trials(self) -> np.ndarray:
        """Sorted indices of the trials that raised, (k,) int."""
        err = self.columns["error"]
        return np.unique(self.columns["trial"][err != ""])

    def values(self, parameter: str) -> np.ndarray:
        """Values of one parameter in row order (trial order for one run), (n,) float."""
        mask = self.columns["parameter"] == parameter
        if not np.any(mask):
            raise KeyError(f"no parameter {parameter!r} in the table (have: {', '.join(self.parameters)})")
        return np.asarray(self.columns["value"][mask], dtype=float)

    def rows(self) -> list[dict]:
        """The rows as dictionaries (column name -> Python scalar)."""
        names = list(self.columns)
        cols = [self.columns[k].tolist() for k in names]
        return [dict(zip(names, r)) for r in zip(*cols)]

    def to_csv(self, path=None) -> str:
        """CSV text of the table (header = column names); written atomically to ``path`` if given.

        Values are written with ``repr`` precision (round-trip exact); NaN as ``nan``.
        """
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        names = list(self.columns)
        w.writerow(names)
        for row in self.rows():
            w.writerow([repr(v) if isinstance(v, float) else v for v in (row[k] for k in names)])
        text = buf.getvalue()
        if path is not None:
            write_text_atomic(path, text)
        return text

    def summary(self, by: Iterable[str] | None = None) -> list[ParameterSummary]:
        """Mean, std, n and their standard errors per parameter (and per setting).

        Parameters
        ----------
        by : iterable of str, optional
            Columns to group by besides ``parameter`` (default: all setting
            columns, so a concatenation of runs summarises per setting).

        Returns
        -------
        list of ParameterSummary
            In order of first appearance.
        """
        keys = list(self.setting_names if by is None else by)
        for k in keys:
            if k not in self.columns or k in BASE_COLUMNS:
                raise KeyError(f"cannot group by {k!r}: not a setting column of this table")
        groups: dict = {}
        setting_cols = [self.columns[k].tolist() for k in keys]
        params = self.columns["parameter"].tolist()
        for r, p in enumerate(params):
            gkey = tuple(c[r] for c in setting_cols) + (p,)
            groups.setdefault(gkey, []).append(r)
        value = np.asarray(self.columns["value"], dtype=float)
        return [_summarise_values(g[-1], value[rows], dict(zip(keys, g[:-1]))) for g, rows in groups.items()]

    def to_pandas(self):
        """The table as a :class:`pandas.DataFrame` (needs pandas)."""
        import pandas as pd

        return pd.DataFrame({k: np.asarray(v) for k, v in self.columns.items()})

    @classmethod
    def concat(cls, tables: Iterable["TrialTable"]) -> "TrialTable":
        """Rows of several tables with the same columns, one after the other."""
        tables = list(tables)
        if not tables:
            raise ValueError("nothing to concatenate")
        names = list(tables[0].columns)
        for t in tables[1:]:
            if list(t.columns) != names:
                raise ValueError("tables to concatenate must have the same columns in the same order")
        return cls({k: np.concatenate([t.columns[k] for t in tables]) for k in names})


def write_csv(table: TrialTable, path) -> None:
    """Write ``table`` as CSV to ``path`` (atomically)."""
    table.to_csv(path)


def summarise(table: TrialTable, by: Iterable[str] | None = None) -> list[ParameterSummary]:
    """Per-parameter summary of ``table`` (see :meth:`TrialTable.summary`)."""
    return table.summary(by)


# ---------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------


def _run_chunk(trial_fn: Callable, first: int, seeds: list, kwargs: dict) -> list:
    """Run trials ``first, first + 1, ...`` in this process; never raises for a trial.

    BLAS runs on one thread meanwhile: the parallelism is the executor's workers, and a BLAS
    thread pool per worker would only oversubscribe the cores (idle OpenBLAS threads also
    busy-wait between calls, burning CPU).
    """
    from psdcal.calibration._refine import _single_threaded_blas

    out = []
    with _single_threaded_blas():
        for k, ss in enumerate(seeds):
            try:
                res = trial_fn(np.random.default_rng(ss), **kwargs)
                if not isinstance(res, Mapping):
                    raise TypeError(f"trial function must return a dict of floats, got {type(res).__name__}")
                row = {str(name): float(val) for name, val in res.items()}
                out.append((first + k, row, ""))
            except Exception as exc:  # a failing trial is recorded, not fatal
                msg = " ".join(f"{type(exc).__name__}: {exc}".split())
                out.append((first + k, None, msg))
    return out


def _is_setting(value) -> bool:
    return isinstance(value, (bool, int, float, str, np.integer, np.floating, np.bool_))


def _progress_bar(enabled: bool):
    if not (enabled and sys.stderr.isatty()):
        return None
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(TextColumn("trials"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                    console=Console(stderr=True), transient=True)


def run_trials(
    trial_fn: Callable,
    n_trials: int,
    *,
    seed,
    executor=None,
    max_workers: int | None = None,
    chunksize: int | None = None,
    progress: bool = True,
    on_error: str = "record",
    **kwargs,
) -> TrialTable:
    """Run ``n_trials`` seeded independent trials, possibly in parallel.

    Parameters
    ----------
    trial_fn : callable
        ``trial_fn(rng, **kwargs) -> dict[str, float]``; a picklable
        top-level function when an executor other than ``"serial"`` is used.
    n_trials : int
    seed : int, numpy.random.SeedSequence or None
        Root seed.  Trial ``i`` gets ``default_rng(SeedSequence(seed).spawn(n_trials)[i])``.
        None draws fresh entropy, stored in :attr:`TrialTable.seed_entropy`.
    executor : concurrent.futures.Executor, "serial" or None
        Any Executor (``submit`` is all that is used: process or thread
        pools, ``dask.distributed.Client.get_executor()``, a Ray-backed
        Executor, MPI's ``MPIPoolExecutor`` ...); it is not shut down.
        ``"serial"``: in this process, no pickling.  None: a
        :class:`~concurrent.futures.ProcessPoolExecutor` with ``max_workers``
        processes (default: this machine's CPU count), shut down at the end;
        ``max_workers=1`` runs serially instead.
    max_workers : int, optional
        Processes of the default pool.
    chunksize : int, optional
        Trials per submitted task (default: about 4 tasks per worker).
    progress : bool
        Show a progress bar (rich) on stderr; never when stderr is not a terminal.
    on_error : {"record", "raise"}
        A failing trial: record NaN and its error message in the table and
        warn (:class:`TrialFailureWarning`), or raise :class:`TrialError`
        for the lowest failing trial index once all trials have run.
    **kwargs
        Passed to every trial.  Scalar ones (numbers, strings, bools) also
        become constant columns of the table.

    Returns
    -------
    TrialTable
        Rows ordered by trial, then by the parameter order of the trial's dict.
    """
    n_trials = int(n_trials)
    if n_trials < 1:
        raise ValueError(f"n_trials must be >= 1, got {n_trials}")
    if on_error not in ("record", "raise"):
        raise ValueError(f"on_error must be 'record' or 'raise', got {on_error!r}")
    if not callable(trial_fn):
        raise TypeError("trial_fn must be callable")
    for name in kwargs:
        if name in BASE_COLUMNS:
            raise ValueError(f"keyword {name!r} clashes with a column of the result table")
    root = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    seeds = root.spawn(n_trials)

    own_pool = False
    serial = executor == "serial" or (executor is None and max_workers == 1)
    if executor is None and not serial:
        workers = max_workers or os.cpu_count() or 1
        executor = cf.ProcessPoolExecutor(max_workers=workers)
        own_pool = True
    elif isinstance(executor, str) and not serial:
        raise ValueError(f"executor must be an Executor, 'serial' or None, got {executor!r}")
    elif not serial and not isinstance(executor, cf.Executor) and not hasattr(executor, "submit"):
        raise TypeError(f"executor must be a concurrent.futures.Executor, got {type(executor).__name__}")

    if serial:
        workers = 1
    elif not own_pool:
        workers = getattr(executor, "_max_workers", None) or os.cpu_count() or 1
    if chunksize is None:
        chunksize = max(1, math.ceil(n_trials / (4 * workers)))
    chunksize = max(1, int(chunksize))
    starts = list(range(0, n_trials, chunksize))

    results: list = []
    bar = _progress_bar(progress)
    task = bar.add_task("trials", total=n_trials) if bar is not None else None
    try:
        if bar is not None:
            bar.start()
        if serial:
            for s0 in starts:
                results.extend(_run_chunk(trial_fn, s0, seeds[s0:s0 + chunksize], kwargs))
                if bar is not None:
                    bar.update(task, completed=len(results))
        else:
            try:
                pickle.dumps((trial_fn, kwargs))
            except Exception as exc:  # pickling errors come in many types
                raise TypeError(
                    f"trial_fn and its keyword arguments must be picklable (a top-level function) to run "
                    f"on an executor ({type(exc).__name__}: {exc}); use executor='serial' otherwise"
                ) from exc
            futures = [executor.submit(_run_chunk, trial_fn, s0, seeds[s0:s0 + chunksize], kwargs) for s0 in starts]
            done_iter = cf.as_completed(futures) if all(isinstance(f, cf.Future) for f in futures) else futures
            for fut in done_iter:
                results.extend(fut.result())
                if bar is not None:
                    bar.update(task, completed=len(results))
    finally:
        if bar is not None:
            bar.stop()
        if own_pool:
            executor.shutdown(wait=True, cancel_futures=True)

    results.sort(key=lambda r: r[0])
    failed = [(i, msg) for i, row, msg in results if row is None]
    if failed and on_error == "raise":
        i, msg = failed[0]
        raise TrialError(f"trial {i} of {n_trials} failed: {msg}", trial=i)
    return _build_table(results, kwargs, root, n_failed=len(failed))


def _build_table(results: list, kwargs: dict, root: np.random.SeedSequence, n_failed: int) -> TrialTable:
    params: dict = {}
    for _, row, _ in results:
        if row is not None:
            params.update(dict.fromkeys(row))
    names = list(params) or [""]
    trial, parameter, value, error = [], [], [], []
    for i, row, msg in results:
        if row is None:
            for p in names:
                trial.append(i)
                parameter.append(p)
                value.append(np.nan)
                error.append(msg)
        else:
            for p, v in row.items():
                trial.append(i)
                parameter.append(p)
                value.append(v)
                error.append("")
    if n_failed:
        first = next(i for i, row, _ in results if row is None)
        first_msg = next(m for _, row, m in results if row is None)
        warnings.warn(
            f"{n_failed} of {len(results)} trials failed (first: trial {first}: {first_msg}); "
            "their values are NaN, see the 'error' column",
            TrialFailureWarning,
            stacklevel=3,
        )
    cols = {
        "trial": np.asarray(trial, dtype=np.int64),
        "parameter": np.asarray(parameter, dtype=str),
        "value": np.asarray(value, dtype=float),
        "error": np.asarray(error, dtype=str),
    }
    for k, v in kwargs.items():
        if _is_setting(v):
            cols[k] = np.full(len(trial), v)
    entropy = root.entropy if isinstance(root.entropy, int) else None
    return TrialTable(cols, seed_entropy=entropy)
