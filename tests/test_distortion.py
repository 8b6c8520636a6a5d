"""The undistortion model and its inverse (docs/model.md#distortion)."""
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from psdcal.model.distortion import distort, distort_jacobians, undistort
from psdcal.model.params import Distortion

C = np.array([0.5, -0.7])
MODELS = {
    "lens1": Distortion(k1=2e-3),
    "lens2": Distortion(k1=1e-2, k2=3e-5),
    "lens2+psd+tang": Distortion(k1=1e-2, k2=3e-5, p1=2e-4, p2=-1e-4, l1=-1.3058e-3),
    "all": Distortion(k1=5e-3, k2=2e-5, k3=1e-7, p1=-3e-4, p2=2e-4, l1=-1.3058e-3, l2=2e-6),
    "pincushion-lens": Distortion(k1=-2e-3, k2=1e-6),
}

sensor_points = arrays(np.float64, (7, 2), elements=st.floats(-4.5, 4.5, allow_nan=False))


@pytest.mark.parametrize("name", list(MODELS))
@given(d=sensor_points)
def test_distort_inverts_undistort(name, d):
    dist = MODELS[name]
    x = undistort(d, dist, C)
    res = distort(x, dist, C)
    assert res.converged.all()
    np.testing.assert_allclose(res.d_mm, d, atol=1e-11, rtol=0)


@pytest.mark.parametrize("name", list(MODELS))
@given(d=sensor_points)
def test_undistort_inverts_distort(name, d):
    # ideal points that are images of sensor points: x = undistort(d); then go back and forth
    dist = MODELS[name]
    x = undistort(d, dist, C)
    x2 = undistort(distort(x, dist, C).d_mm, dist, C)
    np.testing.assert_allclose(x2, x, atol=1e-11, rtol=0)


def test_identity_when_no_distortion(rng):
    d = rng.uniform(-4.5, 4.5, (50, 2))
    np.testing.assert_array_equal(undistort(d, Distortion(), C), d)
    np.testing.assert_allclose(distort(d, Distortion(), C).d_mm, d, atol=1e-15)


def test_closed_form_single_term():
    # pure k1 about C: x - C = e (1 + k1 r^2)
    d = np.array([[2.0, 1.0]])
    k1 = 1e-2
    e = d - C
    expect = C + e * (1 + k1 * np.sum(e**2))
    np.testing.assert_allclose(undistort(d, Distortion(k1=k1), C), expect, rtol=1e-15)
    # PSD term about the electrical centre (0, 0), applied first
    l1 = -1.3058e-3
    u = d * (1 + l1 * np.sum(d**2))
    np.testing.assert_allclose(undistort(d, Distortion(l1=l1), C), u, rtol=1e-15)
    # tangential about C
    p1, p2 = 2e-4, -1e-4
    ex, ey = e[0]
    r2 = ex * ex + ey * ey
    t = np.array([p1 * (r2 + 2 * ex * ex) + 2 * p2 * ex * ey, p2 * (r2 + 2 * ey * ey) + 2 * p1 * ex * ey])
    np.testing.assert_allclose(undistort(d, Distortion(p1=p1, p2=p2), C)[0], d[0] + t, rtol=1e-14)


@pytest.mark.parametrize("name", list(MODELS))
def test_undistort_jacobians_match_finite_differences(name, rng):
    dist = MODELS[name]
    coef = dist.as_array()
    d = rng.uniform(-4.5, 4.5, (20, 2))
    x, dx_dd, dx_dc, dx_dk = undistort(d, coef, C, jacobians=True)
    h = 1e-6
    for i in range(2):
        e = np.zeros(2)
        e[i] = h
        num = (undistort(d + e, coef, C) - undistort(d - e, coef, C)) / (2 * h)
        np.testing.assert_allclose(dx_dd[..., i], num, atol=1e-8)
        num = (undistort(d, coef, C + e) - undistort(d, coef, C - e)) / (2 * h)
        np.testing.assert_allclose(dx_dc[..., i], num, atol=1e-8)
    for k in range(7):
        step = 1e-4 / 4.5 ** (2 * (k % 3 + 1)) if k < 3 else (1e-6 if k < 5 else 1e-4 / 4.5 ** (2 * (k - 4)))
        kp, km = coef.copy(), coef.copy()
        kp[k] += step
        km[k] -= step
        num = (undistort(d, kp, C) - undistort(d, km, C)) / (2 * step)
        scale = np.abs(num).max() + 1e-12
        assert np.abs(dx_dk[..., k] - num).max() / scale < 1e-6, k


def test_distort_jacobians_by_implicit_function(rng):
    dist = MODELS["all"]
    coef = dist.as_array()
    d = rng.uniform(-4, 4, (10, 2))
    x = undistort(d, coef, C)
    dd_dx, dd_dc, dd_dk = distort_jacobians(d, coef, C)
    h = 1e-6
    for i in range(2):
        e = np.zeros(2)
        e[i] = h
        num = (distort(x + e, coef, C).d_mm - distort(x - e, coef, C).d_mm) / (2 * h)
        np.testing.assert_allclose(dd_dx[..., i], num, atol=1e-8)
        num = (distort(x, coef, C + e).d_mm - distort(x, coef, C - e).d_mm) / (2 * h)
        np.testing.assert_allclose(dd_dc[..., i], num, atol=1e-8)


def test_distort_reports_points_where_the_inverse_does_not_exist():
    # a strongly pin-cushion undistortion folds over: far ideal points have no pre-image
    dist = Distortion(k1=-0.02)
    x = np.array([[1.0, 0.5], [30.0, 0.0], [0.0, -40.0]])
    res = distort(x, dist, np.zeros(2))
    assert res.converged.tolist() == [True, False, False]
    assert np.all(np.isfinite(res.d_mm[0])) and np.all(np.isnan(res.d_mm[1:]))


def test_distort_keeps_shape_and_does_not_mutate(rng):
    x = rng.uniform(-4, 4, (3, 4, 2))
    x0 = x.copy()
    res = distort(x, MODELS["lens2"], C)
    assert res.d_mm.shape == x.shape and res.converged.shape == (3, 4)
    np.testing.assert_array_equal(x, x0)


@pytest.mark.parametrize("jac", [False, "d", True])
def test_large_undistort_in_blocks_equals_one_pass(monkeypatch, jac):
    """A large call goes in blocks of BLOCK_POINTS points (temporaries in cache): the same numbers, bit for
    bit, as one pass over all the points (per point the same arithmetic), whatever the leading shape."""
    import psdcal.model.distortion as dm

    rng = np.random.default_rng(8)
    d = rng.uniform(-4, 4, (3, 701, 2))
    coef = np.array([1e-2, 3e-5, 1e-7, 2e-4, -1e-4, -1.3e-3, 2e-6])
    c = np.array([0.3, -0.2])
    whole = dm.undistort(d, coef, c, jacobians=jac)  # 2103 points: below the threshold, one pass
    monkeypatch.setattr(dm, "BLOCK_POINTS", 100)  # 2103 points in 22 blocks, the last one partial
    blocked = dm.undistort(d, coef, c, jacobians=jac)
    whole = whole if isinstance(whole, tuple) else (whole,)
    blocked = blocked if isinstance(blocked, tuple) else (blocked,)
    assert len(whole) == len(blocked)
    for a, b in zip(whole, blocked):
        assert a.shape == b.shape and a.shape[:2] == (3, 701)
        np.testing.assert_array_equal(a, b)
