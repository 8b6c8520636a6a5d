"""The shared chi-squared check (psdcal._consistency): its false-alarm rate, inflation and extra noise.

The data are drawn with numpy's own chi-squared and normal generators, independent of psdcal._stats.
"""
import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from psdcal import _consistency as cons


@pytest.mark.parametrize("dof", [1, 3, 10, 200])
def test_false_alarm_rate_matches_alpha(dof):
    rng = np.random.default_rng(dof)
    n = 20000
    alpha = 0.01
    x = rng.chisquare(dof, n)
    fails = sum(cons.chi2_check(v, dof, alpha=alpha).passed is False for v in x)
    se = math.sqrt(alpha * (1 - alpha) / n)
    assert abs(fails / n - alpha) < 4 * se


def test_passed_leaves_covariance_alone_and_failed_inflates_by_ratio():
    good = cons.chi2_check(10.0, 10)
    assert good.passed and good.inflation == 1.0 and good.effect_sigma == 0.0
    cov = np.eye(2)
    assert cons.inflate(cov, good) is cov
    bad = cons.chi2_check(400.0, 10, what="the angles")
    assert bad.passed is False and bad.inflation == pytest.approx(40.0)
    assert bad.effect_sigma == pytest.approx(math.sqrt(40.0) - 1)
    assert np.allclose(cons.inflate(cov, bad), 40 * cov)
    assert "x40" in bad.message and "the angles" in bad.message
    assert cons.chi2_check(400.0, 10, inflate=False).inflation == 1.0


def test_no_dof_is_not_applicable_and_nan_is_severe():
    c = cons.chi2_check(0.0, 0)
    assert c.passed is None and c.p_value is None
    nan = cons.chi2_check(float("nan"), 3)
    assert nan.passed is False and nan.severe
    assert cons.verdict_of([c, nan]) == "wrong"
    assert cons.verdict_of([c, cons.chi2_check(400.0, 10)]) == "suspect"
    assert cons.verdict_of([c, cons.chi2_check(1.0, 1)]) == "good"


def test_round_trip_json():
    import json

    c = cons.chi2_check(400.0, 10, name="pose_chi2", advice="a reflection")
    d = c.to_dict()
    numpy_typed = cons.Check("x", np.float64(1.0), None, np.float64(0.5), 0.0, np.bool_(True), "m", severe=np.bool_(False))
    assert json.loads(json.dumps(numpy_typed.to_dict()))["passed"] is True
    assert cons.Check.from_dict(d) == c
    assert cons.Check.from_dict({**d, "unknown": 1}) == c


def test_extra_variance_restores_expected_chi2():
    rng = np.random.default_rng(3)
    m = 4000
    var = rng.uniform(0.5, 2.0, m)
    s2_true = 3.0
    r = rng.normal(0, np.sqrt(var + s2_true))
    s2 = cons.extra_variance(r, var, m)
    assert np.sum(r**2 / (var + s2)) == pytest.approx(m, rel=1e-8)
    assert abs(s2 - s2_true) < 0.25  # its sampling error is about 0.08 here
    assert cons.extra_variance(rng.normal(0, np.sqrt(var)) * 0.5, var, m) == 0.0


@settings(max_examples=50, deadline=None)
@given(st.floats(0.0, 1e6), st.integers(1, 500))
def test_inflation_never_below_one_and_sf_consistent(chi2, dof):
    c = cons.chi2_check(chi2, dof)
    assert c.inflation >= 1.0
    assert (c.passed is False) == (c.p_value < cons.ALPHA)
    if c.passed is False:
        assert chi2 > c.threshold * (1 - 1e-9)
