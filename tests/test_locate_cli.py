"""`psdcal locate`, `psdcal aoa`, `psdcal errormap` end to end."""
from __future__ import annotations

import json

import numpy as np
import pytest

from _locate_sim import amplitudes, calib_dict, signals, spot_for_angles
from psdcal.cli import main
from psdcal.measure.locate import MULTI_COLUMNS
from psdcal.model.projection import R_from_r
from psdcal.measure.sensor_model import SensorModel

RATE = 125_000.0


def read(path):
    return np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8")


@pytest.fixture
def calib(tmp_path):
    p = tmp_path / "calib.json"
    p.write_text(json.dumps(calib_dict()))
    return p


def test_locate_two_emitters(tmp_path, calib, capsys):
    m = SensorModel.load(calib)
    alpha = np.array([[10.0, -3.0], [-7.0, 12.0]])
    d = spot_for_angles(m, np.radians(alpha))
    x = signals(RATE, 62_500, [(amplitudes(m, d[0]), 1000.0, 0.0), (amplitudes(m, d[1]), 1300.0, 1.0)], noise=2e-3)
    np.save(tmp_path / "rec.npy", x.T)
    out = tmp_path / "out.csv"
    rc = main(["locate", str(tmp_path / "rec.npy"), "--calib", str(calib), "--rate-hz", "125000",
               "--carrier-hz", "1000", "--carrier-hz", "1300", "--emitter", "tag1", "--emitter", "tag2",
               "--distance-mm", "5000", "--window-s", "0.02", "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    header = out.read_text().splitlines()[0].split(",")
    assert header == ["t_s", "emitter", "x_mm", "y_mm", "alpha_x_deg", "alpha_y_deg", "X_mm", "Y_mm",
                      "sigma_x_mm", "sigma_y_mm", "sigma_alpha_x_deg", "sigma_alpha_y_deg", "sigma_X_mm", "sigma_Y_mm"]
    r = read(out)
    assert len(r) == 2 * 25 and list(r["emitter"][:2]) == ["tag1", "tag2"]
    for k in range(2):
        rows = r[k::2]
        assert np.all(np.abs(rows["alpha_x_deg"] - alpha[k, 0]) < 3 * rows["sigma_alpha_x_deg"])
        assert np.all(np.abs(rows["alpha_y_deg"] - alpha[k, 1]) < 3 * rows["sigma_alpha_y_deg"])
        np.testing.assert_allclose(rows["X_mm"], 5000 * np.tan(np.radians(rows["alpha_x_deg"])), rtol=1e-8)
    assert "wrote 50 rows" in capsys.readouterr().out


def test_locate_tdm_from_csv(tmp_path, calib):
    m = SensorModel.load(calib)
    d = spot_for_angles(m, np.radians([[4.0, 4.0], [-9.0, 2.0]]))
    parts, t = [np.zeros((4, 2000))], 2000 / RATE
    for dd in d:
        parts.append(signals(RATE, 12_500, [(amplitudes(m, dd), 1000.0, 0.3)], t0_s=t, offset=(0, 0, 0, 0)))
        parts.append(np.zeros((4, 4000)))
        t += 16_500 / RATE
    x = np.concatenate(parts, 1) + 0.01 + 1e-3 * np.random.default_rng(1).standard_normal((4, sum(p.shape[1] for p in parts)))
    lines = ["t_s,vx1,vx2,vy1,vy2"] + [f"{i / RATE!r}," + ",".join(repr(float(v)) for v in row) for i, row in enumerate(x.T)]
    (tmp_path / "rec.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "tdm.csv"
    assert main(["locate", str(tmp_path / "rec.csv"), "--calib", str(calib), "--carrier-hz", "1000", "--tdm",
                 "--no-progress", "-o", str(out)]) == 0
    r = read(out)
    assert list(r["emitter"]) == [1, 2]
    np.testing.assert_allclose(r["alpha_x_deg"], [4.0, -9.0], atol=0.05)


def _two_sensors(tmp_path, p_true, offset_mm=0.0):
    """Two sensors' recordings of one emitter; the second sensor's stated centre moved by ``offset_mm`` in y."""
    sensors = []
    for i, (r, c) in enumerate([([0, 0.2, 0], [-900.0, 0, 0]), ([0, -0.2, 0.01], [900.0, 30.0, 0])]):
        cal = calib_dict(seed=i)
        (tmp_path / f"c{i}.json").write_text(json.dumps(cal))
        m = SensorModel.from_dict(cal)
        R = R_from_r(np.array(r, float))
        tvec = -R @ np.array(c)
        pc = R @ p_true + tvec
        dd = spot_for_angles(m, np.arctan(pc[:2] / pc[2]))
        x = signals(RATE, 25_000, [(amplitudes(m, dd), 1000.0, 0.4)], noise=1e-3, rng=np.random.default_rng(i))
        np.save(tmp_path / f"r{i}.npy", x.T)
        stated = tvec - R @ np.array([0.0, offset_mm * i, 0.0])
        sensors.append({"name": f"s{i}", "calib": f"c{i}.json", "rvec": r, "tvec_mm": stated.tolist(),
                        "recording": f"r{i}.npy"})
    (tmp_path / "sensors.json").write_text(json.dumps(sensors))
    return tmp_path / "sensors.json"


def test_locate_several_sensors(tmp_path, capsys):
    p_true = np.array([150.0, -80.0, 4500.0])
    sensors = _two_sensors(tmp_path, p_true)
    out = tmp_path / "xyz.csv"
    assert main(["locate", "--sensors", str(sensors), "--rate-hz", "125000",
                 "--carrier-hz", "1000", "-o", str(out)]) == 0
    assert out.read_text().splitlines()[0] == ",".join(MULTI_COLUMNS)
    r = read(out)
    assert len(r) == 20
    for k, col in enumerate(("X_mm", "Y_mm", "Z_mm")):
        assert np.all(np.abs(r[col] - p_true[k]) < 3 * r["sigma_" + col])
    assert np.all(r["dof"] == 1)
    assert "triangulation_chi2" not in capsys.readouterr().err


def test_locate_several_sensors_with_a_pose_off_warns_and_covers(tmp_path, capsys):
    """A sensor's stated centre 40 mm off: the rays miss each other; the file's rows are flagged, one warning
    gives the extra ray noise, and the inflated sigmas cover the (now real) error where the stated ones did not."""
    p_true = np.array([150.0, -80.0, 4500.0])
    sensors = _two_sensors(tmp_path, p_true, offset_mm=40.0)
    out = tmp_path / "xyz.csv"
    assert main(["locate", "--sensors", str(sensors), "--rate-hz", "125000",
                 "--carrier-hz", "1000", "-o", str(out)]) == 0
    captured = capsys.readouterr()
    warn = [ln for ln in captured.err.splitlines() if "triangulation_chi2" in ln]
    assert len(warn) == 1 and "extra ray noise" in warn[0] and "sigmas grown" in warn[0], captured.err
    assert "20 flagged by their chi2" in captured.out
    r = read(out)
    assert np.all(r["flagged"] == 1)
    err = np.sqrt(sum((r[c] - p_true[k]) ** 2 for k, c in enumerate(("X_mm", "Y_mm", "Z_mm"))))
    sig = np.sqrt(sum(r["sigma_" + c] ** 2 for c in ("X_mm", "Y_mm", "Z_mm")))
    assert np.median(err) > 5.0  # a real error of millimetres
    assert np.all(err < 4 * sig), (err, sig)


def test_aoa_command(tmp_path, calib):
    m = SensorModel.load(calib)
    d = spot_for_angles(m, np.radians([[1.0, 2.0], [-15.0, 10.0]]))
    (tmp_path / "pts.csv").write_text("image_id,point_id,x_mm,y_mm\n" + "".join(
        f"0,{i},{float(a)!r},{float(b)!r}\n" for i, (a, b) in enumerate(d)))
    out = tmp_path / "ang.csv"
    assert main(["aoa", str(tmp_path / "pts.csv"), "--calib", str(calib), "--distance-mm", "1000",
                 "-o", str(out), "--force"]) == 0
    r = read(out)
    assert r.dtype.names[:2] == ("image_id", "point_id")
    np.testing.assert_allclose(r["alpha_x_deg"], [1.0, -15.0], atol=1e-9)
    np.testing.assert_allclose(r["Y_mm"], 1000 * np.tan(np.radians([2.0, 10.0])), rtol=1e-9)
    assert np.all(r["sigma_alpha_y_deg"] > 0)
    # amplitudes in, same angles out
    a = amplitudes(m, d)
    (tmp_path / "amp.csv").write_text("point_id,vx1,vx2,vy1,vy2\n" + "".join(
        f"{i}," + ",".join(repr(float(v)) for v in row) + "\n" for i, row in enumerate(a)))
    assert main(["aoa", str(tmp_path / "amp.csv"), "--calib", str(calib), "-o", str(out), "--force"]) == 0
    np.testing.assert_allclose(read(out)["alpha_y_deg"], [2.0, 10.0], atol=1e-9)


def test_errormap_command(tmp_path, calib, capsys):
    out = tmp_path / "map.png"
    assert main(["errormap", "--calib", str(calib), "--distance-mm", "5000", "--grid", "11",
                 "--mode", "mean+2std", "--csv", str(tmp_path / "map.csv"), "-o", str(out)]) == 0
    assert out.read_bytes()[:4] == b"\x89PNG"
    assert len((tmp_path / "map.csv").read_text().splitlines()) == 1 + 121
    assert "position error" in capsys.readouterr().out


@pytest.mark.parametrize(
    "args, message",
    [
        (["locate", "{rec}", "--calib", "{calib}", "--carrier-hz", "1000", "-o", "{out}"], "--rate-hz"),
        (["locate", "{rec}", "--calib", "{calib}", "--rate-hz", "1000", "--carrier-hz", "1000", "-o", "{out}"],
         "Nyquist"),
        (["locate", "{rec}", "--calib", "{calib}", "--rate-hz", "125000", "--carrier-hz", "1000",
          "--window-s", "0.001", "-o", "{out}"], "periods"),
        (["locate", "{rec}", "--calib", "{tmp}/none.json", "--rate-hz", "125000", "--carrier-hz", "1000",
          "-o", "{out}"], "none.json: calibration file not found"),
        (["locate", "{tmp}/rec.bin", "--calib", "{calib}", "--rate-hz", "125000", "--carrier-hz", "1000",
          "-o", "{out}"], "unknown recording format"),
        (["aoa", "{tmp}/zero.csv", "--calib", "{calib}", "-o", "{out}"], "zero.csv:3"),
        (["locate", "{tmp}/quiet.npy", "--calib", "{calib}", "--rate-hz", "125000", "--carrier-hz", "1000",
          "-o", "{out}"], "no window has a carrier"),
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path, calib, capsys, args, message):
    np.save(tmp_path / "rec.npy", signals(RATE, 5000, [(np.ones(4), 1000.0, 0.0)]).T)
    (tmp_path / "rec.bin").write_bytes(b"x")
    np.save(tmp_path / "quiet.npy", 0.01 + 1e-3 * np.random.default_rng(0).standard_normal((5000, 4)))
    (tmp_path / "zero.csv").write_text("vx1,vx2,vy1,vy2\n1,1,1,1\n0,0,0,0\n")
    out = tmp_path / "out.csv"
    out.write_text("old\n")
    fmt = dict(rec=tmp_path / "rec.npy", calib=calib, out=out, tmp=tmp_path)
    rc = main([a.format(**fmt) for a in args] + ["--force"])
    err = capsys.readouterr().err
    assert rc == 2
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert out.read_text() == "old\n"


def test_help_texts(capsys):
    for cmd in ("locate", "aoa", "errormap"):
        assert main([cmd, "--help"]) == 0
    out = capsys.readouterr().out
    assert "--carrier-hz" in out and "Figure" in out and "POINTS.csv" in out


def test_amplitudes_command_writes_a_calibration_points_csv(tmp_path):
    amp = [np.array([0.2, 0.3, 0.25, 0.15]), np.array([0.1, 0.2, 0.3, 0.4])]
    parts, t = [np.zeros((4, 3000))], 3000 / RATE
    for a in amp:
        parts += [signals(RATE, 10_000, [(a, 1000.0, 0.0)], t0_s=t, offset=(0, 0, 0, 0)), np.zeros((4, 3000))]
        t += 13_000 / RATE
    x = np.concatenate(parts, 1) + 0.02 + 1e-3 * np.random.default_rng(2).standard_normal((4, 29_000))
    np.save(tmp_path / "view.npy", x.T)
    out = tmp_path / "pts.csv"
    assert main(["amplitudes", str(tmp_path / "view.npy"), "--rate-hz", "125000", "--carrier-hz", "1000",
                 "--tdm", "--image-id", "7", "-o", str(out)]) == 0
    r = read(out)
    assert r.dtype.names == ("image_id", "point_id", "vx1", "vx2", "vy1", "vy2")
    assert list(r["image_id"]) == [7, 7] and list(r["point_id"]) == [1, 2]
    np.testing.assert_allclose(np.stack([r[c] for c in ("vx1", "vx2", "vy1", "vy2")], 1), amp, atol=1e-3)
    assert main(["amplitudes", str(tmp_path / "view.npy"), "--rate-hz", "125000", "--carrier-hz", "1000",
                 "-o", str(out), "--force"]) == 0
    assert out.read_text().splitlines()[0] == "t_s,emitter,vx1,vx2,vy1,vy2,sigma_vx1,sigma_vx2,sigma_vy1,sigma_vy2"
