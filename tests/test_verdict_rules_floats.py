"""The verdict's plausibility and determination rules on floats against their numpy formulas (issue 22, item 1).

A default calibration runs these rules once on a handful of numbers (two
sensor sizes, the optical centre, the covariance's diagonal, a few views'
poses), where numpy's per-call cost dominated: they are now evaluated on
Python floats. Each is compared here with the numpy formula it replaces,
written out in the test, including NaN and signed zeros: the same numbers
(to the bit) and the same decisions.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from psdcal.calibration import _verdict_rules as R
from psdcal.calibration.core import calibrate
from psdcal.study.simulate import simulate_set

FINITE = st.floats(-8.0, 8.0, allow_nan=False)
ANY = st.one_of(FINITE, st.just(math.nan), st.just(math.inf), st.just(-0.0))


@pytest.fixture(scope="module")
def fit():
    s = simulate_set("lens2", n_images=6, noise_mm=1e-3, seed=2)
    return calibrate(s.template_mm, s.points_mm, verdict=False)


def _same(a, b) -> bool:
    """Equal floats to the bit (NaN equal to NaN)."""
    return (math.isnan(a) and math.isnan(b)) or (a == b and math.copysign(1.0, a) == math.copysign(1.0, b))


@settings(max_examples=200, deadline=None)
@given(ANY, ANY, st.floats(0.5, 6.0), st.floats(0.5, 6.0))
def test_farthest_corner_is_the_numpy_formula(cx, cy, hx, hy):
    half = np.array([hx, hy])
    want = float(np.max(np.hypot(*(R._CORNER_SIGNS * half - np.array([cx, cy])).T)))
    assert _same(R._farthest_corner(cx, cy, hx, hy), want)


@settings(max_examples=200, deadline=None)
@given(ANY, ANY)
def test_max_and_min_of_two_floats_are_numpys(a, b):
    assert _same(R._max_nan(a, b), float(np.max([a, b])))
    assert _same(R._min_nan(a, b), float(np.min([a, b])))


@pytest.mark.parametrize("c", [(0.1, -0.2), (2.9, 0.0), (-0.0, 1.3), (math.nan, 0.1), (0.1, math.nan), (5.0, -4.0)])
def test_optical_centre_check_is_the_numpy_formula(fit, c):
    """The optical_centre check's statistic, threshold and decision from the numpy formula of the rule."""
    res = replace(fit, intrinsics=replace(fit.intrinsics, cx_mm=c[0], cy_mm=c[1]))
    sensor = np.asarray(res.sensor_mm, dtype=float)
    half = sensor / 2
    lin = type("Lin", (), {"pts": np.array([[-1.0, -1.0], [1.0, 1.0]])})()
    ch = {k.name: k for k in R.plausibility(res, lin, sensor, half)}["optical_centre"]
    cc = np.asarray(res.intrinsics.c, dtype=float)
    rel = float(np.max(np.abs(cc) / half))
    assert _same(ch.statistic, float(np.hypot(*cc)))
    assert ch.threshold == float(R.C_FRACTION * np.min(half))
    assert ch.passed == (rel <= R.C_FRACTION)
    assert ch.severe == (rel > 1.0)
    assert ch.message.startswith(f"C = ({cc[0]:.3g}, {cc[1]:.3g}) mm")


@settings(max_examples=100, deadline=None)
@given(st.lists(st.one_of(st.floats(0.0, 1.0), st.just(-1e-9), st.just(-0.0), st.just(math.nan)), min_size=3,
                max_size=3))
def test_determination_standard_errors_are_the_numpy_formula(fit, var):
    """f and C's standard errors (a NaN or negative variance included) as ``np.sqrt(np.maximum(diag, 0))``."""
    res = fit
    names = ("f_mm", "cx_mm", "cy_mm")
    cov = np.diag(var)
    half = np.asarray(res.sensor_mm, dtype=float) / 2
    ch = R.determination(res, cov, names, half)
    sd = dict(zip(names, np.sqrt(np.maximum(np.diag(cov), 0.0))))
    f = float(res.intrinsics.f_mm)
    rel = sd["f_mm"] / abs(f)
    assert _same(ch.statistic, float(rel))
    worst = max(rel / R.F_REL_SUSPECT, max(sd["cx_mm"], sd["cy_mm"]) / (R.C_STD_SUSPECT * float(np.min(half))))
    assert ch.passed == (bool(worst <= 1.0) and not R._tilt_spread_deg(res) < R.VIEWS_ALIKE_DEG)
    assert f"+- {sd['f_mm']:.2g} mm" in ch.message


def _poses(fit, rvecs, tvecs):
    return replace(fit, rvecs=np.array(rvecs, dtype=float).reshape(-1, 3),
                   tvecs_mm=np.array(tvecs, dtype=float).reshape(-1, 3), image_ids=list(range(len(rvecs))))


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.tuples(ANY, FINITE, FINITE), st.tuples(FINITE, FINITE, ANY)), min_size=1, max_size=12))
def test_template_side_and_tilt_spread_on_floats_are_the_numpy_path(fit, poses):
    """A few views (floats) give the Check and the spread of the numpy path (taken for many views) exactly."""
    res = _poses(fit, [p[0] for p in poses], [p[1] for p in poses])
    few_side, few_spread = R.template_side(res), R._tilt_spread_deg(res)
    old = R._FEW_VIEWS
    try:
        R._FEW_VIEWS = -1  # every call on the numpy path
        side, spread = R.template_side(res), R._tilt_spread_deg(res)
    finally:
        R._FEW_VIEWS = old
    assert few_side == side
    assert (few_spread is None) == (spread is None)
    if spread is not None:
        assert _same(few_spread, spread)


def test_tilt_spread_and_side_of_known_poses(fit):
    """Two views tilted 10 deg about x and 20 deg about y: normals 22.2 deg apart, both seen from the front;
    a view turned half around is seen from behind."""
    a, b = math.radians(10.0), math.radians(20.0)
    res = _poses(fit, [(a, 0.0, 0.0), (0.0, b, 0.0)], [(0.0, 0.0, 100.0), (0.0, 0.0, 100.0)])
    want = math.degrees(math.acos(math.cos(a) * math.cos(b)))
    assert abs(R._tilt_spread_deg(res) - want) < 1e-9
    assert R.template_side(res).passed is True
    res = _poses(fit, [(math.pi, 0.0, 0.0), (0.0, 0.0, 0.0)], [(0.0, 0.0, 100.0), (0.0, 0.0, 100.0)])
    ch = R.template_side(res)  # view 0's normal is -z: it faces away from the sensor's side
    assert ch.passed is False and ch.statistic == 1.0 and "view(s) 0 see the template from behind" in ch.message


def test_uninflated_covariance_in_the_result_s_order_and_permuted(fit):
    """The verdict's covariance of ``lin.names`` is the result's (over its inflation) in either order."""
    from psdcal.calibration import _verdict_linear as L
    from psdcal.calibration import verdict as V

    res = replace(fit, stages={**fit.stages, "covariance_inflation": {"factor": 1.7}})
    lin = L.linearise(res)
    names = list(res.param_names)
    assert tuple(lin.names) == tuple(names)
    np.testing.assert_array_equal(V._uninflated_cov(res, lin), res.covariance / 1.7)
    perm = replace(lin, names=tuple(reversed(lin.names)))
    idx = [names.index(n) for n in perm.names]
    np.testing.assert_array_equal(V._uninflated_cov(res, perm), res.covariance[np.ix_(idx, idx)] / 1.7)


FLOATS = st.one_of(st.floats(-1e6, 1e6), st.just(math.nan), st.just(math.inf), st.just(-math.inf))


@settings(max_examples=300, deadline=None)
@given(st.lists(FLOATS, min_size=1, max_size=12))
def test_views_worst_and_median_on_floats_are_numpys(x):
    """The views check's worst view and the others' median from lists: numpy's argmax (non-finite as -inf) and
    :func:`_median`."""
    from psdcal.calibration import verdict as V

    a = np.array(x, dtype=float)
    assert V._argmax_finite(x) == int(np.argmax(np.where(np.isfinite(a), a, -np.inf)))
    with np.errstate(invalid="ignore"):  # inf + -inf in the middle pair
        assert _same(V._median_floats(list(x)), V._median(a))
    assert _same(V._median_floats([]), V._median(np.array([])))


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=2, max_size=40).filter(lambda v: len(v) % 2 == 0))
def test_led_offset_is_the_numpy_rms(v):
    """The leds check's RMS offset of the worst LED's points (one sum of squares) as ``np.sqrt(np.mean(...))``."""
    from psdcal.calibration import verdict as V

    q = np.array(v, dtype=float).reshape(-1, 2)
    assert V._rms_points(q) == float(np.sqrt(np.mean(q[:, 0] ** 2 + q[:, 1] ** 2)))
    assert V._rms_points(q[:0]) == 0.0
