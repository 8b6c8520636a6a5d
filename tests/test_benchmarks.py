"""The benchmark scripts stay runnable and measure what they claim."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _bench import load_benchmark

from psdcal.model.params import Distortion, Intrinsics
from psdcal.study.simulate import simulate_set

BENCH = Path(__file__).resolve().parent.parent / "benchmarks"


def _load(name):
    return load_benchmark(name, "_bench_")


def test_opencv_conversion_recovers_the_truth_without_distortion():
    """With no distortion and no noise both models are exact: OpenCV's f and C in mm must be the truth."""
    cv2 = pytest.importorskip("cv2")
    bench = _load("bench_opencv")
    lens = (Intrinsics(f_mm=8.0, cx_mm=0.5, cy_mm=-0.7), Distortion())
    s = simulate_set(lens, n_images=9, noise_mm=0.0, seed=3)
    pitch = 0.010
    f, c = bench.opencv_calibrate(cv2, *bench.to_opencv(s, pitch), pitch)
    assert abs(f - 8.0) < 1e-4
    np.testing.assert_allclose(c, [0.5, -0.7], atol=1e-4)
    f, c = bench.psdcal_calibrate(s)
    assert abs(f - 8.0) < 1e-8
    np.testing.assert_allclose(c, [0.5, -0.7], atol=1e-8)


def test_linearised_covariance_of_the_image_cost_is_the_bound():
    """The sandwich covariance reduces to the Cramér-Rao bound when the cost is the likelihood."""
    eff = _load("efficiency")
    s = simulate_set("lens2", n_images=9, noise_mm=0.0, seed=5)
    bound = eff.crb(s, 0.002)
    np.testing.assert_allclose(eff.linearised_covariance(s, 0.002, "image"), bound, rtol=1e-5)
    tpl = eff.linearised_covariance(s, 0.002, "template")
    # a non-likelihood cost is never more efficient (to rounding)
    assert np.all(np.diag(tpl) >= np.diag(bound) * (1 - 1e-6))
    assert np.all(np.linalg.eigvalsh(tpl - bound) > -1e-9 * np.abs(bound).max())


def test_run_all_selects_by_name_and_reports_unknown_names():
    out = subprocess.run([sys.executable, str(BENCH / "run_all.py"), "no-such-bench"], capture_output=True, text=True)
    assert out.returncode == 2 and "no benchmark matches" in out.stderr
    out = subprocess.run([sys.executable, str(BENCH / "run_all.py"), "--sets", "1"], capture_output=True, text=True)
    assert out.returncode == 2 and "must follow '--'" in out.stderr


def test_bench_opencv_runs_end_to_end():
    pytest.importorskip("cv2")
    out = subprocess.run(
        [sys.executable, str(BENCH / "run_all.py"), "opencv", "--", "--sets", "1", "--repeats", "1", "--no-startup"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert "ratio psdcal/OpenCV" in out.stdout and out.stdout.count("lens") >= 4


def test_bench_opencv_start_up_timing_runs_fresh_processes():
    pytest.importorskip("cv2")
    bench = _load("bench_opencv")
    out = bench.first_call_seconds(repeats=1, cold=False)
    assert set(out) == {"psdcal, kernels from the disk cache", "OpenCV"}
    # a fresh interpreter importing numpy and the library: well above a warm call, well below a minute
    assert all(0.01 < v < 60 for v in out.values()), out


def test_bench_montecarlo_runs(capsys):
    bench = _load("bench_montecarlo")
    assert bench.main(["--trials", "1"]) == 0
    out = capsys.readouterr().out
    rows = [ln.split() for ln in out.splitlines() if ln.startswith(("lens1", "lens2"))]
    assert len(rows) == 2
    for r in rows:
        sim_ms, sampled_ms, calib_ms, ratio = (float(v) for v in r[1:5])
        incl, excl, failed = float(r[5]), float(r[6]), int(r[7])
        assert min(sim_ms, sampled_ms, calib_ms, incl, excl) > 0 and failed == 0
        assert ratio == pytest.approx(sim_ms / calib_ms, rel=0.05, abs=0.01)


def test_bench_locate_covers_locate_amplitudes_and_the_live_path(capsys):
    """bench_locate measures locate (CSV and npy), amplitudes (CSV and npy) and the live path against the bare
    lock-in, with 1 and 2 carriers; the live path writes the same rows as the file path."""
    bench = _load("bench_locate")
    res = bench.main(["--seconds", "2", "--repeats", "1", "--markdown"])
    got = {(c["what"], c["carriers"], c["format"]) for c in res["cases"]}
    want = {(w, k, f) for k in (1, 2) for w, f in (("locate", "csv"), ("locate", "npy"), ("amplitudes", "csv"),
                                                   ("amplitudes", "npy"), ("live", "csv"))}
    assert got == want
    rows = {(c["what"], c["carriers"], c["format"]): c["rows"] for c in res["cases"]}
    for k in (1, 2):
        assert rows[("live", k, "csv")] == rows[("locate", k, "csv")] == k * int(2 * bench.RATE_HZ) // 1250
    assert all(0 < c["fraction_of_bare_lockin"] < 5 for c in res["cases"])
    assert "| live | 2 | csv |" in capsys.readouterr().out


def test_bench_startup_light_commands_table(capsys):
    """bench_startup's table 1 runs fresh processes and measures them against `psdcal --help`."""
    bench = _load("bench_startup")
    import os

    rows = bench.startup_table(1, {**os.environ, "OMP_NUM_THREADS": "1"})
    names = [r[0] for r in rows]
    assert names[1].startswith("psdcal --help") and any(n.startswith("locate, 1 sensor") for n in names)
    assert any("aoa" in n for n in names) and any("pose" in n for n in names)
    assert sum("compiled kernels forced" in n for n in names) == 4
    for name, cpu, above in rows:
        assert 0.0 < float(cpu) < 60.0, name
        if name.startswith(("locate", "aoa", "pose")):
            assert float(above) == pytest.approx(float(cpu) - float(rows[1][1]), abs=2e-3)


def test_bench_default_times_the_calibration_with_and_without_the_verdict_against_opencv(capsys):
    """bench_default's three cases: the psdcal calls give the same f with and without the verdict, OpenCV's
    call converges on the same points, and the printed ratios are the times' ratios."""
    cv2 = pytest.importorskip("cv2")
    bench = _load("bench_default")
    cases = bench.cases(cv2)
    assert [c[0].split(",")[0] for c in cases] == ["zhang1998 (real)", "synthetic", "synthetic"]
    for name, with_v, fit, ocv in cases:
        a, b = with_v(), fit()
        assert a.intrinsics.f_mm == pytest.approx(b.intrinsics.f_mm, rel=1e-12), name
        assert a.verdict is not None and b.verdict is None
        rms = ocv()[0]
        assert 0 < rms < 5, name  # pixels
    assert bench.main(["--repeats", "1", "--no-cli", "--markdown"]) == 0
    rows = [r for r in capsys.readouterr().out.splitlines() if r.startswith("| zhang") or r.startswith("| synth")]
    assert len(rows) == 3
    for r in rows:
        cells = [c.strip() for c in r.strip("|").split("|")]
        fit_ms, both_ms, ocv_ms = (float(c) for c in cells[1:4])
        assert float(cells[4].rstrip("x")) == pytest.approx(fit_ms / ocv_ms, abs=0.006)
        assert float(cells[5].rstrip("x")) == pytest.approx(both_ms / ocv_ms, abs=0.006)
