"""Tests of the Monte Carlo runner (psdcal.study.montecarlo)."""
from __future__ import annotations

import concurrent.futures as cf
import csv
import io
import math

import numpy as np
import pytest

from psdcal.study import montecarlo as mc
from psdcal.signal.chain import ChainSettings, measure_point_trial

FAIL_BELOW = 0.25


def gaussian_trial(rng, *, scale=1.0, shift=0.0):
    """Two parameters from one draw each."""
    a, b = rng.standard_normal(2)
    return {"a": shift + scale * a, "b": scale * b**2}


def sometimes_failing_trial(rng, *, threshold=FAIL_BELOW):
    u = rng.uniform()
    if u < threshold:
        raise ValueError(f"unlucky draw {u:.3f}")
    return {"u": u}


def returns_list_trial(rng):
    return [1.0, 2.0]


def _expected_failures(seed, n, threshold=FAIL_BELOW):
    kids = np.random.SeedSequence(seed).spawn(n)
    return [i for i, k in enumerate(kids) if np.random.default_rng(k).uniform() < threshold]


def _same(t1: mc.TrialTable, t2: mc.TrialTable) -> bool:
    return list(t1.columns) == list(t2.columns) and all(
        np.array_equal(t1.columns[k], t2.columns[k]) for k in t1.columns
    )


def test_serial_and_process_pool_give_identical_results():
    kw = dict(seed=2024, progress=False, scale=2.0)
    serial = mc.run_trials(gaussian_trial, 23, executor="serial", **kw)
    pooled = mc.run_trials(gaussian_trial, 23, max_workers=2, chunksize=3, **kw)
    with cf.ThreadPoolExecutor(max_workers=3) as ex:
        threaded = mc.run_trials(gaussian_trial, 23, executor=ex, chunksize=1, **kw)
    assert _same(serial, pooled) and _same(serial, threaded)
    assert len(serial) == 46 and serial.parameters == ("a", "b")
    np.testing.assert_array_equal(serial.columns["trial"], np.repeat(np.arange(23), 2))
    assert np.all(serial.columns["scale"] == 2.0)


def test_results_depend_only_on_seed_and_trial_index():
    a = mc.run_trials(gaussian_trial, 10, seed=5, executor="serial", chunksize=1, progress=False)
    b = mc.run_trials(gaussian_trial, 10, seed=np.random.SeedSequence(5), executor="serial", chunksize=4,
                      progress=False)
    c = mc.run_trials(gaussian_trial, 10, seed=6, executor="serial", progress=False)
    assert _same(a, b) and not np.array_equal(a.values("a"), c.values("a"))
    # trial i uses child i of the seed sequence: the first 10 of 20 trials are the same 10
    d = mc.run_trials(gaussian_trial, 20, seed=5, executor="serial", progress=False)
    np.testing.assert_array_equal(d.values("a")[:10], a.values("a"))
    rng0 = np.random.default_rng(np.random.SeedSequence(5).spawn(1)[0])
    assert a.values("a")[0] == rng0.standard_normal(2)[0]


@pytest.mark.parametrize("executor", ["serial", "pool"])
def test_failing_trials_are_recorded_with_their_index(executor):
    kw = {"executor": "serial"} if executor == "serial" else {"max_workers": 2}
    with pytest.warns(mc.TrialFailureWarning, match=r"trial \d+"):
        table = mc.run_trials(sometimes_failing_trial, 30, seed=7, progress=False, **kw)
    want = _expected_failures(7, 30)
    assert 0 < len(want) < 30
    np.testing.assert_array_equal(table.failed_trials, want)
    rows = [r for r in table.rows() if r["trial"] in want]
    assert len(rows) == len(want)
    assert all(math.isnan(r["value"]) and r["error"].startswith("ValueError: unlucky draw") for r in rows)
    assert all(r["error"] == "" for r in table.rows() if r["trial"] not in want)
    s = table.summary()[0]
    assert (s.parameter, s.n, s.n_failed) == ("u", 30 - len(want), len(want))


def test_failing_trial_raises_when_asked():
    want = _expected_failures(7, 30)
    with pytest.raises(mc.TrialError, match=f"trial {want[0]} of 30") as info:
        mc.run_trials(sometimes_failing_trial, 30, seed=7, executor="serial", progress=False, on_error="raise")
    assert info.value.trial == want[0]


def test_all_trials_failing_and_bad_results():
    with pytest.warns(mc.TrialFailureWarning):
        table = mc.run_trials(sometimes_failing_trial, 4, seed=1, executor="serial", progress=False, threshold=2.0)
    assert len(table) == 4 and np.all(np.isnan(table.columns["value"]))
    with pytest.warns(mc.TrialFailureWarning):
        table = mc.run_trials(returns_list_trial, 3, seed=1, executor="serial", progress=False)
    assert table.columns["error"][0].startswith("TypeError")


def test_unpicklable_trial_needs_serial():
    with pytest.raises(TypeError, match="picklable"):
        mc.run_trials(lambda rng: {"x": 1.0}, 3, seed=1, max_workers=2, progress=False)
    table = mc.run_trials(lambda rng: {"x": 1.0}, 3, seed=1, executor="serial", progress=False)
    assert table.values("x").tolist() == [1.0, 1.0, 1.0]


def test_summary_statistics():
    table = mc.run_trials(gaussian_trial, 400, seed=3, executor="serial", progress=False, shift=1.5)
    a = table.values("a")
    s = {p.parameter: p for p in table.summary()}["a"]
    assert s.n == 400 and s.n_failed == 0
    assert s.mean == pytest.approx(a.mean()) and s.std == pytest.approx(a.std(ddof=1))
    assert s.sem == pytest.approx(a.std(ddof=1) / 20.0)
    # normal data: se(std) ~ std / sqrt(2 (n - 1))
    assert s.se_std == pytest.approx(s.std / math.sqrt(2 * 399), rel=0.15)
    assert s.settings == {"shift": 1.5}
    assert abs(s.mean - 1.5) < 4 * s.sem


def test_std_standard_error_formula():
    x = np.random.default_rng(0).standard_normal(200_000)
    assert mc.std_standard_error(x) == pytest.approx(1 / math.sqrt(2 * 199_999), rel=0.02)
    assert math.isnan(mc.std_standard_error([1.0])) and math.isnan(mc.std_standard_error([2.0, 2.0]))


def test_csv_and_concat(tmp_path):
    t40 = mc.run_trials(measure_point_trial, 5, seed=1, executor="serial", progress=False, snr_db=40.0)
    t50 = mc.run_trials(measure_point_trial, 5, seed=1, executor="serial", progress=False, snr_db=50.0,
                        settings=ChainSettings())
    plain = mc.run_trials(measure_point_trial, 2, seed=1, executor="serial", progress=False)
    with pytest.raises(ValueError, match="same columns"):
        mc.TrialTable.concat([t40, plain])
    both = mc.TrialTable.concat([t40, t40])
    assert len(both) == 20
    path = tmp_path / "out" / "trials.csv"
    mc.write_csv(t40, path)
    rows = list(csv.DictReader(io.StringIO(path.read_text())))
    assert list(rows[0]) == ["trial", "parameter", "value", "error", "snr_db"]
    assert [float(r["value"]) for r in rows] == t40.columns["value"].tolist()
    # settings columns: scalars only (the ChainSettings object is not a column)
    assert t50.setting_names == ("snr_db",)
    summ = mc.summarise(mc.TrialTable.concat([t40, t50]))
    assert [(s.parameter, s.settings["snr_db"]) for s in summ] == [
        ("x_mm", 40.0), ("y_mm", 40.0), ("x_mm", 50.0), ("y_mm", 50.0)]


def test_signal_chain_trial_serial_equals_pool():
    kw = dict(seed=11, progress=True, snr_db=40.0, x_mm=1.0, y_mm=-2.0)  # progress off: not a TTY
    a = mc.run_trials(measure_point_trial, 12, executor="serial", **kw)
    b = mc.run_trials(measure_point_trial, 12, max_workers=2, **kw)
    assert _same(a, b)
    assert np.all(np.abs(a.values("x_mm") - 1.0) < 0.01)


def test_bad_arguments():
    with pytest.raises(ValueError):
        mc.run_trials(gaussian_trial, 0, seed=1, executor="serial")
    with pytest.raises(ValueError):
        mc.run_trials(gaussian_trial, 2, seed=1, executor="threads")
    with pytest.raises(ValueError):
        mc.run_trials(gaussian_trial, 2, seed=1, executor="serial", on_error="ignore")
    with pytest.raises(ValueError):
        mc.run_trials(gaussian_trial, 2, seed=1, executor="serial", value=3)
    with pytest.raises(KeyError):
        mc.run_trials(gaussian_trial, 2, seed=1, executor="serial", progress=False).values("c")


def _blas_threads_trial(rng):
    from threadpoolctl import threadpool_info

    blas = [i["num_threads"] for i in threadpool_info() if i.get("user_api") == "blas"]
    return {"blas_threads": float(max(blas)) if blas else 1.0}


@pytest.mark.parametrize("executor", ["serial", "pool"])
def test_trials_run_on_one_blas_thread(executor):
    # the executor's workers are the parallelism: a BLAS thread pool in each would oversubscribe the cores
    pytest.importorskip("threadpoolctl")
    if executor == "pool":
        with cf.ProcessPoolExecutor(max_workers=2) as ex:
            table = mc.run_trials(_blas_threads_trial, 4, seed=0, executor=ex, progress=False)
    else:
        table = mc.run_trials(_blas_threads_trial, 4, seed=0, executor="serial", progress=False)
    assert np.all(table.values("blas_threads") == 1.0)
