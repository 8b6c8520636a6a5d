"""Recordings of a position-processing module (X, Y, SUM), issue 13.1.

Real recordings (one, two, three LEDs, with and without dark gaps) are read
from the ``shared/data/psd-module-tdm`` folder beside the repository and the tests skip when it is
absent.  The "clean plateau" of an LED is worked out here by another rule
than the code's (a fixed-radius neighbourhood of the 2D-histogram modes and a
SUM band), so the tests are not the code checking itself.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from psdcal.cli import main
from psdcal.errors import InputError
from psdcal.signal.module import DARK, TRANSITION, parse_roles, read_module, segment_module

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "psd-module-tdm"
FILES = {
    "one_blink_signal_100Hz_2ms.Dat": 1,
    "bi_blink_signal_100Hz_2ms.Dat": 2,
    "tri_blink_signal_100Hz_2ms.Dat": 3,
    "tri_blink_signal_1000Hz_2ms.Dat": 3,
}


def modes(x, y, s, n, bin_=0.01):
    """The n most populated 2D-histogram cells of the lit samples, at least 0.1 apart (the test's own rule)."""
    lit = s > 0.1 * s.max()
    H, ex, ey = np.histogram2d(x[lit], y[lit], bins=[np.arange(x.min() - bin_, x.max() + 2 * bin_, bin_),
                                                    np.arange(y.min() - bin_, y.max() + 2 * bin_, bin_)])
    out = []
    for flat in np.argsort(H, axis=None)[::-1]:
        i, j = np.unravel_index(flat, H.shape)
        c = np.array([0.5 * (ex[i] + ex[i + 1]), 0.5 * (ey[j] + ey[j + 1])])
        if all(np.hypot(*(c - o)) > 0.1 for o in out):
            out.append(c)
        if len(out) == n:
            return np.array(out)
    raise AssertionError("fewer modes than LEDs")


def adc_step(v):
    """The module's output step (its quantisation), from the data: the smallest non-zero change between samples."""
    d = np.abs(np.diff(np.round(v, 4)))
    return float(d[d > 5e-5].min())


def leds_by_runs(x, y, s, n_led):
    """Per LED (in order of first appearance) the median x, y of its clean samples, by a rule of the test's own.

    The README: LEDs blink in turn, ~5 samples (10 ms) each, the first sample
    of a slot may blend two LEDs.  Runs are split where the position jumps by
    more than 0.05 units (LEDs are > 0.5 apart; one sample's scatter is
    < 0.01); the first sample of every run (the blend) and runs shorter than
    3 are dropped; each run goes to the LED whose first run lies within
    0.05 units of it.
    """
    lit = s > 0.1 * s.max()
    idx = np.flatnonzero(lit)
    cut = np.flatnonzero((np.diff(idx) > 1) | (np.hypot(np.diff(x[idx]), np.diff(y[idx])) > 0.05)) + 1
    centres, members = [], []
    for run in np.split(idx, cut):
        if run.size < 3:
            continue
        run = run[1:]
        c = np.array([np.median(x[run]), np.median(y[run])])
        k = next((i for i, o in enumerate(centres) if np.hypot(*(c - o)) < 0.05), None)
        if k is None:
            centres.append(c)
            members.append([])
            k = len(centres) - 1
        members[k].append(run)
    assert len(centres) == n_led, f"the test's rule finds {len(centres)} LEDs"
    return [(np.median(x[np.concatenate(m)]), np.median(y[np.concatenate(m)])) for m in members]


@pytest.mark.skipif(not DATA.is_dir(), reason=f"the real module recordings are not present: {DATA} is absent")
@pytest.mark.parametrize("name", sorted(FILES))
def test_real_module_recording(name):
    n_led = FILES[name]
    rec = read_module(DATA / name, "t,x,y,sum")
    assert abs(rec.rate_hz - 500.0) < 1e-6
    seg = segment_module(rec.x, rec.y, rec.sum)
    assert len(seg.emitters) == n_led
    x, y, s = rec.x, rec.y, rec.sum
    centres = modes(x, y, s, n_led)
    lit = s > 0.1 * s.max()
    matched = set()
    for k, e in enumerate(seg.emitters):
        j = int(np.argmin(np.hypot(centres[:, 0] - e.x, centres[:, 1] - e.y)))
        assert j not in matched  # never two emitters for one LED (nor one for two)
        matched.add(j)
        near = lit & (np.hypot(x - centres[j, 0], y - centres[j, 1]) < 0.03)
        s_med = np.median(s[near])
        plateau = near & (np.abs(s - s_med) < 0.1 * s_med)  # the test's clean plateau
        assert plateau.sum() > 100
        # the position equals the median of the test's clean plateau within one step of the module's output
        # (its position resolution, measured here from the data; the plateau's own median is that precise)
        step = adc_step(x)
        assert abs(e.x - np.median(x[plateau])) <= 1.01 * step, (e.x, np.median(x[plateau]), step)
        assert abs(e.y - np.median(y[plateau])) <= 1.01 * adc_step(y), (e.y, np.median(y[plateau]))
        # no transition sample (dark, off every LED, or off this LED's SUM band) is assigned to it
        mine = seg.labels == k
        assert not np.any(mine & ~plateau)
        # and most of the clean plateau is used
        assert (mine & plateau).sum() > 0.8 * plateau.sum()
    assert set(np.unique(seg.labels)) <= {DARK, TRANSITION, *range(n_led)}
    # a wrong expected count is refused, never relabelled
    with pytest.raises(InputError, match=f"found {n_led} emitters"):
        segment_module(x, y, s, n_emitters=n_led + 1)


# --------------------------------------------------------------------------- simulated, known truth
def simulate(leds, *, slot=5, gap=0, cycles=200, blend_first=True, noise=4e-4, seed=0, phase_frac=None):
    """X, Y, SUM samples of LEDs [(x, y, sum)] in turn; returns x, y, s, truth label per sample (-1 dark, -2 blend)."""
    rng = np.random.default_rng(seed)
    xs, ys, ss, lab = [], [], [], []
    prev = None
    for _ in range(cycles):
        for k, (lx, ly, ls) in enumerate(leds):
            for i in range(slot):
                if i == 0 and blend_first and prev is not None:
                    a = rng.uniform(0.2, 0.8)  # fraction of the previous LED in the first sample
                    px, py, ps = prev
                    xs.append(a * px + (1 - a) * lx)
                    ys.append(a * py + (1 - a) * ly)
                    ss.append(a * ps + (1 - a) * ls)
                    lab.append(-2)
                else:
                    xs.append(lx)
                    ys.append(ly)
                    ss.append(ls)
                    lab.append(k)
            prev = (lx, ly, ls)
            for _ in range(gap):
                xs.append(0.0)
                ys.append(0.0)
                ss.append(0.03)
                lab.append(-1)
                prev = (0.0, 0.0, 0.03) if gap else prev
    n = len(xs)
    x = np.array(xs) + noise * rng.standard_normal(n)
    y = np.array(ys) + noise * rng.standard_normal(n)
    s = np.array(ss) * (1 + 2e-3 * rng.standard_normal(n))
    return x, y, s, np.array(lab)


LEDS = [(0.9, 0.4, 4.3), (-0.55, 1.72, 1.9), (-1.35, -0.13, 5.5), (0.2, -1.1, 3.0)]


@pytest.mark.parametrize("n_led,gap", [(1, 3), (2, 2), (3, 0), (4, 0), (4, 1)])
def test_simulated_module_recordings(n_led, gap):
    leds = LEDS[:n_led]
    x, y, s, truth = simulate(leds, gap=gap, seed=n_led + 10 * gap)
    seg = segment_module(x, y, s, n_emitters=n_led)
    # labels follow the order of first appearance: the truth's order
    for k, ((lx, ly, _), e) in enumerate(zip(leds, seg.emitters)):
        assert e.emitter == str(k + 1)
        assert abs(e.x - lx) < 3 * 4e-4 / np.sqrt(e.n_samples) * 3 + 1e-9
        assert abs(e.y - ly) < 3 * 4e-4 / np.sqrt(e.n_samples) * 3 + 1e-9
        np.testing.assert_allclose(e.scatter_x, 4e-4, rtol=0.15)
    # no blend or dark sample assigned; every assigned sample is its own LED's
    assigned = seg.labels >= 0
    assert np.all(truth[assigned] == seg.labels[assigned])
    assert np.mean(seg.labels[truth >= 0] == truth[truth >= 0]) > 0.98


def test_collinear_leds_of_equal_brightness_are_not_taken_for_blends():
    """A template row: the middle LED lies on the segment between its neighbours, with their SUM."""
    leds = [(-1.0, 0.5, 4.0), (0.0, 0.5, 4.0), (1.0, 0.5, 4.0)]
    x, y, s, truth = simulate(leds, gap=1)
    seg = segment_module(x, y, s)
    assert len(seg.emitters) == 3
    np.testing.assert_allclose([e.x for e in seg.emitters], [-1.0, 0.0, 1.0], atol=1e-3)


def test_asynchronous_switching_blends_are_dropped():
    """Switching at 1.5x the sampling: repeated mixtures form dense places of their own; they are not LEDs."""
    rng = np.random.default_rng(5)
    leds = np.array(LEDS[:3])
    n = 6000
    t = np.arange(n) * 2.0  # sample every 2 (time units); each LED on for 1.33 units in turn
    period = 3 * (4.0 / 3.0)
    xs = []
    for ti in t:
        # integrate over the sample [ti, ti + 0.5]: fractions of the LEDs lit in it
        u = np.linspace(ti, ti + 0.5, 51)[:-1] + 0.005 + 1e-3 * ti  # slow drift: the mixtures sweep
        k = ((u % period) // (4.0 / 3.0)).astype(int)
        w = np.bincount(k, minlength=3) / len(u)
        xs.append(w @ leds)
    xs = np.array(xs)
    x = xs[:, 0] + 4e-4 * rng.standard_normal(n)
    y = xs[:, 1] + 4e-4 * rng.standard_normal(n)
    s = xs[:, 2]
    seg = segment_module(x, y, s)
    assert len(seg.emitters) == 3
    got = sorted((round(e.x, 2), round(e.y, 2)) for e in seg.emitters)
    assert got == sorted((round(a, 2), round(b, 2)) for a, b, _ in LEDS[:3])


def test_roles_and_reader_errors(tmp_path):
    assert parse_roles("t, x ,y,SUM") == ("t", "x", "y", "sum")
    with pytest.raises(InputError, match="no 'sum'"):
        parse_roles("t,x,y")
    with pytest.raises(InputError, match="twice"):
        parse_roles("x,x,y,sum")
    p = tmp_path / "m.txt"
    p.write_text("t,x,y,sum\n0.002, 1, 2, 3\n0.004, 1, 2, oops\n")
    with pytest.raises(InputError, match=r"m\.txt:3"):
        read_module(p, "t,x,y,sum")
    p.write_text("1 2 3\n1 2 3\n")
    with pytest.raises(InputError, match="rate-hz"):
        read_module(p, "x,y,sum")
    assert read_module(p, "x,y,sum", rate_hz=100.0).rate_hz == 100.0


@pytest.mark.skipif(not DATA.is_dir(), reason=f"the real module recordings are not present: {DATA} is absent")
def test_cli_module_command(tmp_path, capsys):
    out = tmp_path / "leds.csv"
    rc = main(["module", str(DATA / "tri_blink_signal_100Hz_2ms.Dat"), "--channels", "t,x,y,sum",
               "--mm-per-unit", "2.0", "--n-emitters", "3", "-o", str(out)])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "3 emitters" in cap.out
    rows = np.genfromtxt(out, delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert len(rows) == 3
    # expected: the test's own run-based medians of the raw file, times --mm-per-unit, within 2 output steps
    raw = np.loadtxt(DATA / "tri_blink_signal_100Hz_2ms.Dat", delimiter=",")
    expected = leds_by_runs(raw[:, 1], raw[:, 2], raw[:, 3], 3)
    tol_mm = 2.0 * 2 * max(adc_step(raw[:, 1]), adc_step(raw[:, 2]))
    assert list(rows["emitter"].astype(str)) == ["1", "2", "3"]  # the order of first appearance
    np.testing.assert_allclose(rows["x_mm"], [2.0 * ex for ex, _ in expected], rtol=0, atol=tol_mm)
    np.testing.assert_allclose(rows["y_mm"], [2.0 * ey for _, ey in expected], rtol=0, atol=tol_mm)
    rc = main(["module", str(DATA / "tri_blink_signal_100Hz_2ms.Dat"), "--channels", "t,x,y,sum",
               "--n-emitters", "2", "-o", str(tmp_path / "x.csv")])
    assert rc == 2 and not (tmp_path / "x.csv").exists()
    # a calibration points CSV for one view
    pts = tmp_path / "pts.csv"
    rc = main(["module", str(DATA / "bi_blink_signal_100Hz_2ms.Dat"), "--channels", "t,x,y,sum",
               "--image-id", "7", "-o", str(pts)])
    assert rc == 0
    lines = pts.read_text().splitlines()
    assert lines[0] == "image_id,point_id,x_mm,y_mm" and len(lines) == 3 and lines[1].startswith("7,1,")
