"""Streaming multi-carrier lock-in and time multiplexing (psdcal.signal.stream)."""
from __future__ import annotations

import numpy as np
import pytest

from _locate_sim import amplitudes, model, signals, spot_for_angles
from psdcal.signal.demod import lockin_amplitude
from psdcal.errors import InputError
from psdcal.signal.stream import MultiCarrierLockin, ScheduleEntry, TdmSegmenter, check_carriers, load_schedule

RATE = 100_000.0


def run(lk, x, chunk, t0=0.0):
    blocks = [lk.process(t0 + i / lk.rate_hz, x[:, i : i + chunk]) for i in range(0, x.shape[1], chunk)]
    cat = lambda f: np.concatenate([getattr(b, f) for b in blocks])  # noqa: E731
    return {f: cat(f) for f in ("amplitude", "var_amplitude", "phase_rad", "t_s", "t_start_s", "noise_sigma")}


def test_one_carrier_agrees_with_demod_lockin():
    amp = np.array([0.2, 0.3, 0.25, 0.15])
    x = signals(RATE, 20_000, [(amp, 1000.0, 0.4)], noise=1e-3)
    lk = MultiCarrierLockin(RATE, [1000.0], 0.0123)
    out = run(lk, x, 7_001)
    n = lk.n_window
    for j in (0, 5, len(out["t_s"]) - 1):
        ref = lockin_amplitude(x[:, j * n : (j + 1) * n], RATE, 1000.0)
        # projection on the common phase = |z| up to the (tiny) quadrature noise
        np.testing.assert_allclose(out["amplitude"][j, 0], ref, rtol=0, atol=2e-4)


def test_chunking_does_not_change_results_and_phase_is_coherent():
    amp = np.array([0.2, 0.3, 0.25, 0.15])
    x = signals(RATE, 30_000, [(amp, 1000.0, 0.7), (0.5 * amp, 1300.0, -2.0)], t0_s=3.0, noise=1e-3)
    whole = run(MultiCarrierLockin(RATE, [1000.0, 1300.0], 0.01), x, 30_000, t0=3.0)
    odd = run(MultiCarrierLockin(RATE, [1000.0, 1300.0], 0.01), x, 997, t0=3.0)
    for key in whole:
        np.testing.assert_allclose(odd[key], whole[key], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(whole["phase_rad"][:, 0], 0.7, atol=5e-3)
    np.testing.assert_allclose(whole["phase_rad"][:, 1], -2.0, atol=1e-2)
    np.testing.assert_allclose(whole["t_start_s"][:3], [3.0, 3.01, 3.02])


def test_gap_between_chunks_is_an_error():
    lk = MultiCarrierLockin(RATE, [1000.0], 0.01)
    lk.process(0.0, np.ones((4, 1000)))
    with pytest.raises(InputError, match="gap"):
        lk.process(0.5, np.ones((4, 1000)))


@pytest.mark.parametrize("window_s", [0.0077, 0.01, 0.0333])
def test_two_carriers_cross_talk_below_1e_minus_3(window_s):
    m = model()
    d = spot_for_angles(m, np.radians([[12.0, -6.0], [-20.0, 9.0]]))
    a1, a2 = amplitudes(m, d[0]), amplitudes(m, d[1], total=3.0)  # the interferer 3x stronger
    rng = np.random.default_rng(4)
    noise = 1e-3 * rng.standard_normal((4, 40_000))
    only1 = signals(RATE, 40_000, [(a1, 1000.0, 0.3)]) + noise
    both = only1 + signals(RATE, 40_000, [(a2, 1300.0, 1.9)], offset=(0, 0, 0, 0))
    only2 = signals(RATE, 40_000, [(a2, 1300.0, 1.9)])
    lk = lambda: MultiCarrierLockin(RATE, [1000.0, 1300.0], window_s)  # noqa: E731
    r1, rb, r2 = run(lk(), only1, 8192), run(lk(), both, 8192), run(lk(), only2, 8192)
    # cross-talk: change of emitter 1's amplitude when emitter 2 is switched on, relative to emitter 2
    xt = np.abs(rb["amplitude"][:, 0] - r1["amplitude"][:, 0]).max() / a2.max()
    assert xt < 1e-3
    # with emitter 1 off, its carrier reads (almost) nothing
    assert np.abs(r2["amplitude"][:, 0]).max() < 1e-3 * a2.max()
    # whereas separate single-carrier lock-ins leak when the window is not whole periods of both
    n = int(round(window_s * RATE))
    single = lockin_amplitude(only2[:, :n], RATE, 1000.0)
    if abs(window_s * 1000 - round(window_s * 1000)) > 0.1 or abs(window_s * 1300 - round(window_s * 1300)) > 0.1:
        assert single.max() > 1e-3 * a2.max()


def test_amplitude_variance_matches_scatter():
    """The stated amplitude variance against the scatter about the TRUE amplitudes, two-sided.

    The recording is drawn here with numpy (not the package's simulator): two
    carriers (10 and 13 periods in a 1000-sample window, orthogonal over it),
    white Gaussian noise sigma = 0.02.  Independently of the code, the
    in-phase projection of white noise has variance 2 sigma^2 / N per window.
    4000 windows x 4 channels x 2 carriers = 32000 standardised errors: the
    mean of z^2 has a Monte Carlo standard error sqrt(2 / 32000) = 0.8 %; the
    band is 4 of them (a sigma 3 % off fails).
    """
    n_win, n = 4000, 1000
    sigma = 0.02
    amp = np.array([[0.2, 0.3, 0.25, 0.15], [0.15, 0.25, 0.3, 0.2]])  # (carrier, channel)
    freqs, phases = (1000.0, 1300.0), (0.4, 1.0)
    rng = np.random.default_rng(7)
    t = np.arange(n_win * n) / RATE
    x = 0.05 + sigma * rng.standard_normal((4, t.size))
    for a, f, ph in zip(amp, freqs, phases):
        x += a[:, None] * np.sin(2 * np.pi * f * t + ph)[None, :]
    out = run(MultiCarrierLockin(RATE, list(freqs), 0.01), x, 200_000)
    assert out["amplitude"].shape == (n_win, 2, 4)
    var_indep = 2 * sigma**2 / n
    # the stated variance (from each window's own residual, 995 dof) averages to the independent value
    mean_pred = out["var_amplitude"].mean()
    se_pred = var_indep * np.sqrt(2 / 995 / out["var_amplitude"].size)
    assert abs(mean_pred - var_indep) < 4 * se_pred + 1e-3 * var_indep, (mean_pred, var_indep)
    # the errors about the truth, in their stated sigmas: unbiased, unit variance
    z = (out["amplitude"] - amp[None, :, :]) / np.sqrt(out["var_amplitude"])
    m = z.size
    assert abs(z.mean()) < 4 / np.sqrt(m), z.mean()
    assert abs((z**2).mean() - 1.0) < 4 * np.sqrt(2 / m), (z**2).mean()
    # the noise estimate: sigma itself (mean of 16000 estimates, each with 995 dof: SE 0.006 %)
    np.testing.assert_allclose(out["noise_sigma"].mean(), sigma, rtol=4 * np.sqrt(1 / (2 * 995 * 16000)) + 1e-4)


@pytest.mark.parametrize(
    "carriers, window, match",
    [
        ([60_000.0], 0.01, "Nyquist"),
        ([1000.0], 0.002, "periods"),
        ([1000.0, 1050.0], 0.01, "cannot be separated"),
        ([1000.0, 1000.0], 0.01, "repeated"),
        ([-5.0], 0.01, "positive"),
    ],
)
def test_bad_setups(carriers, window, match):
    with pytest.raises(InputError, match=match):
        check_carriers(RATE, carriers, window)


def _tdm_signal(m, spots, on_s=0.1, off_s=0.03, lead_s=0.021, noise=1e-3):
    parts, truth = [], []
    rng = np.random.default_rng(11)
    t = 0.0
    n_lead = int(lead_s * RATE)
    parts.append(np.zeros((4, n_lead)))
    t += lead_s
    for d in spots:
        n_on, n_off = int(on_s * RATE), int(off_s * RATE)
        a = amplitudes(m, d)
        parts.append(signals(RATE, n_on, [(a, 1000.0, 0.2)], t0_s=t, offset=(0, 0, 0, 0)))
        truth.append((t, t + on_s))
        t += on_s
        parts.append(np.zeros((4, n_off)))
        t += off_s
    x = np.concatenate(parts, axis=1) + 0.05 + noise * rng.standard_normal((4, sum(p.shape[1] for p in parts)))
    return x, truth


def test_tdm_segments_found_from_signal():
    m = model()
    spots = spot_for_angles(m, np.radians([[5.0, 5.0], [-10.0, 3.0], [15.0, -12.0], [-4.0, 8.0]]))
    x, truth = _tdm_signal(m, spots)
    lk = MultiCarrierLockin(RATE, [1000.0], 0.01)
    seg = TdmSegmenter(lk.window_s, n_emitters=2)
    segs = []
    for i in range(0, x.shape[1], 4096):
        segs += seg.feed(lk.process(i / RATE, x[:, i : i + 4096]))
    segs += seg.finish()
    assert [s.emitter for s in segs] == ["1", "2", "1", "2"]
    assert seg.warnings == []
    for s, (t0, t1), d in zip(segs, truth, spots):
        assert t0 <= s.t_start_s and s.t_end_s <= t1 + 1e-9
        assert s.n_windows >= 7
        np.testing.assert_allclose(s.amplitude / s.amplitude.sum(), amplitudes(m, d) / amplitudes(m, d).sum(),
                                   atol=2e-4)


def test_tdm_schedule(tmp_path):
    m = model()
    spots = spot_for_angles(m, np.radians([[5.0, 5.0], [-10.0, 3.0]]))
    x, truth = _tdm_signal(m, spots)
    p = tmp_path / "schedule.csv"
    p.write_text("emitter,t_start_s,t_end_s\n" + "".join(f"led{i},{a},{b}\n" for i, (a, b) in enumerate(truth)))
    sched = load_schedule(p)
    assert sched[1] == ScheduleEntry("led1", truth[1][0], truth[1][1])
    lk = MultiCarrierLockin(RATE, [1000.0], 0.01)
    seg = TdmSegmenter(lk.window_s, schedule=sched)
    segs = []
    for i in range(0, x.shape[1], 3000):
        segs += seg.feed(lk.process(i / RATE, x[:, i : i + 3000]))
    segs += seg.finish()
    assert [s.emitter for s in segs] == ["led0", "led1"]
    for s, d in zip(segs, spots):
        np.testing.assert_allclose(s.amplitude / s.amplitude.sum(), amplitudes(m, d) / amplitudes(m, d).sum(),
                                   atol=2e-4)


def test_schedule_errors(tmp_path):
    p = tmp_path / "s.csv"
    p.write_text("emitter,t_start_s,t_end_s\na,0,1\nb,2,x\n")
    with pytest.raises(InputError, match=r"s\.csv:3.*t_end_s"):
        load_schedule(p)
    p.write_text("emitter,start\n")
    with pytest.raises(InputError, match="t_start_s"):
        load_schedule(p)


def test_tdm_back_to_back_leds_are_split():
    """LEDs switched without a dark gap, the switching in the middle of a window."""
    m = model()
    spots = spot_for_angles(m, np.radians([[5.0, 5.0], [-10.0, 3.0], [15.0, -12.0], [6.0, 5.5]]))
    rng = np.random.default_rng(3)
    n_on = 10_450  # 104.5 ms: not a whole number of 10 ms windows
    parts, t = [], 0.0
    for d in spots:
        parts.append(signals(RATE, n_on, [(amplitudes(m, d), 1000.0, 0.2)], t0_s=t, offset=(0, 0, 0, 0)))
        t += n_on / RATE
    x = np.concatenate(parts, axis=1) + 0.05 + 1e-3 * rng.standard_normal((4, 4 * n_on))
    lk = MultiCarrierLockin(RATE, [1000.0], 0.01)
    seg = TdmSegmenter(lk.window_s)
    segs = []
    for i in range(0, x.shape[1], 5000):
        segs += seg.feed(lk.process(i / RATE, x[:, i : i + 5000]))
    segs += seg.finish()
    assert [s.emitter for s in segs] == ["1", "2", "3", "4"]
    for k, (s, d) in enumerate(zip(segs, spots)):
        assert k * n_on / RATE <= s.t_start_s and s.t_end_s <= (k + 1) * n_on / RATE + 1e-9
        assert s.n_windows >= 7
        np.testing.assert_allclose(s.amplitude / s.amplitude.sum(), amplitudes(m, d) / amplitudes(m, d).sum(),
                                   atol=2e-4)
