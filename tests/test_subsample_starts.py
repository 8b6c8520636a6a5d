"""Starts compared on a spread subset of each view's points, the optimum on all of them.

``calibrate`` fits the closed form's homographies, and refines and compares its
starts, on at most ~32 points per view when views carry more than 64
(:func:`psdcal.calibration.core.subsample_views`); the final refinement takes every point. These tests check the subset (spread,
corners, partial views) and that the answer is the one without the subset.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import psdcal.calibration.core as core
from psdcal.calibration.core import SUBSAMPLE_POINTS, calibrate, subsample_views
from psdcal.io import read_points, read_template
from psdcal.study.simulate import simulate_set

ZHANG = Path(__file__).parent / "data" / "zhang1998"


def _grid(k):
    a = np.linspace(-40.0, 40.0, k)
    X, Y = np.meshgrid(a, a)
    return np.stack([X.ravel(), Y.ravel()], axis=1)


def test_small_templates_are_not_subsampled():
    s = simulate_set("lens2", n_images=5, noise_mm=0.002, seed=0)
    assert subsample_views(s.template_mm, s.points_mm) is None
    T = _grid(8)  # 64 points: not more than twice 32
    assert subsample_views(T, np.zeros((3, 64, 2))) is None


def test_the_subset_is_spread_over_the_plate_and_partial_views_keep_their_points():
    T = _grid(16)  # 256 points
    X = np.tile(T[None] * 0.01, (4, 1, 1))
    X[3, T[:, 0] > 0] = np.nan  # view 3 sees half the plate
    X[2, :200] = np.nan  # view 2 sees 56 points: not more than 64, kept whole
    Xs = subsample_views(T, X)
    kept = np.all(np.isfinite(Xs), axis=-1)
    assert 16 <= kept[0].sum() <= 36 and kept[0].sum() == kept[1].sum()
    chosen = T[kept[0]]
    # every corner cell of the plate has a chosen point, and the subset spans the plate
    for sx in (-1, 1):
        for sy in (-1, 1):
            assert np.any((chosen[:, 0] * sx > 25) & (chosen[:, 1] * sy > 25))
    assert np.all(np.ptp(chosen, axis=0) > 0.8 * np.ptp(T, axis=0))
    assert kept[2].sum() == 56 and np.array_equal(kept[2], np.all(np.isfinite(X[2]), axis=-1))
    assert 8 <= kept[3].sum() <= 18 and not np.any(kept[3] & ~np.all(np.isfinite(X[3]), axis=-1))
    # the points kept are the measured ones, untouched
    np.testing.assert_array_equal(Xs[kept], X[kept])


@pytest.mark.parametrize("general", [False, True])
def test_the_optimum_is_the_one_without_the_subset(monkeypatch, general):
    ids, T = read_template(ZHANG / "template.csv")
    X = read_points(ZHANG / "points.csv", ids, sensor_mm=(6.4, 4.8)).points_mm
    kw = dict(sensor_mm=(6.4, 4.8), verdict=False, aspect=general, tangential=general)
    sub = calibrate(T, X, **kw)
    assert sub.stages["multistart"]["points_per_view"] == SUBSAMPLE_POINTS
    monkeypatch.setattr(core, "SUBSAMPLE_POINTS", 10_000)
    monkeypatch.setattr(core.subsample_views, "__defaults__", (10_000,))
    full = calibrate(T, X, **kw)
    assert "points_per_view" not in full.stages["multistart"]
    for n in sub.param_names:
        a, b = sub.parameter(n), full.parameter(n)
        assert abs(a - b) <= 1e-4 * sub.std[n], n  # the same optimum, to well below its standard error
    np.testing.assert_allclose(sub.covariance, full.covariance, rtol=1e-4)
    assert sub.converged and abs(sub.rms_mm - full.rms_mm) <= 1e-9 * full.rms_mm


def test_the_record_of_the_subset_is_in_the_schema():
    jsonschema = pytest.importorskip("jsonschema")
    from psdcal.schema import calibration_schema

    ids, T = read_template(ZHANG / "template.csv")
    X = read_points(ZHANG / "points.csv", ids, sensor_mm=(6.4, 4.8)).points_mm
    d = calibrate(T, X, sensor_mm=(6.4, 4.8)).to_dict()
    jsonschema.Draft202012Validator(calibration_schema()).validate(d)
    bad = {**d, "stages": {**d["stages"], "multistart": {**d["stages"]["multistart"], "points_per_view": 0}}}
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.Draft202012Validator(calibration_schema()).validate(bad)


def test_the_subset_is_deterministic_and_the_same_with_and_without_missing_points():
    T = _grid(16)
    rng = np.random.default_rng(0)
    X = T[None] * 0.01 + 1e-4 * rng.standard_normal((3, 256, 2))
    a, b = subsample_views(T, X), subsample_views(T.copy(), X.copy())
    np.testing.assert_array_equal(a, b)  # the same points, every call (the mask is cached per template)
    kept = np.isfinite(a[..., 0])
    assert np.array_equal(kept[0], kept[1]) and np.array_equal(kept[0], kept[2])
    # one point missing that the subset does not use: the general path gives the every-point path's subset
    drop = int(np.flatnonzero(~kept[0])[0])
    X2 = X.copy()
    X2[1, drop] = np.nan
    np.testing.assert_array_equal(subsample_views(T, X2), a)


def test_the_closed_form_is_fitted_to_the_subset_and_says_so():
    ids, T = read_template(ZHANG / "template.csv")
    X = read_points(ZHANG / "points.csv", ids, sensor_mm=(6.4, 4.8)).points_mm
    res = calibrate(T, X, sensor_mm=(6.4, 4.8), verdict=False)
    cf = res.stages["closed_form"]
    assert cf["points_per_view"] == SUBSAMPLE_POINTS
    # the subset's closed form is the every-point one to well within the start's own error (a few %)
    from psdcal.calibration.starts import initial_estimate

    full = initial_estimate(T, X)
    sub = initial_estimate(T, X, dlt_points=subsample_views(T, X))
    assert full.points_per_view is None and sub.points_per_view == SUBSAMPLE_POINTS
    assert abs(sub.intrinsics.f_mm - full.intrinsics.f_mm) < 0.01 * full.intrinsics.f_mm
    assert abs(cf["f_mm"] - sub.intrinsics.f_mm) < 1e-12 * sub.intrinsics.f_mm  # the recorded start is the subset's
    assert np.hypot(sub.intrinsics.cx_mm - full.intrinsics.cx_mm, sub.intrinsics.cy_mm - full.intrinsics.cy_mm) < 0.05
    # a 14-point template has no subset, and no record of one
    s = simulate_set("lens2", n_images=5, noise_mm=0.002, seed=0)
    small = calibrate(s.template_mm, s.points_mm, verdict=False)
    assert "points_per_view" not in small.stages["closed_form"]
    assert "points_per_view" not in small.stages["multistart"]


def test_the_closed_form_record_is_in_the_schema():
    jsonschema = pytest.importorskip("jsonschema")
    from psdcal.schema import calibration_schema

    ids, T = read_template(ZHANG / "template.csv")
    X = read_points(ZHANG / "points.csv", ids, sensor_mm=(6.4, 4.8)).points_mm
    d = calibrate(T, X, sensor_mm=(6.4, 4.8), verdict=False).to_dict()
    assert d["stages"]["closed_form"]["points_per_view"] == SUBSAMPLE_POINTS
    jsonschema.Draft202012Validator(calibration_schema()).validate(d)
    bad = {**d, "stages": {**d["stages"], "closed_form": {**d["stages"]["closed_form"], "points_per_view": 0}}}
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.Draft202012Validator(calibration_schema()).validate(bad)
