"""The verdict's evaluation of the richer model (psdcal.calibration._verdict_jacobian) and its small compiled parts.

:func:`~psdcal.calibration._verdict_jacobian.rich_jacobian` calls the compiled
image cost directly, its columns in the verdict's order; its reference is the
:class:`~psdcal.calibration._refine.Evaluator`'s numpy code, its columns gathered
into that order. :func:`~psdcal.calibration._verdict_blocks.normal_bases` takes
that (pose-last) layout as well as the pose-first one: the same bases.
:func:`~psdcal.calibration._verdict_kernel.pinv_sym` is
:func:`~psdcal.calibration._verdict_linear._pinv_sym`'s numpy code in loops.
"""
from __future__ import annotations

import numpy as np
import pytest

import psdcal._jit
from psdcal.calibration import _verdict_blocks as VB
from psdcal.calibration import _verdict_jacobian as VJ
from psdcal.calibration import _verdict_linear as L
from psdcal.calibration.checks import align_to_problem
from psdcal.calibration.core import calibrate
from psdcal.study.simulate import simulate_set

needs_numba = pytest.mark.skipif(not psdcal._jit.enabled(), reason="numba not available")


@pytest.fixture(scope="module")
def sim():
    return simulate_set("lens2", n_images=6, noise_mm=1e-3, seed=11)


def _both(res, fixed, monkeypatch):
    """(compiled, numpy reference) :class:`RichJacobian` of ``res``."""
    res = align_to_problem(res)
    with monkeypatch.context() as m:
        m.setattr(psdcal._jit, "use_compiled", lambda *a, **k: True)
        fast = VJ.rich_jacobian(res, fixed)
    with monkeypatch.context() as m:
        m.setattr(psdcal._jit, "use_compiled", lambda *a, **k: False)
        ref = VJ.rich_jacobian(res, fixed)
    return fast, ref


@needs_numba
@pytest.mark.parametrize("kw", [dict(), dict(aspect=True, skew=True), dict(fix={"k2": 0.0})])
def test_compiled_rich_jacobian_equals_the_evaluators(sim, kw, monkeypatch):
    """The same residuals, columns (in the verdict's order: free, left-out, fixed, pose) and observations as the
    Evaluator's numpy code gathered into that order; f moves fy too when the model has one focal length."""
    res = calibrate(sim.template_mm, sim.points_mm, verdict=False, **kw)
    fixed = tuple(kw.get("fix", {}))
    fast, ref = _both(res, fixed, monkeypatch)
    assert fast.free == ref.free and fast.extra == ref.extra and fast.fixed == ref.fixed == fixed
    assert fast.X.shape == ref.X.shape == (fast.r.size, len(fast.free) + len(fast.extra) + len(fixed) + 6)
    assert fast.X.flags.c_contiguous
    scale = np.abs(ref.X).max(axis=0)
    np.testing.assert_allclose(fast.X / scale, ref.X / scale, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast.r, ref.r, rtol=0, atol=1e-12)
    for a, b in ((fast.img, ref.img), (fast.led, ref.led), (fast.d_meas, ref.d_meas)):
        np.testing.assert_array_equal(a, b)
    assert fast.dense and fast.n_img == sim.points_mm.shape[0]
    # the free columns are those of the fit's own model (f moving fy too where it has one focal length)
    from psdcal.calibration._refine import Evaluator, Problem
    from psdcal.calibration.core import inputs_from_record

    a = align_to_problem(res)
    prob = Problem(*inputs_from_record(a.problem), a.model, cost="image", sensor_mm=tuple(a.sensor_mm),
                   fixed=fixed)
    ev = Evaluator(prob, a.intrinsics, a.distortion, np.ones(4))
    _, Jc = ev.evaluate_compact(prob.pack(a.intrinsics, a.distortion, np.ones(4), a.rvecs, a.tvecs_mm))
    own = Jc[:, [prob.names.index(n) for n in fast.free]]
    np.testing.assert_allclose(fast.X[:, :len(fast.free)] / scale[:len(fast.free)], own / scale[:len(fast.free)],
                               rtol=0, atol=1e-9)
    assert ("fy_mm" in fast.extra) == (not res.model.aspect)


@needs_numba
def test_rich_jacobian_marks_missing_points_not_dense(sim, monkeypatch):
    pts = sim.points_mm.copy()
    pts[2, 3] = np.nan
    res = calibrate(sim.template_mm, pts, verdict=False)
    fast, ref = _both(res, (), monkeypatch)
    assert not fast.dense and not ref.dense
    assert fast.r.size == 2 * (pts.shape[0] * pts.shape[1] - 1)
    np.testing.assert_allclose(fast.r, ref.r, rtol=0, atol=1e-12)


def test_normal_bases_pose_last_layout_equals_pose_first():
    """The pose-last layout (with an ignored column before the poses) gives the pose-first layout's Gram matrices,
    transforms and bases; ``dense=True`` skips the layout check and changes nothing."""
    rng = np.random.default_rng(5)
    v, nr, g, ne = 4, 40, 3, 2
    X = rng.normal(size=(v * nr, 6 + g + ne)) * np.logspace(0, 1, 6 + g + ne)
    row_img = np.repeat(np.arange(v), nr)
    ref = VB.normal_bases(X, g, ne, row_img, v)
    other = rng.normal(size=(v * nr, 1))
    Xl = np.ascontiguousarray(np.concatenate([X[:, 6:], other, X[:, :6]], axis=1))
    got = VB.normal_bases(Xl, g, ne, row_img, v, pose_last=True)
    got_dense = VB.normal_bases(Xl, g, ne, row_img, v, pose_last=True, dense=True)
    assert ref is not None and got is not None
    for b in (got, got_dense):
        for name in ("gram", "T", "Rg", "gtg_view", "Q"):
            a, r = getattr(b, name), getattr(ref, name)
            np.testing.assert_allclose(a, r, rtol=0, atol=1e-12 * np.abs(r).max())
        np.testing.assert_allclose(b.h, ref.h, rtol=0, atol=1e-12)
    assert VB.normal_bases(Xl, g, ne, row_img[::-1].copy(), v, pose_last=True) is None  # still checked


def _pinv_numpy(N, monkeypatch):
    with monkeypatch.context() as m:
        m.setattr(psdcal._jit, "use_compiled", lambda *a, **k: False)
        return L._pinv_sym(N)


@needs_numba
def test_compiled_pinv_sym_equals_numpys(monkeypatch):
    """Full rank (scaled by up to 1e12 by the columns' scales: the scaling removes that), 1 x 1: the compiled call is
    the one taken; rank deficient (a repeated column) and not finite: numpy's code."""
    from psdcal.calibration import _verdict_kernel as vk

    rng = np.random.default_rng(2)
    cases = []
    for n in (1, 4, 9):
        A = rng.normal(size=(50, n)) * 10.0 ** rng.uniform(-6, 6, n)
        cases.append(A.T @ A)
    A = rng.normal(size=(50, 5))
    A[:, 4] = 2 * A[:, 1]
    cases.append(A.T @ A)
    cond = L.PINV_COMPILED_MAX_COND
    for N in cases:
        ref = _pinv_numpy(N, monkeypatch)
        out = np.empty(N.shape)
        if N.shape[0] == 5:  # rank deficient: left to numpy
            assert not vk.pinv_sym(N, out, cond)
            with monkeypatch.context() as m:
                m.setattr(psdcal._jit, "use_compiled", lambda *a, **k: True)
                np.testing.assert_array_equal(L._pinv_sym(N), ref)
            continue
        assert vk.pinv_sym(N, out, cond)
        d = np.sqrt(np.diag(N))
        np.testing.assert_allclose(out * np.outer(d, d), ref * np.outer(d, d), rtol=0, atol=1e-10)
        with monkeypatch.context() as m:
            m.setattr(psdcal._jit, "use_compiled", lambda *a, **k: True)
            np.testing.assert_array_equal(L._pinv_sym(N), out)
    bad = cases[1].copy()
    bad[0, 1] = np.nan
    assert not vk.pinv_sym(bad, np.empty(bad.shape), cond)


@pytest.mark.parametrize("min_points", [0, 10 ** 9])
def test_view_shift_equals_group_shift_of_the_views_rows(sim, min_points, monkeypatch):
    """From the per-view Gram matrices (``min_points`` 0) and by QR: the shift of leaving one view out equals
    :func:`group_shift` of its rows, for every view."""
    res = calibrate(sim.template_mm, sim.points_mm, verdict=False)
    monkeypatch.setattr(L, "NORMAL_BASES_MIN_POINTS", min_points)
    lin = L.linearise(res)
    assert (lin.blocks is not None) == (min_points == 0)
    for k in range(sim.points_mm.shape[0]):
        ref = L.group_shift(lin, np.repeat(lin.img == k, 2))
        got = L.view_shift(lin, k)
        assert np.any(ref != 0)
        np.testing.assert_array_equal(got, ref)
