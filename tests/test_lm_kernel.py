"""The compiled LM loop (image and template costs) against the Python loop it replaces.

:func:`psdcal.calibration._lm_kernel.lm_image` runs the iterations of
:func:`psdcal.calibration._lm.levenberg_marquardt` (with the compiled
image cost) in one call; ``_refine.COMPILED_LOOP = False`` selects the Python
loop, the reference. Both must reach the same solution, covariance and
stopping reason on every kind of problem the image cost takes.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from psdcal import _jit
from psdcal.calibration import _refine
from psdcal.calibration._refine import Problem, SolverOptions, refine
from psdcal.model.params import Distortion, ModelSpec
from psdcal.study.simulate import simulate_set

pytestmark = pytest.mark.skipif(not _jit.enabled(), reason="compiled kernels disabled")


@pytest.fixture
def both(monkeypatch):
    """refine(...) with the compiled loop and with the Python loop: (compiled, reference)."""
    monkeypatch.setattr(_jit, "_MODE", "always")

    def run(*args, **kw):
        monkeypatch.setattr(_refine, "COMPILED_LOOP", True)
        a = refine(*args, **kw)
        monkeypatch.setattr(_refine, "COMPILED_LOOP", False)
        b = refine(*args, **kw)
        return a, b

    return run


def _start(s, spec, seed=0):
    """A start near the truth (perturbed poses and parameters), as the linear stage gives one."""
    rng = np.random.default_rng(seed)
    intr = replace(s.intrinsics, f_mm=s.intrinsics.f_mm * 1.02, cx_mm=s.intrinsics.cx_mm + 0.1,
                   fy_mm=s.intrinsics.f_mm * 0.99 if spec.aspect else None)
    dist = Distortion(k1=0.5 * s.distortion.k1)
    rv = s.rvecs + 0.01 * rng.standard_normal(s.rvecs.shape)
    tv = s.tvecs_mm * (1 + 0.01 * rng.standard_normal(s.tvecs_mm.shape))
    return intr, dist, rv, tv


def _assert_same(a, b):
    sd = np.sqrt(np.diag(b.covariance_global))
    ng = sd.size
    assert a.converged == b.converged
    assert a.message == b.message
    assert abs(a.iterations - b.iterations) <= 1
    np.testing.assert_allclose(a.z[:ng], b.z[:ng], rtol=0, atol=1e-6 * sd.min())
    np.testing.assert_allclose(a.z, b.z, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(a.cost_rms, b.cost_rms, rtol=1e-10)
    np.testing.assert_allclose(a.covariance_global, b.covariance_global, rtol=1e-7, atol=1e-7 * np.abs(b.covariance_global).max())
    np.testing.assert_allclose(a.pose_covariance, b.pose_covariance, rtol=1e-7, atol=1e-7 * np.abs(b.pose_covariance).max())
    np.testing.assert_allclose(a.residuals, b.residuals, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.jacobian_compact, b.jacobian_compact, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(a.model_mm, b.model_mm, rtol=0, atol=1e-12)


@pytest.mark.parametrize("lens, n, spec", [
    ("lens2", 5, ModelSpec(radial=2, tangential=False)),
    ("lens1", 9, ModelSpec(radial=2, tangential=True)),
    ("lens2", 8, ModelSpec(radial=3, tangential=True, psd_radial=1, aspect=True)),
    ("lens1", 6, ModelSpec(radial=2, tangential=False, skew=True)),
])
def test_compiled_loop_equals_python_loop(both, lens, n, spec):
    s = simulate_set(lens, n_images=n, noise_mm=0.002, seed=n)
    pts = s.points_mm.copy()
    pts[1, 3] = np.nan  # a missing point: views of unequal length
    pts[n - 1, :4] = np.nan
    prob = Problem(s.template_mm, pts, spec)
    intr, dist, rv, tv = _start(s, spec, seed=n)
    a, b = both(prob, intr, dist, np.ones(4), rv, tv)
    assert b.converged
    _assert_same(a, b)
    # the solution is the truth to within its standard errors (the loop solved the problem, not only agreed)
    assert abs(a.intrinsics.f_mm - s.intrinsics.f_mm) < 6 * np.sqrt(a.covariance_global[0, 0])


@pytest.mark.parametrize("lens, n, spec", [
    ("lens2", 9, ModelSpec(radial=2, tangential=False)),
    ("lens1", 7, ModelSpec(radial=2, tangential=True, aspect=True)),
])
def test_compiled_loop_equals_python_loop_on_the_template_cost(both, lens, n, spec):
    s = simulate_set(lens, n_images=n, noise_mm=0.002, seed=n + 1)
    pts = s.points_mm.copy()
    pts[2, 4] = np.nan
    prob = Problem(s.template_mm, pts, spec, cost="template")
    intr, dist, rv, tv = _start(s, spec, seed=n)
    a, b = both(prob, intr, dist, np.ones(4), rv, tv)
    assert b.converged and a.model_mm is None and b.model_mm is None
    sd = np.sqrt(np.diag(b.covariance_global))
    assert a.converged == b.converged and a.message == b.message and abs(a.iterations - b.iterations) <= 1
    np.testing.assert_allclose(a.z[: sd.size], b.z[: sd.size], rtol=0, atol=1e-6 * sd.min())
    np.testing.assert_allclose(a.z, b.z, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(a.cost_rms, b.cost_rms, rtol=1e-10)
    np.testing.assert_allclose(a.covariance_global, b.covariance_global, rtol=1e-7, atol=1e-7 * np.abs(b.covariance_global).max())
    np.testing.assert_allclose(a.residuals, b.residuals, rtol=0, atol=1e-12)


def test_template_cost_iteration_limit_stops_both_at_the_same_point(both):
    s = simulate_set("lens1", n_images=7, noise_mm=0.002, seed=5)
    spec = ModelSpec(radial=2, tangential=False)
    prob = Problem(s.template_mm, s.points_mm, spec, cost="template")
    intr, dist, rv, tv = _start(s, spec, seed=5)
    a, b = both(prob, intr, dist, np.ones(4), rv, tv, SolverOptions(max_iterations=2))
    assert not a.converged and not b.converged and a.iterations == b.iterations
    np.testing.assert_allclose(a.z, b.z, rtol=1e-10, atol=1e-13)


def test_compiled_loop_with_fitted_gains_and_fixed_parameters(both):
    from psdcal.model.readout import gain_map

    s = simulate_set("lens2", n_images=8, noise_mm=0.002, seed=4)
    raw = gain_map(s.points_mm, np.array([1.0, 1.02, 0.98, 1.01]))  # read out through unequal channel gains
    spec = ModelSpec(radial=2, tangential=False, fit_gains=True)
    prob = Problem(s.template_mm, raw, spec, fixed=("cy_mm",))
    intr, dist, rv, tv = _start(s, spec, seed=4)
    a, b = both(prob, intr, dist, np.ones(4), rv, tv)
    assert "cy_mm" not in prob.names and "g_x2" in prob.names
    _assert_same(a, b)


def test_noiseless_data_converge_to_round_off_in_both(both):
    s = simulate_set("lens2", n_images=6, noise_mm=0.0, seed=2)
    spec = ModelSpec(radial=2, tangential=False)
    prob = Problem(s.template_mm, s.points_mm, spec)
    intr, dist, rv, tv = _start(s, spec, seed=2)
    a, b = both(prob, intr, dist, np.ones(4), rv, tv)
    for r in (a, b):
        assert r.converged
        assert r.cost_rms < 1e-12
        np.testing.assert_allclose(r.intrinsics.f_mm, s.intrinsics.f_mm, rtol=1e-9)


@pytest.mark.parametrize("iterations", [1, 2, 3])
def test_iteration_limit_stops_both_at_the_same_point(both, iterations):
    s = simulate_set("lens1", n_images=7, noise_mm=0.002, seed=5)
    spec = ModelSpec(radial=2, tangential=True)
    prob = Problem(s.template_mm, s.points_mm, spec)
    intr, dist, rv, tv = _start(s, spec, seed=5)
    opts = SolverOptions(max_iterations=iterations)
    a, b = both(prob, intr, dist, np.ones(4), rv, tv, opts)
    assert not a.converged and not b.converged
    assert a.message == b.message == "iteration limit reached"
    assert a.iterations == b.iterations
    np.testing.assert_allclose(a.z, b.z, rtol=1e-10, atol=1e-13)


def test_bad_residuals_are_replaced_as_the_python_loop_does():
    from psdcal.calibration._lm_kernel import _evaluate

    s = simulate_set("lens2", n_images=3, noise_mm=0.002, seed=1)
    spec = ModelSpec(radial=2, tangential=False)
    prob = Problem(s.template_mm, s.points_mm, spec)
    ev = _refine.Evaluator(prob, s.intrinsics, s.distortion, np.ones(4))
    if ev._kernel is None:
        pytest.skip("numpy path")
    z = prob.pack(s.intrinsics, s.distortion, np.ones(4), s.rvecs, s.tvecs_mm)
    ng = prob.n_global
    z[ng : ng + 3] = 0.0  # view 0 parallel to the sensor ...
    z[ng + 5] = 0.0  # ... in its plane: every point at Z = 0 projects to infinity
    r_ref, J_ref = ev.evaluate_compact(z)
    N = ev.d_meas.shape[0]
    # the kernel writes into given arrays: start them with garbage, every entry must be overwritten
    r, J, d = np.full(2 * N, 7.0), np.full((2 * N, ng + 6), np.nan), np.full((N, 2), np.inf)
    ok = np.zeros(N, dtype=bool)
    _evaluate(ev.P, ev.img_idx, ev._theta0, ev._separate_fy, ev._gmap, ev._gain_basis, ev.d_meas, z,
              prob.n_images, np.full(ev.d_meas.shape, np.nan), 1e-13, 50, r, J, d, ok, d)
    assert np.any(r_ref == 1e3), "the test must reach the bad-residual path"
    np.testing.assert_array_equal(r == 1e3, r_ref == 1e3)
    assert np.all(np.isfinite(r)) and np.all(np.isfinite(J))
    np.testing.assert_allclose(r, r_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(J, J_ref, rtol=1e-10, atol=1e-12)


def test_compiled_undistort_is_the_numpy_one_to_the_bit():
    from psdcal.calibration._image_kernel import undistort_points
    from psdcal.model.distortion import undistort

    rng = np.random.default_rng(7)
    d = rng.uniform(-4.5, 4.5, (6, 25, 2))
    d[2, 3] = np.nan
    for coef in (np.array([-3e-3, 2e-5, 0, 0, 0, 0, 0]), np.array([2e-3, -1e-5, 3e-7, 1e-4, -2e-4, -1e-3, 4e-6])):
        c = np.array([0.3, -0.2])
        np.testing.assert_array_equal(undistort_points(d, coef, c), undistort(d, coef, c))


def test_extent_skips_missing_points():
    from psdcal.calibration.starts import _extent

    X = np.array([[[1.0, -3.0], [np.nan, np.nan]], [[0.5, 2.0], [np.nan, np.nan]]])
    assert _extent(X) == 6.0
    assert _extent(np.full((2, 3, 2), np.nan)) == 1.0


def test_ragged_points_are_an_input_error_not_a_numpy_one():
    from psdcal.calibration.core import calibrate
    from psdcal.errors import InputError

    with pytest.raises(InputError, match="numeric arrays"):
        calibrate(np.zeros((4, 2)), [[[0.0, 0.0]], [[1.0, 1.0], [2.0, 2.0]]], verdict=False)
