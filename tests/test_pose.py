"""Sensor pose from emitters at known positions (psdcal.measure.pose, `psdcal pose`).

Simulated rooms with known truth: the calibration handed to the pose is the
true sensor moved by a draw from its own covariance (so the calibration error
is real, and systematic across the emitters), and the impact points carry
noise.  The pose's NEES must average 6 within its Monte Carlo error, and
positions triangulated with the estimated poses (their covariance included)
must fall within their stated 3 sigma in >= 99 % of windows.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from psdcal.errors import DegenerateViewsError
from psdcal.measure.aoa import angles_from_points
from psdcal.measure.pose import estimate_pose, read_emitters
from psdcal.measure.positioning import SensorPose, triangulate_aoa
from psdcal.measure.sensor_model import SensorModel
from psdcal.model.projection import R_from_r, r_from_R
from psdcal.study.recordings import calib_dict, project_world, room_layout, spot_for_normalised

TRUE = SensorModel.from_dict(calib_dict(seed=4))


def _calibrated(rng, scale=1.0):
    """The calibration a user would hold: the truth moved by a draw from (scale^2 x) its covariance."""
    draw = rng.multivariate_normal(np.zeros(len(TRUE.names)), TRUE.covariance) * scale
    return TRUE.with_values({nm: TRUE.value(nm) + dv for nm, dv in zip(TRUE.names, draw)})


def _observe(cal, sensor, P, sigma_d_mm, rng):
    """AoA results of world points P (k, 3) seen by ``sensor`` (true model TRUE) through calibration ``cal``."""
    n, _ = project_world(P, sensor.rvec, sensor.tvec_mm)
    d = spot_for_normalised(TRUE, n)
    assert np.all(np.isfinite(d))
    d = d + sigma_d_mm * rng.standard_normal(d.shape)
    cov_d = np.broadcast_to(sigma_d_mm**2 * np.eye(2), d.shape + (2,))
    return angles_from_points(d, cal, cov_d)


def _centre(s):
    return -R_from_r(s.rvec).T @ s.tvec_mm


def test_pose_exact_without_noise():
    rng = np.random.default_rng(0)
    sensors, em = room_layout(TRUE, n_sensors=1, n_anchors=6, moving=None, seed=1)
    s = sensors[0]
    P = np.array([e.p0_mm for e in em])
    res = _observe(TRUE, s, P, 0.0, rng)
    r = estimate_pose(res.n, np.broadcast_to(1e-14 * np.eye(2), (6, 2, 2)), P)
    np.testing.assert_allclose(r.center_w_mm, _centre(s), atol=1e-6)
    np.testing.assert_allclose(r.R, R_from_r(s.rvec), atol=1e-10)


def test_pose_nees_monte_carlo_honest_calibration():
    """The calibration error drawn from the very covariance the pose is given: NEES ~ chi2(6)."""
    rng = np.random.default_rng(11)
    nees, alarms = [], 0
    for trial in range(200):
        sensors, em = room_layout(TRUE, n_sensors=1, n_anchors=int(rng.integers(4, 8)), moving=None,
                                  seed=300 + trial)
        s = sensors[0]
        P = np.array([e.p0_mm for e in em])
        cal = _calibrated(rng)
        # 0.03 .. 1 um on the impact points (the noise of the windows' mean)
        res = _observe(cal, s, P, 10 ** rng.uniform(-4.5, -3), rng)
        r = estimate_pose(res.n, res.cov_n_noise, P, dn_dp=res.dn_dp, cov_params=cal.covariance)
        nees.append(r.nees(s.rvec, _centre(s)))
        alarms += any("do not fit" in w for w in r.warnings)
    nees = np.array(nees)
    assert alarms <= 2  # the chi2 check's false-alarm rate is 0.1 %
    mc_err = np.sqrt(12.0 / len(nees))  # chi2(6) has variance 12
    assert abs(nees.mean() - 6.0) < 3 * mc_err, nees.mean()
    # the calibration part matters here: without it the NEES is far too large
    assert np.mean(nees < 16.81) > 0.97  # chi2(6) 99 % quantile


def test_positions_with_estimated_poses_within_3_sigma():
    """Each sensor posed from its own (erroneous) calibration; the tag triangulated with those poses.

    With the poses' calibration dependence (``pose_calibration``) the normalised errors have unit spread;
    with the total pose covariance alone the stated sigma is safe but about twice too large."""
    rng = np.random.default_rng(5)
    zs = {"joint": [], "total": []}
    for room in range(24):
        sensors, em = room_layout(TRUE, n_sensors=2, n_anchors=5, moving="circle", seed=500 + room)
        anchors = np.array([e.p0_mm for e in em if e.kind == "static"])
        tag = em[-1]
        cals = [_calibrated(rng) for _ in sensors]
        fits = []
        for s, cal in zip(sensors, cals):
            res = _observe(cal, s, anchors, 2e-4, rng)
            fits.append(estimate_pose(res.n, res.cov_n_noise, anchors, dn_dp=res.dn_dp, cov_params=cal.covariance))
        t = np.linspace(0, 5, 100)
        P = tag.position(t)
        results = [_observe(cal, s, P, 5e-4, rng) for s, cal in zip(sensors, cals)]
        for mode in zs:
            posed = []
            for s, cal, r in zip(sensors, cals, fits):
                e = r.sensors_entry(s.name, "c.json", calib_names=cal.names)
                pc = None
                if mode == "joint":
                    pc = (np.array(e["pose_calibration"]["jacobian"]), np.array(e["pose_calibration"]["noise_covariance"]))
                posed.append(SensorPose(s.name, cal, r.rvec, r.tvec_mm, cov_pose=r.cov_omega_t(), pose_calib=pc))
            tri = triangulate_aoa(results, posed)
            zs[mode].append((tri.p_w_mm - P) / tri.sigma_p_mm)
    for mode, z in zs.items():
        z = np.concatenate(z)
        assert np.mean(np.all(np.abs(z) < 3, axis=-1)) >= 0.99, mode
    # the errors of one room are nearly the same in every window (systematic): pool the axes
    rms_joint = np.sqrt(np.mean(np.concatenate(zs["joint"]) ** 2))
    rms_total = np.sqrt(np.mean(np.concatenate(zs["total"]) ** 2))
    assert 0.7 < rms_joint < 1.3, rms_joint
    assert rms_total < 0.7 * rms_joint


def test_pose_covariance_enters_the_position():
    rng = np.random.default_rng(2)
    sensors, em = room_layout(TRUE, n_sensors=2, n_anchors=0, moving="circle", seed=9)
    P = em[-1].position(np.linspace(0, 1, 5))
    res = [_observe(TRUE, s, P, 1e-4, rng) for s in sensors]
    exact = triangulate_aoa(res, [SensorPose(s.name, TRUE, s.rvec, s.tvec_mm) for s in sensors])
    C = np.diag([1e-6] * 3 + [4.0] * 3)
    loose = triangulate_aoa(res, [SensorPose(s.name, TRUE, s.rvec, s.tvec_mm, cov_pose=C) for s in sensors])
    assert np.all(loose.sigma_p_mm > exact.sigma_p_mm)
    # a translation uncertainty of 2 mm per axis and sensor: the point's sigma is of that order
    assert np.all(loose.sigma_p_mm > 1.0) and np.all(loose.sigma_p_mm < 12.0)


def test_known_orientation_and_height():
    rng = np.random.default_rng(3)
    sensors, em = room_layout(TRUE, n_sensors=1, n_anchors=2, moving=None, seed=21)
    s = sensors[0]
    P = np.array([e.p0_mm for e in em])
    res = _observe(TRUE, s, P, 1e-4, rng)
    r2 = estimate_pose(res.n, res.cov_n_noise, P, known_rvec=s.rvec)
    assert r2.nees(s.rvec, _centre(s)) < 20
    assert not r2.free[:3].any()
    r1 = estimate_pose(res.n[:1], res.cov_n_noise[:1], P[:1], known_rvec=s.rvec, known_height_mm=_centre(s)[2])
    np.testing.assert_allclose(r1.center_w_mm, _centre(s), atol=5 * r1.sigma_center_mm.max() + 1e-9)
    with pytest.raises(DegenerateViewsError, match="at least"):
        estimate_pose(res.n[:1], res.cov_n_noise[:1], P[:1], known_rvec=s.rvec)
    # a known height alone: five parameters from three or more emitters
    sensors, em = room_layout(TRUE, n_sensors=1, n_anchors=4, moving=None, seed=22)
    s = sensors[0]
    P = np.array([e.p0_mm for e in em])
    res = _observe(TRUE, s, P, 1e-4, rng)
    rh = estimate_pose(res.n, res.cov_n_noise, P, known_height_mm=_centre(s)[2])
    assert rh.center_w_mm[2] == _centre(s)[2] and rh.sigma_center_mm[2] == 0.0
    assert list(rh.free) == [True] * 5 + [False]
    assert rh.nees(s.rvec, _centre(s)) < 25  # chi2(5) 99.99 %
    free = estimate_pose(res.n, res.cov_n_noise, P)
    assert np.all(rh.sigma_center_mm[:2] <= free.sigma_center_mm[:2] * (1 + 1e-9))


def test_degenerate_layouts():
    rng = np.random.default_rng(4)
    sensors, em = room_layout(TRUE, n_sensors=1, n_anchors=5, moving=None, seed=31)
    s = sensors[0]
    P = np.array([e.p0_mm for e in em])
    res = _observe(TRUE, s, P, 1e-4, rng)
    with pytest.raises(DegenerateViewsError, match="at least 3"):
        estimate_pose(res.n[:2], res.cov_n_noise[:2], P[:2])
    line = P[0] + np.linspace(0, 1, 4)[:, None] * (P[1] - P[0])
    rl = _observe(TRUE, s, line, 1e-4, rng)
    with pytest.raises(DegenerateViewsError, match="collinear"):
        estimate_pose(rl.n, rl.cov_n_noise, line)
    # a tight cluster of emitters: a warning with the uncertainty
    c = P[0] + rng.normal(0, 30.0, (4, 3))
    rc = _observe(TRUE, s, c, 1e-3, rng)
    r = estimate_pose(rc.n, rc.cov_n_noise, c)
    assert any("poor emitter layout" in w for w in r.warnings)


def test_cli_pose_from_recording_then_locate(tmp_path):
    """simulate-recording room -> pose (per sensor) -> locate --sensors with the estimated poses."""
    import csv

    from psdcal.cli import main

    room = tmp_path / "room"
    assert main(["simulate-recording", "room", "--sensors", "2", "--anchors", "5", "--duration-s", "1.0",
                 "--survey-s", "0.5",
                 "--snr-db", "50", "--seed", "3", "-o", str(room)]) == 0
    names, P, carriers = read_emitters(room / "emitters.csv")
    assert len(names) == 5 and carriers is not None
    est = tmp_path / "sensors_est.json"
    for s in ("s1", "s2"):
        assert main(["pose", str(room / f"{s}.npy"), "--rate-hz", "20000", "--calib", str(room / "calib_truth.json"),
                     "--emitters", str(room / "emitters.csv"), "--also-carrier-hz", "1750", "--name", s,
                     "--into", str(est)]) == 0
    data = json.loads(est.read_text())
    truth = json.loads((room / "sensors.json").read_text())["sensors"]
    for e, t in zip(data["sensors"], truth):
        c_est = np.array(e["pose"]["center_w_mm"])
        c_true = -R_from_r(np.array(t["rvec"])).T @ np.array(t["tvec_mm"])
        assert np.all(np.abs(c_est - c_true) < 4 * np.array(e["pose"]["sigma_center_mm"]) + 1e-6)
        assert e["recording"] == f"room/{t['name']}.npy"
        assert max(e["pose"]["sigma_center_mm"]) < 5.0 and not e["pose"]["warnings"]
    out = tmp_path / "xyz.csv"
    truth_e = json.loads((room / "truth.json").read_text())["emitters"]
    tag_f = [e["carrier_hz"] for e in truth_e if e["name"] == "tag"][0]
    assert main(["locate", "--allow-no-covariance", "--sensors", str(est), "--rate-hz", "20000", "--carrier-hz", str(tag_f),
                 "--emitter", "tag", "-o", str(out)]) == 0
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    assert 50 <= len(rows) <= 51  # the tag is lit in the second half


def test_cli_pose_from_angles_table_with_known_orientation(tmp_path):
    """An angles table (no impact points) and a known orientation: two emitters fix the centre."""
    from psdcal.cli import main

    rng = np.random.default_rng(8)
    sensors, em = room_layout(TRUE, n_sensors=1, n_anchors=2, moving=None, seed=41)
    s = sensors[0]
    P = np.array([e.p0_mm for e in em])
    n, _ = project_world(P, s.rvec, s.tvec_mm)
    sig = 0.002  # deg
    lines = ["t_s,emitter,alpha_x_deg,alpha_y_deg,sigma_alpha_x_deg,sigma_alpha_y_deg"]
    for w in range(10):
        for e, nn in zip(em, n):
            a = np.degrees(np.arctan(nn)) + sig * rng.standard_normal(2)
            lines.append(f"{w * 0.01:.3f},{e.name},{a[0]:.9f},{a[1]:.9f},{sig},{sig}")
    (tmp_path / "ang.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "em.csv").write_text("emitter,X_m,Y_m,Z_m\n" + "".join(
        f"{e.name},{e.p0_mm[0] / 1000},{e.p0_mm[1] / 1000},{e.p0_mm[2] / 1000}\n" for e in em))
    (tmp_path / "calib.json").write_text(json.dumps(calib_dict(seed=4)))
    assert main(["pose", str(tmp_path / "ang.csv"), "--calib", str(tmp_path / "calib.json"), "--emitters",
                 str(tmp_path / "em.csv"), "--known-rvec", *map(str, s.rvec), "-o", str(tmp_path / "e.json")]) == 0
    e = json.loads((tmp_path / "e.json").read_text())
    assert e["pose"]["free"] == ["cx", "cy", "cz"]
    err = np.abs(np.array(e["pose"]["center_w_mm"]) - _centre(s))
    assert np.all(err < 4 * np.array(e["pose"]["sigma_center_mm"]))
    assert main(["pose", str(tmp_path / "ang.csv"), "--calib", str(tmp_path / "calib.json"), "--emitters",
                 str(tmp_path / "em.csv"), "-o", str(tmp_path / "e2.json")]) == 2  # 2 emitters, no orientation


from hypothesis import given, settings, strategies as st  # noqa: E402


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), angle=st.floats(-3.0, 3.0), shift=st.tuples(*[st.floats(-5e3, 5e3)] * 3))
def test_pose_moves_with_the_world_frame(seed, angle, shift):
    """Re-express the room in another world frame: the estimated pose is the same pose in that frame."""
    rng = np.random.default_rng(seed)
    sensors, em = room_layout(TRUE, n_sensors=1, n_anchors=5, moving=None, seed=seed % 50)
    s = sensors[0]
    P = np.array([e.p0_mm for e in em])
    res = _observe(TRUE, s, P, 1e-4, rng)
    a = estimate_pose(res.n, res.cov_n_noise, P)
    Q = R_from_r(np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0]) * angle)
    P2 = P @ Q.T + np.array(shift)
    b = estimate_pose(res.n, res.cov_n_noise, P2)
    np.testing.assert_allclose(b.center_w_mm, Q @ a.center_w_mm + np.array(shift), atol=1e-5 * (1 + a.sigma_center_mm.max()))
    np.testing.assert_allclose(b.R, a.R @ Q.T, atol=1e-8)
    assert b.chi2 == pytest.approx(a.chi2, rel=1e-6, abs=1e-9)


def test_cli_pose_errors_are_one_line(tmp_path, capsys):
    from psdcal.cli import main

    (tmp_path / "calib.json").write_text(json.dumps(calib_dict(seed=4)))
    (tmp_path / "em.csv").write_text("emitter,X_m,Y_m,Z_m\na,1,1,1\nb,2,2,2\nc,3,3,3\n")
    lines = ["emitter,alpha_x_deg,alpha_y_deg,sigma_alpha_x_deg,sigma_alpha_y_deg"]
    lines += [f"{e},{k},{k},0.01,0.01" for k, e in enumerate("abc")]
    (tmp_path / "ang.csv").write_text("\n".join(lines) + "\n")
    args = ["pose", str(tmp_path / "ang.csv"), "--calib", str(tmp_path / "calib.json"), "--emitters",
            str(tmp_path / "em.csv"), "-o", str(tmp_path / "e.json")]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "collinear" in err and len(err.splitlines()) == 1
    (tmp_path / "em.csv").write_text("emitter,X_m,Y_m\na,1,1\n")
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "em.csv" in err and "Z_m" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "e.json").exists()


def test_ceiling_sensor_over_floor_emitters_is_never_a_mirror_image():
    """The issue's case: every emitter on the floor (z = 0), a sensor on the ceiling looking down, 25 rooms. The old
    solver returned a reflection (the sensor below the floor, a good chi2) in about half of them."""
    rng = np.random.default_rng(19)
    for _ in range(25):
        k = int(rng.integers(4, 9))
        P = np.c_[rng.uniform(0, 6000, k), rng.uniform(0, 4000, k), np.zeros(k)]
        c = np.array([rng.uniform(1000, 5000), rng.uniform(1000, 3000), rng.uniform(2400, 3000)])
        # looking down (camera z = -world z), rolled by a random angle about the vertical, tilted a little
        yaw = rng.uniform(-np.pi, np.pi)
        R = R_from_r(rng.normal(0, 0.1, 3)) @ np.diag([1.0, -1.0, -1.0]) @ R_from_r(np.array([0.0, 0.0, yaw]))
        rvec = r_from_R(R)
        n, _ = project_world(P, rvec, -R @ c)
        sig = 1e-4
        n = n + sig * rng.standard_normal(n.shape)
        r = estimate_pose(n, np.broadcast_to(sig**2 * np.eye(2), (k, 2, 2)), P)
        assert r.usable and r.center_w_mm[2] > 0
        assert r.nees(rvec, c) < 37.95  # chi2(6) at 1e-6
        # the written pose reproduces the fitted angles (a reflection inside would not)
        m, _ = project_world(P, r.rvec, r.tvec_mm)
        np.testing.assert_allclose(m, n - r.residual_n, atol=1e-9)
