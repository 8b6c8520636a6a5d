"""The compiled image cost (psdcal.calibration._image_kernel) against its numpy reference.

The numpy ``Evaluator`` code, ``distortion.distort`` and ``rodrigues_batch``
are the reference (each tested against finite differences and closed forms
elsewhere); the kernel must give the same residuals and Jacobian to
round-off, on every model variant, with missing points, and the whole
calibration must give the same answer with and without it.
"""
from __future__ import annotations

import numpy as np
import pytest

from psdcal import _jit
from psdcal.calibration._refine import Evaluator, Problem, rodrigues_batch
from psdcal.calibration.core import calibrate
from psdcal.model.params import Distortion, ModelSpec
from psdcal.study.simulate import simulate_set

pytestmark = pytest.mark.skipif(not _jit.enabled(), reason="numba not available or PSDCAL_JIT=0")


@pytest.fixture(autouse=True)
def _compiled_always(monkeypatch):
    """The library's default mode: an in-process `psdcal calibrate` of an earlier test leaves "auto", where
    these small problems go to the numpy path unless another module happened to load the kernels."""
    monkeypatch.setattr(_jit, "_MODE", "always")

SPECS = [
    ModelSpec(radial=3, tangential=True, psd_radial=2, skew=True),
    ModelSpec(radial=2, tangential=False, aspect=True),
    ModelSpec(radial=1, tangential=True, psd_radial=1),
    ModelSpec(radial=0, tangential=False),
    ModelSpec(radial=2, tangential=False, fit_gains=True),
]


def _pair(lens, spec, seed, cost="image"):
    """A perturbed state and two evaluators of one problem: compiled and numpy."""
    s = simulate_set(lens, n_images=9, noise_mm=0.002, seed=seed, psd_l1=-0.002, tangential=(1e-4, -2e-4))
    pts = s.points_mm.copy()
    pts[1, 3] = np.nan
    pts[4, :2] = np.nan
    prob = Problem(s.template_mm, pts, spec, cost=cost)
    dist = Distortion.from_array(s.distortion.as_array() * np.array([1, 1, 1, 1, 1, 1, 1]))
    gains = np.array([1.0, 1.01, 0.98, 1.02]) if spec.fit_gains else np.ones(4)
    fast = Evaluator(prob, s.intrinsics, dist, gains)
    ref = Evaluator(prob, s.intrinsics, dist, gains)
    ref._kernel = ref._tkernel = ref._normal = None
    assert (fast._kernel if cost == "image" else fast._tkernel) is not None
    z = prob.pack(s.intrinsics, dist, gains, s.rvecs, s.tvecs_mm)
    rng = np.random.default_rng(seed)
    z = z * (1 + 1e-3 * rng.standard_normal(z.size)) + 1e-6 * rng.standard_normal(z.size)
    return prob, fast, ref, z


@pytest.mark.parametrize("lens", ["lens1", "lens2"])
@pytest.mark.parametrize("k,cost", [(k, c) for k in range(len(SPECS)) for c in ("image", "template")
                                    if c == "image" or not SPECS[k].fit_gains])  # gains: image cost only
def test_kernel_matches_numpy_evaluator(lens, k, cost):
    prob, fast, ref, z = _pair(lens, SPECS[k], seed=10 + k, cost=cost)
    r_f, J_f = fast.evaluate(z)
    r_r, J_r = ref.evaluate(z)
    assert r_f.shape == r_r.shape and J_f.shape == J_r.shape
    np.testing.assert_allclose(r_f, r_r, rtol=0, atol=1e-12)
    scale = np.abs(J_r).max(axis=0) + 1e-30  # column scale: parameters differ by orders of magnitude
    assert np.max(np.abs(J_f - J_r) / scale) < 1e-9
    A, g = fast.normal_equations(J_f, r_f)  # the block-sparse normal equations
    np.testing.assert_allclose(A, J_f.T @ J_f, rtol=1e-12, atol=1e-12 * np.abs(A).max())
    np.testing.assert_allclose(g, J_f.T @ r_f, rtol=1e-12, atol=1e-12 * np.abs(g).max())
    # the residual-only path agrees with the full one
    np.testing.assert_allclose(fast.residuals(z + 0.0), r_f, rtol=0, atol=1e-12)
    z2 = z.copy()
    z2[0] *= 1 + 1e-4
    np.testing.assert_allclose(fast.residuals(z2), ref.residuals(z2), rtol=0, atol=1e-12)


def test_kernel_rotations_match_rodrigues_including_zero_angle():
    from psdcal.calibration._image_kernel import _rotations

    rng = np.random.default_rng(0)
    rv = np.concatenate([rng.normal(size=(5, 3)), np.zeros((1, 3)), 1e-14 * np.ones((1, 3))])
    R, dR = _rotations(rv, True)
    R0, dR0 = rodrigues_batch(rv)
    np.testing.assert_allclose(R, R0, atol=1e-14)
    np.testing.assert_allclose(dR, dR0, atol=1e-12)


def test_kernel_reports_points_without_an_inverse():
    """A strongly folding lens: the kernel's convergence flags equal distort()'s."""
    from psdcal.calibration._image_kernel import image_model, global_map
    from psdcal.model.distortion import distort

    rng = np.random.default_rng(5)
    n = 400
    P = rng.uniform(-40, 40, size=(n, 2))
    coef = np.array([-0.02, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # x = d (1 + k1 r^2) folds at r^2 = -1 / (3 k1): |x| <= 2.7 mm
    poses = np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 200.0]])
    intr = np.array([20.0, 0.1, -0.2, 0.0, 20.0])
    d, ok, _, _ = image_model(P, np.zeros(n, dtype=np.int64), np.concatenate([intr, coef, np.ones(4)]), False, poses,
                              np.full((n, 2), np.nan), P * 0.1, global_map(["f_mm"]), False, 1e-13, 50,
                              np.zeros((0, 3, 3)))
    x = P * 0.1 + intr[1:3]
    ref = distort(x, coef, intr[1:3])
    assert 0 < ok.sum() < n  # the test covers both outcomes
    np.testing.assert_array_equal(ok, ref.converged)
    np.testing.assert_allclose(d[ok], ref.d_mm[ok], atol=1e-12)


@pytest.mark.parametrize("lens,kw", [
    ("lens1", dict(radial=2, tangential=False)),
    ("lens1", dict(radial=2, tangential=True, cost="template")),
    ("lens2", dict(radial=3, tangential=True, psd_radial=1)),
    ("lens2", dict(radial=2, tangential=True, skew=True)),
    ("lens2", dict(radial=2, tangential=False, fit_gains=True)),
])
def test_calibration_is_the_same_with_and_without_the_kernel(lens, kw, monkeypatch):
    s = simulate_set(lens, n_images=10, noise_mm=0.002, seed=4, psd_l1=-0.002 if kw.get("psd_radial") else 0.0)
    fast = calibrate(s.template_mm, s.points_mm, **kw)
    monkeypatch.setattr(_jit, "AVAILABLE", False)
    ref = calibrate(s.template_mm, s.points_mm, **kw)
    for name in fast.param_names:
        a, b = fast.parameter(name), ref.parameter(name)
        assert abs(a - b) <= 1e-6 * fast.std[name], name  # same minimum, well inside the noise
    assert abs(fast.rms_mm - ref.rms_mm) <= 1e-9 * ref.rms_mm


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=60, deadline=None)
@given(
    k1=st.floats(-0.02, 0.02), k2=st.floats(-1e-4, 1e-4), p1=st.floats(-1e-3, 1e-3), p2=st.floats(-1e-3, 1e-3),
    l1=st.floats(-5e-3, 5e-3), cx=st.floats(-1, 1), cy=st.floats(-1, 1), seed=st.integers(0, 2**16),
)
def test_kernel_inverse_is_an_inverse_over_the_sensor(k1, k2, p1, p2, l1, cx, cy, seed):
    """Property: where the kernel's Newton inverse converges, undistort(d) == x.

    It converges exactly where distort() converges from one of the kernel's
    starts (here: the fixed-point start, or the measured point).
    """
    from psdcal.calibration._image_kernel import global_map, image_model
    from psdcal.model.distortion import distort, undistort

    coef = np.array([k1, k2, 0.0, p1, p2, l1, 0.0])
    c = np.array([cx, cy])
    d_true = np.random.default_rng(seed).uniform(-4.5, 4.5, size=(50, 2))  # on the 9 x 9 mm PSD
    x = undistort(d_true, coef, c)
    # a view straight on, f = 1, so that the ideal point is x = P + c for template point P = x - c
    poses = np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 1.0]])
    theta = np.concatenate([[1.0, cx, cy, 0.0, 1.0], coef, np.ones(4)])
    meas = d_true + 0.01
    d, ok, y, _ = image_model(x - c, np.zeros(len(x), dtype=np.int64), theta, False, poses, np.full(x.shape, np.nan),
                              meas, global_map(["f_mm"]), False, 1e-13, 50, np.zeros((0, 3, 3)))
    ref = distort(x, coef, c).converged | distort(x, coef, c, d0_mm=meas).converged
    np.testing.assert_array_equal(ok, ref)
    np.testing.assert_array_equal(y, d)  # no gains: the modelled point is the spot position
    np.testing.assert_allclose(undistort(d[ok], coef, c), x[ok], rtol=0, atol=1e-11)


@pytest.mark.parametrize("k", range(len(SPECS)))
def test_image_model_into_overwrites_its_arrays_with_image_model_s_values(k):
    """The LM loop's buffers: every entry written (garbage in them does not show), the same bits as image_model;
    the PSD columns are computed only when asked for, the others unchanged by that."""
    from psdcal.calibration._image_kernel import GLOBAL_ORDER, image_model, image_model_into

    prob, fast, _, z = _pair("lens2", SPECS[k], k)
    theta = fast._theta(z)
    poses = z[fast._gmap.size:].reshape(-1, 6)
    N = fast.P.shape[0]
    args = (fast.P, fast.img_idx, theta, fast._separate_fy, poses, np.full((N, 2), np.nan), fast.d_meas)
    gains_on = fast._gain_basis.shape[0] == 4
    d, ok, y, J = image_model(*args, fast._gmap, True, 1e-13, 50, fast._gain_basis)
    d2, y2 = np.full((N, 2), np.inf), np.full((N, 2), -np.inf)
    ok2, J2 = np.ones(N, dtype=bool), np.full(J.shape, np.nan)
    image_model_into(*args, fast._gmap, True, 1e-13, 50, fast._gain_basis, d2, ok2, y2 if gains_on else d2, J2)
    np.testing.assert_array_equal(d2, d)
    np.testing.assert_array_equal(ok2, ok)
    np.testing.assert_array_equal(J2, J)
    if gains_on:
        np.testing.assert_array_equal(y2, y)
    # every derivative (PSD terms included) against the model's own, column by column
    full = np.arange(12 if not gains_on else 16, dtype=np.int64)
    _, _, _, Jf = image_model(*args, full, True, 1e-13, 50, fast._gain_basis)
    for c, g in enumerate(fast._gmap):
        np.testing.assert_array_equal(J[:, c], Jf[:, g], err_msg=GLOBAL_ORDER[g])
    np.testing.assert_array_equal(J[:, -6:], Jf[:, -6:])


@pytest.mark.parametrize("max_iter", [50, 3])
def test_newton_sweeps_are_the_point_by_point_newton_bit_for_bit(max_iter):
    """The sweeps (one iteration of every point per sweep) give each point exactly what ``_newton`` gives it:
    converged points, points that backtrack (strong distortion, far starts), that run out of iterations, that
    fail (starts on the wrong branch, a NaN target)."""
    from psdcal.calibration._image_kernel import _newton, _newton_sweeps

    rng = np.random.default_rng(7)
    n = 400
    coef = np.array([-0.03, 0.004, -1e-4, 2e-4, -3e-4, 0.001, 0.0])
    cx, cy = 0.05, -0.03
    X0 = rng.uniform(-3.0, 3.0, n)
    X1 = rng.uniform(-2.5, 2.5, n)
    X0[5] = np.nan
    TOL = 1e-13 * np.maximum(1.0, np.hypot(X0, X1))
    S0 = X0 + rng.normal(0.0, 0.5, n)  # starts near and far: a few backtrack, fail or take many steps
    S1 = X1 + rng.normal(0.0, 0.5, n)
    S0[:20] *= 4.0
    D0, D1, conv = S0.copy(), S1.copy(), np.empty(n, dtype=bool)
    _newton_sweeps(X0, X1, TOL, D0, D1, coef, cx, cy, max_iter, conv)
    ref = np.array([_newton(X0[i], X1[i], S0[i], S1[i], coef, cx, cy, TOL[i], max_iter) for i in range(n)])
    np.testing.assert_array_equal(D0, ref[:, 0])
    np.testing.assert_array_equal(D1, ref[:, 1])
    np.testing.assert_array_equal(conv, ref[:, 2].astype(bool))
    assert 0 < conv.sum() < n  # both kinds of outcome were exercised
