"""``psdcal reproduce --scheduler``: the whole quick study on a Dask cluster of real worker processes.

The test starts a ``distributed.LocalCluster`` with two worker *processes* (every trial and its result
is pickled across a process boundary, as on a real cluster), runs ``psdcal reproduce --quick`` through
its scheduler address, and compares every written table byte for byte with the serial run.
"""
from __future__ import annotations

import subprocess
import sys

import pytest

distributed = pytest.importorskip("distributed")


def _reproduce(out, *extra):
    cmd = [sys.executable, "-m", "psdcal.cli", "reproduce", "--quick", "--seed", "3", "--out", str(out), *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc


@pytest.mark.slow
def test_reproduce_quick_on_worker_processes_gives_the_serial_tables(tmp_path):
    serial = tmp_path / "serial"
    _reproduce(serial, "--workers", "1")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        pids = set(cluster.scheduler_info["workers"])
        assert len(pids) == 2
        on_cluster = tmp_path / "cluster"
        _reproduce(on_cluster, "--scheduler", cluster.scheduler_address)
        with distributed.Client(cluster) as client:
            # the workers ran trials: each holds psdcal's trial module (imported there, not here)
            mods = client.run(lambda: "psdcal.study.reproduce.trials" in sys.modules)
    assert any(mods.values())
    tables = sorted(p.name for p in serial.iterdir() if p.suffix == ".csv")
    assert len(tables) >= 11
    assert tables == sorted(p.name for p in on_cluster.iterdir() if p.suffix == ".csv")
    for name in tables:
        assert (on_cluster / name).read_bytes() == (serial / name).read_bytes(), name


def test_unreachable_scheduler_is_one_line_and_exit_2(tmp_path):
    cmd = [sys.executable, "-m", "psdcal.cli", "reproduce", "--quick", "--table", "1", "--out", str(tmp_path / "o"),
           "--scheduler", "tcp://127.0.0.1:9"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env={**__import__("os").environ,
                          "DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT": "2s"})
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert "scheduler" in proc.stderr and "127.0.0.1:9" in proc.stderr
    assert not (tmp_path / "o").exists()
