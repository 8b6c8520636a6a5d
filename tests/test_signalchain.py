"""Tests of the simulated signal chain (psdcal.signal.chain) and of the demodulation it uses."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings as hsettings, strategies as st

from psdcal.signal import demod
from psdcal.signal import chain as sc
from psdcal.errors import InputError, PsdcalError, ZeroSignalError
from psdcal.model.readout import gain_homography, gain_map, impact_point

METHODS = ("lockin", "bandpass")
HALF = 4.5


def _grid():
    """Spots over the whole active area, including its corners (outside the split's diamond)."""
    v = np.linspace(-HALF, HALF, 7)
    return np.stack(np.meshgrid(v, v, indexing="ij"), axis=-1).reshape(-1, 2)


# ---------------------------------------------------------------------------
# Noiseless readout
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("method", METHODS)
def test_noiseless_readout_returns_the_spot(method):
    # Exact for both methods: every channel of a spot carries the same waveform
    # scaled by its amplitude, and both estimators are homogeneous of degree 1,
    # so any estimator bias is one common factor that cancels in Eq 1-2.
    xy = _grid()
    got = sc.measure_points(xy, sc.ChainSettings(method=method))
    np.testing.assert_allclose(got, xy, rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", METHODS)
@hsettings(max_examples=15, deadline=None)
@given(
    x=st.floats(-HALF, HALF),
    y=st.floats(-HALF, HALF),
    phase=st.floats(0, 2 * np.pi),
    duration_ms=st.floats(12.3, 30.0),
)
def test_noiseless_readout_any_phase_and_length(method, x, y, phase, duration_ms):
    s = sc.ChainSettings(method=method, phase_rad=phase, duration_s=duration_ms * 1e-3)
    got = sc.measure_points(np.array([x, y]), s)
    np.testing.assert_allclose(got, [x, y], rtol=0, atol=1e-9)


def test_signed_amplitudes_outside_the_diamond():
    # At the corners (4.5, 4.5) and (-4.5, 4.5) the linear split gives vx1, vy1 a negative current.
    xy = np.array([[HALF, HALF], [-HALF, HALF], [1.0, 0.5]])
    clean = sc.signal_amplitudes(xy)
    assert clean[0, 0] < 0 and clean[1, 2] < 0 and np.all(clean[2] > 0)
    np.testing.assert_allclose(sc.measure_amplitudes(xy), clean, rtol=1e-12, atol=0)
    # band-pass: the residual edge transient is a common factor (about 1e-3 at 20 ms)
    bp = sc.measure_amplitudes(xy, sc.ChainSettings(method="bandpass"))
    assert np.all(np.sign(bp) == np.sign(clean))
    ratio = bp / clean
    np.testing.assert_allclose(ratio, ratio[0, 0], rtol=1e-10)
    assert abs(ratio[0, 0] - 1) < 3e-3


def test_spots_outside_the_active_area_are_nan():
    xy = np.array([[0.0, 0.0], [4.6, 0.0], [0.0, -5.0], [np.nan, 1.0]])
    got = sc.measure_points(xy, sc.ChainSettings(snr_db=40.0), rng=1)
    assert np.all(np.isfinite(got[0])) and np.all(np.isnan(got[1:]))


def test_leading_shape_and_inputs_untouched():
    xy = np.zeros((3, 5, 2))
    xy[..., 0] = np.linspace(-2, 2, 5)
    xy_copy = xy.copy()
    gains = np.array([1.0, 1.1, 0.9, 1.05])
    g_copy = gains.copy()
    pts = sc.measure_points(xy, sc.ChainSettings(snr_db=50.0), gains, rng=3)
    sig = sc.simulate_signals(xy[0], sc.ChainSettings(), gains)
    assert pts.shape == (3, 5, 2) and sig.shape == (5, 4, 1000)
    assert np.array_equal(xy, xy_copy) and np.array_equal(gains, g_copy)


# ---------------------------------------------------------------------------
# Demodulation
# ---------------------------------------------------------------------------


@hsettings(max_examples=40, deadline=None)
@given(
    amp=st.floats(1e-6, 1e3),
    phase=st.floats(0, 2 * np.pi),
    offset=st.floats(-1e3, 1e3),
    n=st.integers(60, 3000),
    rate_hz=st.sampled_from([8_000.0, 44_100.0, 50_000.0, 96_000.0]),
)
def test_lockin_amplitude_exact_for_a_pure_carrier(amp, phase, offset, n, rate_hz):
    # any phase, any offset, any (non-integer) number of periods
    t = np.arange(n) / rate_hz
    x = amp * np.sin(2 * np.pi * 1000.0 * t + phase) + offset
    got = demod.lockin_amplitude(x, rate_hz, 1000.0)
    assert got == pytest.approx(amp, rel=1e-9, abs=1e-9 * (abs(offset) + amp))


@pytest.mark.parametrize("duration_s, tol", [(0.020, 2.5e-3), (0.040, 1e-3)])
@pytest.mark.parametrize("phase", [0.0, 0.7, 1.9, 4.0])
def test_bandpass_amplitude_bias_is_small(duration_s, tol, phase):
    # was ~3 % at 20 ms (no settle window dropped); the gain |H(f_c)|^2 is divided out
    rate = 50_000.0
    t = np.arange(int(round(rate * duration_s))) / rate
    x = 2.5 * np.sin(2 * np.pi * 1000.0 * t + phase) - 0.3
    assert demod.bandpass_amplitude(x, rate, 1000.0) == pytest.approx(2.5, rel=tol)
    assert demod.bandpass_gain(rate, 1000.0) == pytest.approx(1.0, abs=1e-5)


def test_bandpass_window_is_whole_periods():
    win = demod.bandpass_window(1000, 50_000.0, 1000.0, 5.0)
    assert (win.start, win.stop) == (250, 750)
    win = demod.bandpass_window(1234, 44_100.0, 1000.0, 5.0)
    periods = (win.stop - win.start) * 1000.0 / 44_100.0
    assert abs(periods - round(periods)) < 0.02 and win.start >= 220
    assert demod.bandpass_window(400, 50_000.0, 1000.0, 5.0) == slice(0, 400)


# ---------------------------------------------------------------------------
# Noise and SNR
# ---------------------------------------------------------------------------


def test_snr_definition():
    # every channel of a spot gets sigma = A_mean / sqrt(2) / 10^(SNR/20)
    s = sc.ChainSettings(snr_db=30.0, duration_s=0.1)
    xy = np.array([[HALF, -2.0]] * 40)  # unequal channel amplitudes, one negative
    gains = np.array([1.3e4, 5e4, 2e4, 8e4])
    clean = sc.simulate_signals(xy, replace(s, snr_db=None), gains)
    noisy = sc.simulate_signals(xy, s, gains, rng=11)
    resid = (noisy - clean).transpose(1, 0, 2).reshape(4, -1)
    amps = sc.signal_amplitudes(xy[0], s, gains)
    sigma = np.mean(np.abs(amps)) / np.sqrt(2) / 10 ** (30 / 20)
    np.testing.assert_allclose(resid.std(axis=1), sigma, rtol=0.01)
    assert sc.noise_sigma(amps, 30.0) == pytest.approx(sigma, rel=1e-14)
    # SNR = mean channel signal power / noise power
    assert 10 * np.log10(np.mean(np.abs(amps)) ** 2 / 2 / sigma**2) == pytest.approx(30.0, abs=1e-12)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("xy", [(0.0, 0.0), (HALF, HALF)])
def test_point_noise_falls_tenfold_per_20_db(method, xy):
    res = sc.point_noise_vs_snr([30, 40, 50, 60], sc.ChainSettings(method=method), n=1500, rng=2024, xy_mm=xy)
    std = res.measured_std_mm
    for lo, hi in ((0, 2), (1, 3)):
        np.testing.assert_allclose(std[lo] / std[hi], 10.0, rtol=0.15)
    # and matches the first-order prediction (SE of a std at n=1500: 1.8 %)
    np.testing.assert_allclose(res.ratio, 1.0, rtol=0.08)


def test_predicted_noise_closed_form():
    # lock-in, equal gains, inside the diamond: std(x) = sqrt(Lx^2 + 4x^2) / (4 sqrt(n) 10^(SNR/20))
    s = sc.ChainSettings(snr_db=40.0)
    xy = np.array([[0.0, 0.0], [1.5, -2.0], [-3.0, 1.0]])
    got = sc.predicted_point_std(xy, s)
    n = s.n_samples
    want = np.sqrt(81.0 + 4 * xy**2) / (4 * np.sqrt(n) * 100.0)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert sc.amplitude_noise_factor(s) == pytest.approx(2.0 / n, rel=1e-12)
    # band-pass keeps m = 500 of 1000 samples: about 2 / m
    assert sc.amplitude_noise_factor(replace(s, method="bandpass")) * 500 / 2 == pytest.approx(1.0, abs=0.1)
    long = replace(s, method="bandpass", duration_s=0.5)  # beyond the exact computation
    assert sc.amplitude_noise_factor(long) == pytest.approx(2.0 / 24_500, rel=1e-12)


def test_noise_with_gains_and_distortion_matches_prediction():
    s = sc.ChainSettings(snr_db=40.0)
    gains = sc.channel_gains(s, np.random.default_rng(5))
    res = sc.point_noise_vs_snr([40.0], s, n=1500, rng=9, xy_mm=(2.0, -3.0), gains=gains, l1=-1.3058e-3)
    np.testing.assert_allclose(res.ratio, 1.0, rtol=0.08)


def test_noise_is_reproducible_and_independent_of_blocks():
    s = sc.ChainSettings(snr_db=35.0)
    xy = np.random.default_rng(0).uniform(-4, 4, (50, 2))
    a = sc.measure_points(xy, s, rng=42)
    b = sc.measure_points(xy, s, rng=np.random.default_rng(42), block_points=7)
    c = sc.measure_points(xy, s, rng=43)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


# ---------------------------------------------------------------------------
# Gains (Eq 43) and imbalance
# ---------------------------------------------------------------------------


def test_eq43_gain_at_nominal_values():
    paper = sc.ChainSettings.paper()
    np.testing.assert_allclose(sc.channel_gains(paper), 53_572.0, atol=0.5)  # Section 4.4
    assert sc.gain_variation_first_order(paper) == pytest.approx(4017.9, abs=0.05)
    wrc = 2 * np.pi * 13_793.0 * 1e5 * 1e-10
    np.testing.assert_allclose(sc.channel_gains(), 1e5 / np.sqrt(1 + wrc**2), rtol=1e-14)
    assert sc.transimpedance_gain(1e5, 0.0, 1e3, "paper") == 1e5


@pytest.mark.parametrize("gain_model", sc.GAIN_MODELS)
def test_imbalance_draws_within_tolerance(gain_model):
    s = sc.ChainSettings(gain_model=gain_model)
    rng = np.random.default_rng(7)
    r, c = np.array([sc.channel_components(s, rng) for _ in range(500)]).transpose(1, 0, 2)
    assert np.all(np.abs(r / s.r_ohm - 1) <= s.r_tol) and np.all(np.abs(c / s.c_farad - 1) <= s.c_tol)
    # uniform over the whole interval, not a narrower one
    assert np.abs(r / s.r_ohm - 1).max() > 0.98 * s.r_tol and np.abs(c / s.c_farad - 1).max() > 0.98 * s.c_tol
    g = np.array([sc.channel_gains(s, rng) for _ in range(500)])
    lo = sc.transimpedance_gain(s.r_ohm * (1 - s.r_tol), s.c_farad * (1 + s.c_tol), s.f_gain_hz, gain_model)
    hi = sc.transimpedance_gain(s.r_ohm * (1 + s.r_tol), s.c_farad * (1 - s.c_tol), s.f_gain_hz, gain_model)
    assert np.all((g >= lo) & (g <= hi)) and g.std() > 0
    # no tolerance: nominal even with a generator
    flat = replace(s, r_tol=0.0, c_tol=0.0)
    np.testing.assert_array_equal(sc.channel_gains(flat, rng), sc.channel_gains(flat))


@pytest.mark.parametrize("method", METHODS)
def test_equal_gains_leave_points_unchanged(method):
    xy = _grid()
    s = sc.ChainSettings(method=method)
    np.testing.assert_allclose(sc.measure_points(xy, s, gains=[3.7e4] * 4), xy, rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", METHODS)
def test_unequal_gains_reproduce_gain_map(method):
    xy = _grid()
    s = sc.ChainSettings(method=method)
    gains = sc.channel_gains(s, np.random.default_rng(123))
    got = sc.measure_points(xy, s, gains=gains)
    np.testing.assert_allclose(got, gain_map(xy, gains), rtol=0, atol=1e-12)
    h = gain_homography(gains) @ np.c_[xy, np.ones(len(xy))].T
    np.testing.assert_allclose(got, (h[:2] / h[2]).T, rtol=0, atol=1e-12)


@hsettings(max_examples=25, deadline=None)
@given(
    gains=st.lists(st.floats(0.5, 2.0), min_size=4, max_size=4),
    x=st.floats(-HALF, HALF),
    y=st.floats(-HALF, HALF),
)
def test_gains_property_projective_readout(gains, x, y):
    got = sc.measure_points(np.array([x, y]), sc.ChainSettings(), gains=gains)
    np.testing.assert_allclose(got, gain_map([x, y], gains), rtol=0, atol=1e-11)
    # a common factor of the gains cancels
    got2 = sc.measure_points(np.array([x, y]), sc.ChainSettings(), gains=7.5 * np.asarray(gains))
    np.testing.assert_allclose(got2, got, rtol=0, atol=1e-12)


@pytest.mark.parametrize("snr_db", [None, 40.0])
def test_zero_signal_raises(snr_db):
    s = sc.ChainSettings(snr_db=snr_db)
    with pytest.raises(ZeroSignalError):
        sc.measure_points(np.zeros(2), s, gains=np.zeros(4), rng=1)
    with pytest.raises(ZeroSignalError):
        impact_point(sc.estimate_amplitudes(np.zeros((4, 1000)), s))


# ---------------------------------------------------------------------------
# PSD distortion
# ---------------------------------------------------------------------------


def test_psd_distortion_readout():
    l1 = -1.3058e-3
    xy = _grid()
    d = sc.measure_points(xy, sc.ChainSettings(), l1=l1)
    r2 = np.sum(d * d, axis=-1, keepdims=True)
    np.testing.assert_allclose(d * (1 + l1 * r2), xy, rtol=0, atol=1e-9)
    assert np.all(np.linalg.norm(d, axis=-1) >= np.linalg.norm(xy, axis=-1))  # pin-cushion: pushed outwards


# ---------------------------------------------------------------------------
# Settings, errors and the CLI
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "changes",
    [
        {"method": "fft"},
        {"gain_model": "ideal"},
        {"rate_hz": 1500.0},
        {"duration_s": 1e-4},
        {"c_tol": 1.5},
        {"snr_db": float("inf")},
        {"method": "bandpass", "rate_hz": 2500.0},
    ],
)
def test_bad_settings_raise_psdcal_errors(changes):
    with pytest.raises(PsdcalError):
        sc.ChainSettings(**changes)


def test_settings_are_frozen_and_paper_preset():
    s = sc.ChainSettings()
    with pytest.raises(AttributeError):
        s.snr_db = 3.0  # type: ignore[misc]
    assert (s.n_samples, s.rate_hz, s.duration_s, s.carrier_hz) == (1000, 50_000.0, 0.02, 1000.0)
    p = sc.ChainSettings.paper(snr_db=40.0)
    assert (p.method, p.gain_model, p.snr_db, p.bandwidth_hz) == ("bandpass", "paper", 40.0, 600.0)


def test_point_noise_rejects_bad_input():
    with pytest.raises(InputError):
        sc.point_noise_vs_snr([40.0], n=1)
    with pytest.raises(InputError):
        sc.point_noise_vs_snr([40.0], xy_mm=(6.0, 0.0))
    with pytest.raises(InputError):
        sc.predicted_point_std(np.zeros(2), sc.ChainSettings())


def test_cli_signal_noise(capsys):
    from psdcal.cli import main

    assert main(["signal-noise", "--snr-db", "40", "--snr-db", "50", "--trials", "200", "--seed", "3"]) == 0
    out = capsys.readouterr().out
    assert "std x (mm)" in out and "40" in out and "50" in out
    assert main(["signal-noise", "--rate-hz", "1500"]) == 2
    assert "Nyquist" in capsys.readouterr().err
    assert main(["signal-noise", "--method", "bandpass", "--x-mm", "9"]) == 2


@pytest.mark.parametrize("method", METHODS)
def test_closed_form_noise_has_the_law_of_the_sampled_records(method):
    """noise="closed-form" draws what demodulating sampled records gives: same mean and std.

    Low SNR (10 dB) and a spot on the diamond's edge, where one channel's
    amplitude is near zero, so the magnitude's bias and the sign's flips
    (the non-Gaussian parts of the law) are in play; within 5 Monte Carlo
    standard errors for every channel.
    """
    s = replace(sc.ChainSettings(method=method, snr_db=10.0), duration_s=0.01)
    spots = np.array([[0.4, -0.6], [2.2, 2.3], [-3.5, 1.0]])
    n = 3000
    xy = np.broadcast_to(spots, (n,) + spots.shape)
    ref = sc.measure_amplitudes(xy, s, rng=11)
    fast = sc.measure_amplitudes(xy, s, rng=12, noise="closed-form")
    assert fast.shape == ref.shape and np.all(np.isfinite(fast))
    m_r, m_f = ref.mean(0), fast.mean(0)
    s_r, s_f = ref.std(0), fast.std(0)
    assert np.all(np.abs(m_f - m_r) <= 5 * np.sqrt((s_r**2 + s_f**2) / n))
    # std of a std: sqrt((kurtosis - 1) / (4 n)) relative; kurtosis from the reference draws
    kurt = np.mean((ref - m_r) ** 4, 0) / s_r**4
    assert np.all(np.abs(s_f / s_r - 1) <= 5 * np.sqrt(2 * (kurt - 1) / (4 * n)))
    # the low SNR really reaches the non-Gaussian regime: the near-zero channel changes sign
    assert np.any(np.sign(ref) != np.sign(ref[0])) and np.any(np.sign(fast) != np.sign(fast[0]))


def test_closed_form_noise_variance_matches_the_noise_factor():
    """Its amplitude variance at high SNR is amplitude_noise_factor's first-order value."""
    for method in METHODS:
        s = replace(sc.ChainSettings(method=method, snr_db=60.0), duration_s=0.01)
        xy = np.zeros((20000, 2))
        a = sc.measure_amplitudes(xy, s, rng=3, noise="closed-form")
        sigma = sc.noise_sigma(a.mean(0), 60.0)
        want = sigma * np.sqrt(sc.amplitude_noise_factor(s))
        assert np.allclose(a.std(0), want, rtol=5 / np.sqrt(2 * 20000))


def test_closed_form_noise_rejects_unknown_mode_and_ignores_no_noise():
    s = sc.ChainSettings(snr_db=None)
    xy = np.array([[0.5, 0.5]])
    assert np.array_equal(sc.measure_amplitudes(xy, s, noise="closed-form"), sc.measure_amplitudes(xy, s))
    with pytest.raises(ValueError):
        sc.measure_amplitudes(xy, sc.ChainSettings(snr_db=40.0), rng=0, noise="fft")


def test_closed_form_noise_falls_back_to_records_when_long(monkeypatch):
    """Above the closed form's record length the sampled path runs (the same draws as noise="sampled")."""
    monkeypatch.setattr(sc, "_CLOSED_FORM_MAX_SAMPLES", 100)
    s = sc.ChainSettings(snr_db=30.0)
    xy = np.array([[0.5, -1.0], [2.0, 2.0]])
    assert np.array_equal(sc.measure_amplitudes(xy, s, rng=4, noise="closed-form"), sc.measure_amplitudes(xy, s, rng=4))
