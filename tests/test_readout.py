"""PSD readout, Eq 1-2, and the gain map (docs/model.md#psd-readout, #gain-homography)."""
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from psdcal.errors import ZeroSignalError
from psdcal.model.readout import gain_homography, gain_map, impact_point, photocurrents

spots = arrays(np.float64, (5, 2), elements=st.floats(-4.5, 4.5, allow_nan=False))
gainss = arrays(np.float64, 4, elements=st.floats(0.7, 1.3, allow_nan=False))


@given(xy=spots)
def test_readout_of_current_split_is_exact(xy):
    np.testing.assert_allclose(impact_point(photocurrents(xy, total=3.7)), xy, atol=1e-12)


def test_equation_1_2_by_hand():
    v = np.array([1.0, 2.0, 3.0, 4.0])  # vx1, vx2, vy1, vy2
    x = 4.5 * ((2 + 3) - (1 + 4)) / 10
    y = 4.5 * ((2 + 4) - (1 + 3)) / 10
    np.testing.assert_allclose(impact_point(v), [x, y])


def test_zero_sum_is_an_error():
    with pytest.raises(ZeroSignalError):
        impact_point(np.array([[1.0, 1, 1, 1], [1.0, -1.0, 0.5, -0.5]]))
    with pytest.raises(ZeroSignalError):
        impact_point(np.zeros(4))


@given(xy=spots, g=gainss)
def test_gain_map_is_the_readout_through_gains_and_a_homography(xy, g):
    direct = impact_point(photocurrents(xy) * g)
    np.testing.assert_allclose(gain_map(xy, g), direct, atol=1e-12)
    H = gain_homography(g)
    ph = np.c_[xy, np.ones(len(xy))] @ H.T
    np.testing.assert_allclose(ph[:, :2] / ph[:, 2:], direct, atol=1e-11)
    # a common factor cancels
    np.testing.assert_allclose(gain_map(xy, 3.0 * g), direct, atol=1e-12)


def test_equal_gains_are_the_identity(rng):
    xy = rng.uniform(-4.5, 4.5, (10, 2))
    np.testing.assert_allclose(gain_map(xy, np.full(4, 2.0)), xy, atol=1e-14)


def test_gain_map_jacobians(rng):
    xy = rng.uniform(-4, 4, (6, 2))
    g = np.array([1.0, 1.05, 0.93, 1.1])
    _, dxy, dg = gain_map(xy, g, jacobians=True)
    h = 1e-6
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        np.testing.assert_allclose(dxy[..., k], (gain_map(xy + e, g) - gain_map(xy - e, g)) / (2 * h), atol=1e-8)
    for k in range(4):
        e = np.zeros(4)
        e[k] = h
        np.testing.assert_allclose(dg[..., k], (gain_map(xy, g + e) - gain_map(xy, g - e)) / (2 * h), atol=1e-7)
