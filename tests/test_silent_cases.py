"""Issue 19, "smaller silent cases": each gives the right answer or one clear line (exit 2)."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
from _bench import load_benchmark

from psdcal.cli import main


def _one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("psdcal: error:"), err
    assert "Traceback" not in err
    return lines[0]


# --------------------------------------------------------------------------- TDM carrier check
def test_tdm_carrier_check_no_false_alarm_and_catches_a_real_offset():
    """Issue 19: the tutorial's TDM views warned 'measured at 985 Hz' (a keying side-band) in 5 of 8 views.

    40 records (on 10-50 ms, gaps 0-8 ms, SNR 30-70 dB): 0 false alarms (the spectral peak gave about
    64 %; benchmarks/study_tdm_carrier.py: 0/400 against 257/400), and each of 40 records whose carrier
    is 0.2-1 % off is caught, with the offset measured within 1 %."""
    from psdcal.signal.inspect import check_carrier, measure_carrier

    study = load_benchmark("study_tdm_carrier")  # records written there, independently of psdcal's simulator
    rng = np.random.default_rng(19)
    alarms, caught = 0, 0
    for _ in range(40):
        snr, on, gap, w = study.draw(rng)
        x = study.tdm_record(rng, on_s=on, gap_s=gap, snr_db=snr)
        alarms += not check_carrier(1000.0, measure_carrier(x, 50_000.0, 1000.0, tdm=True), w, tdm=True).ok
        f = 1000.0 * (1 + rng.choice([-1, 1]) * rng.uniform(0.002, 0.01))
        chk = check_carrier(1000.0, measure_carrier(study.tdm_record(rng, on_s=on, gap_s=gap, snr_db=snr, f_hz=f),
                                                    50_000.0, 1000.0, tdm=True), w, tdm=True)
        caught += (not chk.ok) and abs(chk.offset_hz - (f - 1000.0)) < 0.01 * abs(f - 1000.0)
    assert alarms == 0
    assert caught == 40


def test_tutorial_tdm_views_do_not_cry_wolf_and_a_wrong_rate_is_caught(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["simulate-recording", "template", "--views", "8", "--snr-db", "60", "--seed", "1", "-o", "cal"]) == 0
    capsys.readouterr()
    for v in range(8):
        rc = main(["amplitudes", f"cal/view_0{v}.npy", "--rate-hz", "50000", "--carrier-hz", "1000", "--window-s",
                   "0.005", "--schedule", "cal/schedule.csv", "--image-id", str(v), "-o", f"cal/amp_0{v}.csv"])
        assert rc == 0
        assert "warning" not in capsys.readouterr().err
    # the same view read at a rate 0.5 % off: the carrier is where the rate puts it, 1005 Hz
    rc = main(["amplitudes", "cal/view_00.npy", "--rate-hz", "50250", "--carrier-hz", "1000", "--window-s", "0.005",
               "--tdm", "-o", "off.csv"])
    err = capsys.readouterr().err
    assert re.search(r"measured at 100(4\.99|5 |5\.00)", err), err


# --------------------------------------------------------------------------- live channel order
def _live_setup(tmp_path, *, n=12_000):
    from psdcal.study.recordings import amplitudes, calib_dict, model, signals, spot_for_angles

    m = model()
    (tmp_path / "calib.json").write_text(json.dumps(calib_dict()))
    rng = np.random.default_rng(5)
    # alpha_y 0.27 deg (the case seen) and a larger one
    d1 = spot_for_angles(m, np.radians([2.0, 0.27]))
    d2 = spot_for_angles(m, np.radians([-5.0, 4.0]))
    return signals(20_000.0, n, [(amplitudes(m, d1), 1000.0, 0.3), (amplitudes(m, d2), 1300.0, 1.1)],
                   noise=1e-3, rng=rng)


def _run_live(monkeypatch, frames, out, extra=()):
    import io
    import sys

    class _Stdin:
        buffer = io.BytesIO(np.ascontiguousarray(frames).astype("<f8").tobytes())

    monkeypatch.setattr(sys, "stdin", _Stdin())
    return main(["locate", "-", "--calib", "calib.json", "--rate-hz", "20000", "--carrier-hz", "1000",
                 "--carrier-hz", "1300", "-o", str(out), *extra])


def _alpha(path):
    rows = np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8")
    return np.array([[r["alpha_x_deg"], r["alpha_y_deg"]] for r in rows if r["emitter"] == "1000Hz"])


def test_live_channels_in_another_order_are_caught_and_reordered(tmp_path, monkeypatch, capsys):
    """Issue 19: frames wired vx1,vy1,vx2,vy2 gave alpha_y 0 for 0.27 deg with no warning."""
    monkeypatch.chdir(tmp_path)
    x = _live_setup(tmp_path)
    swapped = x[[0, 2, 1, 3]].T  # frames vx1, vy1, vx2, vy2
    # the documented order: right angles, no warning (no false alarm)
    assert _run_live(monkeypatch, x.T, "ok.csv") == 0
    assert "warning" not in capsys.readouterr().err
    a_ok = _alpha("ok.csv")
    np.testing.assert_allclose(a_ok.mean(0), [2.0, 0.27], atol=0.01)
    # another order, not said: the sums show it, and the warning says what to do
    assert _run_live(monkeypatch, swapped, "bad.csv") == 0
    err = capsys.readouterr().err
    assert "channel sums differ" in err and "--raw-order" in err and "Traceback" not in err
    rows = np.genfromtxt("bad.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert np.all(np.abs(rows["y_mm"]) < 5e-3)  # (noise 5e-4 mm) what it would have been: the impact point's y read as 0
    # the order given: the same rows as the documented order, no warning
    assert _run_live(monkeypatch, swapped, "fixed.csv", ["--raw-order", "vx1,vy1,vx2,vy2"]) == 0
    assert "warning" not in capsys.readouterr().err
    np.testing.assert_allclose(_alpha("fixed.csv"), a_ok, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("extra, field", [
    (["--raw-order", "vx1,vy1,vx2"], "raw_order"),
    (["--raw-order", "vx1,vx1,vy1,vy2"], "raw_order"),
    (["--channels", "a,b,c,d"], "channels"),
])
def test_live_bad_channel_order_is_one_line(tmp_path, monkeypatch, capsys, extra, field):
    monkeypatch.chdir(tmp_path)
    x = _live_setup(tmp_path, n=2000)
    assert _run_live(monkeypatch, x.T, "out.csv", extra) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert f"field '{field}'" in line
    assert not (tmp_path / "out.csv").exists()


def test_file_channels_in_another_order_are_caught(tmp_path, monkeypatch, capsys):
    from psdcal.study.recordings import write_recording

    monkeypatch.chdir(tmp_path)
    x = _live_setup(tmp_path)
    write_recording(tmp_path / "ok.npy", x, 20_000.0)
    write_recording(tmp_path / "bad.npy", x[[0, 2, 1, 3]], 20_000.0)
    args = ["--calib", "calib.json", "--rate-hz", "20000", "--carrier-hz", "1000", "--carrier-hz", "1300"]
    assert main(["locate", "ok.npy", *args, "-o", "ok.csv"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert main(["locate", "bad.npy", *args, "-o", "bad.csv"]) == 0
    assert "channel sums differ" in capsys.readouterr().err


# --------------------------------------------------------------------------- wrong --rate-hz on TDM
@pytest.fixture(scope="module")
def tdm_views(tmp_path_factory):
    d = tmp_path_factory.mktemp("tdm")
    assert main(["simulate-recording", "template", "--views", "4", "--snr-db", "60", "--seed", "3",
                 "-o", str(d / "cal")]) == 0
    return d / "cal"


@pytest.mark.parametrize("rate_hz", [47_500.0, 52_500.0])
def test_wrong_rate_on_a_tdm_recording_is_named(tdm_views, tmp_path, capsys, rate_hz):
    """Issue 19: a rate 5 % off moved every slot of the schedule off its LED; the calibration then blamed the
    LED order.  The on-times found are compared with the schedule and the rate is named (with the rate the
    schedule fits); the right rate gives no warning."""
    capsys.readouterr()
    base = ["amplitudes", str(tdm_views / "view_00.npy"), "--carrier-hz", "1000", "--window-s", "0.005",
            "--schedule", str(tdm_views / "schedule.csv"), "--no-check-carriers"]
    assert main([*base, "--rate-hz", "50000", "-o", str(tmp_path / "ok.csv")]) == 0
    assert "warning" not in capsys.readouterr().err
    assert main([*base, "--rate-hz", str(rate_hz), "-o", str(tmp_path / "bad.csv")]) == 0
    err = capsys.readouterr().err
    m = re.search(r"--rate-hz \S+ is probably wrong, the schedule fits ([\d.]+) Hz", err)
    assert m, err
    assert abs(float(m.group(1)) - 50_000.0) < 0.005 * 50_000.0


def test_wrong_rate_without_schedule_names_the_carrier_in_the_error(tdm_views, tmp_path, capsys):
    """A rate 20 % off splits and merges the LEDs: the refusal (one line) carries the pre-scan's finding."""
    capsys.readouterr()
    rc = main(["amplitudes", str(tdm_views / "view_00.npy"), "--rate-hz", "60000", "--carrier-hz", "1000", "--tdm",
               "--n-emitters", "14", "-o", str(tmp_path / "a.csv")])
    line = _one_error_line(capsys.readouterr().err)
    assert rc == 2 and "n_emitters" in line and re.search(r"measured at 1(199|200)", line) and "--rate-hz" in line
    assert not (tmp_path / "a.csv").exists()


# --------------------------------------------------------------------------- gains: positions checked
def _bench_files(tmp_path, transform):
    from psdcal.calibration.gains import calibration_spots
    from psdcal.model.readout import photocurrents

    rng = np.random.default_rng(4)
    spots = calibration_spots()
    a = photocurrents(spots, 1.0) * np.array([1.0, 1.04, 0.96, 1.02])
    a = a + 1e-3 * rng.standard_normal(a.shape)
    (tmp_path / "amp.csv").write_text("point_id,vx1,vx2,vy1,vy2\n" + "".join(
        f"s{i}," + ",".join(repr(float(v)) for v in r) + "\n" for i, r in enumerate(a)))
    p = transform(spots)
    (tmp_path / "pos.csv").write_text("point_id,x_mm,y_mm\n" + "".join(
        f"s{i},{float(x)!r},{float(y)!r}\n" for i, (x, y) in enumerate(p)))


@pytest.mark.parametrize("transform, frag", [
    (lambda s: s / 1000.0, "x the positions: another unit"),
    (lambda s: s[:, ::-1], "x and y swapped"),
    (lambda s: s * [-1.0, 1.0], "an axis mirrored"),
    (lambda s: s * 3.0, "outside the 9 x 9 mm PSD"),
])
def test_gains_refuses_positions_that_do_not_match(tmp_path, capsys, transform, frag):
    """Issue 19: positions in metres or x/y swapped gave a gains file that 'aoa --gains' then refused."""
    _bench_files(tmp_path, transform)
    out = tmp_path / "gains.json"
    rc = main(["gains", str(tmp_path / "amp.csv"), "--positions", str(tmp_path / "pos.csv"), "-o", str(out)])
    line = _one_error_line(capsys.readouterr().err)
    assert rc == 2 and "pos.csv" in line and "field 'x_mm'" in line and frag in line, line
    assert not out.exists()


def test_gains_right_positions_still_fit(tmp_path, capsys):
    _bench_files(tmp_path, lambda s: s)
    out = tmp_path / "gains.json"
    assert main(["gains", str(tmp_path / "amp.csv"), "--positions", str(tmp_path / "pos.csv"), "-o", str(out)]) == 0
    g = json.loads(out.read_text())["gains"]
    np.testing.assert_allclose(g, [1.0, 1.04, 0.96, 1.02], atol=5e-3)


# --------------------------------------------------------------------------- calibrations that cannot be used
@pytest.fixture
def calib_json(tmp_path):
    from psdcal.study.recordings import calib_dict

    def write(name="calib.json", **changes):
        d = calib_dict()
        for key, value in changes.items():
            if isinstance(value, dict) and isinstance(d.get(key), dict):
                d[key] = {**d[key], **value}
            else:
                d[key] = value
        p = tmp_path / name
        p.write_text(json.dumps(d))
        return p

    return write


def test_errormap_without_covariance_is_refused(tmp_path, calib_json, capsys):
    """Issue 19: a calibration without covariance drew zero error everywhere, exit 0."""
    cal = calib_json(covariance=None, std={})
    out = tmp_path / "e.png"
    rc = main(["errormap", "--calib", str(cal), "--grid", "5", "-o", str(out)])
    line = _one_error_line(capsys.readouterr().err)
    assert rc == 2 and "calib.json" in line and "field 'covariance'" in line and "--allow-no-covariance" in line
    assert not out.exists()
    assert main(["errormap", "--calib", str(cal), "--grid", "5", "-o", str(out), "--allow-no-covariance"]) == 0
    assert out.exists()


def _npy_recording(tmp_path):
    from psdcal.study.recordings import amplitudes, model, signals, spot_for_angles, write_recording

    m = model()
    x = signals(20_000.0, 4000, [(amplitudes(m, spot_for_angles(m, np.radians([2.0, 1.0]))), 1000.0, 0.3)],
                noise=1e-3, rng=np.random.default_rng(1))
    write_recording(tmp_path / "rec.npy", x, 20_000.0)
    return tmp_path / "rec.npy"


@pytest.mark.parametrize("changes, field", [
    ({"distortion": {"k1": 1e300}}, "distortion.k1"),
    ({"distortion": {"p2": -1e30}}, "distortion.p2"),
])
def test_locate_refuses_an_implausible_calibration(tmp_path, calib_json, capsys, changes, field):
    """Issue 19: k1 = 1e300 wrote NaN sigmas, exit 0."""
    cal = calib_json(**changes)
    rec = _npy_recording(tmp_path)
    out = tmp_path / "xyz.csv"
    rc = main(["locate", str(rec), "--calib", str(cal), "--rate-hz", "20000", "--carrier-hz", "1000", "-o", str(out)])
    line = _one_error_line(capsys.readouterr().err)
    assert rc == 2 and "calib.json" in line and f"field '{field}'" in line and "implausible distortion" in line
    assert not out.exists()


def test_locate_never_writes_nan_sigmas():
    """The last guard: a model whose covariance propagation is not finite (the loaders refuse such a file;
    a SensorModel built in code is not loaded) raises instead of writing NaN sigmas beside finite angles."""
    import dataclasses

    from psdcal.errors import InputError
    from psdcal.measure.locate import _rows_single
    from psdcal.measure.sensor_model import SensorModel
    from psdcal.study.recordings import amplitudes, calib_dict, model, spot_for_angles

    m = SensorModel.from_dict(calib_dict(), source="calib.json")
    bad = dataclasses.replace(m, covariance=np.full_like(m.covariance, np.inf))
    a = amplitudes(model(), spot_for_angles(model(), np.radians([[2.0, 1.0], [-3.0, 4.0]])))
    t, names, var = np.array([0.0, 0.01]), np.array(["e", "e"], dtype=object), np.full((2, 4), 1e-8)
    cols, _ = _rows_single(t, names, a, var, m, None, 10.0)
    assert np.all(np.isfinite(cols["sigma_alpha_x_deg"]))
    with pytest.raises(InputError, match="non-finite sigmas") as exc:
        _rows_single(t, names, a, var, bad, None, 10.0)
    assert exc.value.path == "calib.json" and exc.value.field == "covariance"


def test_compare_refuses_sensors_of_different_sizes(tmp_path, calib_json, capsys):
    """Issue 19: two calibrations of 9 x 9 and 10 x 10 mm sensors were compared point for point."""
    a = calib_json("a.json")
    b = calib_json("b.json", sensor={"lx_mm": 10.0, "ly_mm": 10.0})
    out = tmp_path / "diff.png"
    rc = main(["compare", str(a), str(b), "-o", str(out), "--json", str(tmp_path / "c.json")])
    line = _one_error_line(capsys.readouterr().err)
    assert rc == 2 and "field 'sensor'" in line and "a.json: 9 x 9 mm" in line and "b.json: 10 x 10 mm" in line
    assert not out.exists() and not (tmp_path / "c.json").exists()
    assert main(["compare", str(a), str(a), "--json", str(tmp_path / "c.json")]) == 0  # the same size: compared


# --------------------------------------------------------------------------- tracebacks -> one line
def test_calibrate_directions_with_az_el_swapped_is_one_line(tmp_path, capsys):
    """Issue 19: az and el swapped ended in numpy's 'All-NaN slice' traceback."""
    from psdcal.calibration.directions import simulate_sweep, sweep_grid, write_directions
    from psdcal.model.params import Distortion, Intrinsics

    az, el = sweep_grid(20.165894394179496, 23.23741402459996, 6, 6)
    d = simulate_sweep(Intrinsics(8.0, 0.5, -0.7), Distortion(k1=1e-2, k2=3e-5, p1=2e-4, p2=-1e-4),
                       np.array([0.02, -0.03, 0.1]), az, el, noise_mm=0.002, rng=1)
    write_directions(tmp_path / "sweep.csv", el, az, d)  # the columns swapped
    out = tmp_path / "cal.json"
    rc = main(["calibrate-directions", str(tmp_path / "sweep.csv"), "-o", str(out)])
    line = _one_error_line(capsys.readouterr().err)
    assert rc == 2 and ("swapped" in line or "not a camera" in line or "did not converge" in line), line
    assert not out.exists()


@pytest.mark.parametrize("key, value, field", [
    ("model", [], "model"),
    ("model", {"radial": 7}, "model.radial"),
    ("model", {"tangential": "yes"}, "model.tangential"),
    ("residuals", {"rms_mm": "a"}, "residuals.rms_mm"),
    ("residuals", {"per_image_rms_mm": "abc"}, "residuals.per_image_rms_mm"),
    ("residuals", {"points": {"rows": [["a", "b", "c", "d"]]}}, "residuals.points.rows"),
    ("iterations", "x", "iterations"),
    ("stages", [], "stages"),
    ("verdict", [], "verdict"),
    ("checks", "x", "checks"),
    ("std", {"f_mm": 10 ** 400}, "std.f_mm"),
    ("intrinsics", {"f_mm": 10 ** 400, "cx_mm": 0.0, "cy_mm": 0.0}, "intrinsics.f_mm"),
    ("sensor", {"lx_mm": 10 ** 400}, "sensor.lx_mm"),
])
def test_odd_calibration_json_is_one_line_everywhere(tmp_path, calib_json, capsys, key, value, field):
    """Issue 19: 'report' on a JSON whose model is a list, load_calibration on odd JSON: raw AttributeError,
    OverflowError (an integer too large for a float).  One validator serves every reader."""
    from psdcal.errors import InputError
    from psdcal.io import load_calibration
    from psdcal.measure.sensor_model import SensorModel

    d = json.loads(calib_json().read_text())
    d[key] = value
    p = tmp_path / "odd.json"
    p.write_text(json.dumps(d))
    for reader in (load_calibration, SensorModel.load):
        with pytest.raises(InputError) as exc:
            reader(p)
        assert exc.value.field == field and exc.value.path == str(p)
    out = tmp_path / "r.html"
    rc = main(["report", str(p), "-o", str(out)])
    line = _one_error_line(capsys.readouterr().err)
    assert rc == 2 and f"field '{field}'" in line and not out.exists()


@pytest.mark.parametrize("kw, field", [({"radial": 4}, "radial"), ({"psd_radial": 2.5}, "psd_radial"),
                                       ({"radial": "2"}, "radial"), ({"tangential": "no"}, "tangential")])
def test_calibrate_api_bad_model_is_an_input_error(kw, field):
    """Issue 19: psdcal.calibrate(radial=4) raised a bare ValueError."""
    import psdcal
    from psdcal.errors import InputError
    from psdcal.study.simulate import simulate_set

    s = simulate_set("lens2", n_images=6, seed=1)
    with pytest.raises(InputError) as exc:
        psdcal.calibrate(s.template_mm, s.points_mm, **kw)
    assert exc.value.field == field


def test_amplitudes_on_a_corrupt_hdf5_is_one_line(tmp_path, capsys):
    """Issue 19: a corrupt object header raised h5py's RuntimeError (a traceback)."""
    h5py = pytest.importorskip("h5py")
    with h5py.File(tmp_path / "good.h5", "w") as f:
        f.create_dataset("signals", data=np.random.default_rng(0).standard_normal((20_000, 4)))
        f.attrs["rate_hz"] = 20_000.0
    raw = bytearray((tmp_path / "good.h5").read_bytes())
    hits = 0
    for off in range(0, 2048, 8):  # every place of the file's metadata, corrupted in turn
        bad = bytearray(raw)
        bad[off:off + 8] = b"\xff" * 8
        (tmp_path / "bad.h5").write_bytes(bad)
        out = tmp_path / "a.csv"
        rc = main(["amplitudes", str(tmp_path / "bad.h5"), "--carrier-hz", "1000", "--no-check-carriers",
                   "-o", str(out)])
        err = capsys.readouterr().err
        assert rc in (0, 2) and "Traceback" not in err
        if rc == 2:
            line = _one_error_line(err)
            assert "bad.h5" in line and not out.exists()
            hits += "not a readable HDF5 file" in line
        out.unlink(missing_ok=True)
    assert hits > 0


def test_channel_sums_check_false_alarms_and_detection():
    """False alarms of the sums check in 400 runs of 50 rows (SNR 30-80 dB per channel, calibrated gains
    known to 0.05-0.5 % with that covariance): the chi2 is at a 1e-3 false-alarm rate and needs 1 sigma of
    effect besides, so at most 2 (0.4 expected at 1e-3; benchmarks/study_channel_sums.py: 0 of 3000).
    Detection of frames wired vx1,vy1,vx2,vy2: every run whose spots' y error reaches 3 row sigmas is caught."""
    study = load_benchmark("study_channel_sums")
    rng = np.random.default_rng(7)
    alarms, missed, relevant = 0, 0, 0
    for _ in range(400):
        alarm, rel, caught = study.one_run(rng, "r")
        alarms += alarm
        relevant += rel
        missed += rel and not caught
    assert alarms <= 2
    assert relevant > 300 and missed == 0


def test_every_reader_of_a_sensor_calibration_refuses_an_implausible_distortion():
    """The sibling readers: a sensors file's entries are built by SensorModel.from_dict, not load()."""
    from psdcal.errors import InputError
    from psdcal.measure.sensor_model import SensorModel
    from psdcal.study.recordings import calib_dict

    d = calib_dict()
    SensorModel.from_dict(d)  # a plausible one is read
    d["distortion"]["k2"] = -1e200
    with pytest.raises(InputError, match="implausible distortion") as exc:
        SensorModel.from_dict(d, source="sensors.json")
    assert exc.value.field == "distortion.k2" and exc.value.path == "sensors.json"
