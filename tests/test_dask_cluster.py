"""A Monte Carlo study on a Dask cluster gives the same table as the serial run.

run_trials seeds each trial from (seed, trial index) only; this runs the
paper's calibration trial on a ``distributed.LocalCluster`` (two in-process
worker threads, started by the test) and compares the tables value by value.
"""
from __future__ import annotations

import numpy as np
import pytest

from psdcal.study.montecarlo import run_trials
from psdcal.study.reproduce import case_trial

distributed = pytest.importorskip("distributed")


def test_dask_local_cluster_gives_the_serial_table():
    kw = dict(lens="lens2", snr_db=60.0, imbalance=False, psd=False)
    serial = run_trials(case_trial, 6, seed=11, executor="serial", progress=False, **kw)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        table = run_trials(case_trial, 6, seed=11, executor=client.get_executor(), progress=False, **kw)
    assert table.parameters == serial.parameters and len(table) == len(serial)
    assert sorted(set(serial.columns["trial"].tolist())) == list(range(6))
    for p in serial.parameters:
        np.testing.assert_array_equal(table.values(p), serial.values(p), err_msg=p)
    assert table.to_csv() == serial.to_csv()
