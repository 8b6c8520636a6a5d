"""Reflections: a sensor whose ray disagrees is found and left out; two sensors say they cannot tell
(docs/guide/positioning.md#reflections).

The rays here come from a simulator written for the test: pinhole sensors on a ring near the
ceiling aimed at the room's middle, emitters at random in the lower half, a floor mirror seen by one
sensor as the power-weighted centroid of the direct and mirrored directions (a PSD), Gaussian noise.
Rates are asserted at a stated sample size with two-sided bands of 4 Monte Carlo standard errors.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from psdcal.cli import main
from psdcal.errors import InputError
from psdcal.measure.positioning import triangulate
from psdcal.measure.reflections import left_out_names, reflection_warnings, screen_rays

SIGMA = 2e-4  # ray noise, normalised units
TAN_HALF_FOV = 0.8


# --------------------------------------------------------------------------- the test's own simulator
def ring(k, rng, radius_mm=2800.0):
    """k sensors (R world->camera, t_mm, centre) near the ceiling on a ring, aimed at (0, 0, 700)."""
    out = []
    for j in range(k):
        phi = 2 * math.pi * j / k + rng.uniform(-0.25, 0.25)
        c = np.array([radius_mm * math.cos(phi), radius_mm * math.sin(phi), rng.uniform(2300, 2800)])
        z = np.array([0.0, 0.0, 700.0]) - c
        z /= np.linalg.norm(z)
        x = np.cross([0.0, 0.0, -1.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        out.append((R, -R @ c, c))
    return out


def rays(sensors, P):
    """Normalised coordinates (k, N, 2) of world points P (N, 3); NaN out of view."""
    n = []
    for R, t, _ in sensors:
        pc = P @ R.T + t
        v = pc[:, :2] / pc[:, 2:]
        ok = (pc[:, 2] > 0) & (np.abs(v).max(-1) < TAN_HALF_FOV)
        n.append(np.where(ok[:, None], v, np.nan))
    return np.stack(n)


def draw(k, N, seed, reflect=True, att=(0.1, 0.5), p_reflect=1.0):
    """Rays of N emitters seen by k sensors, one random sensor per row (a fraction ``p_reflect`` of the rows)
    biased by a floor reflection.

    Returns (n_observed, cov, R, t, P, reflected_index (-1: none counted), bias_over_sigma).
    """
    rng = np.random.default_rng(seed)
    sensors = ring(k, rng)
    P = np.stack([rng.uniform(-1200, 1200, N), rng.uniform(-1200, 1200, N), rng.uniform(300, 1300, N)], -1)
    n = rays(sensors, P)
    img = rays(sensors, P * [1.0, 1.0, -1.0])  # the floor z = 0 as a mirror: the image source
    j = rng.integers(0, k, N)
    refl = np.full(N, -1)
    bias = np.zeros(N)
    out = n.copy()
    if reflect:
        for i in range(N):
            c = sensors[j[i]][2]
            d1 = np.sum((P[i] - c) ** 2)
            d2 = np.sum((P[i] * [1, 1, -1] - c) ** 2)
            w = rng.uniform(*att) * d1 / d2
            a, b = n[j[i], i], img[j[i], i]
            if np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and rng.uniform() < p_reflect:
                out[j[i], i] = (a + w * b) / (1 + w)
                refl[i] = j[i]
                bias[i] = np.linalg.norm(out[j[i], i] - a) / SIGMA
    out = out + SIGMA * rng.standard_normal(out.shape)
    cov = np.broadcast_to(SIGMA ** 2 * np.eye(2), (k, N, 2, 2)).copy()
    R = np.stack([s[0] for s in sensors])
    t = np.stack([s[1] for s in sensors])
    return out, cov, R, t, P, refl, bias


def band(x, p, z=4.0):
    """Whether the rate of the bools x is within z Monte Carlo standard errors of p."""
    x = np.asarray(x, bool)
    se = math.sqrt(p * (1 - p) / len(x))
    return abs(x.mean() - p) <= z * se, x.mean(), se


# --------------------------------------------------------------------------- false alarms
def test_two_sensors_flag_at_the_stated_rate_and_never_choose():
    """k = 2, consistent rays, alpha = 0.05, N = 3000: 'ambiguous' in 5 % +- 4 SE, no sensor ever left out."""
    n, cov, R, t, _, _, _ = draw(2, 3000, seed=1, reflect=False)
    s = screen_rays(n, cov, R, t, alpha=0.05)
    m = np.all(np.isfinite(n), -1).sum(0)
    both = m == 2
    assert both.sum() > 2500
    ok, rate, se = band(s.flag[both] == "ambiguous", 0.05)
    assert ok, (rate, se)
    assert np.all(s.left_out == -1)
    assert set(s.flag.tolist()) <= {"", "ambiguous"}


def test_false_alarms_with_four_sensors_within_the_bonferroni_bounds():
    """k = 4, consistent rays, alpha = 0.05, N = 3000: the flagged rate lies in [alpha / 4, alpha] (4 SE)."""
    n, cov, R, t, _, _, _ = draw(4, 3000, seed=2, reflect=False)
    s = screen_rays(n, cov, R, t, alpha=0.05)
    m = np.all(np.isfinite(n), -1).sum(0)
    four = m == 4
    assert four.sum() > 2000
    x = (s.flag[four] != "").astype(float)
    se = math.sqrt(0.05 * 0.95 / len(x))
    assert 0.05 / 4 - 4 * se <= x.mean() <= 0.05 + 4 * se, (x.mean(), se)


def test_default_false_alarm_rate_is_at_most_a_tenth_of_a_percent():
    """Default alpha (1e-3), k = 4, N = 6000 consistent rows: at most 1e-3 + 4 SE flagged."""
    n, cov, R, t, _, _, _ = draw(4, 6000, seed=3, reflect=False)
    s = screen_rays(n, cov, R, t)
    x = s.flag != ""
    assert x.mean() <= 1e-3 + 4 * math.sqrt(1e-3 / len(x)), x.mean()
    assert s.alpha == 1e-3


# --------------------------------------------------------------------------- reflections found
@pytest.mark.parametrize("k, floor", [(4, 0.95), (5, 0.95), (3, 0.85)])
def test_reflected_sensor_found_and_left_out(k, floor):
    """N = 600 rows with a floor reflection on one sensor: that sensor left out in >= floor (4 SE);
    never another one; the position without it covers the truth (NEES 3 +- 4 SE)."""
    n, cov, R, t, P, refl, bias = draw(k, 600, seed=10 + k)
    # inflate=False: the stated covariance (the batch's pooled rule would add the noise of the rows where the
    # reflection could not be placed to every row's sigmas)
    s = screen_rays(n, cov, R, t, inflate=False)
    m = np.all(np.isfinite(n), -1).sum(0)
    rows = (refl >= 0) & (m == k) & (bias > 10)
    assert rows.sum() > 300
    found = s.left_out[rows] == refl[rows]
    se = math.sqrt(floor * (1 - floor) / rows.sum())
    assert found.mean() >= floor - 4 * se, (found.mean(), se)
    wrong = (s.left_out[rows] >= 0) & ~found
    assert wrong.sum() == 0
    assert np.all(s.flag[rows][found] == "left_out")
    assert np.all(s.tri.n_sensors[rows][found] == k - 1)
    d = (s.tri.p_w_mm - P)[rows][found]
    C = s.tri.cov_p_mm2[rows][found]
    nees = np.einsum("ni,nij,nj->n", d, np.linalg.inv(C), d)
    se_nees = nees.std(ddof=1) / math.sqrt(len(nees))
    assert abs(nees.mean() - 3.0) <= 4 * se_nees + 0.05, (nees.mean(), se_nees)
    # with every ray kept, the same rows are far off: the left-out does matter
    keep = triangulate(n, cov, R, t)
    err_keep = np.linalg.norm(keep.p_w_mm - P, axis=-1)[rows][found]
    err_left = np.linalg.norm(d, axis=-1)
    assert np.median(err_keep) > 10 * np.median(err_left)


def test_two_sensors_with_a_reflection_say_so_and_keep_both_rays():
    """k = 2 with a floor reflection, N = 600: flagged 'ambiguous' in most rows, never a sensor left out,
    the position is the triangulation of both rays."""
    n, cov, R, t, _, refl, _ = draw(2, 600, seed=20)
    s = screen_rays(n, cov, R, t)
    m = np.all(np.isfinite(n), -1).sum(0)
    rows = (refl >= 0) & (m == 2)
    assert rows.sum() > 300
    assert np.all(s.left_out == -1)
    assert (s.flag[rows] == "ambiguous").mean() > 0.8
    both = triangulate(n, cov, R, t)
    np.testing.assert_allclose(s.tri.p_w_mm[m == 2], both.p_w_mm[m == 2])
    w = reflection_warnings(left_out_names(s, ["a", "b"])[m == 2], s.flag[m == 2])
    assert any("cannot tell which" in x for x in w)


def test_warnings_name_the_sensor_and_the_rate():
    w = reflection_warnings(np.array(["", "s2", "s2", ""], object), np.array(["", "left_out", "left_out", ""], object))
    assert len(w) == 1 and "sensor s2 left out of 2 of 4 rows" in w[0] and "0.1 %" in w[0]
    assert reflection_warnings(np.array(["", ""], object), np.array(["", ""], object)) == []


# --------------------------------------------------------------------------- the simulator's mirror
def test_mirror_image_and_weight():
    from psdcal.study.reflections import observed_rays, parse_reflection

    rf = parse_reflection("x=6:0.25:s2,s3:tag", (6000.0, 4000.0, 3000.0))
    assert rf.normal == (-1.0, 0.0, 0.0) and rf.sensors == ("s2", "s3") and rf.emitters == ("tag",)
    assert rf.applies("s2", "tag") and not rf.applies("s1", "tag") and not rf.applies("s2", "a1")
    P = np.array([5000.0, 1000.0, 800.0])
    np.testing.assert_allclose(rf.mirror(P), [7000.0, 1000.0, 800.0])
    C = np.array([1000.0, 2000.0, 2500.0])
    d1 = np.sum((P - C) ** 2)
    d2 = np.sum((np.array([7000.0, 1000.0, 800.0]) - C) ** 2)
    assert rf.weight(P, C) == pytest.approx(0.25 * d1 / d2)
    assert rf.weight(np.array([6500.0, 1000.0, 800.0]), C) == 0.0  # behind the wall
    nd, ni = np.array([0.1, 0.0]), np.array([0.3, 0.2])
    np.testing.assert_allclose(observed_rays(nd, ni, 0.5), (nd + 0.5 * ni) / 1.5)
    np.testing.assert_allclose(observed_rays(nd, ni, 0.5, "ghost"), ni)
    np.testing.assert_allclose(observed_rays(nd, np.array([np.nan, np.nan]), 0.5), nd)
    for bad in ("w=0:0.3", "z=0", "z=0:1.5", "z=1.5:0.3"):
        with pytest.raises(InputError):
            parse_reflection(bad, (6000.0, 4000.0, 3000.0))


# --------------------------------------------------------------------------- end to end
def test_cli_room_with_a_floor_reflection_locate_leaves_the_sensor_out(tmp_path, capsys):
    """simulate-recording room --reflection z=0:0.3:s2 -> locate --sensors: s2 left out, with the warning;
    the same room without the reflection: nothing left out, no warning."""
    common = ["simulate-recording", "room", "--sensors", "4", "--anchors", "2", "--moving", "none",
              "--duration-s", "0.1", "--seed", "3"]
    assert main(common + ["--reflection", "z=0:0.3:s2", "-o", str(tmp_path / "r")]) == 0
    assert main(common + ["-o", str(tmp_path / "c")]) == 0
    truth = json.loads((tmp_path / "r" / "truth.json").read_text())
    assert truth["reflections"][0]["sensors"] == ["s2"]
    capsys.readouterr()
    got = {}
    for name in ("r", "c"):
        out = tmp_path / f"{name}.csv"
        assert main(["locate", "--sensors", str(tmp_path / name / "sensors.json"), "--rate-hz", "20000",
                     "--carrier-hz", "1000", "--carrier-hz", "1150", "--allow-no-covariance", "--no-progress",
                     "-o", str(out)]) == 0
        err = capsys.readouterr().err
        lines = out.read_text().splitlines()
        assert lines[0].endswith(",left_out,reflection")
        got[name] = ([ln.split(",")[-2:] for ln in lines[1:]], err)
    rows, err = got["r"]
    assert len(rows) == 20 and all(r == ["s2", "left_out"] for r in rows)
    assert "sensor s2 left out of 20 of 20 rows" in err
    rows, err = got["c"]
    assert all(r == ["", ""] for r in rows)
    assert "left out" not in err


def test_cli_bad_reflection_is_exit_2(tmp_path, capsys):
    assert main(["simulate-recording", "room", "--reflection", "floor", "-o", str(tmp_path / "x")]) == 2
    assert "reflection" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_pose_and_calibration_terms_pass_through_to_the_refits():
    """Zero pose covariance and zero calibration dependence (as ray_inputs builds them) change nothing."""
    n, cov, R, t, _, _, _ = draw(4, 200, seed=30)
    plain = screen_rays(n, cov, R, t)
    D = np.zeros((4, 200, 2, 3))
    kw = {"cov_pose": np.zeros((4, 6, 6)), "calib": (D, np.stack([np.eye(3)] * 4), np.zeros((4, 6, 3)))}
    full = screen_rays(n, cov, R, t, **kw)
    assert (plain.flag != "").sum() > 150
    np.testing.assert_array_equal(full.left_out, plain.left_out)
    np.testing.assert_allclose(full.tri.p_w_mm, plain.tri.p_w_mm, rtol=1e-9, atol=1e-9)


def _angles_table(path, n, names, t_s, sigma):
    """An angles table (psdcal convention: alpha = atan of the normalised coordinate) of rays n (k, N, 2)."""
    lines = ["# convention: psdcal", "t_s,sensor,emitter,alpha_x_deg,alpha_y_deg,sigma_alpha_x_deg,sigma_alpha_y_deg"]
    s = math.degrees(sigma)
    for j, nm in enumerate(names):
        for i in range(n.shape[1]):
            if np.all(np.isfinite(n[j, i])):
                ax, ay = np.degrees(np.arctan(n[j, i]))
                lines.append(f"{t_s[i]:.6f},{nm},tag,{ax:.12g},{ay:.12g},{s:.6g},{s:.6g}")
    path.write_text("\n".join(lines) + "\n")


def _sensors_file(path, R, t, names):
    from scipy.spatial.transform import Rotation

    ents = [{"name": nm, "rvec": Rotation.from_matrix(Rj).as_rotvec().tolist(), "tvec_mm": tj.tolist()}
            for nm, Rj, tj in zip(names, R, t)]
    path.write_text(json.dumps({"sensors": ents}))


@pytest.mark.parametrize("k", [2, 4])
def test_cli_angles_locate_and_track_say_what_they_found(tmp_path, capsys, k):
    """locate --angles and track --sensors on a table with one reflected sensor in a third of the steps: with
    four sensors that sensor is named in 'left_out'; with two, those rows say 'ambiguous' and no sensor is
    left out (the other rows: nothing, at the false-alarm rate)."""
    n, _, R, t, _, refl, _ = draw(k, 150, seed=40 + k, p_reflect=0.33)
    names = [f"c{j}" for j in range(k)]
    keep = np.all(np.isfinite(n), -1).sum(0) == k
    t_s = np.arange(150) * 0.01
    _angles_table(tmp_path / "a.csv", n[:, keep], names, t_s[keep], SIGMA)
    _sensors_file(tmp_path / "s.json", R, t, names)
    assert main(["locate", "--angles", str(tmp_path / "a.csv"), "--sensors", str(tmp_path / "s.json"),
                 "-o", str(tmp_path / "xyz.csv")]) == 0
    err = capsys.readouterr().err
    rows = [ln.split(",") for ln in (tmp_path / "xyz.csv").read_text().splitlines()]
    assert rows[0][-2:] == ["left_out", "reflection"]
    body = rows[1:]
    assert len(body) == keep.sum() > 100
    hit = refl[keep] >= 0
    assert 20 < hit.sum() < len(body) - 20
    if k == 4:
        want = [names[j] if j >= 0 else "" for j in refl[keep]]
        assert np.mean([r[-2] == w for r, w, h in zip(body, want, hit) if h]) >= 0.9
        assert all(r[-2] in ("", w) for r, w in zip(body, want))  # never another sensor, never a clean row
        assert "left out of" in err
    else:
        assert all(r[-2] == "" for r in body)
        assert np.mean([r[-1] == "ambiguous" for r, h in zip(body, hit) if h]) >= 0.8
        assert sum(r[-1] != "" for r, h in zip(body, hit) if not h) <= 1
        assert "cannot tell which" in err
    assert main(["track", str(tmp_path / "a.csv"), "--sensors", str(tmp_path / "s.json"),
                 "-o", str(tmp_path / "track.csv")]) == 0
    err = capsys.readouterr().err
    assert ("left out of" in err) if k == 4 else ("cannot tell which" in err)


def test_angles_noisier_than_stated_are_not_called_reflections(tmp_path, capsys):
    """Rays 4x noisier than the table states, no reflection (k = 4, N = 400): the screening is redone against
    the file's extra ray noise, so sensors are left out at about the stated rate (<= 0.1 % + 4 SE), not for noise;
    the same screening with the stated noise alone would flag most rows."""
    n, cov, R, t, _, _, _ = draw(4, 400, seed=50, reflect=False)
    rng = np.random.default_rng(51)
    n = n + 3.87 * SIGMA * rng.standard_normal(n.shape)  # total sigma 4x the stated one
    names = [f"c{j}" for j in range(4)]
    keep = np.all(np.isfinite(n), -1).sum(0) >= 3
    _angles_table(tmp_path / "a.csv", n[:, keep], names, np.arange(400)[keep] * 0.01, SIGMA)
    _sensors_file(tmp_path / "s.json", R, t, names)
    assert main(["locate", "--angles", str(tmp_path / "a.csv"), "--sensors", str(tmp_path / "s.json"),
                 "-o", str(tmp_path / "xyz.csv")]) == 0
    err = capsys.readouterr().err
    assert "extra ray noise" in err
    body = [ln.split(",") for ln in (tmp_path / "xyz.csv").read_text().splitlines()[1:]]
    assert len(body) > 300
    left = np.mean([r[-2] != "" for r in body])
    assert left <= 1e-3 + 4 * math.sqrt(1e-3 / len(body)), left
    naive = screen_rays(n[:, keep], cov[:, keep], R, t, inflate=False)
    assert (naive.flag != "").mean() > 0.3
