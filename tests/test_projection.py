"""Poses, pinhole model, homographies (docs/model.md#pinhole-model)."""
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from psdcal.calibration._refine import rodrigues_batch
from psdcal.model.params import Intrinsics
from psdcal.model.projection import R_from_r, backproject_to_plane, homography_from_pose, pinhole, project, r_from_R, rays, transform

rvecs = arrays(np.float64, 3, elements=st.floats(-3.0, 3.0, allow_nan=False)).filter(lambda r: np.linalg.norm(r) < 3.1)


@given(r=rvecs)
def test_rotation_round_trip(r):
    R = R_from_r(r)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R_from_r(r_from_R(R)), R, atol=1e-9)


@pytest.mark.parametrize("gap_rad", [2.0, 1.0, 1e-1, 1e-3, 1e-5, 1e-6, 2e-6, 1e-7, 1e-9, 0.0])
def test_rotation_vector_is_accurate_up_to_a_half_turn(gap_rad):
    # theta = pi - gap: the arccos-of-the-trace formula lost up to 5e-4 relative within 1e-6 rad of pi
    # (a sensor looking straight down is rotated by about pi); atan2 and the symmetric part do not
    rng = np.random.default_rng(int(gap_rad * 1e9) % 1000)
    for _ in range(50):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        r = u * (np.pi - gap_rad)
        got = r_from_R(R_from_r(r))
        err = np.linalg.norm(got - r) if gap_rad > 0 else min(np.linalg.norm(got - r), np.linalg.norm(got + r))
        assert err <= 1e-14 * np.pi


@pytest.mark.parametrize("angle_rad", [0.0, 1e-12, 1e-9, 1e-7, 1e-4, 0.5, 2.0])
def test_rotation_vector_is_accurate_near_zero_and_in_between(angle_rad):
    rng = np.random.default_rng(3)
    for _ in range(20):
        u = rng.normal(size=3)
        r = u / np.linalg.norm(u) * angle_rad
        np.testing.assert_allclose(r_from_R(R_from_r(r)), r, rtol=1e-14, atol=1e-30)


@given(r=rvecs)
def test_rotation_derivative_matches_finite_differences(r):
    _, dR = R_from_r(r, jacobian=True)
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        num = (R_from_r(r + e) - R_from_r(r - e)) / (2 * h)
        np.testing.assert_allclose(dR[k], num, atol=1e-7)


def test_batched_rodrigues_equals_single(rng):
    r = rng.normal(0, 1, (6, 3))
    r[0] = 0.0
    R, dR = rodrigues_batch(r)
    for i in range(6):
        Ri, dRi = R_from_r(r[i], jacobian=True)
        np.testing.assert_allclose(R[i], Ri, atol=1e-14)
        np.testing.assert_allclose(dR[i], dRi, atol=1e-12)


def test_pinhole_formula_and_jacobian(rng):
    intr = Intrinsics(f_mm=8.0, cx_mm=0.5, cy_mm=-0.7, skew=0.01)
    Pc = np.c_[rng.uniform(-100, 100, (10, 2)), rng.uniform(300, 900, 10)]
    x, dx_dPc, dx_dintr = pinhole(Pc, intr, jacobians=True)
    np.testing.assert_allclose(x[:, 0], 8 * Pc[:, 0] / Pc[:, 2] + 0.01 * Pc[:, 1] / Pc[:, 2] + 0.5)
    np.testing.assert_allclose(x[:, 1], 8 * Pc[:, 1] / Pc[:, 2] - 0.7)
    h = 1e-4
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        num = (pinhole(Pc + e, intr) - pinhole(Pc - e, intr)) / (2 * h)
        np.testing.assert_allclose(dx_dPc[..., k], num, atol=1e-9)


def test_backprojection_inverts_projection(rng):
    intr = Intrinsics(f_mm=25.0, cx_mm=0.5, cy_mm=-0.7)
    r, t = np.array([0.2, -0.3, 0.4]), np.array([10.0, -20.0, 700.0])
    P = rng.uniform(-80, 80, (20, 2))
    x = project(P, intr, r, t)
    np.testing.assert_allclose(backproject_to_plane(x, intr, r, t), P, atol=1e-9)
    H = homography_from_pose(intr, r, t)
    xh = np.c_[P, np.ones(20)] @ H.T
    np.testing.assert_allclose(xh[:, :2] / xh[:, 2:], x, atol=1e-12)
    # rays point at the 3D points
    Pc = transform(P, r, t)
    np.testing.assert_allclose(rays(x, intr), Pc / np.linalg.norm(Pc, axis=1, keepdims=True), atol=1e-12)
