"""The verdict's compiled distortion evaluations (psdcal.calibration._rules_kernel) against the numpy code they replace.

The angles' sensitivities (:func:`psdcal.calibration._verdict_linear.angle_jacobians`, from
:func:`psdcal.model.distortion.undistort` with its Jacobians) and the one-to-one test of the distortion
(:func:`psdcal.calibration._verdict_rules._monotonic`) run as scalar loops where the calibration's kernels are
loaded; the numpy code is the reference: the same points to the last bit, the Jacobians to rounding (relative
1e-12), the same answer of the test on distortions that fold the sensor and on ones that do not.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from psdcal import _jit
from psdcal.calibration import _verdict_linear as L
from psdcal.calibration import _verdict_rules as R
from psdcal.model.distortion import undistort
from psdcal.model.params import Distortion

pytestmark = pytest.mark.skipif(not _jit.AVAILABLE, reason="numba not installed")

#: Typical sizes of each coefficient (k1, k2, k3, p1, p2, l1, l2) on a sensor of a few mm: the random draws below
#: scale them by up to 3, enough to fold the sensor in some cases.
SCALES = np.array([5e-2, 5e-3, 1e-4, 1e-3, 1e-3, 1e-2, 1e-3])


def _numpy_only(monkeypatch):
    monkeypatch.setattr(_jit, "use_compiled", lambda *a, **k: False)


def test_undistort_jacobians_equal_numpys():
    from psdcal.calibration._rules_kernel import undistort_jacobians

    rng = np.random.default_rng(7)
    for trial in range(100):
        co = rng.normal(size=7) * SCALES * rng.uniform(0, 3)
        if trial % 3 == 0:
            co[5:] = 0.0  # no PSD terms (undistort's other branch of nothing: the same formulas)
        c = rng.normal(size=2) * 0.3
        d = rng.uniform(-3.5, 3.5, size=(49, 2))
        ref = undistort(d, co, c, jacobians=True)
        got = undistort_jacobians(d, co, c)
        assert np.array_equal(ref[0], got[0])
        for a, b in zip(ref[1:], got[1:]):
            assert a.shape == b.shape
            np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-15 * np.max(np.abs(a)))


def _result(rng):
    co = rng.normal(size=7) * SCALES * rng.uniform(0, 3)
    intr = SimpleNamespace(c=tuple(rng.normal(size=2) * 0.3))
    return SimpleNamespace(distortion=Distortion.from_array(co), intrinsics=intr, sensor_mm=(6.4, 4.8))


def test_monotonic_test_answers_as_numpy(monkeypatch):
    rng = np.random.default_rng(3)
    cases = [_result(rng) for _ in range(300)]
    got = [R._monotonic(r) for r in cases]
    _numpy_only(monkeypatch)
    ref = [R._monotonic(r) for r in cases]
    assert got == ref
    assert 20 <= sum(ref) <= 280  # both answers are exercised (folding and one-to-one distortions)


def test_compiled_angle_sensitivities_equal_numpys(monkeypatch):
    from psdcal.calibration.core import calibrate
    from psdcal.study.simulate import simulate_set

    s = simulate_set("lens2", n_images=6, noise_mm=1e-3, seed=2)
    res = calibrate(s.template_mm, s.points_mm, tangential=True, aspect=True, verdict=False)
    grid = np.random.default_rng(1).uniform(-3, 3, size=(49, 2))
    names = ("f_mm", "fy_mm", "cx_mm", "cy_mm", "k1", "k2", "p1", "p2", "k3", "l1", "skew", "g_x2")
    assert _jit.use_compiled(grid.shape[0])  # (calibrate loaded the kernels)
    A, D = L.angle_jacobians(res, grid, names)
    _numpy_only(monkeypatch)
    A0, D0 = L.angle_jacobians(res, grid, names)
    np.testing.assert_allclose(A, A0, rtol=1e-12, atol=1e-14 * np.max(np.abs(A0)))
    np.testing.assert_allclose(D, D0, rtol=1e-12, atol=1e-14 * np.max(np.abs(D0)))


@pytest.mark.parametrize("n", [1, 49, 640])
def test_compiled_field_parts_equal_numpys(n, monkeypatch):
    rng = np.random.default_rng(n)
    pts = rng.uniform(-3, 3, size=(n, 2))
    c, half = np.array([0.2, -0.1]), np.array([3.2, 2.4])
    got = L.field_parts(pts, c, half)
    _numpy_only(monkeypatch)
    ref = L.field_parts(pts, c, half)
    assert got.shape == ref.shape
    assert np.array_equal(got.mono, ref.mono) and np.array_equal(got.R, ref.R)
