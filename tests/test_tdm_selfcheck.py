"""Demodulation that checks itself (issue 14.4): each case that used to be silently wrong.

Time multiplexing with dark gaps shorter than the window, a segment count
that does not match --n-emitters, an overlapping schedule, a constant
recording, a carrier or a sampling rate off by 1 %.
"""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from _locate_sim import amplitudes, calib_dict, model, signals, spot_for_angles
from psdcal.cli import main
from psdcal.errors import InputError, ZeroSignalError
from psdcal.measure.locate import LocateConfig, amplitudes_to_csv, prescan
from psdcal.signal.inspect import carrier_near, check_carrier, choose_tdm_window, find_carriers, scan_tdm
from psdcal.signal.recording import open_recording
from psdcal.signal.stream import MultiCarrierLockin, ScheduleEntry, TdmSegmenter

RATE = 100_000.0
M = model()
SPOTS = spot_for_angles(M, np.radians([[5.0, 5.0], [-10.0, 3.0], [15.0, -12.0], [-3.0, 10.0]]))


def tdm_record(spots, on_s, gap_s, *, noise=1e-3, f=1000.0, seed=1, lead_s=0.0):
    """LEDs on one after the other, ``gap_s`` of darkness between them; returns (x (4, n), truth [(t0, t1)])."""
    rng = np.random.default_rng(seed)
    parts, truth, t = [], [], 0.0
    if lead_s:
        parts.append(np.zeros((4, int(round(lead_s * RATE)))))
        t += parts[-1].shape[1] / RATE
    for d in spots:
        n = int(round(on_s * RATE))
        parts.append(signals(RATE, n, [(amplitudes(M, d), f, 0.3)], t0_s=t, offset=(0, 0, 0, 0)))
        truth.append((t, t + n / RATE))
        t += n / RATE
        g = int(round(gap_s * RATE))
        parts.append(np.zeros((4, g)))
        t += g / RATE
    x = np.concatenate(parts, axis=1) + 0.05
    return x + noise * rng.standard_normal(x.shape), truth


def segment(x, window_s, f=1000.0, **kw):
    lk = MultiCarrierLockin(RATE, [f], window_s)
    seg = TdmSegmenter(lk.window_s, **kw)
    out = []
    for i in range(0, x.shape[1], 4096):
        out += seg.feed(lk.process(i / RATE, x[:, i: i + 4096]))
    return out + seg.finish(), seg


def ratio(a):
    return a / a.sum()


@pytest.mark.parametrize("gap_s", [0.002, 0.005, 0.008])
def test_dark_gaps_shorter_than_the_window_do_not_merge_leds(gap_s):
    """Issue 14: 2-8 ms gaps against a 10 ms window merged two LEDs and shifted every later label."""
    x, truth = tdm_record(SPOTS, 0.05, gap_s, noise=0.1, seed=7)
    segs, seg = segment(x, 0.01, min_snr=10.0, n_emitters=4)
    assert [s.emitter for s in segs] == ["1", "2", "3", "4"]
    for s, (t0, t1), d in zip(segs, truth, SPOTS):
        # every window used lies inside its LED's on-time: no light of a neighbour
        assert t0 - 1e-9 <= s.t_start_s and s.t_end_s <= t1 + 1e-9
        # and the ratios are this LED's (the LEDs differ by > 0.1 in some ratio)
        np.testing.assert_allclose(ratio(s.amplitude), ratio(amplitudes(M, d)), atol=0.02)


def test_segment_count_not_matching_n_emitters_is_refused():
    """Two LEDs at the same spot back to back cannot be told apart: 3 segments for 4 emitters."""
    spots = np.array([SPOTS[0], SPOTS[1], SPOTS[1], SPOTS[2]])
    x, _ = tdm_record(spots, 0.05, 0.0)
    segs, _ = segment(x, 0.01)  # without --n-emitters: 3 segments, no check possible
    assert len(segs) == 3
    with pytest.raises(InputError, match="found 3 segments, not a multiple of --n-emitters 4"):
        segment(x, 0.01, n_emitters=4)
    # a recording cut in the middle of a cycle: refused too (labels could not be trusted)
    x, _ = tdm_record(SPOTS[:3], 0.05, 0.01)
    with pytest.raises(InputError, match="not a multiple of --n-emitters 2"):
        segment(x, 0.01, n_emitters=2)


def test_n_emitters_must_be_positive():
    with pytest.raises(InputError, match="n-emitters"):
        TdmSegmenter(0.01, n_emitters=0)


def test_overlapping_schedule_is_refused():
    sched = [ScheduleEntry("a", 0.0, 0.06), ScheduleEntry("b", 0.05, 0.1)]
    with pytest.raises(InputError, match="'a'.*'b'.*overlap"):
        TdmSegmenter(0.01, schedule=sched)
    TdmSegmenter(0.01, schedule=[ScheduleEntry("a", 0.0, 0.05), ScheduleEntry("b", 0.05, 0.1)])  # touching: fine


def test_schedule_entry_without_a_whole_window_is_reported():
    x, truth = tdm_record(SPOTS[:2], 0.05, 0.01)
    sched = [ScheduleEntry("a", *truth[0]), ScheduleEntry("short", truth[1][0], truth[1][0] + 0.005)]
    segs, seg = segment(x, 0.01, schedule=sched)
    assert [s.emitter for s in segs] == ["a"]
    assert any("'short'" in w for w in seg.warnings)


def test_constant_recording_gives_no_detection(tmp_path):
    """Issue 14: a constant recording gave 'detections' of 1e-17 with sigma 0."""
    x = np.full((4, 20_000), 0.25)
    lk = MultiCarrierLockin(RATE, [1000.0], 0.01)
    wb = lk.process(0.0, x)
    assert np.all(wb.var_amplitude > 0)
    total = wb.amplitude[:, 0].sum(-1)
    assert np.all(total < 10 * np.sqrt(wb.var_amplitude[:, 0].sum(-1)))
    np.save(tmp_path / "c.npy", x.T)
    rec = open_recording(tmp_path / "c.npy", RATE)
    with pytest.raises(ZeroSignalError):
        amplitudes_to_csv(rec, tmp_path / "a.csv", LocateConfig((1000.0,), tdm=True))
    assert not (tmp_path / "a.csv").exists()


# --------------------------------------------------------------------------- carriers
def one_led(f_hz, *, noise=1e-3, seed=0, n=1 << 16):
    return signals(RATE, n, [(amplitudes(M, SPOTS[0]), f_hz, 0.3)], noise=noise, rng=np.random.default_rng(seed))


def test_carrier_finder_measures_frequency_and_snr():
    x = signals(RATE, 1 << 16, [(amplitudes(M, SPOTS[0]), 1003.7, 0.3), (amplitudes(M, SPOTS[1]) * 0.5, 1310.0, 1.0)],
                noise=1e-3, rng=np.random.default_rng(2))
    found = find_carriers(x, RATE)
    assert len(found) == 2
    f = sorted(c.freq_hz for c in found)
    res = found[0].resolution_hz
    assert abs(f[0] - 1003.7) < 0.1 * res and abs(f[1] - 1310.0) < 0.1 * res
    c = carrier_near(x, RATE, 1000.0)
    np.testing.assert_allclose(c.amplitude, amplitudes(M, SPOTS[0]), rtol=0.02)
    np.testing.assert_allclose(c.noise_sigma, 1e-3, rtol=0.15)
    # SNR: peak power over the noise power in one bin (closed form for a Hann window)
    w = np.hanning(x.shape[1])
    expected = 10 * np.log10((amplitudes(M, SPOTS[0]) * w.sum() / 2) ** 2 / (1e-6 * (w * w).sum()))
    np.testing.assert_allclose(c.snr_db, expected, atol=1.0)


@pytest.mark.parametrize("noise", [1e-3, 3e-3])
def test_carrier_off_by_one_percent_is_reported_and_the_prediction_holds(noise):
    """Issue 14: 1 % off left the angles right but sigma 10-18x larger, with no word."""
    x = one_led(1010.0, noise=noise)
    chk = check_carrier(1000.0, carrier_near(x, RATE, 1000.0), 0.01)
    assert not chk.ok and "measured at 10" in chk.message and abs(chk.offset_hz - 10.0) < 0.2
    # the predicted inflation bounds what the demodulation really does (largest channel)
    s_true = np.sqrt(MultiCarrierLockin(RATE, [1010.0], 0.01).process(0.0, x).var_amplitude[:, 0]).mean(0)
    s_off = np.sqrt(MultiCarrierLockin(RATE, [1000.0], 0.01).process(0.0, x).var_amplitude[:, 0]).mean(0)
    assert s_off.max() / s_true.max() > 5
    assert 0.7 < (s_off.max() / s_true.max()) / chk.sigma_inflation < 1.3


def test_carrier_check_false_alarm_rate_is_zero_on_40_exact_records():
    """Measured false-alarm rate of the carrier check: 0 of 40 (exact carrier, SNR 30-70 dB, random phase)."""
    rng = np.random.default_rng(11)
    alarms = 0
    for i in range(40):
        f = float(rng.uniform(500.0, 5000.0))
        x = signals(RATE, 1 << 15, [(amplitudes(M, SPOTS[i % 4]), f, float(rng.uniform(0, 6)))],
                    noise=float(10 ** rng.uniform(-4, -2)), rng=rng)
        alarms += not check_carrier(f, carrier_near(x, RATE, f), 0.01).ok
    assert alarms == 0


def test_wrong_sampling_rate_is_reported(tmp_path):
    """A rate off by 1 % shifts every carrier by 1 %: reported by locate's pre-scan."""
    x = one_led(1000.0)
    np.save(tmp_path / "r.npy", x.T)
    rec = open_recording(tmp_path / "r.npy", RATE * 1.01)
    _, warnings = prescan(rec, LocateConfig((1000.0,)))
    assert len(warnings) == 1 and "measured at 1010" in warnings[0]
    rec = open_recording(tmp_path / "r.npy", RATE)
    assert prescan(rec, LocateConfig((1000.0,)))[1] == []


def test_fdm_second_carrier_off_is_named():
    x = signals(RATE, 1 << 16, [(amplitudes(M, SPOTS[0]), 1000.0, 0.3), (amplitudes(M, SPOTS[1]), 1313.0, 1.0)],
                noise=1e-3, rng=np.random.default_rng(4))
    checks = [check_carrier(f, carrier_near(x, RATE, f), 0.02) for f in (1000.0, 1300.0)]
    assert checks[0].ok and not checks[1].ok
    assert abs(checks[1].offset_hz - 13.0) < 0.5


# --------------------------------------------------------------------------- window choice
def test_window_chosen_from_on_times_finds_every_led():
    """30 ms on-times: a 10 ms window keeps 1-2 windows per LED; the chosen window keeps them all."""
    x, truth = tdm_record(SPOTS, 0.03, 0.004, noise=1e-2, lead_s=0.013)
    scan = scan_tdm(x, RATE, 1000.0)
    assert len(scan.segments) == 4
    np.testing.assert_allclose(scan.on_s, 0.03, atol=2 * scan.window_s)
    w = choose_tdm_window(scan, 1000.0)
    assert scan.window_s <= w <= 0.03 / 6
    segs, seg = segment(x, w, n_emitters=4)
    assert [s.emitter for s in segs] == ["1", "2", "3", "4"] and seg.warnings == []
    for s, (t0, t1), d in zip(segs, truth, SPOTS):
        assert t0 - 1e-9 <= s.t_start_s and s.t_end_s <= t1 + 1e-9
        np.testing.assert_allclose(ratio(s.amplitude), ratio(amplitudes(M, d)), atol=5e-3)


# --------------------------------------------------------------------------- CLI
@pytest.fixture
def calib(tmp_path):
    p = tmp_path / "calib.json"
    p.write_text(json.dumps(calib_dict()))
    return p


def test_cli_refuses_wrong_count_and_writes_nothing(tmp_path, calib, capsys):
    spots = np.array([SPOTS[0], SPOTS[1], SPOTS[1], SPOTS[2]])
    x, _ = tdm_record(spots, 0.05, 0.0)
    np.save(tmp_path / "r.npy", x.T)
    out = tmp_path / "out.csv"
    rc = main(["locate", str(tmp_path / "r.npy"), "--calib", str(calib), "--rate-hz", str(RATE), "--carrier-hz",
               "1000", "--tdm", "--n-emitters", "4", "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and "found 3 segments" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_cli_tdm_auto_window_and_carrier_warning(tmp_path, calib, capsys):
    x, _ = tdm_record(SPOTS, 0.03, 0.004, noise=1e-3, f=1010.0)
    np.save(tmp_path / "r.npy", x.T)
    out = tmp_path / "out.csv"
    rc = main(["locate", str(tmp_path / "r.npy"), "--calib", str(calib), "--rate-hz", str(RATE), "--carrier-hz",
               "1010", "--tdm", "--n-emitters", "4", "-o", str(out)])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "4 TDM segments" in cap.out and "warning" not in cap.err
    assert len(out.read_text().splitlines()) == 5
    rc = main(["amplitudes", str(tmp_path / "r.npy"), "--rate-hz", str(RATE), "--carrier-hz", "1000", "--tdm",
               "-o", str(tmp_path / "a.csv")])
    cap = capsys.readouterr()
    assert "warning" in cap.err and re.search(r"measured at 10(09|10)\.\d", cap.err)


def test_cli_inspect(tmp_path, capsys):
    x, _ = tdm_record(SPOTS, 0.05, 0.005, f=1010.0)
    np.save(tmp_path / "r.npy", x.T)
    rc = main(["inspect", str(tmp_path / "r.npy"), "--rate-hz", str(RATE), "--carrier-hz", "1010"])
    out = capsys.readouterr().out
    assert rc == 0
    assert re.search(r"\n  10(09\.9|10\.0)\d* ", out) and "4 segments" in out and "check 1010 Hz: ok" in out
    rc = main(["inspect", str(tmp_path / "r.npy"), "--rate-hz", str(RATE), "--carrier-hz", "1000"])
    assert rc == 1 and "WARNING" in capsys.readouterr().out


@pytest.mark.parametrize("noise", [1e-3, 0.05, 0.3])
def test_level_and_ratio_splits_false_alarm_rate_is_zero_on_40_slots(noise):
    """The split rules never cut one LED in two: 40 slots of 100 ms (10 windows each), 0 false splits."""
    rng = np.random.default_rng(21)
    spots = SPOTS[rng.integers(0, 4, 40)]
    x, truth = tdm_record(spots, 0.1, 0.012, noise=noise, seed=22)
    segs, seg = segment(x, 0.01, n_emitters=40)
    assert len(segs) == 40 and seg.warnings == []
    for s, (t0, t1) in zip(segs, truth):
        assert t0 - 1e-9 <= s.t_start_s and s.t_end_s <= t1 + 1e-9 and s.n_windows >= 7
