"""Outliers: robust noise, flags, rejection with refit (psdcal.calibration.outliers, calibrate --reject)."""
import json

import numpy as np
import pytest

from psdcal.calibration.core import CalibrationResult, calibrate
from psdcal.errors import InputError
from psdcal.calibration.outliers import (
    flag_outliers,
    reject_outliers,
    removed_points,
    robust_sigma_mm,
)
from psdcal.study.simulate import simulate_set

NOISE_MM = 0.003


@pytest.fixture(scope="module")
def sets():
    s = simulate_set("lens2", n_images=12, noise_mm=NOISE_MM, seed=7)
    clean = calibrate(s.template_mm, s.points_mm)
    X = s.points_mm.copy()
    X[4, 6] += np.array([0.6, -0.8]) * 50 * NOISE_MM  # one point moved by 50 sigma
    bad = calibrate(s.template_mm, X)
    return s, clean, bad


def test_robust_sigma_of_gaussian_residuals(rng):
    r = rng.normal(0.0, 0.002, (4000, 2))
    assert robust_sigma_mm(r) == pytest.approx(0.002, rel=0.05)
    r[:200] += 1.0  # 5 % gross errors barely move it
    assert robust_sigma_mm(r) == pytest.approx(0.002, rel=0.12)
    assert np.isnan(robust_sigma_mm(np.full((3, 2), np.nan)))


def test_clean_set_has_no_outlier(sets):
    _, clean, _ = sets
    f = flag_outliers(clean, 5.0)
    assert f.n_points == 0 and not f.images.any()
    assert f.sigma_mm == pytest.approx(NOISE_MM, rel=0.2)
    rej = reject_outliers(clean, 5.0)
    assert rej.removed == () and rej.rounds == 0
    assert rej.result.problem["outlier_rejection"]["removed"] == []


def test_planted_outlier_is_flagged(sets):
    _, _, bad = sets
    raw = flag_outliers(bad, 5.0)
    assert raw.points[4, 6] and raw.ratio[4, 6] == np.nanmax(raw.ratio)
    confirmed = flag_outliers(bad, 5.0, refit=True)
    assert np.argwhere(confirmed.points).tolist() == [[4, 6]]


def test_reject_removes_it_and_refit_returns_to_the_clean_fit(sets):
    _, clean, bad = sets
    rej = reject_outliers(bad, 5.0)
    assert [(p.image_id, p.point_id) for p in rej.removed] == [(4, 6)]
    p = rej.removed[0]
    assert 35 < p.ratio < 70  # planted at 50 sigma
    assert np.isnan(rej.result.residuals_mm[4, 6]).all()
    for name in clean.param_names:
        z = (rej.result.parameter(name) - clean.parameter(name)) / clean.std[name]
        assert abs(z) < 2.0, (name, z)
    # the contaminated fit was visibly off somewhere
    zb = max(abs(bad.parameter(n) - clean.parameter(n)) / clean.std[n] for n in clean.param_names)
    assert zb > 1.0


def test_failed_led_in_every_image_is_removed(sets):
    s, clean, _ = sets
    X = s.points_mm.copy()
    X[:, 9] += np.array([0.05, 0.04])  # a reflection: one LED off by ~21 sigma in every view
    res = calibrate(s.template_mm, X)
    rej = reject_outliers(res, 5.0)
    assert sorted(p.image_id for p in rej.removed) == list(range(12))
    assert {p.point_id for p in rej.removed} == {9}
    for name in clean.param_names:
        assert abs(rej.result.parameter(name) - clean.parameter(name)) < 2 * clean.std[name], name


def test_rejection_record_survives_json(sets):
    _, _, bad = sets
    rej = reject_outliers(bad, 5.0, line_numbers=np.arange(12 * 14).reshape(12, 14) + 2)
    d = json.loads(json.dumps(rej.result.to_dict()))
    back = CalibrationResult.from_dict(d)
    got = removed_points(back)
    assert len(got) == 1 and got[0].image_id == 4 and got[0].point_id == 6
    assert got[0].line == 4 * 14 + 6 + 2
    assert d["problem"]["outlier_rejection"]["k"] == 5.0


@pytest.mark.parametrize("k", [0.0, -1.0, float("nan"), "5"])
def test_bad_threshold(sets, k):
    with pytest.raises(InputError):
        flag_outliers(sets[1], k)


def test_cli_reject_lists_removed_point(tmp_path):
    from psdcal.cli import main
    from psdcal.io import write_points, write_template

    s = simulate_set("lens2", n_images=10, noise_mm=NOISE_MM, seed=3)
    X = s.points_mm.copy()
    X[2, 3] += np.array([0.12, 0.09])
    write_template(tmp_path / "t.csv", list(range(14)), s.template_mm)
    write_points(tmp_path / "p.csv", list(range(10)), list(range(14)), X)
    out = tmp_path / "c.json"
    import io
    from contextlib import redirect_stdout

    buf = io.StringIO()
    with redirect_stdout(buf):
        rc = main([ "calibrate", str(tmp_path / "p.csv"), "-t", str(tmp_path / "t.csv"), "-o", str(out), "--reject", "5"])
    assert rc == 0
    text = buf.getvalue()
    line = 1 + 2 * 14 + 3 + 1
    assert "removed 1 point(s)" in text and f"p.csv:{line}: image 2, point 3" in text
    d = json.loads(out.read_text())
    rec = d["problem"]["outlier_rejection"]
    assert [(r["image_id"], r["point_id"], r["line"]) for r in rec["removed"]] == [(2, 3, line)]
    assert "files" in d["problem"]
