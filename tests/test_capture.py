"""Taking calibration views: predicted information, next-view ranking, guided vs random capture."""
from __future__ import annotations

import numpy as np
import pytest

from psdcal import calibrate
from psdcal.cli import main
from psdcal.model.params import ModelSpec
from psdcal.report.compare import fov_uncertainty, sensor_grid_mm
from psdcal.study.capture import (aoa_jacobian, candidate_views, grid_capture, guided_sequence, information_of_calibration,
                                  next_view, view_information, worst_sigma_deg)
from psdcal.study.simulate import LENSES, default_template, measured_points, random_poses, simulate_set


def test_information_reproduces_the_calibration_covariance():
    """sigma^2 (sum S_v)^-1 is the covariance calibrate reports; the worst AoA sigma is fov_uncertainty's."""
    s = simulate_set("lens2", n_images=6, noise_mm=0.003, seed=1)
    r = calibrate(s.template_mm, s.points_mm)
    S = information_of_calibration(r)
    assert np.allclose(np.linalg.inv(S) * r.sigma_mm**2, r.covariance, rtol=1e-6, atol=0)
    Ja = aoa_jacobian(r.intrinsics, r.distortion, r.model.global_names, sensor_grid_mm(r.sensor_mm, 11).reshape(-1, 2))
    assert worst_sigma_deg(S, Ja, r.sigma_mm) == pytest.approx(np.nanmax(fov_uncertainty(r, n=11).sigma_total_deg),
                                                               rel=1e-9)


def test_fixed_parameters_are_left_out_of_the_prediction():
    """With f held fixed the prediction is over the free parameters: it equals the calibration's own covariance."""
    s = simulate_set("lens1", n_images=5, noise_mm=0.003, seed=4)
    r = calibrate(s.template_mm, s.points_mm, fix={"f_mm": 25.0})
    assert "f_mm" not in r.param_names
    free = tuple(n for n in r.model.global_names if n in r.param_names)
    S = information_of_calibration(r)
    keep = [r.model.global_names.index(n) for n in free]
    Sf = S[keep][:, keep]
    assert np.allclose(np.linalg.inv(Sf) * r.sigma_mm**2, r.covariance, rtol=1e-4)
    nv = next_view(s.template_mm, r.intrinsics, r.distortion, r.model, S, r.sigma_mm, free=free)
    assert nv.current_deg == pytest.approx(np.nanmax(fov_uncertainty(r, n=11).sigma_total_deg), rel=1e-4)


def test_candidates_are_on_the_sensor_and_instructions_true():
    intr, dist = LENSES["lens1"]
    P = default_template()
    cands = candidate_views(P, intr, dist)
    assert len(cands) > 50
    d = measured_points(P, intr, dist, [c.rvec for c in cands], [c.tvec_mm for c in cands])
    assert np.all(np.abs(d) <= 4.5)
    from psdcal.model.projection import R_from_r

    for c in cands[::37]:
        # the template's centre is seen where the instruction says, at the stated distance and tilt
        ctr = measured_points(P.mean(0, keepdims=True), intr, dist, [c.rvec], [c.tvec_mm])[0, 0]
        assert np.allclose(ctr, c.centre_mm, atol=1e-9)
        Pc = R_from_r(c.rvec) @ np.r_[P.mean(0), 0.0] + c.tvec_mm
        assert Pc[2] == pytest.approx(c.distance_mm)
        normal = R_from_r(c.rvec) @ np.array([0.0, 0.0, 1.0])
        assert np.degrees(np.arccos(normal[2])) == pytest.approx(c.tilt_deg, abs=1e-6)


def test_adding_the_suggested_view_really_improves_the_calibration():
    """The predicted worst sigma after the top view matches the covariance of a real calibration with that view."""
    s = simulate_set("lens2", n_images=4, noise_mm=0.003, seed=2)
    r = calibrate(s.template_mm, s.points_mm)
    nv = next_view(s.template_mm, r.intrinsics, r.distortion, r.model, information_of_calibration(r), 0.003)
    assert not nv.stop and nv.best_deg < nv.current_deg
    best = nv.ranked[0][0]
    d = measured_points(s.template_mm, s.intrinsics, s.distortion, [best.rvec], [best.tvec_mm])
    X = np.concatenate([s.points_mm, d + np.random.default_rng(5).normal(0, 0.003, d.shape)])
    r2 = calibrate(s.template_mm, X)
    after = np.nanmax(fov_uncertainty(r2, n=11).sigma_total_deg) * 0.003 / r2.sigma_mm
    assert after == pytest.approx(nv.best_deg, rel=0.1)
    worst = nv.ranked[-1][1]
    assert nv.best_deg < worst


@pytest.mark.parametrize("lens", ["lens1", "lens2"])
def test_guided_reaches_the_target_with_fewer_views_than_random_or_grid(lens):
    intr, dist = LENSES[lens]
    P = default_template()
    spec = ModelSpec()
    noise = 0.003
    Ja = aoa_jacobian(intr, dist, spec.global_names, sensor_grid_mm((9.0, 9.0), 9).reshape(-1, 2))
    n = 20
    rand = []
    for seed in range(4):
        rv, tv = random_poses(P, intr, dist, n, np.random.default_rng(seed))
        rand.append(worst_sigma_deg(np.cumsum(view_information(P, intr, dist, spec, rv, tv), 0), Ja, noise))
    rand = np.array(rand)
    target = 0.7 * float(np.median(rand[:, 8]))
    # guided: the first 3 random views of seed 0, then next-view's choices
    rv, tv = random_poses(P, intr, dist, 3, np.random.default_rng(0))
    S3 = view_information(P, intr, dist, spec, rv, tv).sum(0)
    _, guided = guided_sequence(P, intr, dist, spec, S3, noise, n - 3, grid=9)
    need_g = 3 + int(np.nonzero(np.array(guided) <= target)[0][0]) + 1
    need_r = [int(np.nonzero(c <= target)[0][0]) + 1 if np.any(c <= target) else n + 1 for c in rand]
    assert need_g < min(need_r)
    # and than the fixed grid protocol
    gq = grid_capture(candidate_views(P, intr, dist), n)
    g = worst_sigma_deg(np.cumsum(view_information(P, intr, dist, spec, [c.rvec for c in gq],
                                                   [c.tvec_mm for c in gq]), 0), Ja, noise)
    need_grid = int(np.nonzero(g <= target)[0][0]) + 1 if np.any(g <= target) else n + 1
    assert need_g < need_grid
    assert np.all(np.diff(guided) <= 1e-12)  # information only adds


def test_cli_next_view(tmp_path, capsys):
    d = tmp_path / "s"
    assert main(["simulate", "--lens", "lens2", "--images", "4", "-o", str(d)]) == 0
    capsys.readouterr()
    assert main(["next-view", str(d / "points.csv"), "-t", str(d / "template.csv"), "--top", "3"]) == 0
    out = capsys.readouterr().out
    assert out.count(" deg about ") + out.count("no tilt") >= 3 and "verdict: take it" in out
    assert main(["next-view", str(d / "points.csv"), "-t", str(d / "template.csv"), "--target-deg", "10"]) == 0
    assert "meets the target" in capsys.readouterr().out
    assert main(["next-view", str(d / "points.csv")]) == 2
    js = tmp_path / "nv.json"
    assert main(["next-view", str(d / "points.csv"), "-t", str(d / "template.csv"), "--max-tilt-deg", "30",
                 "--json", str(js)]) == 0
    import json

    doc = json.loads(js.read_text())
    assert doc["stop"] is False and 0 < doc["gain"] < 1 and len(doc["candidates"]) == 5
    assert all(c["tilt_deg"] <= 30 for c in doc["candidates"])
    assert doc["candidates"][0]["worst_sigma_deg"] == pytest.approx(doc["current_deg"] * (1 - doc["gain"]))
