"""``--scheduler`` of the commands that run many trials, on a Dask cluster of real worker processes.

The module starts one ``distributed.LocalCluster`` with two worker *processes* (every trial and its
result is pickled across a process boundary, as on a real cluster) and runs ``psdcal reproduce --quick``
and ``psdcal signal-noise`` through its scheduler address; their tables are compared byte for byte with
the serial runs.
"""
from __future__ import annotations

import subprocess
import sys

import pytest

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def cluster():
    """Two worker processes, one thread each, shared by the module's tests."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as c:
        assert len(c.scheduler_info["workers"]) == 2
        yield c


def _workers_imported(cluster, module: str) -> bool:
    """Whether any worker process has imported ``module`` (it ran a task from it; this process did not ship it)."""
    with distributed.Client(cluster) as client:
        return any(client.run(lambda: module in sys.modules).values())


def _reproduce(out, *extra):
    cmd = [sys.executable, "-m", "psdcal.cli", "reproduce", "--quick", "--seed", "3", "--out", str(out), *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc


@pytest.mark.slow
def test_reproduce_quick_on_worker_processes_gives_the_serial_tables(tmp_path, cluster):
    serial = tmp_path / "serial"
    _reproduce(serial, "--workers", "1")
    on_cluster = tmp_path / "cluster"
    _reproduce(on_cluster, "--scheduler", cluster.scheduler_address)
    # the workers ran trials: each holds psdcal's trial module (imported there, not here)
    assert _workers_imported(cluster, "psdcal.study.reproduce.trials")
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


def _signal_noise(*extra):
    cmd = [sys.executable, "-m", "psdcal.cli", "signal-noise", "--snr-db", "30", "--snr-db", "45", "--snr-db", "60",
           "--trials", "300", "--seed", "7", *extra]
    proc = subprocess.run(cmd, capture_output=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def test_signal_noise_on_worker_processes_prints_the_serial_table(cluster):
    serial = _signal_noise()
    assert b"300 trials" in serial and serial.count(b"e-0") >= 12  # the table, 3 rows of 4 numbers
    assert _signal_noise("--scheduler", cluster.scheduler_address) == serial
    assert _signal_noise("--workers", "2") == serial
    assert _workers_imported(cluster, "psdcal.signal.chain")


def test_point_noise_vs_snr_on_the_cluster_is_the_serial_result_bit_for_bit(cluster):
    # the printed table rounds to 3 digits; the arrays themselves must be the same bits
    import numpy as np

    from psdcal.signal.chain import ChainSettings, point_noise_vs_snr

    args = ([35.0, 50.0], ChainSettings(method="bandpass"))
    kw = dict(n=200, rng=11, xy_mm=(1.0, -0.5))
    serial = point_noise_vs_snr(*args, **kw)
    with distributed.Client(cluster) as client:
        remote = point_noise_vs_snr(*args, **kw, executor=client.get_executor())
    for name in ("snr_db", "measured_std_mm", "measured_std_se_mm", "predicted_std_mm", "mean_mm"):
        assert np.array_equal(getattr(remote, name), getattr(serial, name)), name
    # and the SNRs are independent streams: a different seed gives a different result
    other = point_noise_vs_snr(*args, **{**kw, "rng": 12})
    assert not np.array_equal(other.measured_std_mm, serial.measured_std_mm)


def test_signal_noise_unreachable_scheduler_is_one_line_and_exit_2():
    cmd = [sys.executable, "-m", "psdcal.cli", "signal-noise", "--trials", "10", "--scheduler", "tcp://127.0.0.1:9"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env={**__import__("os").environ,
                          "DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT": "2s"})
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert "scheduler" in proc.stderr and "127.0.0.1:9" in proc.stderr
