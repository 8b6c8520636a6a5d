"""Installation planning maps (psdcal.measure.planning, `psdcal plan`)."""
from __future__ import annotations

import json

import numpy as np

from psdcal.measure.aoa import angles_from_points
from psdcal.measure.planning import plan_map
from psdcal.measure.positioning import SensorPose, triangulate
from psdcal.measure.sensor_model import SensorModel
from psdcal.model.params import Distortion, Intrinsics
from psdcal.study.recordings import calib_dict, look_at, spot_for_normalised


def test_coverage_of_a_pinhole_looking_down():
    """No distortion: a point is seen iff |f X/Z + c| < L/2 on both axes (closed form)."""
    m = SensorModel(Intrinsics(f_mm=8.0, cx_mm=0.3, cy_mm=-0.2), Distortion())
    count = 0
    sensors = []
    for cx in (2000.0, 4000.0):
        rvec, tvec = look_at([cx, 2000.0, 3000.0], [cx, 2000.0, 0.0], up=(0, 1, 0))
        s = SensorPose(f"s{cx:g}", m, rvec, tvec)
        sensors.append(s)
        XX, YY = np.meshgrid(np.arange(48.5, 6000, 97.0), np.arange(48.5, 4000, 97.0))
        P = np.stack([XX, YY, np.zeros_like(XX)], -1)
        pc = P @ s.R.T + tvec
        x = 8.0 * pc[..., 0] / pc[..., 2] + 0.3
        y = 8.0 * pc[..., 1] / pc[..., 2] - 0.2
        count = count + ((np.abs(x) < 4.5) & (np.abs(y) < 4.5))
    pm = plan_map(sensors, (6000.0, 4000.0, 3000.0), z_mm=0.0, grid_mm=97.0)
    assert (count == 2).any() and (count == 1).any() and (count == 0).any()
    np.testing.assert_array_equal(pm.count, count)
    assert np.all(np.isfinite(pm.sigma_mm[count == 2])) and np.all(np.isnan(pm.sigma_mm[count < 2]))


def test_sigma_matches_triangulation_and_monte_carlo():
    m = SensorModel.from_dict(calib_dict(seed=1))
    poses = [look_at(c, [3000.0, 2000.0, 800.0]) for c in ([500.0, 500.0, 2700.0], [5500.0, 3500.0, 2700.0],
                                                           [5500.0, 500.0, 2700.0])]
    sensors = [SensorPose(f"s{j}", m, r, t) for j, (r, t) in enumerate(poses)]
    pm = plan_map(sensors, (6000.0, 4000.0, 3000.0), z_mm=1000.0, grid_mm=400.0, sigma_d_mm=2e-3)
    ok = np.argwhere(pm.count == 3)
    assert len(ok) > 5
    rng = np.random.default_rng(0)
    for iy, ix in ok[:: max(1, len(ok) // 4)]:
        P = np.array([pm.x_mm[ix], pm.y_mm[iy], 1000.0])
        ns, covs = [], []
        for s in sensors:
            pc = s.R @ P + s.tvec_mm
            n = pc[:2] / pc[2]
            d = spot_for_normalised(m, n)
            res = angles_from_points(d, m, 4e-6 * np.eye(2))
            ns.append(res.n)
            covs.append(res.cov_n)
        tri = triangulate(np.array(ns), np.array(covs), np.stack([s.R for s in sensors]),
                          np.stack([s.tvec_mm for s in sensors]))
        np.testing.assert_allclose(tri.cov_p_mm2, pm.cov_mm2[iy, ix], rtol=1e-3)
        # Monte Carlo: rays drawn with their covariance, triangulated
        draws = np.array(ns)[:, None] + np.einsum("kij,knj->kni", np.linalg.cholesky(np.array(covs)),
                                                  rng.standard_normal((3, 4000, 2)))
        t = triangulate(draws, np.broadcast_to(np.array(covs)[:, None], (3, 4000, 2, 2)),
                        np.stack([s.R for s in sensors]), np.stack([s.tvec_mm for s in sensors]))
        sd = t.p_w_mm.std(axis=0)
        np.testing.assert_allclose(sd, pm.sigma_xyz_mm[iy, ix], rtol=0.08)


def test_cli_plan(tmp_path):
    from psdcal.cli import main

    room = tmp_path / "room"
    assert main(["simulate-recording", "room", "--sensors", "3", "--anchors", "3", "--moving", "none",
                 "--duration-s", "0.05", "-o", str(room)]) == 0
    assert main(["plan", "--sensors", str(room / "sensors.json"), "--room-m", "6", "4", "3", "--grid-mm", "250",
                 "-o", str(tmp_path / "plan.png"), "--csv", str(tmp_path / "plan.csv")]) == 0
    assert (tmp_path / "plan.png").read_bytes()[:4] == b"\x89PNG"
    rows = (tmp_path / "plan.csv").read_text().splitlines()
    assert rows[0] == "X_m,Y_m,Z_m,n_sensors,sigma_mm,sigma_X_mm,sigma_Y_mm,sigma_Z_mm"
    assert len(rows) == 1 + 24 * 16
    counts = [int(r.split(",")[3]) for r in rows[1:]]
    assert max(counts) == 3 and min(counts) < 3
    _ = json


def test_cli_plan_candidates_equal_the_sensors_file(tmp_path):
    """Centre + aim point candidates give the same maps as the equivalent sensors file."""
    from psdcal.cli import main

    (tmp_path / "calib.json").write_text(json.dumps(calib_dict(seed=2)))
    cand = [("n", 0.5, 0.5, 2.7, 3.0, 2.0, 0.8), ("e", 5.5, 3.5, 2.7, 3.0, 2.0, 0.8), ("w", 5.5, 0.5, 2.5, 2.5, 2.5, 1.0)]
    (tmp_path / "c.csv").write_text("name,X_m,Y_m,Z_m,aim_X_m,aim_Y_m,aim_Z_m\n"
                                    + "".join(",".join(map(str, c)) + "\n" for c in cand))
    entries = []
    for nm, *v in cand:
        r, t = look_at(np.array(v[:3]) * 1000, np.array(v[3:]) * 1000)
        entries.append({"name": nm, "calib": "calib.json", "rvec": r.tolist(), "tvec_mm": t.tolist()})
    (tmp_path / "s.json").write_text(json.dumps(entries))
    common = ["--room-m", "6", "4", "3", "--grid-mm", "300"]
    assert main(["plan", "--candidates", str(tmp_path / "c.csv"), "--calib", str(tmp_path / "calib.json"), *common,
                 "-o", str(tmp_path / "a.png"), "--csv", str(tmp_path / "a.csv")]) == 0
    assert main(["plan", "--sensors", str(tmp_path / "s.json"), *common, "-o", str(tmp_path / "b.png"),
                 "--csv", str(tmp_path / "b.csv")]) == 0
    assert (tmp_path / "a.csv").read_text() == (tmp_path / "b.csv").read_text()
    assert main(["plan", "--candidates", str(tmp_path / "c.csv"), *common, "-o", str(tmp_path / "x.png")]) == 2
