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


def test_recovers_truth_with_consistent_nees():
    rng = np.random.default_rng(0)
    nees_pose, nees_pt = [], []
    for trial in range(25):
        sensors, names, P, known, js, ii, n, cov = _scene(rng)
        rv0, c0 = _random_start(rng, sensors)
        res = bundle_adjust([s.name for s in sensors], names, js, ii, n, cov, known, init_rvecs=rv0,
                            init_centers_mm=c0)
        for j, s in enumerate(sensors):
            e = res.pose_error(j, s.rvec, -R_from_r(s.rvec).T @ s.tvec_mm)
            nees_pose.append(e @ np.linalg.solve(res.cov_poses[j], e))
        unk = ~res.known
        e = res.points_mm[unk] - P[unk]
        nees_pt += list(np.einsum("mi,mij,mj->m", e, np.linalg.inv(res.cov_points[unk]), e))
        assert res.dof == 2 * len(n) - 18 - 3 * unk.sum()
        assert res.chi2 < 2 * res.dof
    nees_pose, nees_pt = np.array(nees_pose), np.array(nees_pt)
    assert abs(nees_pose.mean() - 6) < 3 * np.sqrt(12 / len(nees_pose)) * 1.3, nees_pose.mean()
    assert abs(nees_pt.mean() - 3) < 3 * np.sqrt(6 / len(nees_pt)) * 2, nees_pt.mean()


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


def test_calibration_error_propagated_not_averaged():
    """Each sensor observes through its own erroneous calibration: with the calibration propagated through
    the solution the pose NEES is ~6; treated as independent noise per observation it is far larger."""
    from psdcal.measure.aoa import angles_from_points
    from psdcal.measure.pose import estimate_pose
    from psdcal.study.recordings import calib_dict, spot_for_normalised

    true = SensorModel.from_dict(calib_dict(seed=4))
    rng = np.random.default_rng(3)
    nees = {"propagated": [], "independent": []}
    for trial in range(12):
        sensors, names, P, known, js, ii, n_true, cov = _scene(rng, n_unknown=4, n_wand=40, sigma_n=0.0)
        cals = []
        for _ in sensors:
            draw = rng.multivariate_normal(np.zeros(len(true.names)), true.covariance)
            cals.append(true.with_values({nm: true.value(nm) + dv for nm, dv in zip(true.names, draw)}))
        n = np.zeros_like(n_true)
        cov_noise = np.zeros((len(n), 2, 2))
        cov_tot = np.zeros((len(n), 2, 2))
        D = np.zeros((len(n), 2, len(true.names)))
        for j, s in enumerate(sensors):
            m = js == j
            # the true directions through the TRUE sensor (with its own PSD/lens), read with calibration j
            from psdcal.study.recordings import project_world

            nn, _ = project_world(P[ii[m]], s.rvec, s.tvec_mm)
            d = spot_for_normalised(true, nn) + 2e-4 * rng.standard_normal((m.sum(), 2))
            res = angles_from_points(d, cals[j], np.broadcast_to(4e-8 * np.eye(2), (m.sum(), 2, 2)))
            n[m], cov_noise[m], cov_tot[m], D[m] = res.n, res.cov_n_noise, res.cov_n, res.dn_dp
        starts = []
        for j, s in enumerate(sensors):
            k = np.flatnonzero((js == j) & np.isin(ii, [0, 1, 2, 3]))
            st = estimate_pose(n[k], cov_tot[k], P[ii[k]])
            starts.append((st.rvec, st.center_w_mm))
        rv0, c0 = np.array([a for a, _ in starts]), np.array([b for _, b in starts])
        sn = [s.name for s in sensors]
        prop = bundle_adjust(sn, names, js, ii, n, cov_noise, known, init_rvecs=rv0, init_centers_mm=c0,
                             calib=(D, np.stack([c.covariance for c in cals])))
        ind = bundle_adjust(sn, names, js, ii, n, cov_tot, known, init_rvecs=rv0, init_centers_mm=c0)
        for key, res in (("propagated", prop), ("independent", ind)):
            for j, s in enumerate(sensors):
                e = res.pose_error(j, s.rvec, -R_from_r(s.rvec).T @ s.tvec_mm)
                nees[key].append(e @ np.linalg.solve(res.cov_poses[j], e))
    prop_mean = np.mean(nees["propagated"])
    assert 3.0 < prop_mean < 10.0, prop_mean  # 36 poses from 12 scenes (correlated within a scene)
    assert np.mean(nees["independent"]) > 2 * prop_mean
