"""Sigmas that cover the error for streams of triangulated points (positioning.triangulate, locate --sensors).

The rule (docs/guide/positioning.md#sigmas-that-cover-the-error): each point is
flagged when its own chi2 fails at alpha; all the points of a call (or of a
``locate`` file) are tested together, and only when that pooled test fails
does one extra ray noise, estimated from every residual, inflate every point.

The rooms, rays and noise are drawn here with numpy alone (rotations from QR
of Gaussian matrices, pinhole projection written out, anisotropic Gaussian
noise with the stated covariance): nothing of psdcal's simulator is used.
Sample sizes and Monte Carlo bands are stated at each assertion.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from psdcal._consistency import extra_variance, extra_variance_on_grid
from psdcal.measure.positioning import triangulate


def _rotation(rng):
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _looking_at(centre, target, rng):
    """A rotation world -> camera whose z axis points from ``centre`` to ``target`` (random roll)."""
    z = target - centre
    z = z / np.linalg.norm(z)
    a = rng.standard_normal(3)
    x = a - (a @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def _room(rng, k=3):
    centres = np.array([[-2000.0, 0, 2500], [2000.0, 300, 2400], [0.0, 2500, 2600], [300, -2400, 2500]])[:k]
    target = np.array([0.0, 0.0, 800.0])
    R = np.stack([_looking_at(c, target + rng.normal(0, 100, 3), rng) for c in centres])
    t = -np.einsum("kij,kj->ki", R, centres)
    return R, t


def _rays(rng, R, t, P, sigma_scale=1.0):
    """Rays of points P (N, 3) with random anisotropic stated covariances; noise drawn as sigma_scale x stated."""
    k, N = len(R), len(P)
    pc = np.einsum("kij,nj->kni", R, P) + t[:, None, :]
    n_true = pc[..., :2] / pc[..., 2:3]
    A = rng.normal(0, 1, (k, N, 2, 2)) * 1e-4
    cov = A @ np.swapaxes(A, -1, -2) + 1e-9 * np.eye(2)
    Lc = np.linalg.cholesky(cov)
    n = n_true + sigma_scale * np.einsum("knij,knj->kni", Lc, rng.standard_normal((k, N, 2)))
    return n, cov


def _points(rng, N):
    return np.column_stack([rng.uniform(-800, 800, N), rng.uniform(-800, 800, N), rng.uniform(200, 1500, N)])


def test_row_flags_fire_at_alpha_on_correct_data():
    rng = np.random.default_rng(11)
    R, t = _room(rng, 3)
    N, alpha = 40000, 0.01
    P = _points(rng, N)
    n, cov = _rays(rng, R, t, P)
    tri = triangulate(n, cov, R, t, alpha=alpha, inflate=False)
    assert np.all(tri.dof == 3)
    rate = tri.flagged.mean()
    se = math.sqrt(alpha * (1 - alpha) / N)  # 5e-4
    assert abs(rate - alpha) < 4 * se, rate


def test_pooled_rule_false_alarm_rate_on_correct_data():
    """2000 'files' of 20 points each: the pooled test at alpha = 0.02 inflates about 2 % of them."""
    rng = np.random.default_rng(12)
    files, per, alpha = 2000, 20, 0.02
    fails = 0
    growth = []
    for _ in range(files):
        R, t = _room(rng, int(rng.integers(2, 5)))
        P = _points(rng, per)
        n, cov = _rays(rng, R, t, P)
        tri = triangulate(n, cov, R, t, alpha=alpha)
        if tri.check.passed is False:
            fails += 1
            growth.append(tri.check.inflation)
        else:
            assert tri.extra_var_n == 0.0 and np.array_equal(tri.cov_p_mm2, tri.cov_p_stated_mm2)
    se = math.sqrt(alpha * (1 - alpha) / files)  # 0.0031
    assert abs(fails / files - alpha) < 4 * se, fails / files
    # a false alarm inflates moderately: the chi2 is just beyond its 2 % quantile (the isotropic extra noise
    # weighs most on the rays' best-measured directions: covariance traces grow x2.4 in the median here)
    assert np.sqrt(np.median(growth)) < 2.0, np.median(growth)


def test_wrong_noise_is_detected_and_the_inflated_covariance_covers_the_error():
    """Rays 3x noisier than stated (isotropic stated noise): NEES of 3000 points ~ 3 after inflation."""
    rng = np.random.default_rng(13)
    R, t = _room(rng, 3)
    N = 3000
    P = _points(rng, N)
    n, _ = _rays(rng, R, t, P)
    pc = np.einsum("kij,nj->kni", R, P) + t[:, None, :]
    sig = 1e-4
    n = pc[..., :2] / pc[..., 2:3] + 3 * sig * rng.standard_normal(n.shape)
    cov = np.broadcast_to(sig**2 * np.eye(2), n.shape + (2,))
    tri = triangulate(n, cov, R, t)
    assert tri.check.passed is False
    # extra variance 8 sigma^2 (true 9 sigma^2 = stated + extra), to its Monte Carlo precision (~2 %)
    assert tri.extra_var_n / sig**2 == pytest.approx(8.0, rel=0.08)
    assert "urad" in tri.check.message and "sigmas grown" in tri.check.message
    e = tri.p_w_mm - P
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(tri.cov_p_mm2), e)
    se = math.sqrt(6 / N)  # chi2(3): variance 6
    assert abs(nees.mean() - 3) < 4 * se, nees.mean()
    nees0 = np.einsum("ni,nij,nj->n", e, np.linalg.inv(tri.cov_p_stated_mm2), e)
    assert nees0.mean() > 20


def test_one_bad_point_is_flagged_without_inflating_the_others():
    rng = np.random.default_rng(14)
    R, t = _room(rng, 3)
    P = _points(rng, 2000)
    n, cov = _rays(rng, R, t, P)
    n[0, 7] += 0.01  # one ray 10 mrad off
    tri = triangulate(n, cov, R, t)
    assert tri.flagged[7]
    # 2000 points x 3 dof: one chi2 of ~1e4 fails the pooled test too, but the extra noise it implies is small
    if tri.check.passed is False:
        grow = np.sqrt(np.trace(tri.cov_p_mm2, axis1=1, axis2=2) / np.trace(tri.cov_p_stated_mm2, axis1=1, axis2=2))
        assert np.median(grow) < 3.0


@pytest.mark.parametrize("scale", [0.5, 3.0, 30.0])
def test_pooled_grid_solution_matches_the_direct_one(scale):
    rng = np.random.default_rng(15)
    v = rng.uniform(0.5, 2.0, 5000) * 1e-8
    r = rng.standard_normal(5000) * np.sqrt(v * scale)
    dof = 4000
    grid = np.logspace(-20, 2, 441)
    sums = ((r[:, None] ** 2) / (v[:, None] + grid[None, :])).sum(0)
    direct = extra_variance(r, v, dof)
    pooled = extra_variance_on_grid(grid, sums, dof)
    if direct == 0.0:
        assert pooled == 0.0
    else:
        assert pooled == pytest.approx(direct, rel=0.01)
