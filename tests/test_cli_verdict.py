"""Each case of the issue's "What was seen", through the CLI: the verdict and the advice printed."""
from __future__ import annotations

import json

import numpy as np
import pytest
from psdcal.cli import main
from psdcal.study.faults import random_case


_CAP = {}


@pytest.fixture(autouse=True)
def _capture(capsys):
    _CAP["c"] = capsys


def _run(args):
    code = main([str(a) for a in args])
    out = _CAP["c"].readouterr()
    return code, " ".join((out.out + out.err).split(" "))


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    root = tmp_path_factory.mktemp("seen")
    out = {}
    specs = {
        "minima": dict(seed=7, lens="lens1", n_images=10, noise_mm=1e-3, model={"radial": 2, "tangential": False}),
        "gains": dict(seed=3, fault="gains", lens="lens2", n_images=12),
        "mislabel": dict(seed=4, fault="mislabel", lens="lens1", n_images=10, noise_mm=1e-3),
        "metres": dict(seed=5, fault="metres", lens="lens1", n_images=10, noise_mm=1e-3),
        "swap": dict(seed=6, fault="swap", lens="lens2", n_images=10, noise_mm=2e-3),
        "valid": dict(seed=11, lens="lens2", n_images=8, noise_mm=2e-3, model={"radial": 2, "tangential": True}),
    }
    for name, kw in specs.items():
        seed = kw.pop("seed")
        c = random_case(seed, **kw)
        out[name] = (c, *c.write(root / name))
    return out


def test_seen_1_wrong_minimum_is_gone_and_good(cases, tmp_path):
    c, t, p = cases["minima"]
    for extra in ([], ["--radial", "1"]):
        code, text = _run(["calibrate", p, "-t", t, "--no-tangential", *extra, "-o", tmp_path / "c.json", "--force"])
        assert code == 0, text
        d = json.loads((tmp_path / "c.json").read_text())
        assert abs(d["intrinsics"]["f_mm"] - 25.0) < 6 * d["std"]["f_mm"]
        assert np.hypot(d["intrinsics"]["cx_mm"] - 0.5, d["intrinsics"]["cy_mm"] + 0.7) < 0.5
        assert d["verdict"] == "good" and "verdict: GOOD" in text


def test_seen_2_ignored_gains_say_fit_gains_and_reject_refuses(cases, tmp_path):
    c, t, p = cases["gains"]
    code, text = _run(["calibrate", p, "-t", t, "--no-tangential", "-o", tmp_path / "c.json"])
    assert code == 0
    assert "verdict: WRONG" in text
    assert "--fit-gains" in text
    d = json.loads((tmp_path / "c.json").read_text())
    assert d["verdict"] == "wrong"
    assert any(ch["name"] == "structure" and ch["passed"] is False for ch in d["checks"])
    code, text = _run(["calibrate", p, "-t", t, "--no-tangential", "--reject", "5", "-o", tmp_path / "r.json"])
    assert code == 2
    assert "--reject refused" in text and "--fit-gains" in text
    assert not (tmp_path / "r.json").exists()
    # the fix the advice names gives a good verdict
    code, text = _run(["calibrate", p, "-t", t, "--no-tangential", "--fit-gains"])
    assert code == 0 and "verdict: GOOD" in text


def test_seen_3_mislabelled_view_is_named(cases):
    c, t, p = cases["mislabel"]
    code, text = _run(["calibrate", p, "-t", t, "--no-tangential", "--radial", "1"])
    assert f"view {c.bad_image} " in text
    assert "check its labels" in text
    assert "negative focal length" not in text
    code, text = _run(["calibrate", p, "-t", t, "--no-tangential", "--radial", "1", "--reject", "5"])
    assert "negative focal length" not in text
    assert f"view {c.bad_image} " in text


def test_seen_4_metres_and_swapped_leds_point_to_units_and_template(cases):
    c, t, p = cases["metres"]
    code, text = _run(["calibrate", p, "-t", t, "--no-tangential", "--radial", "1"])
    assert "verdict: WRONG" in text
    assert "are they in metres?" in text
    c, t, p = cases["swap"]
    code, text = _run(["calibrate", p, "-t", t, "--no-tangential"])
    a, b = np.nonzero(np.any(c.template_mm != c.set.template_mm, axis=1))[0]
    assert "degenerate views" not in text
    assert "template" in text and ("WRONG" in text or code == 2)
    assert f"LEDs {a} and {b}" in text or f"LEDs {b} and {a}" in text


def test_seen_5_valid_irregular_views_are_not_refused(cases):
    c, t, p = cases["valid"]
    code, text = _run(["calibrate", p, "-t", t, "--skew"])
    assert code == 0, text
    assert "verdict: GOOD" in text


def test_strict_and_noise_options(cases, tmp_path):
    c, t, p = cases["gains"]
    code, _ = _run(["calibrate", p, "-t", t, "--no-tangential", "--strict", "-q", "-o", tmp_path / "s.json"])
    assert code == 2 and "--strict: the verdict is wrong" in _ and not (tmp_path / "s.json").exists()
    c, t, p = cases["valid"]
    code, text = _run(["calibrate", p, "-t", t, "--noise-um", "2", "-o", tmp_path / "n.json"])
    d = json.loads((tmp_path / "n.json").read_text())
    noise = next(ch for ch in d["checks"] if ch["name"] == "noise")
    assert noise["passed"] is True and noise["p_value"] > 1e-3
    # a stated noise far below the real one fails the noise check
    code, text = _run(["calibrate", p, "-t", t, "--noise-um", "0.2", "-o", tmp_path / "n2.json"])
    d = json.loads((tmp_path / "n2.json").read_text())
    assert next(ch for ch in d["checks"] if ch["name"] == "noise")["passed"] is False


def test_report_opens_with_the_verdict(cases, tmp_path):
    c, t, p = cases["gains"]
    _run(["calibrate", p, "-t", t, "--no-tangential", "-o", tmp_path / "c.json"])
    code, text = _run(["report", tmp_path / "c.json", "-o", tmp_path / "r.html"])
    assert code == 0
    assert text.splitlines()[0].startswith("verdict: WRONG")
    html = (tmp_path / "r.html").read_text()
    assert html.index('id="verdict"') < html.index('id="summary"')
    assert "--fit-gains" in html
    assert "psdcal calibrate --reject 5 removes them" not in html  # the report no longer sends a systematic misfit to --reject


def test_seen_4_row_listed_in_reverse_points_to_the_template(tmp_path):
    from psdcal.io import write_points, write_template
    from psdcal.study.simulate import simulate_set

    s = simulate_set("lens2", n_images=10, noise_mm=2e-3, seed=0)
    T = s.template_mm.copy()
    T[:5] = T[:5][::-1]  # the first row of the default template, listed in reverse
    write_template(tmp_path / "t.csv", list(range(14)), T)
    write_points(tmp_path / "p.csv", list(range(10)), list(range(14)), s.points_mm)
    code, text = _run(["calibrate", tmp_path / "p.csv", "-t", tmp_path / "t.csv"])
    assert "degenerate views" not in text
    assert "the row of LEDs 0, 1, 2, 3, 4 looks listed in reverse" in text


def test_seen_good_where_it_should_not_is_no_longer_good(tmp_path):
    """Issue 19: nearly fronto-parallel views (f known to tens of per cent) and six identical views are not good and
    are told to tilt the template (never "the data need l1"); a fixed f the data contradict is wrong, named in
    sigmas."""
    from psdcal.io import write_points, write_template
    from psdcal.model.params import Distortion, Intrinsics
    from psdcal.study.simulate import measured_points, simulate_set

    s = simulate_set("lens2", n_images=10, noise_mm=1e-4, seed=1)
    T = s.template_mm
    ids = list(range(len(T)))
    write_template(tmp_path / "t.csv", ids, T)
    intr, dist = Intrinsics(f_mm=8.0, cx_mm=0.1, cy_mm=-0.05), Distortion(k1=1e-3)
    rng = np.random.default_rng(0)
    rv = np.array([[rng.normal(0, 0.01), rng.normal(0, 0.01), a] for a in (0.1, 0.9, 2.0, -1.2, 0.5, -0.3)])
    tv = np.array([[x, y, 600.0] for x, y in ((0, 0), (40, 10), (-30, 20), (10, -50), (20, 20), (-20, -20))])
    fronto = measured_points(T, intr, dist, rv, tv)
    same = np.repeat(measured_points(T, intr, dist, np.array([[0.3, -0.2, 0.1]]), np.array([[0, 0, 500.0]])), 6, axis=0)
    for name, X in (("fronto", fronto), ("same", same)):
        write_points(tmp_path / f"{name}.csv", list(range(6)), ids, X + rng.normal(0, 1e-3, X.shape))
        code, text = _run(["calibrate", tmp_path / f"{name}.csv", "-t", tmp_path / "t.csv"])
        assert "verdict: GOOD" not in text, text
        assert "determination:" in text and "tilt the template" in text
        assert "the data need" not in text
    write_points(tmp_path / "p.csv", list(range(10)), ids, s.points_mm)
    code, text = _run(["calibrate", tmp_path / "p.csv", "-t", tmp_path / "t.csv", "--fix", "f_mm=8.05"])
    assert "verdict: WRONG" in text
    assert "held_values: f_mm fixed at 8.05: the data say 8.000" in text and "sigma)" in text
