"""The chunked block normal equations (psdcal.calibration._gram_kernel) against the numpy reference.

``gram_block_normal`` sums a view's run of at least ``CHUNK_MIN_POINTS``
observations in SIMD chunks (rounding-level differences from a sequential
sum) and shorter runs row by row (the bits of :func:`_row_by_row`, every run row by row).
"""
from __future__ import annotations

import numpy as np
import pytest

from psdcal import _jit
from psdcal.calibration._normal import block_normal_reference

pytestmark = pytest.mark.skipif(not _jit.enabled(), reason="compiled kernels disabled")


def _jacobian(n_views, points, ng, seed=0, order="runs"):
    rng = np.random.default_rng(seed)
    img = np.repeat(np.arange(n_views), points)
    if order == "shuffled":
        img = rng.permutation(img)
    N = img.size
    Jc = rng.standard_normal((2 * N, ng + 6)) * np.logspace(-3, 3, ng + 6)  # columns of very different scales
    r = rng.standard_normal(2 * N) * 1e-3
    return Jc, r, img


def _row_by_row(Jc, r, img, n_views):
    """The blocks with every run of a view summed row by row (``_run_rows``), long runs too: the kernel's
    sums without chunks."""
    from psdcal.calibration._gram_kernel import _run_rows, add_view_block, mirror_blocks

    m = Jc.shape[1]
    ng = m - 6
    U, W, V = np.zeros((ng, ng)), np.zeros((n_views, ng, 6)), np.zeros((n_views, 6, 6))
    gg, gp = np.zeros(ng), np.zeros((n_views, 6))
    i = 0
    while i < img.size:
        j = i
        while j < img.size and img[j] == img[i]:
            j += 1
        M, gl = np.zeros((m, m)), np.zeros(m)
        _run_rows(Jc, r, i, j, m, M, gl)
        add_view_block(M, gl, img[i], ng, U, W, V, gg, gp)
        i = j
    mirror_blocks(U, V)
    return U, W, V, gg, gp


def _assert_blocks_close(got, ref, rtol):
    for a, b in zip(got, ref):
        assert a.shape == b.shape
        scale = np.max(np.abs(b))
        assert np.max(np.abs(a - b)) <= rtol * scale


@pytest.mark.parametrize("points, ng", [(64, 8), (256, 5), (257, 9), (1024, 6), (200, 12)])
def test_chunked_sums_are_the_reference(points, ng):
    from psdcal.calibration._gram_kernel import CHUNK_MIN_POINTS, gram_block_normal

    assert points >= CHUNK_MIN_POINTS  # every run is summed in chunks (the last one partial when not a multiple)
    Jc, r, img = _jacobian(5, points, ng)
    got = gram_block_normal(Jc, r, img, 5)
    ref = block_normal_reference(Jc, r, img, 5)
    _assert_blocks_close(got, ref, 1e-13)
    U, W, V, gg, gp = got
    np.testing.assert_array_equal(U, U.T)
    np.testing.assert_array_equal(V, np.swapaxes(V, 1, 2))
    # the global block is the plain Gram matrix of the global columns
    ng_ = U.shape[0]
    np.testing.assert_allclose(U, Jc[:, :ng_].T @ Jc[:, :ng_], rtol=1e-12, atol=1e-12 * np.max(np.abs(U)))


def test_short_runs_are_the_row_by_row_sums_bit_for_bit():
    from psdcal.calibration._gram_kernel import gram_block_normal

    for points, order in ((14, "runs"), (63, "runs"), (256, "shuffled")):  # shuffled: runs of one or a few points
        Jc, r, img = _jacobian(6, points, 7, seed=points, order=order)
        got = gram_block_normal(Jc, r, img, 6)
        for a, b in zip(got, _row_by_row(Jc, r, img, 6)):
            np.testing.assert_array_equal(a, b)
        _assert_blocks_close(got, block_normal_reference(Jc, r, img, 6), 1e-13)
    # long runs are not summed row by row (else the test above compares nothing of the chunked path)
    Jc, r, img = _jacobian(2, 256, 7, seed=1)
    assert any(np.any(a != b) for a, b in zip(gram_block_normal(Jc, r, img, 2), _row_by_row(Jc, r, img, 2)))


def test_mixed_runs_and_views_in_any_order():
    """Long and short runs of the same view (a view split in two runs) add up to the reference."""
    from psdcal.calibration._gram_kernel import gram_block_normal

    rng = np.random.default_rng(4)
    img = np.concatenate([np.full(100, 2), np.full(10, 0), np.full(70, 1), np.full(5, 2), np.full(130, 0)])
    Jc = rng.standard_normal((2 * img.size, 14))
    r = rng.standard_normal(2 * img.size)
    _assert_blocks_close(gram_block_normal(Jc, r, img, 3), block_normal_reference(Jc, r, img, 3), 1e-13)


def test_non_finite_entries_propagate():
    from psdcal.calibration._gram_kernel import gram_block_normal

    Jc, r, img = _jacobian(2, 128, 6)
    Jc[7, 2] = np.nan
    U, W, V, gg, gp = gram_block_normal(Jc, r, img, 2)
    assert np.isnan(U[2, 2]) and np.isnan(gg[2]) and np.all(np.isfinite(V))


def test_the_refinement_uses_it_and_agrees_with_the_row_by_row_sums(monkeypatch):
    """A fit of 256-point views with the chunked sums is the fit with the row-by-row sums, to rounding."""
    from psdcal.calibration import _lm_kernel
    from psdcal.calibration._refine import Problem, refine
    from psdcal.model.params import ModelSpec
    from psdcal.study.simulate import simulate_set

    a = np.linspace(-40.0, 40.0, 16)
    T = np.stack(np.meshgrid(a, a), axis=-1).reshape(-1, 2)
    s = simulate_set("lens2", n_images=5, noise_mm=0.002, seed=1, template_mm=T)
    prob = Problem(s.template_mm, s.points_mm, ModelSpec(radial=2, tangential=True))
    i0 = s.intrinsics.__class__(f_mm=s.intrinsics.f_mm * 1.01, cx_mm=0.1, cy_mm=-0.1)
    fit = refine(prob, i0, s.distortion, np.ones(4), s.rvecs * 1.001, s.tvecs_mm)
    assert fit.converged
    # the row-by-row sums through the Python loop of the same compiled costs
    import psdcal.calibration._refine as rf

    monkeypatch.setattr(rf, "COMPILED_LOOP", False)
    ev_blocks = []

    orig = rf.Evaluator.__init__

    def init(self, *args, **kw):
        orig(self, *args, **kw)
        if self._blocks is not None:
            self._blocks = _row_by_row
            ev_blocks.append(True)

    monkeypatch.setattr(rf.Evaluator, "__init__", init)
    ref = refine(prob, i0, s.distortion, np.ones(4), s.rvecs * 1.001, s.tvecs_mm)
    assert ev_blocks and ref.converged and ref.iterations == fit.iterations
    np.testing.assert_allclose(fit.z, ref.z, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(fit.covariance_global, ref.covariance_global, rtol=1e-8)
    from psdcal.calibration._gram_kernel import gram_block_normal

    assert _lm_kernel.gram_block_normal is gram_block_normal  # the compiled loop's sums are the chunked ones
