"""The compiled angles-with-uncertainty kernel against its numpy reference (exact to 1e-12)."""
from __future__ import annotations

import numpy as np
import pytest

from _locate_sim import amplitudes, model
from psdcal import _jit
from psdcal.measure.aoa import _angles_compiled, angles_from_points_reference, impact_from_amplitudes
from psdcal.measure.sensor_model import SensorModel

pytestmark = pytest.mark.skipif(not _jit.enabled(), reason="compiled kernels disabled")

VARIANTS = [{}, {"skew": 0.02}, {"fy": 8.1}, {"skew": -0.01, "fy": 7.9, "gains": [1.0, 1.03, 0.97, 1.01]},
            {"names": ["f_mm", "cx_mm", "cy_mm", "k1", "k2", "k3", "p1", "p2", "l1", "l2"],
             "std": [1e-2, 5e-3, 5e-3, 1e-4, 1e-6, 1e-8, 1e-5, 1e-5, 1e-4, 1e-6], "skew": 0.01, "fy": 8.05}]


def _check(a, b, what):
    scale = np.max(np.abs(b)) if b.size else 1.0
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * max(scale, 1e-300), err_msg=what)


@pytest.mark.parametrize("kw", VARIANTS)
@pytest.mark.parametrize("with_noise", [True, False])
def test_kernel_equals_reference(kw, with_noise):
    m = model(**kw)
    rng = np.random.default_rng(3)
    d_true = rng.uniform(-4, 4, (7, 5, 2))
    a = amplitudes(SensorModel.from_dict({"intrinsics": {"f_mm": 8, "cx_mm": 0, "cy_mm": 0}}), d_true.reshape(-1, 2))
    imp = impact_from_amplitudes(a, m, var_a=np.full(4, 1e-6) if with_noise else None)
    d = imp.d_mm.reshape(7, 5, 2)
    cov = imp.cov_d_mm2.reshape(7, 5, 2, 2) if with_noise else None
    ddg = imp.dd_dgains.reshape(7, 5, 2, 3) if "gains" in kw else None
    fast = _angles_compiled(d, m, cov, ddg)
    ref = angles_from_points_reference(d, m, cov, ddg)
    for name in ("x_mm", "n", "alpha_rad", "cov_n_calib", "cov_n_noise", "dn_dp", "dn_dd"):
        a_, b_ = getattr(fast, name), getattr(ref, name)
        assert a_.shape == b_.shape, name
        _check(a_, b_, name)
    assert fast.names == ref.names


def test_kernel_with_a_semidefinite_covariance_equals_reference():
    """A rank-deficient calibration covariance (e.g. two parameters exactly correlated) has no Cholesky
    factor: the kernel's eigen-decomposition factor gives the reference's dn/dp C dn/dp^T all the same."""
    import dataclasses

    from psdcal.measure._aoa_kernel import covariance_factor

    m = model()
    C = np.array(m.covariance, dtype=float)
    u = np.sqrt(np.diag(C))
    C[0, 1] = C[1, 0] = u[0] * u[1]  # f and cx perfectly correlated: rank deficient
    C[1:, 0] = C[0, 1:] = C[1, 1:] * u[0] / u[1]
    w = np.linalg.eigvalsh(C)
    assert w.min() > -1e-12 * w.max()
    m2 = dataclasses.replace(m, covariance=C)
    B, lower = covariance_factor(C)
    assert not lower  # the eigen-decomposition path
    np.testing.assert_allclose(B @ B.T, C, rtol=0, atol=1e-12 * np.abs(C).max())
    d = np.random.default_rng(4).uniform(-4, 4, (50, 2))
    fast = _angles_compiled(d, m2, None, None)
    ref = angles_from_points_reference(d, m2, None, None)
    _check(fast.cov_n_calib, ref.cov_n_calib, "cov_n_calib")


FIELDS = ("x_mm", "n", "alpha_rad", "cov_n_calib", "cov_n_noise", "dn_dp", "dn_dd")


def _several_blocks():
    """A model with fitted gains and points over several kernel blocks plus a partial one."""
    from psdcal.measure._aoa_kernel import BLOCK

    m = model(skew=-0.01, fy=7.9, gains=[1.0, 1.03, 0.97, 1.01])
    n_pts = 3 * BLOCK + 5
    d_true = np.random.default_rng(5).uniform(-4, 4, (n_pts, 2))
    a = amplitudes(SensorModel.from_dict({"intrinsics": {"f_mm": 8, "cx_mm": 0, "cy_mm": 0}}), d_true)
    imp = impact_from_amplitudes(a, m, var_a=np.full(4, 1e-6))
    shape = (n_pts // 7, 7) if n_pts % 7 == 0 else (n_pts,)
    return (m, imp.d_mm.reshape(shape + (2,)), imp.cov_d_mm2.reshape(shape + (2, 2)),
            imp.dd_dgains.reshape(shape + (2, 3)))


def test_kernel_over_several_blocks_equals_reference():
    """Points beyond one block of the kernel (and a last, partial block) get the reference's values."""
    m, d, cov, ddg = _several_blocks()
    fast = _angles_compiled(d, m, cov, ddg)
    ref = angles_from_points_reference(d, m, cov, ddg)
    for name in FIELDS:
        a_, b_ = getattr(fast, name), getattr(ref, name)
        assert a_.shape == b_.shape, name
        _check(a_, b_, name)


@pytest.mark.parametrize("compiled", [True, False])
def test_without_derivatives_every_other_field_is_the_same(compiled):
    """derivatives=False leaves out dn_dp only: the angles and both covariances are those of the default call."""
    from psdcal.measure.aoa import angles_from_amplitudes, angles_from_points

    fn = angles_from_points if compiled else angles_from_points_reference
    m, d, cov, ddg = _several_blocks()
    full = fn(d, m, cov, ddg)
    lean = fn(d, m, cov, ddg, derivatives=False)
    assert lean.dn_dp is None
    assert full.dn_dp.shape == d.shape[:-1] + (2, len(m.names))
    for name in FIELDS:
        if name != "dn_dp":
            np.testing.assert_array_equal(getattr(lean, name), getattr(full, name), err_msg=name)
    np.testing.assert_array_equal(lean.sigma_alpha_rad, full.sigma_alpha_rad)
    if compiled:
        a = amplitudes(m, d.reshape(-1, 2)[:20])
        assert angles_from_amplitudes(a, m, derivatives=False).dn_dp is None
        assert angles_from_amplitudes(a, m).dn_dp.shape == (20, 2, len(m.names))


def test_fields_are_separate_contiguous_arrays():
    """The kernel's outputs share one allocation: each field is C-contiguous and overlaps no other, so
    writing into one leaves the others unchanged."""
    m, d, cov, ddg = _several_blocks()
    res = _angles_compiled(d, m, cov, ddg)
    arrays = [getattr(res, name) for name in FIELDS]
    for a_ in arrays:
        assert a_.flags.c_contiguous
    for i, a_ in enumerate(arrays):
        for b_ in arrays[i + 1:]:
            assert not np.shares_memory(a_, b_)
    before = res.n.copy()
    res.dn_dp[...] = np.nan
    res.cov_n_noise[...] = np.nan
    np.testing.assert_array_equal(res.n, before)
    assert np.isfinite(res.cov_n_calib).all()



def test_arctangent_equals_numpy():
    """The kernel's arctangent (range reduction + series, vectorisable) is numpy's to a few ulp, over every
    range it reduces (|x| <= tan(pi/8), up to 1, beyond 1), at the switch points and special values."""
    from psdcal.measure._aoa_kernel import _TAN_PI_8, _atan

    rng = np.random.default_rng(6)
    special = [0.0, -0.0, 1.0, -1.0, _TAN_PI_8, np.nextafter(_TAN_PI_8, 1.0), np.nextafter(1.0, 2.0), 1e-300, 5e-324,
               -1e-300, 1e300, -1e300, np.inf, -np.inf]
    x = np.concatenate([rng.uniform(-1, 1, 20000), rng.uniform(-4, 4, 20000),
                        np.exp(rng.uniform(-50, 50, 20000)) * rng.choice([-1.0, 1.0], 20000), special])
    ref = np.arctan(x)
    plain = getattr(_atan, "py_func", _atan)  # the same arithmetic in Python floats (fast enough for 60000)
    got = np.array([plain(v) for v in x.tolist()])
    np.testing.assert_allclose(got, ref, rtol=2e-15, atol=0)
    assert np.array_equal(np.signbit(got), np.signbit(ref))
    some = np.concatenate([x[::60], special])  # and the compiled function itself
    np.testing.assert_allclose([_atan(v) for v in some], np.arctan(some), rtol=2e-15, atol=0)
    assert np.isnan(_atan(np.nan)) and np.isnan(plain(float("nan")))


def test_large_call_output_memory_kept_and_never_shared(monkeypatch):
    """A large call's output memory is kept for the next call (fresh memory costs its page faults), but
    only once no result of the earlier call is alive: results are never overwritten by a later call."""
    import psdcal.measure.aoa as aoa

    monkeypatch.setattr(aoa, "SPARE_MIN", 1000)  # "large" from 56 points (the kept memory: a small test)
    monkeypatch.setattr(aoa, "_spare", [])
    m = model()
    rng = np.random.default_rng(5)
    d1, d2 = rng.uniform(-3, 3, (2, 3000, 2))
    cov = np.broadcast_to(np.diag([1e-6, 2e-6]), (3000, 2, 2))
    r1 = aoa.angles_from_points(d1, m, cov, derivatives=False)
    alpha1 = r1.alpha_rad.copy()
    r2 = aoa.angles_from_points(d2, m, cov, derivatives=False)  # r1 alive: fresh memory
    assert not np.shares_memory(r1.alpha_rad, r2.alpha_rad)
    np.testing.assert_array_equal(r1.alpha_rad, alpha1)
    ref2 = angles_from_points_reference(d2, m, cov, derivatives=False)
    _check(r2.alpha_rad, ref2.alpha_rad, "alpha")
    _check(r2.cov_n_calib, ref2.cov_n_calib, "cov_calib")
    del r1
    kept = aoa._spare[0]
    r3 = aoa.angles_from_points(d1, m, cov, derivatives=False)  # r2 alive: fresh memory again (kept in place of r2's)
    assert not np.shares_memory(r3.alpha_rad, r2.alpha_rad)
    del r2
    r4 = aoa.angles_from_points(d2, m, cov, derivatives=False)  # r3 holds the kept buffer: still not shared
    assert not np.shares_memory(r4.alpha_rad, r3.alpha_rad)
    np.testing.assert_array_equal(r3.alpha_rad, alpha1)
    del r3, r4
    r5 = aoa.angles_from_points(d1, m, cov, derivatives=False)  # nothing alive: the kept memory reused
    assert np.shares_memory(r5.alpha_rad, aoa._spare[0])
    np.testing.assert_array_equal(r5.alpha_rad, alpha1)
    del kept
    aoa.release_output_buffers()
    assert aoa._spare == []
