"""Bundle adjustment of several sensors (psdcal.measure.bundle).

Simulated rooms: three sensors, four known emitters, unknown fixed emitters
and a wand's positions.  From starting poses far from the truth the
adjustment recovers the simulated poses and points with a consistent NEES,
and the answer does not depend on the order of the sensors.
"""
from __future__ import annotations

import numpy as np
import pytest

from psdcal.errors import DegenerateViewsError
from psdcal.measure.bundle import bundle_adjust
from psdcal.measure.sensor_model import SensorModel
from psdcal.model.projection import R_from_r, r_from_R
from psdcal.study.recordings import _in_view, project_world, room_sensors
from psdcal.study.simulate import LENSES

TRUE = SensorModel(*LENSES["lens2"])


def _scene(rng, n_unknown=6, n_wand=25, sigma_n=1e-4):
    sensors = room_sensors(3, (6000.0, 4000.0, 3000.0), TRUE)
    pts = []
    while len(pts) < 4 + n_unknown + n_wand:
        p = np.array([rng.uniform(1800, 4200), rng.uniform(1000, 3000), rng.uniform(200, 1800)])
        if all(_in_view(TRUE, p, s.rvec, s.tvec_mm, 0.85) for s in sensors):
            pts.append(p)
    P = np.array(pts)
    names = [f"k{i}" for i in range(4)] + [f"u{i}" for i in range(n_unknown)] + [f"w{i}" for i in range(n_wand)]
    known = {names[i]: P[i] for i in range(4)}
    js, ii, ns = [], [], []
    for j, s in enumerate(sensors):
        n, _ = project_world(P, s.rvec, s.tvec_mm)
        for i in range(len(P)):
            js.append(j)
            ii.append(i)
            ns.append(n[i] + sigma_n * rng.standard_normal(2))
    cov = np.broadcast_to(sigma_n**2 * np.eye(2), (len(ns), 2, 2)).copy()
    return sensors, names, P, known, np.array(js), np.array(ii), np.array(ns), cov


def _random_start(rng, sensors, deg=3.0, mm=150.0):
    rv, cs = [], []
    for s in sensors:
        R = R_from_r(rng.normal(0, np.radians(deg) / np.sqrt(3), 3)) @ R_from_r(s.rvec)
        rv.append(r_from_R(R))
        cs.append(-R_from_r(s.rvec).T @ s.tvec_mm + rng.normal(0, mm, 3))
    return np.array(rv), np.array(cs)


# --------------------------------------------------------------------------- an independent generator
# The two NEES tests below draw their rooms with numpy and scipy alone (sensors on three walls aimed at the
# room's centre, a pinhole projection written out, Gaussian noise): nothing of psdcal's simulator.
WALLS = np.array([[200.0, 2000.0, 2600.0], [5800.0, 1000.0, 2600.0], [3000.0, 3800.0, 2600.0]])
AIM = np.array([3000.0, 2000.0, 1000.0])


def _aimed(c, target, roll):
    """Rotation world -> camera with the camera's z from ``c`` to ``target``, rolled by ``roll`` rad."""
    z = (target - c) / np.linalg.norm(target - c)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    cr, sr = np.cos(roll), np.sin(roll)
    return np.array([[cr, sr, 0.0], [-sr, cr, 0.0], [0.0, 0.0, 1.0]]) @ R


def _independent_scene(rng, n_unknown=6, n_wand=25):
    """Rotations (3, 3, 3), point names, points (M, 3) mm, observation indices and true directions."""
    Rs = np.stack([_aimed(c, AIM + rng.normal(0, 150, 3), rng.uniform(-0.3, 0.3)) for c in WALLS])
    pts = []
    while len(pts) < 4 + n_unknown + n_wand:
        p = rng.uniform([1800, 1000, 200], [4200, 3000, 1800])
        pc = np.einsum("kij,kj->ki", Rs, p - WALLS)
        if np.all(pc[:, 2] > 0) and np.all(np.hypot(pc[:, 0], pc[:, 1]) < 0.55 * pc[:, 2]):
            pts.append(p)
    P = np.array(pts)
    names = [f"k{i}" for i in range(4)] + [f"u{i}" for i in range(n_unknown)] + [f"w{i}" for i in range(n_wand)]
    js = np.repeat(np.arange(3), len(P))
    ii = np.tile(np.arange(len(P)), 3)
    pc = np.einsum("nij,nj->ni", Rs[js], P[ii] - WALLS[js])
    return Rs, names, P, js, ii, pc[:, :2] / pc[:, 2:]


def _starts(rng, Rs, deg=3.0, mm=150.0):
    from scipy.spatial.transform import Rotation

    rv = np.array([(Rotation.from_rotvec(rng.normal(0, np.radians(deg) / np.sqrt(3), 3)) * Rotation.from_matrix(R))
                   .as_rotvec() for R in Rs])
    return rv, WALLS + rng.normal(0, mm, (3, 3))


def _pose_nees(res, Rs):
    from scipy.spatial.transform import Rotation

    out = []
    for j, R in enumerate(Rs):
        e = res.pose_error(j, Rotation.from_matrix(R).as_rotvec(), WALLS[j])
        out.append(float(e @ np.linalg.solve(res.cov_poses[j], e)))
    return out


def _band(scene_means, expected, k=3.0):
    """``|mean - expected| < k * se`` with se the Monte Carlo standard error over scenes (poses within a scene
    are correlated, scenes are independent)."""
    m = np.asarray(scene_means)
    se = m.std(ddof=1) / np.sqrt(len(m))
    return abs(m.mean() - expected) < k * se, m.mean(), se


def test_recovers_truth_with_consistent_nees():
    """360 poses (120 rooms of 3 sensors, 4 known points, 6 unknown, 25 wand positions), starts 3 deg and
    150 mm off: pose NEES mean within 3 Monte Carlo standard errors of 6, point NEES of 3 (two-sided)."""
    rng = np.random.default_rng(0)
    sigma_n = 1e-4
    pose_means, pt_means = [], []
    for trial in range(120):
        Rs, names, P, js, ii, n_true = _independent_scene(rng)
        n = n_true + sigma_n * rng.standard_normal(n_true.shape)
        cov = np.broadcast_to(sigma_n**2 * np.eye(2), (len(n), 2, 2)).copy()
        rv0, c0 = _starts(rng, Rs)
        known = {names[i]: P[i] for i in range(4)}
        res = bundle_adjust(["a", "b", "c"], names, js, ii, n, cov, known, init_rvecs=rv0, init_centers_mm=c0)
        pose_means.append(np.mean(_pose_nees(res, Rs)))
        unk = ~res.known
        e = res.points_mm[unk] - P[unk]
        pt_means.append(np.mean(np.einsum("mi,mij,mj->m", e, np.linalg.inv(res.cov_points[unk]), e)))
        assert res.dof == 2 * len(n) - 18 - 3 * unk.sum()
        assert res.chi2 < 2 * res.dof
    ok, mean, se = _band(pose_means, 6.0)
    assert ok, (mean, se)  # measured: 5.74 +- 0.25
    ok, mean, se = _band(pt_means, 3.0)
    assert ok, (mean, se)  # measured: 2.93 +- 0.09


def test_same_answer_with_sensors_reordered():
    rng = np.random.default_rng(1)
    sensors, names, P, known, js, ii, n, cov = _scene(rng)
    rv0, c0 = _random_start(rng, sensors)
    a = bundle_adjust(["s1", "s2", "s3"], names, js, ii, n, cov, known, init_rvecs=rv0, init_centers_mm=c0)
    perm = np.array([2, 0, 1])  # new index k holds old sensor perm[k]
    inv = np.argsort(perm)
    order = np.argsort(inv[js], kind="stable")  # observations listed sensor by sensor in the new order
    rv1, c1 = _random_start(rng, [sensors[k] for k in perm])  # and another start
    b = bundle_adjust(["s3", "s1", "s2"], names, inv[js][order], ii[order], n[order], cov[order], known,
                      init_rvecs=rv1, init_centers_mm=c1)
    np.testing.assert_allclose(b.centers_mm, a.centers_mm[perm], atol=1e-6)
    np.testing.assert_allclose(b.rvecs, a.rvecs[perm], atol=1e-9)
    np.testing.assert_allclose(b.cov_poses, a.cov_poses[perm], rtol=1e-5, atol=1e-14)
    np.testing.assert_allclose(b.points_mm, a.points_mm, atol=1e-6)


def test_frame_needs_three_known_points():
    rng = np.random.default_rng(2)
    sensors, names, P, known, js, ii, n, cov = _scene(rng, n_wand=5)
    rv0, c0 = _random_start(rng, sensors)
    two = dict(list(known.items())[:2])
    with pytest.raises(DegenerateViewsError, match="three known points"):
        bundle_adjust(["a", "b", "c"], names, js, ii, n, cov, two, init_rvecs=rv0, init_centers_mm=c0)


def test_cli_bundle_with_wand(tmp_path):
    """simulate-recording room (3 sensors) -> locate per sensor -> bundle with 3 known emitters + wand."""
    import json

    from psdcal.cli import main

    room = tmp_path / "room"
    assert main(["simulate-recording", "room", "--sensors", "3", "--anchors", "5", "--moving", "circle",
                 "--duration-s", "0.6", "--snr-db", "50", "--seed", "8", "-o", str(room)]) == 0
    lines = (room / "emitters.csv").read_text().splitlines()
    (tmp_path / "known.csv").write_text("\n".join(lines[:5]) + "\n")  # a1..a4 known; a5 unknown
    truth = json.loads((room / "truth.json").read_text())
    carriers = [(e["name"], e["carrier_hz"]) for e in truth["emitters"]]
    args = []
    for s in ("s1", "s2", "s3"):
        out = tmp_path / f"{s}.csv"
        cmd = ["locate", str(room / f"{s}.npy"), "--calib", str(room / "calib_truth.json"), "--allow-no-covariance", "--rate-hz", "20000",
               "-o", str(out)]
        for nm, f in carriers:
            cmd += ["--carrier-hz", str(f), "--emitter", nm]
        assert main(cmd) == 0
        args.append(f"{s}={out}")
    assert main(["bundle", *args, "--calib", str(room / "calib_truth.json"), "--known", str(tmp_path / "known.csv"),
                 "--wand", "tag", "-o", str(tmp_path / "sensors.json"), "--points-out", str(tmp_path / "pts.csv")]) == 0
    est = json.loads((tmp_path / "sensors.json").read_text())["sensors"]
    tru = {s["name"]: s for s in truth["sensors"]}
    for e in est:
        t = tru[e["name"]]
        c_true = -R_from_r(np.array(t["rvec"])).T @ np.array(t["tvec_mm"])
        err = np.abs(np.array(e["pose"]["center_w_mm"]) - c_true)
        assert np.all(err < 5 * np.array(e["pose"]["sigma_center_mm"]) + 0.05), (err, e["pose"]["sigma_center_mm"])
    pts = {r.split(",")[0]: np.array(r.split(",")[1:4], float) * 1000 for r in (tmp_path / "pts.csv").read_text().splitlines()[1:]}
    a5 = [e["p0_mm"] for e in truth["emitters"] if e["name"] == "a5"][0]
    assert np.linalg.norm(pts["a5"] - a5) < 2.0
    # the estimated sensors file works for locate --sensors
    assert main(["locate", "--allow-no-covariance", "--sensors", str(tmp_path / "sensors.json"), str(room / "s1.npy"), str(room / "s2.npy"),
                 str(room / "s3.npy"), "--rate-hz", "20000", "--carrier-hz", "1000", "--emitter", "a1",
                 "-o", str(tmp_path / "xyz.csv")]) == 0


def _calib_jacobian(n):
    """d n / d theta of this test's own calibration error model, theta = (scale, cx, cy, k1) (N, 2, 4)."""
    D = np.zeros((len(n), 2, 4))
    D[:, :, 0] = -n
    D[:, 0, 1] = 1.0
    D[:, 1, 2] = 1.0
    D[:, :, 3] = (n**2).sum(1)[:, None] * n
    return D


CAL_COV = np.diag([1e-3, 5e-4, 5e-4, 2e-3]) ** 2


def _calibrated_runs(rng, scale=1.0, scenes=40):
    """Per scene, the mean pose NEES with the calibration propagated (covariance ``scale`` x the true one
    given to the code) and with it treated as independent noise per observation."""
    sigma_n = 1e-4
    prop, ind = [], []
    for trial in range(scenes):
        Rs, names, P, js, ii, n_true = _independent_scene(rng, n_unknown=4, n_wand=40)
        theta = rng.multivariate_normal(np.zeros(4), CAL_COV, size=3)  # one calibration error per sensor
        D = _calib_jacobian(n_true)
        n = n_true + np.einsum("nij,nj->ni", D, theta[js]) + sigma_n * rng.standard_normal(n_true.shape)
        cov_noise = np.broadcast_to(sigma_n**2 * np.eye(2), (len(n), 2, 2)).copy()
        cov_tot = cov_noise + D @ CAL_COV @ np.swapaxes(D, 1, 2)
        rv0, c0 = _starts(rng, Rs, deg=1.0, mm=50.0)
        known = {names[i]: P[i] for i in range(4)}
        res = bundle_adjust(["a", "b", "c"], names, js, ii, n, cov_noise, known, init_rvecs=rv0, init_centers_mm=c0,
                            calib=(D, np.stack([scale * CAL_COV] * 3)))
        prop.append(np.mean(_pose_nees(res, Rs)))
        res = bundle_adjust(["a", "b", "c"], names, js, ii, n, cov_tot, known, init_rvecs=rv0, init_centers_mm=c0)
        ind.append(np.mean(_pose_nees(res, Rs)))
    return np.array(prop), np.array(ind)


def test_calibration_error_propagated_not_averaged():
    """Each sensor observes through its own calibration error (drawn from its covariance; this test's own
    linear model): with the calibration propagated the pose NEES of 120 poses (40 rooms) is within 3 Monte
    Carlo standard errors of 6; treated as independent noise per observation it is far larger."""
    prop, ind = _calibrated_runs(np.random.default_rng(3))
    ok, mean, se = _band(prop, 6.0)
    assert ok, (mean, se)
    assert ind.mean() > 2 * prop.mean(), (ind.mean(), prop.mean())


def test_calibration_nees_band_rejects_a_covariance_2_5x_too_large():
    """The band of the test above has the power to see a calibration covariance 2.5x too large."""
    prop, _ = _calibrated_runs(np.random.default_rng(3), scale=2.5)
    ok, mean, se = _band(prop, 6.0)
    assert not ok, (mean, se)


def test_noise_larger_than_stated_is_detected_and_covered():
    """Rays 3x noisier than stated: the chi2 check fails in every room, the covariance grows by chi2/dof
    (~9) and the pose NEES of 180 poses (60 rooms) is back within 3 Monte Carlo standard errors of 6."""
    rng = np.random.default_rng(7)
    sigma_n = 1e-4
    means = []
    for trial in range(60):
        Rs, names, P, js, ii, n_true = _independent_scene(rng)
        n = n_true + 3 * sigma_n * rng.standard_normal(n_true.shape)
        cov = np.broadcast_to(sigma_n**2 * np.eye(2), (len(n), 2, 2)).copy()
        rv0, c0 = _starts(rng, Rs)
        known = {names[i]: P[i] for i in range(4)}
        res = bundle_adjust(["a", "b", "c"], names, js, ii, n, cov, known, init_rvecs=rv0, init_centers_mm=c0)
        assert res.check.passed is False and 6 < res.check.inflation < 12
        assert "covariance inflated" in res.check.message
        np.testing.assert_allclose(res.cov_poses, res.check.inflation * res.cov_poses_stated)
        means.append(np.mean(_pose_nees(res, Rs)))
    ok, mean, se = _band(means, 6.0)
    assert ok, (mean, se)
