"""Cases that used to exit 0 with a wrong answer: now a right answer or one error line."""
import csv
import json

import numpy as np
import pytest

from psdcal.cli import main


def run(args, capsys):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    d = tmp_path_factory.mktemp("sw")
    assert main(["simulate", "--images", "6", "--seed", "3", "-o", str(d / "s")]) == 0
    assert main(["calibrate", str(d / "s/points.csv"), "-t", str(d / "s/template.csv"), "-o", str(d / "c.json"), "-q",
                 "--sensor-id", "SN-7"]) == 0
    return d


def read_csv(p):
    with open(p, newline="") as fh:
        return list(csv.DictReader(fh))


def test_sensor_id_is_kept_and_checked(made, capsys, tmp_path):
    assert json.loads((made / "c.json").read_text())["sensor_id"] == "SN-7"
    code, out, err = run(["report", made / "c.json", "-o", tmp_path / "r.html"], capsys)
    assert code == 0 and "SN-7" in out and "SN-7" in (tmp_path / "r.html").read_text()
    code, _, err = run(["aoa", made / "s/points.csv", "--calib", made / "c.json", "--expect-sensor", "SN-8",
                        "-o", tmp_path / "a.csv"], capsys)
    assert code == 2 and "SN-8" in err and "SN-7" in err and not (tmp_path / "a.csv").exists()
    code, out, _ = run(["aoa", made / "s/points.csv", "--calib", made / "c.json", "--expect-sensor", "SN-7",
                        "-o", tmp_path / "a.csv"], capsys)
    assert code == 0 and "SN-7" in out


def test_calibration_without_uncertainty_is_refused_not_sigma_zero(made, capsys, tmp_path):
    code, _, err = run(["aoa", made / "s/points.csv", "--calib", made / "s/truth.json", "-o", tmp_path / "a.csv"], capsys)
    assert code == 2 and "--allow-no-covariance" in err
    code, _, _ = run(["aoa", made / "s/points.csv", "--calib", made / "s/truth.json", "--allow-no-covariance",
                      "--sigma-d-mm", "0.001", "-o", tmp_path / "a.csv"], capsys)
    assert code == 0
    rows = read_csv(tmp_path / "a.csv")
    assert all(float(r["sigma_alpha_x_deg"]) > 0 for r in rows)  # the points' noise alone


def _locate_like(made, tmp_path, sigma_mm):
    """A locate-style file (t_s, emitter, x/y, alpha, sigmas) from the simulated points."""
    pts = read_csv(made / "s/points.csv")[:10]
    p = tmp_path / "loc.csv"
    with open(p, "w") as fh:
        fh.write("t_s,emitter,x_mm,y_mm,alpha_x_deg,alpha_y_deg,sigma_x_mm,sigma_y_mm,sigma_alpha_x_deg,"
                 "sigma_alpha_y_deg\n")
        for k, r in enumerate(pts):
            fh.write(f"{0.01 * (k + 1):.2f},e{k % 2},{r['x_mm']},{r['y_mm']},9,9,{sigma_mm},{sigma_mm},1,1\n")
    return p, pts


def test_aoa_on_a_locate_output_keeps_time_replaces_angles_and_uses_its_sigmas(made, capsys, tmp_path):
    small, _ = _locate_like(made, tmp_path, 0.0)
    run(["aoa", small, "--calib", made / "c.json", "-o", tmp_path / "a0.csv"], capsys)
    big, pts = _locate_like(made, tmp_path, 0.05)
    code, _, err = run(["aoa", big, "--calib", made / "c.json", "-o", tmp_path / "a1.csv"], capsys)
    assert code == 0, err
    header = (tmp_path / "a1.csv").read_text().splitlines()[0].split(",")
    assert len(header) == len(set(header))  # no duplicate alpha_* columns
    r0, r1 = read_csv(tmp_path / "a0.csv"), read_csv(tmp_path / "a1.csv")
    assert [float(r["t_s"]) for r in r1] == pytest.approx([0.01 * (k + 1) for k in range(10)])  # not 0
    assert all(abs(float(r["alpha_x_deg"]) - 9) > 1e-6 for r in r1)  # recomputed, not the stale input
    # the input's 50 um sigma enters: larger than the calibration alone, by about f-scaled 0.05 mm
    for a, b in zip(r0, r1):
        assert float(b["sigma_alpha_x_deg"]) > float(a["sigma_alpha_x_deg"])
    f = json.loads((made / "c.json").read_text())["intrinsics"]["f_mm"]
    extra = np.sqrt(float(r1[0]["sigma_alpha_x_deg"]) ** 2 - float(r0[0]["sigma_alpha_x_deg"]) ** 2)
    assert extra == pytest.approx(np.degrees(0.05 / f), rel=0.3)


def test_aoa_refuses_a_point_off_the_sensor(made, capsys, tmp_path):
    p = tmp_path / "off.csv"
    p.write_text("x_mm,y_mm\n0.5,0.5\n4.4,0\n7.0,0.1\n")
    code, _, err = run(["aoa", p, "--calib", made / "c.json", "-o", tmp_path / "a.csv"], capsys)
    assert code == 2 and "off.csv:4" in err and "off the" in err
    assert not (tmp_path / "a.csv").exists()


def test_aoa_streams_in_blocks_with_the_same_result(made, tmp_path):
    from psdcal.measure.locate import aoa_csv
    from psdcal.measure.sensor_model import SensorModel

    m = SensorModel.load(made / "c.json")
    n1 = aoa_csv(made / "s/points.csv", m, tmp_path / "one.csv")
    n2 = aoa_csv(made / "s/points.csv", m, tmp_path / "many.csv", chunk_rows=7)
    assert n1 == n2 > 7
    assert (tmp_path / "one.csv").read_text() == (tmp_path / "many.csv").read_text()


def test_compare_with_unknown_sigma_is_undecided(made, capsys, tmp_path):
    d = json.loads((made / "c.json").read_text())
    d.pop("covariance")
    d["std"] = {}
    (tmp_path / "a.json").write_text(json.dumps(d))
    d["intrinsics"]["f_mm"] *= 1.01
    (tmp_path / "b.json").write_text(json.dumps(d))
    code, out, _ = run(["compare", tmp_path / "a.json", tmp_path / "b.json"], capsys)
    assert code == 0 and "nan sigma" not in out and "undecided" in out.split("verdict:")[1]


def test_future_major_version_refused_and_minor_warned(made, tmp_path):
    from psdcal.errors import InputError
    from psdcal.io import load_calibration

    d = json.loads((made / "c.json").read_text())
    d["software"]["version"] = "99.0"
    (tmp_path / "f.json").write_text(json.dumps(d))
    with pytest.raises(InputError, match="newer major"):
        load_calibration(tmp_path / "f.json")
    from psdcal import __version__

    major = __version__.split(".")[0]
    d["software"]["version"] = f"{major}.999.0"
    (tmp_path / "g.json").write_text(json.dumps(d))
    with pytest.warns(UserWarning, match="newer"):
        load_calibration(tmp_path / "g.json")


def test_sensors_at_one_position_are_one_error(made, tmp_path):
    from psdcal.errors import InputError
    from psdcal.measure.positioning import load_sensors

    (tmp_path / "c.json").write_text((made / "c.json").read_text())
    s = {"sensors": [{"name": "a", "calib": "c.json", "rvec": [0, 0, 0], "tvec_mm": [0, 0, 0]},
                     {"name": "b", "calib": "c.json", "rvec": [0, 0.5, 0], "tvec_mm": [0, 0, 0]}]}
    (tmp_path / "s.json").write_text(json.dumps(s))
    with pytest.raises(InputError, match="same position"):
        load_sensors(tmp_path / "s.json")


def test_overlapping_schedule_is_refused(tmp_path):
    from psdcal.errors import InputError
    from psdcal.signal.stream import load_schedule

    p = tmp_path / "s.csv"
    p.write_text("emitter,t_start_s,t_end_s\na,0,0.02\nb,0.015,0.03\n")
    with pytest.raises(InputError, match="overlap"):
        load_schedule(p)


def test_bom_is_not_copied_into_outputs(made, capsys, tmp_path):
    p = tmp_path / "bom.csv"
    p.write_bytes(b"\xef\xbb\xbf" + (made / "s/points.csv").read_bytes())
    code, _, err = run(["aoa", p, "--calib", made / "c.json", "-o", tmp_path / "a.csv"], capsys)
    assert code == 0, err
    assert (tmp_path / "a.csv").read_bytes().startswith(b"image_id,")


def test_resource_guard_names_the_option(made, capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("PSDCAL_MAX_BYTES", str(50 << 20))
    code, _, err = run(["errormap", "--calib", made / "c.json", "--grid", "2000", "-o", tmp_path / "m.png"], capsys)
    assert code == 2 and "--grid" in err and "MiB" in err
    code, _, err = run(["errormap", "--calib", made / "c.json", "--grid", "11", "-o", tmp_path / "m.png"], capsys)
    assert code == 0


def test_simulate_accepts_its_advertised_image_count(tmp_path):
    from psdcal.study.simulate import LENSES, simulate_set

    s = simulate_set(LENSES["lens2"], n_images=3000, noise_mm=0.0, seed=0)
    assert s.points_mm.shape[0] == 3000


def test_big_template_is_refused_quickly(made, capsys, tmp_path):
    t = tmp_path / "t.csv"
    g = np.stack(np.meshgrid(np.arange(60), np.arange(60)), -1).reshape(-1, 2) * 2.0
    t.write_text("point_id,X_mm,Y_mm\n" + "\n".join(f"{k},{x},{y}" for k, (x, y) in enumerate(g)) + "\n")
    p = tmp_path / "p.csv"
    p.write_text("image_id,point_id,x_mm,y_mm\n0,0,0,0\n")
    code, _, err = run(["calibrate", p, "-t", t], capsys)
    assert code == 2 and "3600 template points" in err


def test_parallel_noiseless_views_are_refused_not_standard_error_zero(tmp_path, capsys):
    from psdcal.io import write_points, write_template
    from psdcal.study.simulate import LENSES, default_template, measured_points

    P = default_template()
    intr, dist = LENSES["lens2"]
    rng = np.random.default_rng(0)
    R = np.array([[0, 0, rng.uniform(-1, 1)] for _ in range(8)])
    T = np.array([[rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(400, 600)] for _ in range(8)])
    X = measured_points(P, intr, dist, R, T)
    write_template(tmp_path / "t.csv", list(range(len(P))), P)
    write_points(tmp_path / "p.csv", list(range(8)), list(range(len(P))), X)
    code, _, err = run(["calibrate", tmp_path / "p.csv", "-t", tmp_path / "t.csv", "-o", tmp_path / "c.json"], capsys)
    assert code == 2 and "do not determine" in err and "f_mm" in err
    assert not (tmp_path / "c.json").exists()


def test_tilted_noiseless_views_still_calibrate(tmp_path, capsys):
    from psdcal.io import write_points, write_template
    from psdcal.study.simulate import default_template, simulate_set

    s = simulate_set("lens2", 8, noise_mm=0.0, seed=1)
    P = default_template()
    write_template(tmp_path / "t.csv", list(range(len(P))), P)
    write_points(tmp_path / "p.csv", list(range(8)), list(range(len(P))), s.points_mm)
    code, _, err = run(["calibrate", tmp_path / "p.csv", "-t", tmp_path / "t.csv", "-o", tmp_path / "c.json", "-q"],
                       capsys)
    assert code == 0, err


def test_several_sensors_without_calibration_uncertainty_are_refused(made, capsys, tmp_path):
    """`locate --sensors` with a sensor whose calibration has no covariance (a truth.json): one error line
    naming the file and the switch that accepts it, nothing written."""
    (tmp_path / "t.json").write_text((made / "s/truth.json").read_text())
    (tmp_path / "c.json").write_text((made / "c.json").read_text())
    s = {"sensors": [{"name": "a", "calib": "c.json", "rvec": [0, 0, 0], "tvec_mm": [0, 0, 0]},
                     {"name": "b", "calib": "t.json", "rvec": [0, 0.5, 0], "tvec_mm": [500, 0, 0]}]}
    (tmp_path / "s.json").write_text(json.dumps(s))
    rec = tmp_path / "r.npy"
    np.save(rec, np.ones((1000, 4)))
    out = tmp_path / "xyz.csv"
    code, _, err = run(["locate", "--sensors", tmp_path / "s.json", rec, rec, "--rate-hz", "20000",
                        "--carrier-hz", "1000", "-o", out], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "t.json" in lines[0] and "--allow-no-covariance" in lines[0]
    assert not out.exists()


def test_undetermined_parameters_from_the_reduced_information():
    """Parallel views leave f undetermined whatever round-off made of the covariance; well-posed sets name none."""
    from psdcal.calibration.checks import undetermined_parameters
    from psdcal.calibration.core import calibrate
    from psdcal.study.simulate import LENSES, default_template, measured_points, simulate_set

    P = default_template()
    intr, dist = LENSES["lens2"]
    rng = np.random.default_rng(0)
    R = np.array([[0, 0, rng.uniform(-1, 1)] for _ in range(8)])
    T = np.array([[rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(400, 600)] for _ in range(8)])
    res = calibrate(P, measured_points(P, intr, dist, R, T), verdict=False)
    assert "f_mm" in undetermined_parameters(res)
    for lens, n, seed in (("lens1", 3, 0), ("lens1", 12, 1), ("lens2", 3, 2), ("lens2", 40, 3)):
        s = simulate_set(lens, n_images=n, noise_mm=0.002, seed=seed)
        assert undetermined_parameters(calibrate(s.template_mm, s.points_mm, verdict=False)) == []
