"""Angles in, everywhere: `locate`, `pose`, `bundle` (and `track` through locate) from angle tables of any
AoA front-end, no calibration (docs/guide/positioning.md#angles-in).

The simulator here is written for the test: sensors aimed at the middle of a room, emitters still or
moving, the angles of each convention computed from the camera-frame point by the definitions of the
guide (not by psdcal's converters), Gaussian noise on the angles.
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2 as chi2_dist

from psdcal.cli import main

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "lighthouse-lh1"
CONVENTIONS = ("psdcal", "azel", "tangent")
COLUMNS = {"psdcal": ("alpha_x", "alpha_y"), "azel": ("azimuth", "elevation"), "tangent": ("h", "v")}


# --------------------------------------------------------------------------- simulator
def look_at(centre, target, roll):
    """World -> camera rotation of a camera at ``centre`` whose z axis points at ``target`` (y roughly down)."""
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    down = np.array([0.0, 0.0, -1.0])
    x = np.cross(down, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in the world
    Rz = Rotation.from_rotvec([0, 0, roll]).as_matrix()
    return Rz @ R


def angles_of(Pc, convention):
    """The two angles (rad) of camera-frame points (x right, y down, z forward) in a convention."""
    X, Y, Z = Pc[..., 0], Pc[..., 1], Pc[..., 2]
    if convention == "psdcal":
        return np.stack([np.arctan2(X, Z), np.arctan2(Y, Z)], -1)
    x, y, z = Z, -X, -Y  # the frame x forward, y left, z up
    if convention == "azel":
        return np.stack([np.arctan2(y, x), np.arctan2(z, np.hypot(x, y))], -1)
    return np.stack([np.arctan2(y, x), np.arctan2(z, x)], -1)  # tangent: ray (1, tan h, tan v)


def make_room(rng, n_sensors=4, radius_mm=3000.0):
    names = [f"cam{k}" for k in range(n_sensors)]
    sensors = []
    for k in range(n_sensors):
        phi = 2 * math.pi * k / n_sensors + rng.uniform(-0.3, 0.3)
        c = np.array([radius_mm * math.cos(phi), radius_mm * math.sin(phi), rng.uniform(1800, 2600)])
        R = look_at(c, rng.normal(0, 150, 3) + [0, 0, 1000], rng.uniform(-0.2, 0.2))
        sensors.append((names[k], R, c))
    return sensors


def sensors_json(path, sensors):
    ents = [{"name": nm, "rvec": Rotation.from_matrix(R).as_rotvec().tolist(), "tvec_mm": (-R @ c).tolist()}
            for nm, R, c in sensors]
    Path(path).write_text(json.dumps({"sensors": ents}))


def observe(rng, sensors, points, t_s, emitters, convention, sigma_rad, p_drop=0.0):
    """Rows (t, sensor, emitter, a1, a2) of every sensor seeing every point; ``points`` (T, E, 3)."""
    rows = []
    for nm, R, c in sensors:
        Pc = (points - c) @ R.T
        a = angles_of(Pc, convention) + rng.normal(0, sigma_rad, Pc.shape[:-1] + (2,))
        for i, t in enumerate(t_s):
            for j, e in enumerate(emitters):
                if rng.uniform() >= p_drop:
                    rows.append((t, nm, e, a[i, j, 0], a[i, j, 1]))
    return rows


def write_table(path, rows, convention, sigma_rad, *, declare="comment"):
    a, b = COLUMNS[convention]
    lines = [f"# convention: {convention}"] if declare == "comment" else []
    lines.append(f"t_s,sensor,emitter,{a}_deg,{b}_deg,sigma_{a}_deg,sigma_{b}_deg")
    s = math.degrees(sigma_rad)
    for t, nm, e, x, y in rows:
        lines.append(f"{t:.6f},{nm},{e},{math.degrees(x):.12g},{math.degrees(y):.12g},{s:.6g},{s:.6g}")
    Path(path).write_text("\n".join(lines) + "\n")


def read_csv(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def moving_points(rng, T, E):
    t_s = np.arange(T) * 0.05
    base = rng.normal(0, 400, (E, 3)) + [0, 0, 1000]
    vel = rng.normal(0, 300, (E, 3))
    return t_s, base[None] + t_s[:, None, None] * vel[None]


# --------------------------------------------------------------------------- locate
def test_locate_from_each_convention_matches_the_truth(tmp_path, capsys):
    """NEES of the triangulated points over 3 conventions x 40 steps x 3 emitters (some rays dropped)."""
    rng = np.random.default_rng(1)
    sensors = make_room(rng)
    sensors_json(tmp_path / "s.json", sensors)
    sigma = 1e-4
    nees = []
    for conv in CONVENTIONS:
        t_s, P = moving_points(rng, 40, 3)
        emitters = ["led1", "led2", "tag"]
        rows = observe(rng, sensors, P, t_s, emitters, conv, sigma, p_drop=0.25)
        write_table(tmp_path / f"{conv}.csv", rows, conv, sigma, declare="comment" if conv != "azel" else "option")
        extra = ["--convention", "azel"] if conv == "azel" else []
        out = tmp_path / f"xyz_{conv}.csv"
        assert main(["locate", "--angles", str(tmp_path / f"{conv}.csv"), "--sensors", str(tmp_path / "s.json"),
                     "-o", str(out), *extra]) == 0
        got = read_csv(out)
        assert list(got[0]) == ["t_s", "emitter", "X_mm", "Y_mm", "Z_mm", "sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm",
                                "n_sensors", "chi2", "left_out", "reflection"]
        seen = {}
        for t, nm, e, _, _ in rows:
            seen.setdefault((round(t, 6), e), set()).add(nm)
        expect = sum(1 for v in seen.values() if len(v) >= 2)
        assert len(got) == expect  # every (step, emitter) seen by two sensors or more, and only those
        for r in got:
            i = round(float(r["t_s"]) / 0.05)
            j = emitters.index(r["emitter"])
            # a row whose sensor was left out as a reflection (a false alarm: <= 0.1 % of rows) has one ray less
            left = 1 if r["left_out"] else 0
            assert int(r["n_sensors"]) == len(seen[(round(float(r["t_s"]), 6), r["emitter"])]) - left
            d = np.array([float(r[k]) for k in ("X_mm", "Y_mm", "Z_mm")]) - P[i, j]
            s = np.array([float(r[k]) for k in ("sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm")])
            nees.append(np.sum((d / s) ** 2))  # the diagonal only: chi2_3 in the mean when the axes are
    nees = np.array(nees)
    # diagonal NEES: mean exactly 3 whatever the correlation; sd of one term <= sqrt(2*3*... ) ~ 2.45 * 1.7
    se = nees.std(ddof=1) / math.sqrt(len(nees))
    assert len(nees) > 250
    print(f"locate --angles: {len(nees)} points, mean diagonal NEES {nees.mean():.3f} +- {se:.3f} (ideal 3)")
    assert abs(nees.mean() - 3.0) < 4 * se, (nees.mean(), se)
    out = capsys.readouterr().out
    assert "convention tangent" in out and "convention azel" in out


def test_locate_widens_the_sigmas_when_the_angles_are_noisier_than_stated(tmp_path, capsys):
    """Rays 4x noisier than the table states: the file's check fails, says so, and the widened sigmas
    cover the error again (diagonal NEES of 3 +- 4 standard errors; about 16 without the rule)."""
    rng = np.random.default_rng(7)
    sensors = make_room(rng)
    sensors_json(tmp_path / "s.json", sensors)
    t_s, P = moving_points(rng, 120, 3)
    emitters = ["led1", "led2", "tag"]
    rows = observe(rng, sensors, P, t_s, emitters, "tangent", 4e-4)
    write_table(tmp_path / "a.csv", rows, "tangent", 1e-4)
    out = tmp_path / "xyz.csv"
    assert main(["locate", "--angles", str(tmp_path / "a.csv"), "--sensors", str(tmp_path / "s.json"),
                 "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "locate_angles_chi2" in err and "extra ray noise" in err
    nees = []
    for r in read_csv(out):
        i = round(float(r["t_s"]) / 0.05)
        d = np.array([float(r[k]) for k in ("X_mm", "Y_mm", "Z_mm")]) - P[i, emitters.index(r["emitter"])]
        s = np.array([float(r[k]) for k in ("sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm")])
        nees.append(np.sum((d / s) ** 2))
    nees = np.array(nees)
    se = nees.std(ddof=1) / math.sqrt(len(nees))
    assert len(nees) > 300
    assert abs(nees.mean() - 3.0) < 4 * se, (nees.mean(), se)


def test_locate_equals_the_python_path_and_calls_triangulate(tmp_path):
    from psdcal.measure.angles_locate import load_angle_sensors, triangulate_table
    from psdcal.measure.angles_table import read_angles
    from psdcal.measure.positioning import triangulate

    rng = np.random.default_rng(2)
    sensors = make_room(rng, 3)
    sensors_json(tmp_path / "s.json", sensors)
    t_s, P = moving_points(rng, 10, 2)
    rows = observe(rng, sensors, P, t_s, ["a", "b"], "tangent", 2e-4, p_drop=0.2)
    write_table(tmp_path / "t.csv", rows, "tangent", 2e-4)
    assert main(["locate", "--angles", str(tmp_path / "t.csv"), "--sensors", str(tmp_path / "s.json"),
                 "-o", str(tmp_path / "xyz.csv")]) == 0
    got = read_csv(tmp_path / "xyz.csv")
    res = triangulate_table(read_angles(tmp_path / "t.csv"), load_angle_sensors(tmp_path / "s.json"))
    assert len(got) == len(res)
    cols = res.columns()
    for k, r in enumerate(got):
        assert r["emitter"] == cols["emitter"][k]
        for c in ("t_s", "X_mm", "Y_mm", "Z_mm", "sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm", "chi2"):
            assert float(r[c]) == pytest.approx(float(cols[c][k]), rel=1e-9, abs=1e-12)
    # one step by hand through positioning.triangulate
    tab = read_angles(tmp_path / "t.csv")
    t0, e0 = res.t_s[0], res.emitter[0]
    m = (tab.t_s == t0) & (tab.emitter == e0)
    names = tab.sensor[m].tolist()
    Rs = np.stack([R for nm, R, c in sensors if nm in names])
    ts = np.stack([-R @ c for nm, R, c in sensors if nm in names])
    order = [names.index(nm) for nm, _, _ in sensors if nm in names]
    tri = triangulate(tab.n[m][order], tab.cov_n[m][order], Rs, ts)
    np.testing.assert_allclose(res.p_w_mm[0], tri.p_w_mm, rtol=1e-12)
    np.testing.assert_allclose(res.cov_p_mm2[0], tri.cov_p_mm2, rtol=1e-9)
    # the columns are those of the multi-sensor locate (a prefix: new columns go at the end)
    from psdcal.measure.angles_locate import ANGLES_LOCATE_COLUMNS
    from psdcal.measure.locate import MULTI_COLUMNS

    assert tuple(MULTI_COLUMNS[:10]) == tuple(ANGLES_LOCATE_COLUMNS[:10])
    # both end with the reflection columns (docs/guide/positioning.md#reflections)
    assert MULTI_COLUMNS[-2:] == ANGLES_LOCATE_COLUMNS[-2:] == ("left_out", "reflection")


def test_locate_aligns_sensors_that_do_not_sample_together_and_tracks(tmp_path, capsys):
    """Two sensors 20 ms apart: without --align-to nothing is seen twice; with it, the positions are right."""
    rng = np.random.default_rng(3)
    sensors = make_room(rng, 2)
    sensors_json(tmp_path / "s.json", sensors)
    T = 60
    t_s = np.arange(T) * 0.04
    vel = np.array([200.0, -100.0, 50.0])
    rows = []
    for k, (nm, R, c) in enumerate(sensors):
        tk = t_s + 0.02 * k
        Pk = (np.array([0, 0, 1000.0]) + tk[:, None] * vel)[:, None, :]
        rows += observe(rng, [(nm, R, c)], Pk, tk, ["tag"], "psdcal", 1e-4)
    write_table(tmp_path / "a.csv", rows, "psdcal", 1e-4)
    args = ["locate", "--angles", str(tmp_path / "a.csv"), "--sensors", str(tmp_path / "s.json")]
    assert main([*args, "-o", str(tmp_path / "none.csv")]) == 2
    assert "--align-to" in capsys.readouterr().err
    assert main([*args, "-o", str(tmp_path / "xyz.csv"), "--align-to", "cam0", "--track",
                 str(tmp_path / "track.csv")]) == 0
    got = read_csv(tmp_path / "xyz.csv")
    assert len(got) == T - 1  # the last step of cam0 has no later cam1 sample
    err = [np.linalg.norm(np.array([float(r[c]) for c in ("X_mm", "Y_mm", "Z_mm")])
                          - (np.array([0, 0, 1000.0]) + float(r["t_s"]) * vel)) for r in got]
    sig = [np.linalg.norm([float(r[c]) for c in ("sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm")]) for r in got]
    assert np.median(np.array(err) / np.array(sig)) < 2.0
    track = read_csv(tmp_path / "track.csv")
    assert len(track) == T - 1 and "vX_mm_s" in track[0]
    # `track` of the angles directly: the same rows as through locate
    assert main(["track", str(tmp_path / "a.csv"), "--sensors", str(tmp_path / "s.json"), "--align-to", "cam0",
                 "-o", str(tmp_path / "track2.csv")]) == 0
    assert (tmp_path / "track2.csv").read_text() == (tmp_path / "track.csv").read_text()
    assert main(["track", str(tmp_path / "a.csv"), "--sensors", str(tmp_path / "s.json"), "-o",
                 str(tmp_path / "track3.csv")]) == 2
    assert not (tmp_path / "track3.csv").exists()


# --------------------------------------------------------------------------- pose
def _known_emitters(rng, k=7):
    return {f"k{j}": rng.uniform([-1500, -1500, 0], [1500, 1500, 2200]) for j in range(k)}


def _write_emitters(path, known):
    Path(path).write_text("emitter,X_m,Y_m,Z_m\n" + "".join(f"{nm},{p[0] / 1000:.9f},{p[1] / 1000:.9f},"
                                                           f"{p[2] / 1000:.9f}\n" for nm, p in known.items()))


def _pose_nees(entry, R_true, c_true):
    from psdcal.measure.tagpose import omega_t_to_omega_c

    R = Rotation.from_rotvec(entry["rvec"]).as_matrix()
    c = -R.T @ np.array(entry["tvec_mm"])
    C = np.array(entry["pose_covariance"]["matrix"])
    T = omega_t_to_omega_c(R, c)
    Coc = T @ C @ T.T
    omega = Rotation.from_matrix(R_true @ R.T).as_rotvec()  # R_true = exp([omega]) R
    e = np.concatenate([omega, c_true - c])
    return float(e @ np.linalg.solve(Coc, e))


def test_pose_from_each_convention_without_calibration(tmp_path):
    from psdcal.measure.angles_locate import pose_from_table
    from psdcal.measure.angles_table import read_angles
    from psdcal.measure.pose import read_emitters

    rng = np.random.default_rng(4)
    sensors = make_room(rng, 3)
    known = _known_emitters(rng)
    _write_emitters(tmp_path / "known.csv", known)
    names = list(known)
    P = np.array([known[n] for n in names])[None]
    nees = []
    for conv in CONVENTIONS:
        rows = observe(rng, sensors, np.repeat(P, 5, 0), np.arange(5) * 0.1, names, conv, 3e-4)
        write_table(tmp_path / f"{conv}.csv", rows, conv, 3e-4)
        for nm, R, c in sensors:
            out = tmp_path / f"{conv}_{nm}.json"
            assert main(["pose", str(tmp_path / f"{conv}.csv"), "--emitters", str(tmp_path / "known.csv"),
                         "--sensor", nm, "--name", nm, "-o", str(out), "--into", str(tmp_path / f"{conv}.json")]) == 0
            entry = json.loads(out.read_text())
            assert "calib" not in entry
            nees.append(_pose_nees(entry, R, c))
            py = pose_from_table(read_angles(tmp_path / f"{conv}.csv"), nm, *read_emitters(tmp_path / "known.csv")[:2])
            np.testing.assert_allclose(entry["rvec"], py.rvec, rtol=1e-12, atol=1e-15)
        # the sensors file it wrote places the sensors for `locate --angles`
        tri = tmp_path / f"xyz_{conv}.csv"
        assert main(["locate", "--angles", str(tmp_path / f"{conv}.csv"), "--sensors",
                     str(tmp_path / f"{conv}.json"), "-o", str(tri)]) == 0
        # ... with their pose covariances: the same poses without them give smaller sigmas
        d = json.loads((tmp_path / f"{conv}.json").read_text())
        for e in d["sensors"]:
            e.pop("pose_covariance")
        (tmp_path / "exact.json").write_text(json.dumps(d))
        assert main(["locate", "--angles", str(tmp_path / f"{conv}.csv"), "--sensors", str(tmp_path / "exact.json"),
                     "-o", str(tmp_path / "exact.csv"), "--force"]) == 0
        a, b = read_csv(tri), read_csv(tmp_path / "exact.csv")
        assert any(r["X_mm"] != s["X_mm"] for r, s in zip(a, b))  # the weights change with the pose covariance
        ratio = [float(r[k]) / float(s[k]) for r, s in zip(a, b) for k in ("sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm")]
        assert min(ratio) > 1.0 and np.mean(ratio) > 1.01, (min(ratio), np.mean(ratio))  # ignored: exactly 1
    # 9 poses of 6 dof each: every one below chi2_6's 99.99 % point, the mean within a wide band
    print(f"pose from angle tables: NEES of 9 poses {np.round(nees, 2).tolist()} (ideal mean 6)")
    assert max(nees) < chi2_dist.ppf(0.9999, 6), nees
    assert 6 * 0.35 < np.mean(nees) < 6 * 2.0, nees


def test_pose_of_a_multi_sensor_table_needs_the_sensor(tmp_path, capsys):
    rng = np.random.default_rng(5)
    sensors = make_room(rng, 2)
    known = _known_emitters(rng, 5)
    _write_emitters(tmp_path / "known.csv", known)
    rows = observe(rng, sensors, np.array([list(known.values())]), [0.0], list(known), "tangent", 1e-4)
    write_table(tmp_path / "t.csv", rows, "tangent", 1e-4)
    assert main(["pose", str(tmp_path / "t.csv"), "--emitters", str(tmp_path / "known.csv"), "-o",
                 str(tmp_path / "e.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--sensor" in err[0]
    # a recording still needs its calibration
    (tmp_path / "rec.npy").write_bytes(b"")
    assert main(["pose", str(tmp_path / "rec.npy"), "--emitters", str(tmp_path / "known.csv"), "-o",
                 str(tmp_path / "e.json")]) == 2
    assert "--calib" in capsys.readouterr().err


# --------------------------------------------------------------------------- bundle
@pytest.mark.parametrize("convention", CONVENTIONS)
def test_bundle_from_angles_with_a_wand(tmp_path, capsys, convention):
    from psdcal.measure.angles_locate import bundle_from_table
    from psdcal.measure.angles_table import read_angles

    rng = np.random.default_rng(6)
    sensors = make_room(rng, 3)
    known = _known_emitters(rng, 5)
    _write_emitters(tmp_path / "known.csv", known)
    t_s, W = moving_points(rng, 30, 1)
    rows = []
    for conv in (convention,):
        rows += observe(rng, sensors, np.repeat(np.array([list(known.values())]), 3, 0), np.arange(3) * 0.05,
                        list(known), conv, 2e-4)
        rows += observe(rng, sensors, W, t_s + 10.0, ["wand"], conv, 2e-4, p_drop=0.1)
    write_table(tmp_path / "a.csv", rows, convention, 2e-4)
    out = tmp_path / "sensors.json"
    assert main(["bundle", "--angles", str(tmp_path / "a.csv"), "--known", str(tmp_path / "known.csv"),
                 "--wand", "wand", "-o", str(out), "--points-out", str(tmp_path / "pts.csv")]) == 0
    d = json.loads(out.read_text())
    assert [e["name"] for e in d["sensors"]] == ["cam0", "cam1", "cam2"]
    nees = [_pose_nees(e, R, c) for e, (_, R, c) in zip(d["sensors"], sensors)]
    assert max(nees) < chi2_dist.ppf(0.9999, 6), nees
    assert all("calib" not in e for e in d["sensors"])
    from psdcal.measure.pose import read_emitters

    kn, kp, _ = read_emitters(tmp_path / "known.csv")
    br = bundle_from_table(read_angles(tmp_path / "a.csv"), dict(zip(kn, kp)), ["wand"])
    for j, e in enumerate(d["sensors"]):
        np.testing.assert_allclose(e["rvec"], br.rvecs[j], rtol=1e-12, atol=1e-15)
    pts = read_csv(tmp_path / "pts.csv")
    wand = [p for p in pts if p["emitter"].startswith("wand@")]
    assert len(wand) >= 25
    z = []
    for p in wand:
        i = round((float(p["emitter"].split("@")[1]) - 10.0) / 0.05)
        d_mm = np.array([float(p[c]) * 1000 for c in ("X_m", "Y_m", "Z_m")]) - W[i, 0]
        z += list(d_mm / np.array([float(p[c]) for c in ("sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm")]))
    assert np.max(np.abs(z)) < 5.0
    assert 0.5 < np.std(z) < 1.6
    # LOCATED files with --angles, or neither: one line, exit 2
    assert main(["bundle", "s1=x.csv", "--angles", str(tmp_path / "a.csv"), "--known", str(tmp_path / "known.csv"),
                 "-o", str(tmp_path / "b.json")]) == 2
    assert main(["bundle", "--known", str(tmp_path / "known.csv"), "-o", str(tmp_path / "b.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(e.startswith("psdcal: error:") for e in err)
    assert not (tmp_path / "b.json").exists()


# --------------------------------------------------------------------------- errors
@pytest.mark.parametrize("case", ["missing sensor", "unknown convention", "no sensors file", "calib too"])
def test_errors_are_one_line_exit_2(tmp_path, capsys, case):
    rng = np.random.default_rng(7)
    sensors = make_room(rng, 3)
    sensors_json(tmp_path / "s.json", sensors[:2] if case == "missing sensor" else sensors)
    t_s, P = moving_points(rng, 3, 1)
    write_table(tmp_path / "a.csv", observe(rng, sensors, P, t_s, ["e"], "psdcal", 1e-4), "psdcal", 1e-4)
    args = ["locate", "--angles", str(tmp_path / "a.csv"), "-o", str(tmp_path / "out.csv")]
    if case != "no sensors file":
        args += ["--sensors", str(tmp_path / "s.json")]
    if case == "unknown convention":
        args += ["--convention", "polar"]
    if case == "calib too":
        args += ["--calib", str(tmp_path / "s.json")]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("psdcal: error:"), err
    words = {"missing sensor": ["'cam2'", "s.json"], "unknown convention": ["polar", "known:"],
             "no sensors file": ["--sensors"], "calib too": ["--calib"]}[case]
    assert all(w in err[0] for w in words), err[0]
    assert not (tmp_path / "out.csv").exists()


def test_locate_still_needs_a_carrier_without_angles(tmp_path, capsys):
    assert main(["locate", "rec.npy", "--calib", "c.json", "-o", str(tmp_path / "o.csv")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--carrier-hz" in err[0]


# --------------------------------------------------------------------------- lighthouse
def stations_file(path):
    """geometry.json -> a psdcal sensors file: camera frame Zc = x, Xc = -y, Yc = -z of the station's frame."""
    g = json.loads((DATA / "geometry.json").read_text())
    M = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    ents = []
    for b in g["base_stations"]:
        U, _, Vt = np.linalg.svd(np.array(b["rotation_bs_to_world"]))  # nearest rotation (float32 in the source)
        Rbw = U @ Vt
        R = M @ Rbw.T  # world -> camera
        c = np.array(b["origin_m"]) * 1000.0
        ents.append({"name": str(b["station"]), "rvec": Rotation.from_matrix(R).as_rotvec().tolist(),
                     "tvec_mm": (-R @ c).tolist()})
    Path(path).write_text(json.dumps({"sensors": ents}))
    return g


def _kabsch(A, B):
    a, b = A.mean(0), B.mean(0)
    U, _, Vt = np.linalg.svd((A - a).T @ (B - b))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, b - R @ a


def score_against_mocap(folder, xyz_rows):
    """(median, p95, n) of the deck centre (mean of the photodiodes at each step) and of the Crazyflie's estimate
    against the motion capture, on the same steps, a rigid fit on alternate 10 s blocks scored on the others."""
    t = np.array([float(r["t_s"]) for r in xyz_rows])
    P = np.array([[float(r[c]) for c in ("X_mm", "Y_mm", "Z_mm")] for r in xyz_rows])
    tu, inv = np.unique(t, return_inverse=True)
    C = np.zeros((len(tu), 3))
    np.add.at(C, inv, P)
    C /= np.bincount(inv)[:, None]
    m = np.loadtxt(DATA / folder / "mocap.csv", delimiter=",", skiprows=1)
    cf = np.loadtxt(DATA / folder / "crazyflie_estimate.csv", delimiter=",", skiprows=1)
    cf = cf[cf[:, 4] < 0.1]
    j = np.clip(np.searchsorted(cf[:, 0], tu), 1, len(cf) - 1)
    j = np.where(np.abs(cf[j - 1, 0] - tu) < np.abs(cf[j, 0] - tu), j - 1, j)
    keep = (np.abs(cf[j, 0] - tu) < 0.005) & (tu >= m[0, 0]) & (tu <= m[-1, 0])

    def mocap_at(tt):
        i = np.clip(np.searchsorted(m[:, 0], tt), 1, len(m) - 1)
        return np.stack([np.interp(tt, m[:, 0], m[:, k]) for k in (1, 2, 3)], -1) * 1000, (m[i, 0] - m[i - 1, 0]) < 0.01

    tk, tc = tu[keep], cf[j[keep], 0]
    ours, theirs = C[keep], cf[j[keep], 1:4] * 1000
    (Mo, ok1), (Mc, ok2) = mocap_at(tk), mocap_at(tc)
    blk = np.floor(tk / 10).astype(int) % 2
    out = {}
    for fit in (0, 1):
        F, S = (blk == fit) & ok1 & ok2, (blk != fit) & ok1 & ok2
        row = []
        for X, M in ((ours, Mo), (theirs, Mc)):
            R, b = _kabsch(X[F], M[F])
            e = np.linalg.norm(X[S] @ R.T + b - M[S], axis=1)
            row.append((float(np.median(e)), float(np.percentile(e, 95))))
        out["even" if fit == 0 else "odd"] = (row[0], row[1], int(S.sum()))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("folder", ["lh1_crossingBeam_flight_00", "lh1_crossingBeam_flight_01"])
def test_lighthouse_triangulation_from_the_command_line(tmp_path, capsys, folder):
    if not (DATA / folder / "angles.csv").exists():
        pytest.skip("lighthouse-lh1 data not present")
    from psdcal.measure.angles_locate import (
        load_angle_sensors,
        sensors_entry_xfwd,
        triangulate_table,
    )
    from psdcal.measure.angles_table import align_to_sensor, read_angles

    g = stations_file(tmp_path / "stations.json")
    # the converter here and the module's agree
    for e, b in zip(json.loads((tmp_path / "stations.json").read_text())["sensors"], g["base_stations"]):
        U, _, Vt = np.linalg.svd(np.array(b["rotation_bs_to_world"]))
        mine = sensors_entry_xfwd(e["name"], U @ Vt, np.array(b["origin_m"]) * 1000)
        np.testing.assert_allclose(mine["tvec_mm"], e["tvec_mm"], atol=1e-6)
        np.testing.assert_allclose(Rotation.from_rotvec(mine["rvec"]).as_matrix(),
                                   Rotation.from_rotvec(e["rvec"]).as_matrix(), atol=1e-12)
    out = tmp_path / "xyz.csv"
    assert main(["locate", "--angles", str(DATA / folder / "angles.csv"), "--sensors", str(tmp_path / "stations.json"),
                 "--convention", "lighthouse", "--sensor-column", "station", "--emitter-column", "sensor",
                 "--sigma-rad", "7e-5", "--align-to", "1", "-o", str(out)]) == 0
    printed = capsys.readouterr()
    assert "locate_angles_chi2" in printed.err  # 70 urad is the noise at rest: in flight the rays disagree more
    rows = read_csv(out)
    # equal to the Python path
    tab = align_to_sensor(read_angles(DATA / folder / "angles.csv", "lighthouse", sigma_rad=7e-5,
                                      columns={"sensor": "station", "emitter": "sensor"}), "1", max_gap_s=0.05)
    res = triangulate_table(tab, load_angle_sensors(tmp_path / "stations.json"))
    assert len(rows) == len(res) > 2500
    got = np.array([[float(r[c]) for c in ("t_s", "X_mm", "Y_mm", "Z_mm", "sigma_X_mm")] for r in rows])
    want = np.column_stack([res.t_s, res.p_w_mm, res.sigma_p_mm[:, 0]])
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    # the photodiodes are where the deck says: 15 mm and 30 mm apart, median over the steps
    by = {}
    for r in rows:
        by.setdefault(r["t_s"], {})[r["sensor"] if "sensor" in r else r["emitter"]] = np.array(
            [float(r[c]) for c in ("X_mm", "Y_mm", "Z_mm")])
    full = [v for v in by.values() if len(v) == 4]
    assert np.median([np.linalg.norm(v["0"] - v["1"]) for v in full]) == pytest.approx(15.0, abs=1.5)
    assert np.median([np.linalg.norm(v["0"] - v["2"]) for v in full]) == pytest.approx(30.0, abs=1.5)
    # against motion capture, the same steps as the Crazyflie's own estimate (same station poses)
    sc = score_against_mocap(folder, rows)
    for half, ((med, p95), (cf_med, cf_p95), n) in sc.items():
        print(f"{folder} fitted on {half}: {n} steps; psdcal median {med:.2f} p95 {p95:.2f} mm; "
              f"Crazyflie median {cf_med:.2f} p95 {cf_p95:.2f} mm")
        assert n > 250
        assert 0.8 < med / cf_med < 1.25  # the same geometry and rays: the same accuracy
        assert med < 30.0
    # paired as the firmware pairs them (station 0's latest frame at or before each station-1 frame, no
    # interpolation), the weighted triangulation scores as the Crazyflie's midpoints within 5 %
    raw = read_angles(DATA / folder / "angles.csv", "lighthouse", sigma_rad=7e-5,
                      columns={"sensor": "station", "emitter": "sensor"})
    from _bench import load_benchmark

    held = load_benchmark("study_angles_lighthouse").latest_frame(raw)  # the study's pairing (one copy)
    res_h = triangulate_table(held, load_angle_sensors(tmp_path / "stations.json"))
    cols = res_h.columns()
    rows_h = [{k: cols[k][i] for k in ("t_s", "X_mm", "Y_mm", "Z_mm")} for i in range(len(res_h))]
    for half, ((med, p95), (cf_med, _), n) in score_against_mocap(folder, rows_h).items():
        print(f"{folder} fitted on {half}, latest-frame pairing: psdcal median {med:.2f} p95 {p95:.2f} mm")
        assert abs(med / cf_med - 1) < 0.05


def test_pose_of_psdcal_single_sensor_angles_needs_no_calibration(tmp_path):
    """The older angles input of `pose` (alpha_x_deg... without a sensor column) works without --calib too."""
    rng = np.random.default_rng(8)
    (_, R, c), = make_room(rng, 1)
    known = _known_emitters(rng, 6)
    _write_emitters(tmp_path / "known.csv", known)
    lines = ["t_s,emitter,alpha_x_deg,alpha_y_deg,sigma_alpha_x_deg,sigma_alpha_y_deg"]
    for e, p in known.items():
        a = angles_of((p - c) @ R.T, "psdcal") + rng.normal(0, 2e-4, 2)
        lines.append(f"0,{e},{math.degrees(a[0]):.12g},{math.degrees(a[1]):.12g},{math.degrees(2e-4):.6g},"
                     f"{math.degrees(2e-4):.6g}")
    (tmp_path / "alpha.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "e.json"
    assert main(["pose", str(tmp_path / "alpha.csv"), "--emitters", str(tmp_path / "known.csv"), "-o", str(out)]) == 0
    entry = json.loads(out.read_text())
    assert "calib" not in entry
    assert _pose_nees(entry, R, c) < chi2_dist.ppf(0.9999, 6)


def test_pose_warns_of_an_emitter_that_moved(tmp_path, capsys):
    rng = np.random.default_rng(9)
    sensors = make_room(rng, 1)
    known = _known_emitters(rng, 6)
    _write_emitters(tmp_path / "known.csv", known)
    P = np.repeat(np.array([list(known.values())]), 6, 0)
    P[:, 2] += np.arange(6)[:, None] * np.array([30.0, 0, 0])  # k2 slides 30 mm per step
    rows = observe(rng, sensors, P, np.arange(6) * 0.1, list(known), "azel", 1e-4)
    write_table(tmp_path / "a.csv", rows, "azel", 1e-4)
    assert main(["pose", str(tmp_path / "a.csv"), "--emitters", str(tmp_path / "known.csv"), "-o",
                 str(tmp_path / "e.json")]) == 0
    warn = json.loads((tmp_path / "e.json").read_text())["pose"]["warnings"]
    assert any("'k2'" in w and "scatter" in w for w in warn) and not any("'k1'" in w for w in warn)
    assert "'k2'" in capsys.readouterr().err
