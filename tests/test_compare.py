"""Comparing calibrations in angle of arrival (psdcal.report.compare, psdcal compare)."""
import json
from dataclasses import replace

import numpy as np
import pytest

from psdcal.calibration.core import calibrate
from psdcal.report.compare import VISIBLE_SIGMA, _mahalanobis, aoa_field, compare, fov_uncertainty, sensor_grid_mm
from psdcal.errors import InputError
from psdcal.model.params import Distortion
from psdcal.study.simulate import simulate_set


def _cal(lens, seed, n_images=12, noise_mm=0.003):
    s = simulate_set(lens, n_images=n_images, noise_mm=noise_mm, seed=seed)
    return calibrate(s.template_mm, s.points_mm)


@pytest.fixture(scope="module")
def cals():
    return {"a": _cal("lens2", 0), "b": _cal("lens2", 1), "l1": _cal("lens1", 2)}


def test_self_comparison_is_zero(cals):
    c = compare(cals["a"], cals["a"], distance_mm=5000.0)
    assert c.max_deg == 0.0 and c.rms_deg == 0.0
    assert c.max_sigma == 0.0 and c.rms_sigma == 0.0
    assert c.summary()["position_max_mm"] == 0.0
    assert not c.visible and c.verdict().startswith("identical")


def test_independent_sets_of_one_sensor_agree_within_uncertainty(cals):
    c = compare(cals["a"], cals["b"])
    s = c.summary()
    assert 0 < s["max_deg"] < 1.0
    assert s["max_sigma"] < VISIBLE_SIGMA and s["rms_sigma"] < 2.0
    assert not c.visible and c.verdict().startswith("consistent")


def test_lens1_against_lens2_is_large(cals):
    c = compare(cals["l1"], cals["a"])
    assert c.max_deg > 10.0 and c.rms_deg > 5.0
    assert c.max_sigma > 20 * VISIBLE_SIGMA
    assert c.visible and c.verdict().startswith("different")


def test_ray_difference_matches_a_known_focal_change(cals):
    a = cals["a"]
    b = replace(a, intrinsics=replace(a.intrinsics, f_mm=a.intrinsics.f_mm * 1.01))
    c = compare(a, b, n=21)
    # at the optical centre nothing changes; elsewhere atan(r/f) - atan(r/1.01f)
    d0 = aoa_field(a, a.intrinsics.c)
    assert np.allclose(d0.alpha_rad, 0.0, atol=1e-12)
    alpha = np.abs(c.a.alpha_rad[..., 0])
    tan_b = np.tan(alpha) / 1.01
    expected = np.degrees(alpha - np.arctan(tan_b))
    row = c.delta_deg.shape[0] // 2  # a row where alpha_y is small: the ray angle is nearly the x angle
    assert np.max(np.abs(np.abs(c.dalpha_deg[row, :, 0]) - expected[row])) < 1e-9


def test_mahalanobis():
    cov = np.array([[4.0, 0.0], [0.0, 1.0]])
    assert _mahalanobis(np.array([2.0, 0.0]), cov) == pytest.approx(1.0)
    assert _mahalanobis(np.array([0.0, 3.0]), cov) == pytest.approx(3.0)
    assert _mahalanobis(np.array([0.0, 0.0]), np.zeros((2, 2))) == 0.0
    assert np.isnan(_mahalanobis(np.array([1.0, 0.0]), np.zeros((2, 2))))


def test_aoa_covariance_matches_finite_differences(cals):
    """J Sigma J^T of the AoA field against a Jacobian from finite differences of an independent formula."""
    from psdcal.model.distortion import undistort

    r = cals["a"]
    d = sensor_grid_mm(r.sensor_mm, 5)
    names = r.param_names

    def alpha(vals):
        intr = {**r.intrinsics.to_dict(), **{k: v for k, v in vals.items() if k in ("f_mm", "cx_mm", "cy_mm")}}
        dist = Distortion(**{**r.distortion.to_dict(), **{k: v for k, v in vals.items() if k in Distortion().to_dict()}})
        c = np.array([intr["cx_mm"], intr["cy_mm"]])
        x = undistort(d, dist, c)
        return np.arctan((x - c) / intr["f_mm"])

    base = {n: r.parameter(n) for n in names}
    J = np.zeros(d.shape + (len(names),))
    for k, n in enumerate(names):
        h = 1e-6 * max(abs(base[n]), r.std[n])
        J[..., k] = (alpha({**base, n: base[n] + h}) - alpha({**base, n: base[n] - h})) / (2 * h)
    cov_fd = J @ r.covariance @ np.swapaxes(J, -1, -2)
    got = aoa_field(r, d).cov_alpha_rad2
    assert np.allclose(got, cov_fd, rtol=1e-4, atol=1e-14)
    f = fov_uncertainty(r, 11)
    assert f.sigma_total_deg.shape == (11, 11)
    assert 0.01 < np.median(f.sigma_total_deg) < 1.0


def test_bad_arguments(cals):
    with pytest.raises(InputError):
        compare(cals["a"], cals["b"], distance_mm=-1.0)
    with pytest.raises(InputError):
        sensor_grid_mm((9.0, 9.0), 5, margin_mm=5.0)


def test_cli_compare(tmp_path, cals, capsys):
    from psdcal.cli import main
    from psdcal.io import save_calibration

    save_calibration(tmp_path / "a.json", cals["a"])
    save_calibration(tmp_path / "b.json", cals["l1"])
    rc = main(["compare", str(tmp_path / "a.json"), str(tmp_path / "b.json"), "-o", str(tmp_path / "d.png"),
               "--json", str(tmp_path / "d.json"), "--distance-mm", "5000", "--grid", "15"])
    out = capsys.readouterr().out
    assert rc == 0 and "verdict: different" in out and "ray difference (deg)" in out
    assert (tmp_path / "d.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    s = json.loads((tmp_path / "d.json").read_text())
    assert s["visible"] and s["max_deg"] > 10 and s["distance_mm"] == 5000
    # a failed run leaves an existing output alone
    (tmp_path / "keep.txt").write_text("old")
    rc = main(["compare", str(tmp_path / "a.json"), str(tmp_path / "missing.json"), "-o", str(tmp_path / "keep.png")])
    assert rc == 2 and "missing.json" in capsys.readouterr().err
    rc = main(["compare", str(tmp_path / "a.json"), str(tmp_path / "b.json"), "-o", str(tmp_path / "keep.txt")])
    assert rc == 2 and (tmp_path / "keep.txt").read_text() == "old"
