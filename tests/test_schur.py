"""The block (Schur complement) normal equations against dense linear algebra.

The LM step and the covariance of a calibration eliminate the 6 x 6 pose
blocks (:class:`psdcal.calibration._normal.BlockNormal`); these tests compare
the compiled kernels and their numpy references with the dense ``J^T J``
built from the dense Jacobian, and the refinement with the dense reference.
"""
from __future__ import annotations

import numpy as np
import pytest

from psdcal import _jit
from psdcal.calibration._normal import (BlockNormal, DenseNormal, block_normal_reference, compact_from_dense,
                                        schur_covariance_reference, schur_solve_reference)
from psdcal.calibration._refine import Evaluator, Problem, refine
from psdcal.model.params import Distortion, ModelSpec
from psdcal.study.simulate import simulate_set

pytestmark = pytest.mark.skipif(not _jit.enabled(), reason="compiled kernels disabled")


def _system(seed=3, spec=ModelSpec(radial=2, tangential=True, psd_radial=1, skew=False, aspect=True, fit_gains=False)):
    s = simulate_set("lens1", n_images=7, noise_mm=0.002, seed=seed, psd_l1=-0.002, tangential=(1e-4, -2e-4))
    pts = s.points_mm.copy()
    pts[2, 5] = np.nan
    prob = Problem(s.template_mm, pts, spec)
    ev = Evaluator(prob, s.intrinsics, s.distortion, np.ones(4))
    z = prob.pack(s.intrinsics, s.distortion, np.ones(4), s.rvecs, s.tvecs_mm)
    z = z * (1 + 1e-4 * np.random.default_rng(seed).standard_normal(z.size))
    return prob, ev, z


def test_compact_jacobian_is_the_dense_one():
    prob, ev, z = _system()
    r, Jc = ev.evaluate_compact(z)
    _, J = ev.evaluate(z)
    np.testing.assert_array_equal(compact_from_dense(J, ev.img_idx, prob.n_global), Jc)


@pytest.mark.parametrize("compiled", [True, False])
def test_block_normal_equations_are_the_dense_ones(compiled):
    prob, ev, z = _system()
    r, Jc = ev.evaluate_compact(z)
    J = ev.jacobian(z)
    if compiled:
        sysm = ev.block_system(Jc, r)
    else:
        sysm = BlockNormal(*block_normal_reference(Jc, r, ev.img_idx, prob.n_images), compiled=False)
    A = J.T @ J
    np.testing.assert_allclose(sysm.dense(), A, rtol=1e-12, atol=1e-12 * np.abs(A).max())
    np.testing.assert_allclose(sysm.g, J.T @ r, rtol=1e-12, atol=1e-12 * np.abs(J.T @ r).max())
    np.testing.assert_allclose(sysm.diagonal(), np.diag(A), rtol=1e-12)


@pytest.mark.parametrize("compiled", [True, False])
def test_schur_step_and_covariance_match_dense_solves(compiled):
    prob, ev, z = _system(seed=5)
    r, Jc = ev.evaluate_compact(z)
    sysm = ev.block_system(Jc, r)
    sysm.compiled = compiled
    A, g = sysm.dense(), sysm.g
    damp = 1e-3 * np.diag(A) * np.random.default_rng(1).uniform(0.5, 2.0, A.shape[0])
    h = sysm.solve(damp)
    h_dense = np.linalg.solve(A + np.diag(damp), g)
    np.testing.assert_allclose(h, h_dense, rtol=1e-7, atol=1e-9 * np.abs(h_dense).max())
    Cg, Cp, Cx = sysm.covariance_blocks()
    C = np.linalg.inv(A)
    ng = prob.n_global
    scale = np.sqrt(np.outer(np.diag(C), np.diag(C)))
    np.testing.assert_allclose(Cg / scale[:ng, :ng], C[:ng, :ng] / scale[:ng, :ng], atol=1e-7)
    for v in range(prob.n_images):
        sl = slice(ng + 6 * v, ng + 6 * v + 6)
        np.testing.assert_allclose(Cp[v] / scale[sl, sl], C[sl, sl] / scale[sl, sl], atol=1e-7)
        np.testing.assert_allclose(Cx[v] / scale[:ng, sl], C[:ng, sl] / scale[:ng, sl], atol=1e-7)
    # the dense fallback of a normal-equations tuple gives the same step
    np.testing.assert_allclose(DenseNormal(A, g).solve(damp), h_dense, rtol=1e-7, atol=1e-9 * np.abs(h_dense).max())


def test_kernels_equal_their_numpy_references():
    from psdcal.calibration._gram_kernel import gram_block_normal
    from psdcal.calibration._schur_kernel import schur_covariance, schur_solve

    prob, ev, z = _system(seed=8)
    r, Jc = ev.evaluate_compact(z)
    blocks = gram_block_normal(Jc, r, ev.img_idx, prob.n_images)
    ref = block_normal_reference(Jc, r, ev.img_idx, prob.n_images)
    for a, b in zip(blocks, ref):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    U, W, V, gg, gp = blocks
    dg, dp = 1e-6 * np.diag(U), 1e-6 * np.einsum("naa->na", V)
    ok, hg, hp = schur_solve(U, W, V, gg, gp, dg, dp)
    ok_r, hg_r, hp_r = schur_solve_reference(U, W, V, gg, gp, dg, dp)
    assert ok and ok_r
    np.testing.assert_allclose(hg, hg_r, rtol=1e-8, atol=1e-10 * np.abs(hg_r).max())
    np.testing.assert_allclose(hp, hp_r, rtol=1e-8, atol=1e-10 * np.abs(hp_r).max())
    ok, *cov = schur_covariance(U, W, V)
    ok_r, *cov_r = schur_covariance_reference(U, W, V)
    assert ok and ok_r
    for a, b in zip(cov, cov_r):
        np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9 * np.abs(b).max())


def test_not_positive_definite_is_reported():
    from psdcal.calibration._schur_kernel import schur_solve

    U = np.eye(2)
    W = np.zeros((1, 2, 6))
    V = np.zeros((1, 6, 6))  # a view with no information
    ok, _, _ = schur_solve(U, W, V, np.ones(2), np.ones((1, 6)), np.zeros(2), np.zeros((1, 6)))
    assert not ok
    assert BlockNormal(U, W, V, np.ones(2), np.ones((1, 6))).solve(np.zeros(8)) is None


def test_refinement_with_block_solver_equals_dense_reference():
    """The same optimum and covariance as the numpy reference path (dense Jacobian, numpy blocks)."""
    s = simulate_set("lens2", n_images=6, noise_mm=0.003, seed=2)
    spec = ModelSpec(radial=2, tangential=False, psd_radial=0, skew=False, aspect=False, fit_gains=False)
    prob = Problem(s.template_mm, s.points_mm, spec)
    start = (s.intrinsics, Distortion.from_array(s.distortion.as_array() * 0.9), np.ones(4), s.rvecs, s.tvecs_mm)
    fast = refine(prob, *start)
    import psdcal.calibration._refine as R

    orig = R.Evaluator.__init__

    def numpy_init(self, *a, **k):
        orig(self, *a, **k)
        self._kernel = self._tkernel = self._normal = self._blocks = None

    R.Evaluator.__init__ = numpy_init
    try:
        slow = refine(prob, *start)
    finally:
        R.Evaluator.__init__ = orig
    np.testing.assert_allclose(fast.z, slow.z, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast.covariance_global, slow.covariance_global, rtol=1e-6)
    np.testing.assert_allclose(fast.pose_covariance, slow.pose_covariance, rtol=1e-6, atol=1e-18)
    # the block covariance is the inverse of the dense J^T J, times sigma^2
    J = slow.jacobian
    C = slow.sigma2 * np.linalg.inv(J.T @ J)
    np.testing.assert_allclose(fast.covariance, C, rtol=1e-5, atol=1e-9 * np.abs(C).max())


def test_block_normal_kernel_with_views_in_any_order():
    """The kernel sums runs of one view; observations of a view need not be contiguous."""
    from psdcal.calibration._gram_kernel import gram_block_normal

    rng = np.random.default_rng(3)
    img = rng.integers(0, 4, size=60)  # views interleaved, one view (say) never seen
    Jc = rng.normal(size=(120, 11))
    r = rng.normal(size=120)
    for a, b in zip(gram_block_normal(Jc, r, img, 5), block_normal_reference(Jc, r, img, 5)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
