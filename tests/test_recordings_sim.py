"""The recording simulator (psdcal.study.recordings, `psdcal simulate-recording`) round-trips.

* every format it writes reads back through psdcal.signal.recording to the samples;
* `amplitudes` + `calibrate` on a simulated template recording give the truth
  within 3 standard errors (TDM with the schedule; FDM with a gain imbalance
  and --fit-gains);
* `locate` on a simulated moving emitter stays within 3 sigma of the trajectory.
"""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from psdcal.cli import main
from psdcal.signal.recording import open_recording
from psdcal.study.recordings import (look_at, project_world, room_layout, simulate_room,
                                     write_recording)


def _read_all(rec):
    return np.concatenate([b for _, b in rec.chunks(1000)], axis=1)


@pytest.mark.parametrize("suffix", [".npy", ".csv", ".h5", ".tdms"])
def test_formats_round_trip(tmp_path, suffix):
    rng = np.random.default_rng(1)
    x = rng.normal(size=(4, 2500))
    p = write_recording(tmp_path / f"r{suffix}", x, 12_500.0)
    rec = open_recording(p, 12_500.0 if suffix == ".npy" else None)
    assert rec.rate_hz == pytest.approx(12_500.0, rel=1e-6)
    np.testing.assert_allclose(_read_all(rec), x, rtol=1e-10, atol=1e-12)


def test_look_at_points_the_axis():
    c = np.array([100.0, -200.0, 2500.0])
    target = np.array([1500.0, 900.0, 300.0])
    rvec, tvec = look_at(c, target)
    n, z = project_world(target, rvec, tvec)
    np.testing.assert_allclose(n, 0.0, atol=1e-12)
    assert z == pytest.approx(np.linalg.norm(target - c))
    n0, z0 = project_world(c, rvec, tvec)
    assert z0 == pytest.approx(0.0, abs=1e-9)


def _run(args):
    assert main([str(a) for a in args]) == 0


def _merge(paths, out):
    rows = []
    for i, p in enumerate(paths):
        lines = p.read_text().splitlines()
        rows += lines[1:] if i else lines
    out.write_text("\n".join(rows) + "\n")


def _check_truth(calib_path, truth, k=3.0, names=("f_mm", "cx_mm", "cy_mm", "k1", "k2")):
    cal = json.loads(calib_path.read_text())
    for name in names:
        group = "intrinsics" if name in truth["intrinsics"] else "distortion"
        est, sd = cal[group][name], cal["std"][name]
        assert abs(est - truth[group][name]) < k * sd, (name, est, truth[group][name], sd)
    return cal


def test_template_tdm_amplitudes_calibrate_round_trip(tmp_path):
    out = tmp_path / "cal"
    _run(["simulate-recording", "template", "--views", 6, "--snr-db", 50, "--seed", 3, "-o", out])
    truth = json.loads((out / "truth.json").read_text())
    amps = []
    for v, name in enumerate(truth["recordings"]):
        a = out / f"amp_{v}.csv"
        _run(["amplitudes", out / name, "--rate-hz", truth["rate_hz"], "--carrier-hz", truth["carriers_hz"][0],
              "--window-s", truth["window_s"], "--schedule", out / "schedule.csv", "--image-id", v, "-o", a])
        amps.append(a)
    _merge(amps, out / "points.csv")
    _run(["calibrate", out / "points.csv", "-t", out / "template.csv", "-o", tmp_path / "calib.json", "-q"])
    _check_truth(tmp_path / "calib.json", truth)


def test_template_fdm_gains_hdf5_round_trip(tmp_path):
    out = tmp_path / "cal"
    _run(["simulate-recording", "template", "--views", 6, "--mux", "fdm", "--format", "hdf5", "--snr-db", 55,
          "--gain-imbalance", 0.03, "--on-s", 0.05, "--seed", 5, "-o", out])
    truth = json.loads((out / "truth.json").read_text())
    amps = []
    for v, name in enumerate(truth["recordings"]):
        a = out / f"amp_{v}.csv"
        args = ["amplitudes", out / name, "--window-s", truth["window_s"], "--image-id", v, "-o", a]
        for pid, f in enumerate(truth["carriers_hz"]):
            args += ["--carrier-hz", f, "--emitter", pid]
        _run(args)
        amps.append(a)
    _merge(amps, out / "points.csv")
    _run(["calibrate", out / "points.csv", "-t", out / "template.csv", "--fit-gains", "-o",
          tmp_path / "calib.json", "-q"])
    cal = _check_truth(tmp_path / "calib.json", truth)
    g = np.asarray(cal["gains"], dtype=float)
    g_true = np.asarray(truth["relative_gains"])
    np.testing.assert_allclose(g / g[0], g_true, atol=5e-3)


def test_locate_moving_emitter_within_3_sigma(tmp_path):
    from psdcal.measure.sensor_model import SensorModel
    from psdcal.study.simulate import LENSES

    intr, dist = LENSES["lens2"]
    m = SensorModel(intrinsics=intr, distortion=dist)
    sensors, emitters = room_layout(m, n_sensors=2, n_anchors=0, moving="line", speed_mm_s=300.0, seed=2)
    rr = simulate_room(sensors, emitters, duration_s=1.0, rate_hz=20_000.0, snr_db=55.0, seed=2)
    assert rr.visible.all()
    entries = []
    calib = tmp_path / "calib.json"
    d = m.to_dict()
    d.pop("covariance")
    calib.write_text(json.dumps(d))
    for s, x in zip(sensors, rr.x):
        write_recording(tmp_path / f"{s.name}.npy", x, rr.rate_hz)
        entries.append({"name": s.name, "calib": "calib.json", "rvec": s.rvec.tolist(), "tvec_mm": s.tvec_mm.tolist(),
                        "recording": f"{s.name}.npy"})
    (tmp_path / "sensors.json").write_text(json.dumps(entries))
    out = tmp_path / "xyz.csv"
    _run(["locate", "--allow-no-covariance", "--sensors", tmp_path / "sensors.json", "--rate-hz", rr.rate_hz, "--carrier-hz",
          emitters[0].carrier_hz, "--emitter", "tag", "-o", out])
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 100
    t = np.array([float(r["t_s"]) for r in rows])
    p = np.array([[float(r[c]) for c in ("X_mm", "Y_mm", "Z_mm")] for r in rows])
    s = np.array([[float(r[c]) for c in ("sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm")] for r in rows])
    # the lock-in averages the amplitudes over the window: the truth is the mean position in the window
    tw = t[:, None] + (np.arange(200) - 99.5)[None] / rr.rate_hz
    truth = emitters[0].position(tw).mean(axis=1)
    z = (p - truth) / s
    # the turning points of the back-and-forth line bend the mean: leave their windows out
    L = np.linalg.norm(np.subtract(emitters[0].p1_mm, emitters[0].p0_mm))
    turn = np.abs(np.mod(300.0 * t + L, 2 * L) - L) > L - 10.0
    turn |= np.abs(np.mod(300.0 * t, 2 * L) - L) > L - 10.0
    assert np.all(np.abs(z[~turn]) < 4.5)
    assert np.mean(np.abs(z[~turn]) < 3.0) >= 0.99
    assert 0.5 < np.std(z[~turn]) < 1.5


def test_room_tdm_locate_angles_and_pose(tmp_path):
    """A time-multiplexed room: locate --schedule gives each emitter's true angles within 3 sigma, and
    pose --schedule finds the sensor where the simulator put it."""
    from psdcal.model.projection import R_from_r

    room = tmp_path / "room"
    _run(["simulate-recording", "room", "--sensors", 1, "--anchors", 4, "--moving", "none", "--mux", "tdm",
          "--duration-s", 0.8, "--snr-db", 50, "--seed", 6, "-o", room])
    out = tmp_path / "ang.csv"
    _run(["locate", room / "s1.npy", "--calib", room / "calib_truth.json", "--allow-no-covariance", "--rate-hz", 20000, "--carrier-hz", 1000,
          "--schedule", room / "schedule.csv", "--window-s", 0.005, "-o", out])
    truth = json.loads((room / "truth.json").read_text())
    s = truth["sensors"][0]
    pos = {e["name"]: np.array(e["p0_mm"]) for e in truth["emitters"]}
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 40
    z = []
    for r in rows:
        n, _ = project_world(pos[r["emitter"]], s["rvec"], s["tvec_mm"])
        a = np.degrees(np.arctan(n))
        z += [(float(r["alpha_x_deg"]) - a[0]) / float(r["sigma_alpha_x_deg"]),
              (float(r["alpha_y_deg"]) - a[1]) / float(r["sigma_alpha_y_deg"])]
    assert np.mean(np.abs(z) < 3) >= 0.97 and np.max(np.abs(z)) < 5
    _run(["pose", room / "s1.npy", "--rate-hz", 20000, "--calib", room / "calib_truth.json", "--emitters",
          room / "emitters.csv", "--carrier-hz", 1000, "--schedule", room / "schedule.csv", "--window-s", 0.005,
          "-o", tmp_path / "entry.json"])
    e = json.loads((tmp_path / "entry.json").read_text())
    c_true = -R_from_r(np.array(s["rvec"])).T @ np.array(s["tvec_mm"])
    assert np.all(np.abs(np.array(e["pose"]["center_w_mm"]) - c_true) < 4 * np.array(e["pose"]["sigma_center_mm"]))


def test_room_from_given_sensors_and_emitters(tmp_path):
    """--sensors-in / --emitters-in reproduce a layout exactly (simulate your own installation)."""
    a, b = tmp_path / "a", tmp_path / "b"
    _run(["simulate-recording", "room", "--sensors", 3, "--anchors", 4, "--moving", "none", "--duration-s", 0.05,
          "--seed", 9, "-o", a])
    _run(["simulate-recording", "room", "--sensors-in", a / "sensors.json", "--emitters-in", a / "emitters.csv",
          "--moving", "none", "--duration-s", 0.05, "--seed", 9, "-o", b])
    sa = json.loads((a / "sensors.json").read_text())["sensors"]
    sb = json.loads((b / "sensors.json").read_text())["sensors"]
    assert [(s["name"], s["rvec"], s["tvec_mm"]) for s in sa] == [(s["name"], s["rvec"], s["tvec_mm"]) for s in sb]
    assert (a / "emitters.csv").read_text() == (b / "emitters.csv").read_text()
    # the emitters file keeps 9 digits in metres: the signals agree to that
    np.testing.assert_allclose(np.load(a / "s2.npy"), np.load(b / "s2.npy"), rtol=0, atol=1e-7)
