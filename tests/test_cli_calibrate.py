"""`psdcal calibrate` / `simulate` / `demo` from the command line, and bad input."""
import json
import subprocess
import sys

import pytest

from psdcal.cli import main
from psdcal.io import write_amplitudes, write_points, write_template
from psdcal.model.readout import photocurrents
from psdcal.study.simulate import simulate_set


def run(args, capsys):
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def simset(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    s = simulate_set("lens2", n_images=9, noise_mm=0.002, seed=5)
    write_template(d / "template.csv", range(14), s.template_mm)
    write_points(d / "points.csv", range(9), range(14), s.points_mm)
    return d, s


def test_simulate_then_calibrate_round_trip(tmp_path, capsys):
    code, out, err = run(["simulate", "--lens", "lens1", "--images", "9", "--noise-mm", "0.001", "--seed", "4", "-o", tmp_path], capsys)
    assert code == 0, err
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert truth["intrinsics"]["f_mm"] == 25.0 and len(truth["extrinsics"]) == 9
    code, out, err = run(["calibrate", tmp_path / "points.csv", "-t", tmp_path / "template.csv", "-o", tmp_path / "c.json", "--radial", "1", "--no-tangential"], capsys)
    assert code == 0, err
    assert "f_mm" in out and "std error" in out and "residual RMS" in out
    d = json.loads((tmp_path / "c.json").read_text())
    assert abs(d["intrinsics"]["f_mm"] - 25.0) < 5 * d["std"]["f_mm"]
    assert d["model"]["radial"] == 1 and d["model"]["tangential"] is False
    assert d["problem"]["files"]["points"]["sha256"]


def test_same_seed_same_files(tmp_path, capsys):
    for sub in ("a", "b"):
        assert run(["simulate", "--seed", "9", "--images", "4", "-o", tmp_path / sub], capsys)[0] == 0
    assert (tmp_path / "a" / "points.csv").read_bytes() == (tmp_path / "b" / "points.csv").read_bytes()


def test_demo_runs(tmp_path, capsys):
    code, out, err = run(["demo", "-o", tmp_path / "c.json"], capsys)
    assert code == 0, err
    assert "truth" in out and "error / std" in out
    d = json.loads((tmp_path / "c.json").read_text())
    assert abs(d["intrinsics"]["f_mm"] - 8.0) < 0.1


def test_help_lists_the_switches():
    out = subprocess.run([sys.executable, "-m", "psdcal.cli", "calibrate", "--help"], capture_output=True, text=True).stdout
    for opt in ("--cost", "--radial", "--tangential", "--psd-radial", "--skew", "--preliminary", "--normalize", "--fit-gains"):
        assert opt in out


def _points_text(s, images=range(9)):
    rows = ["image_id,point_id,x_mm,y_mm"]
    for i in images:
        for j in range(14):
            rows.append(f"{i},{j},{s.points_mm[i, j, 0]:.9f},{s.points_mm[i, j, 1]:.9f}")
    return rows


BAD = {
    # name: (edit of the points rows, expected fragments of the message)
    "nan": (lambda r: r[:5] + ["0,4,nan,0.1"] + r[6:], ["points.csv:6", "x_mm", "finite"]),
    "text": (lambda r: r[:3] + ["0,2,abc,0.1"] + r[4:], ["points.csv:4", "x_mm", "not a number"]),
    "header": (lambda r: ["image,point,x,y"] + r[1:], ["points.csv:1", "header"]),
    "empty": (lambda r: [], ["points.csv", "empty"]),
    "header-only": (lambda r: r[:1], ["points.csv", "no data"]),
    "duplicate": (lambda r: r + [r[3]], ["points.csv:128", "duplicate", "point_id"]),
    "unknown-point": (lambda r: r[:2] + ["0,99,0.1,0.1"] + r[3:], ["points.csv:3", "point_id", "not in the template"]),
    "off-sensor": (lambda r: r[:7] + ["0,6,5.2,0.1"] + r[8:], ["points.csv:8", "x_mm", "off the"]),
    "fields": (lambda r: r[:4] + ["0,3,0.1"] + r[5:], ["points.csv:5", "expected 4 fields"]),
    "one-image": (lambda r: r[:15], ["points.csv", "1 images", "at least 2"]),
    "collinear-view": (lambda r: r[:1] + r[1:6] + r[15:], ["points.csv", "image 0", "collinear"]),
    "too-few-points": (lambda r: r[:1] + r[1:4] + r[15:], ["points.csv", "image 0", "3 points"]),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_points_file(case, simset, tmp_path, capsys):
    d, s = simset
    edit, frags = BAD[case]
    p = tmp_path / "points.csv"
    p.write_text("\n".join(edit(_points_text(s))) + ("\n" if case != "empty" else ""))
    out_json = tmp_path / "calib.json"
    out_json.write_text("precious")
    code, out, err = run(["calibrate", p, "-t", d / "template.csv", "-o", out_json, "--force"], capsys)
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("psdcal: error:"), err
    for f in frags:
        assert f in lines[0], (f, lines[0])
    assert "Traceback" not in err
    assert out_json.read_text() == "precious"  # nothing overwritten


TEMPLATE_BAD = {
    "duplicate-id": ("point_id,X_mm,Y_mm\n0,0,0\n1,10,0\n1,0,10\n2,10,10\n", ["template.csv:4", "duplicate", "point_id"]),
    "nan": ("point_id,X_mm,Y_mm\n0,0,0\n1,nan,0\n2,0,10\n3,10,10\n", ["template.csv:3", "X_mm"]),
    "collinear": ("point_id,X_mm,Y_mm\n0,0,0\n1,10,0\n2,20,0\n3,30,0\n", ["template.csv", "collinear"]),
    "too-few": ("point_id,X_mm,Y_mm\n0,0,0\n1,10,0\n2,0,10\n", ["template.csv", "at least 4"]),
    "header": ("id,X,Y\n0,0,0\n", ["template.csv:1", "header"]),
    "missing": (None, ["template.csv", "not found"]),
}


@pytest.mark.parametrize("case", list(TEMPLATE_BAD))
def test_bad_template_file(case, simset, tmp_path, capsys):
    d, s = simset
    text, frags = TEMPLATE_BAD[case]
    t = tmp_path / "template.csv"
    if text is not None:
        t.write_text(text)
    code, out, err = run(["calibrate", d / "points.csv", "-t", t], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    for f in frags:
        assert f in err, (f, err)


def test_zero_signal_sum_in_amplitude_file(simset, tmp_path, capsys):
    d, s = simset
    amps = photocurrents(s.points_mm)
    amps[2, 5] = 0.0
    p = tmp_path / "amps.csv"
    write_amplitudes(p, range(9), range(14), amps)
    code, out, err = run(["calibrate", p, "-t", d / "template.csv"], capsys)
    assert code == 2
    line = 1 + 2 * 14 + 5 + 1
    assert f"amps.csv:{line}" in err and "zero" in err


def test_amplitude_file_calibrates_like_points(simset, tmp_path, capsys):
    d, s = simset
    p = tmp_path / "amps.csv"
    write_amplitudes(p, range(9), range(14), photocurrents(s.points_mm, total=2e-9))
    code, out, err = run(["calibrate", p, "-t", d / "template.csv", "-o", tmp_path / "a.json"], capsys)
    assert code == 0, err
    code, out, err = run(["calibrate", d / "points.csv", "-t", d / "template.csv", "-o", tmp_path / "b.json"], capsys)
    a = json.loads((tmp_path / "a.json").read_text())
    b = json.loads((tmp_path / "b.json").read_text())
    assert a["intrinsics"]["f_mm"] == pytest.approx(b["intrinsics"]["f_mm"], rel=1e-8)


def test_non_convergence_exits_2_and_keeps_output(simset, tmp_path, capsys):
    d, s = simset
    out_json = tmp_path / "calib.json"
    out_json.write_text("keep")
    code, out, err = run(["calibrate", d / "points.csv", "-t", d / "template.csv", "-o", out_json, "--force", "--max-iterations", "1"], capsys)
    assert code == 2 and "did not converge" in err and len(err.strip().splitlines()) == 1
    assert out_json.read_text() == "keep"


def test_fit_gains_needs_amplitudes(simset, capsys):
    d, s = simset
    code, out, err = run(["calibrate", d / "points.csv", "-t", d / "template.csv", "--fit-gains"], capsys)
    assert code == 2 and "amplitudes" in err


def test_bad_calibration_json(tmp_path):
    from psdcal.errors import InputError
    from psdcal.io import load_calibration

    p = tmp_path / "c.json"
    p.write_text("{not json")
    with pytest.raises(InputError, match="c.json:1.*invalid JSON"):
        load_calibration(p)
    p.write_text("{}")
    with pytest.raises(InputError, match="intrinsics"):
        load_calibration(p)


def test_a_converged_but_impossible_fit_is_flagged(tmp_path, simset, capsys):
    """Template rows of two LEDs swapped: the solver converges, but far from any noise level."""
    d, s = simset
    code, out, err = run(["calibrate", d / "points.csv", "-t", d / "template.csv", "-o", tmp_path / "ok.json"], capsys)
    assert code == 0 and "warning" not in out
    assert json.loads((tmp_path / "ok.json").read_text())["warnings"] == []
    T = s.template_mm.copy()
    T[[6, 7]] = T[[7, 6]]  # (many other swaps: the closed form already refuses the views)
    write_template(tmp_path / "wrong.csv", range(14), T)
    code, out, err = run(["calibrate", d / "points.csv", "-t", tmp_path / "wrong.csv", "-o", tmp_path / "bad.json"], capsys)
    assert code == 0, err  # a result is still written: the report shows what is wrong with it
    assert "warning" in out and "template" in out
    w = json.loads((tmp_path / "bad.json").read_text())["warnings"]
    assert len(w) == 1 and "% of the points' spread" in w[0]
