"""Calibration from known directions (rotation stage, issue 13.2).

Truths: the stage convention in closed form (a centred distortion-free sensor
sees az at x = f tan(az)); noiseless sweeps recover every parameter to 1e-9;
the analytic Jacobian equals central differences; a Monte Carlo of noisy
sweeps has the Cramer-Rao spread (sigma^2 (J^T J)^-1 at the truth); angles
predicted for held-out directions lie within their stated 3 sigma.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from psdcal.calibration.core import CalibrationResult, recalibrate
from psdcal.calibration.directions import (
    DirectionsModel,
    calibrate_directions,
    direction_warnings,
    predict_directions,
    read_directions,
    simulate_sweep,
    stage_directions,
    sweep_grid,
    write_directions,
)
from psdcal.cli import main
from psdcal.errors import DegenerateViewsError, InputError
from psdcal.model.params import Distortion, Intrinsics, ModelSpec
from psdcal.model.projection import r_from_R

INTR = Intrinsics(8.0, 0.5, -0.7)
DIST = Distortion(k1=1e-2, k2=3e-5, p1=2e-4, p2=-1e-4)
RVEC = np.array([0.02, -0.03, 0.1])


def _truth_values(intr=INTR, dist=DIST, rvec=RVEC, offset=(0.0, 0.0, 0.0), gains=(1, 1, 1, 1)):
    return {"f_mm": intr.f_mm, "cx_mm": intr.cx_mm, "cy_mm": intr.cy_mm, "skew": intr.skew, "fy_mm": intr.fy,
            **dist.to_dict(), "g_x2": gains[1], "g_y1": gains[2], "g_y2": gains[3],
            **dict(zip(("stage_rx", "stage_ry", "stage_rz"), rvec)),
            **dict(zip(("offset_x_mm", "offset_y_mm", "offset_z_mm"), offset))}


def test_stage_convention_closed_form():
    u = stage_directions([30.0, 0.0, 90.0], [0.0, 20.0, 0.0])
    np.testing.assert_allclose(u, [[0.5, 0, np.sqrt(3) / 2], [0, np.sin(np.radians(20)), np.cos(np.radians(20))], [1, 0, 0]],
                               atol=1e-15)
    d = simulate_sweep(Intrinsics(8.0), Distortion(), np.zeros(3), [10.0, 0.0, 10.0], [0.0, -15.0, 15.0])
    t10, t15 = np.tan(np.radians(10)), np.tan(np.radians(15))
    np.testing.assert_allclose(d[0], [8 * t10, 0.0], atol=1e-13)
    np.testing.assert_allclose(d[1], [0.0, -8 * t15], atol=1e-13)
    # (az, el) = (10, 15): u = (cos el sin az, sin el, cos el cos az) -> x = f tan az, y = f tan el / cos az
    np.testing.assert_allclose(d[2], [8 * t10, 8 * t15 / np.cos(np.radians(10))], atol=1e-13)


def test_r_from_R_inverts_rodrigues_as_the_stage_start_needs():
    from psdcal.calibration._refine import rodrigues_batch

    rng = np.random.default_rng(0)
    for r in [*rng.normal(size=(20, 3)), np.zeros(3), np.array([0, 0, np.pi - 1e-9])]:
        r = r if np.linalg.norm(r) < np.pi else r / np.linalg.norm(r) * (np.pi - 0.1)
        R = rodrigues_batch(r[None], derivatives=False)[0][0]
        np.testing.assert_allclose(r_from_R(R), r, atol=1e-7)


@pytest.mark.parametrize("case", ["infinity", "finite", "aspect_psd"])
def test_noiseless_recovery(case):
    az, el = sweep_grid(25, 25, 9, 9)
    kw, intr, dist, off = {}, INTR, DIST, (0.0, 0.0, 0.0)
    if case == "finite":
        off = (3.0, -2.0, 15.0)
        kw = {"distance_mm": 300.0}
    if case == "aspect_psd":
        intr = Intrinsics(8.0, 0.5, -0.7, fy_mm=8.05)
        dist = Distortion(k1=1e-2, k2=3e-5, p1=2e-4, p2=-1e-4, l1=-1.3e-3)
        kw = {"aspect": True, "psd_radial": 1}
    d = simulate_sweep(intr, dist, RVEC, az, el, distance_mm=kw.get("distance_mm"), offset_mm=off)
    res = calibrate_directions(az, el, d, **kw)
    truth = _truth_values(intr, dist, RVEC, off)
    for n in res.param_names:
        assert res.parameter(n) == pytest.approx(truth[n], rel=1e-9, abs=1e-12), n
    np.testing.assert_allclose(res.rvecs[0], RVEC, rtol=1e-9, atol=1e-12)
    if case == "finite":
        np.testing.assert_allclose(res.problem["stage"]["offset_mm"], off, rtol=1e-8, atol=1e-9)
        assert all(v is not None and v > 0 for v in res.problem["stage"]["std"].values())
    assert res.rms_mm < 1e-11 and res.converged


def test_noiseless_recovery_gains_from_amplitudes():
    az, el = sweep_grid(25, 25, 9, 9)
    g = np.array([1.0, 1.03, 0.98, 1.01])
    d = simulate_sweep(INTR, DIST, RVEC, az, el, gains=g)
    res = calibrate_directions(az, el, d, fit_gains=True)
    np.testing.assert_allclose(res.gains, g, rtol=1e-9)
    assert res.intrinsics.f_mm == pytest.approx(8.0, rel=1e-9)


def test_jacobian_matches_central_differences():
    az, el = sweep_grid(20, 20, 5, 5)
    truth = _truth_values(offset=(1.0, -2.0, 5.0), gains=(1, 1.02, 0.99, 1.01))
    spec = ModelSpec(radial=3, tangential=True, psd_radial=2, skew=True, aspect=True, fit_gains=True)
    truth.update(k3=1e-7, l1=-1e-3, l2=2e-6, skew=0.01, fy_mm=8.02)
    d = simulate_sweep(INTR, DIST, RVEC, az, el)
    m = DirectionsModel(stage_directions(az, el), d, spec, truth, distance_mm=400.0)
    z = m.pack(truth)
    J = m.jacobian(z)
    Jn = np.zeros_like(J)
    for k in range(z.size):
        h = 1e-6 * max(abs(z[k]), 1e-3)
        zp, zm = z.copy(), z.copy()
        zp[k] += h
        zm[k] -= h
        Jn[:, k] = (m.predict(zp) - m.predict(zm)).ravel() / (2 * h)
    scale = np.abs(J).max(axis=0)
    assert np.max(np.abs(J - Jn) / scale) < 1e-6


def test_monte_carlo_at_the_cramer_rao_bound():
    """300 noisy 5 x 5 sweeps: the spread of every estimate within 10 % of the CRB."""
    az, el = sweep_grid(20, 20, 5, 5)
    noise = 0.002
    d0 = simulate_sweep(INTR, DIST, RVEC, az, el)
    truth = _truth_values()
    m = DirectionsModel(stage_directions(az, el), d0, ModelSpec(), truth)
    J = m.jacobian(m.pack(truth))
    crb = np.sqrt(np.diag(noise**2 * np.linalg.inv(J.T @ J)))
    rng = np.random.default_rng(2024)
    est = []
    for _ in range(300):
        r = calibrate_directions(az, el, d0 + rng.normal(0.0, noise, d0.shape))
        assert r.converged
        est.append([r.parameter(n) for n in r.param_names] + list(r.rvecs[0]))
    est = np.array(est)
    assert tuple(r.param_names) + ("stage_rx", "stage_ry", "stage_rz") == m.names
    ratio = est.std(axis=0, ddof=1) / crb
    assert np.all(np.abs(ratio - 1) < 0.10), dict(zip(m.names, ratio.round(3)))
    bias = (est.mean(axis=0) - m.pack(truth)) / crb
    assert np.all(np.abs(bias) < 0.25)


def test_held_out_directions_within_three_sigma():
    az, el = sweep_grid(25, 25, 9, 9)
    rng = np.random.default_rng(7)
    noise = 0.003
    res = calibrate_directions(az, el, simulate_sweep(INTR, DIST, RVEC, az, el, noise_mm=noise, rng=rng))
    az_h = rng.uniform(-22, 22, 200)
    el_h = rng.uniform(-22, 22, 200)
    d_h = simulate_sweep(INTR, DIST, RVEC, az_h, el_h, noise_mm=noise, rng=rng)
    ang, cov = predict_directions(res.to_dict(), d_h)
    err = ang - np.stack([az_h, el_h], axis=1)
    sd = np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], axis=1))
    z = err / sd
    assert np.mean(np.abs(z) < 3) >= 0.98 and np.max(np.abs(z)) < 5
    assert 0.7 < np.std(z) < 1.3  # the stated sigma is honest, neither too small nor too large
    # the uncertainty is mostly the spot noise: predicted angles are good to ~ noise / f
    assert np.median(sd) < 3 * np.degrees(noise / 8.0)


def test_finite_distance_held_out():
    """A source 150 mm from the axes, the lens 10, -5, 20 mm off them (z measured and fixed)."""
    az, el = sweep_grid(25, 25, 7, 7)
    off = (10.0, -5.0, 20.0)
    rng = np.random.default_rng(3)
    d = simulate_sweep(INTR, DIST, RVEC, az, el, distance_mm=150.0, offset_mm=off, noise_mm=0.002, rng=rng)
    res = calibrate_directions(az, el, d, distance_mm=150.0, fix={"offset_z_mm": 20.0})
    st = res.problem["stage"]
    for k, n in enumerate(("offset_x_mm", "offset_y_mm")):
        assert abs(st["offset_mm"][k] - off[k]) < 3 * st["std"][n]
    assert abs(res.intrinsics.f_mm - 8.0) < 3 * res.std["f_mm"]
    az_h, el_h = rng.uniform(-20, 20, 100), rng.uniform(-20, 20, 100)
    d_h = simulate_sweep(INTR, DIST, RVEC, az_h, el_h, distance_mm=150.0, offset_mm=off, noise_mm=0.002, rng=rng)
    ang, cov = predict_directions(res, d_h)
    z = (ang - np.stack([az_h, el_h], 1)) / np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], 1))
    assert np.mean(np.abs(z) < 3) >= 0.97
    # the offset along the boresight trades against f (tan a' = tan a (1 + t_z / D) to first order):
    # free, it is found with an honest, large error and f with it
    free_z = calibrate_directions(az, el, d, distance_mm=150.0)
    assert free_z.problem["stage"]["std"]["offset_z_mm"] > 5.0 and free_z.std["f_mm"] > 50 * res.std["f_mm"]
    warn = direction_warnings(free_z)
    assert any("f_mm" in w and "offset_z_mm" in w for w in warn) and direction_warnings(res) == []
    assert abs(free_z.intrinsics.f_mm - 8.0) < 3 * free_z.std["f_mm"]
    # ignoring the offsets (a source at infinity) leaves residuals far above the noise
    res_inf = calibrate_directions(az, el, d)
    assert res_inf.rms_mm > 5 * res.rms_mm


def test_fix_and_prior_in_direction_calibration():
    az, el = sweep_grid(20, 20, 7, 7)
    d = simulate_sweep(INTR, DIST, RVEC, az, el, noise_mm=0.002, rng=5)
    free = calibrate_directions(az, el, d)
    fixed = calibrate_directions(az, el, d, fix={"f_mm": 8.0, "stage_rz": 0.1})
    assert fixed.intrinsics.f_mm == 8.0 and fixed.std["f_mm"] is None
    assert fixed.rvecs[0, 2] == 0.1 and fixed.problem["stage"]["std"]["stage_rz"] is None
    sf = free.std["f_mm"]
    pri = calibrate_directions(az, el, d, priors={"f_mm": (free.intrinsics.f_mm, sf)})
    assert pri.std["f_mm"] < sf
    n = len(free.problem["fit"]["names"])
    C_free = np.array(free.problem["fit"]["covariance"])
    P = np.zeros((n, n))
    P[0, 0] = 1 / sf**2
    s2r = pri.sigma_mm**2 / free.sigma_mm**2
    expect = np.linalg.inv(np.linalg.inv(C_free) / s2r + P)
    np.testing.assert_allclose(np.array(pri.problem["fit"]["covariance"]), expect, rtol=1e-5,
                               atol=1e-9 * np.max(np.abs(np.diag(expect))))
    # a prior on the stage rotation (the mount's drawing): the same information sum
    i = free.problem["fit"]["names"].index("stage_rx")
    sr = free.problem["stage"]["std"]["stage_rx"]
    pr = calibrate_directions(az, el, d, priors={"stage_rx": (free.rvecs[0, 0], sr)})
    P = np.zeros((n, n))
    P[i, i] = 1 / sr**2
    s2r = pr.sigma_mm**2 / free.sigma_mm**2
    expect = np.linalg.inv(np.linalg.inv(C_free) / s2r + P)
    np.testing.assert_allclose(np.array(pr.problem["fit"]["covariance"]), expect, rtol=1e-5,
                               atol=1e-9 * np.max(np.abs(np.diag(expect))))
    assert pr.std["cy_mm"] < 0.9 * free.std["cy_mm"]  # a rotation about x shifts the spots in y, like cy: both sharpen


def test_json_round_trip_recalibrate_and_bad_sweeps(tmp_path):
    az, el = sweep_grid(20, 20, 7, 7)
    d = simulate_sweep(INTR, DIST, RVEC, az, el, noise_mm=0.002, rng=9)
    res = calibrate_directions(az, el, d)
    dd = json.loads(json.dumps(res.to_dict()))
    assert dd["extrinsics"][0]["image_id"] == "stage" and dd["problem"]["kind"] == "directions"
    back = CalibrationResult.from_dict(dd)
    assert back.intrinsics == res.intrinsics
    again = recalibrate(dd)
    for n in res.param_names:
        assert again.parameter(n) == pytest.approx(res.parameter(n), rel=1e-10, abs=1e-15)
    with pytest.raises(DegenerateViewsError, match="both"):
        calibrate_directions(np.linspace(-20, 20, 12), np.zeros(12), d[:12])
    with pytest.raises(InputError):
        calibrate_directions(az, el, d[:-1])


def test_cli_calibrate_directions_and_use(tmp_path, capsys):
    az, el = sweep_grid(20, 20, 7, 7)
    d = simulate_sweep(INTR, DIST, RVEC, az, el, noise_mm=0.002, rng=1)
    write_directions(tmp_path / "sweep.csv", az, el, d)
    f = read_directions(tmp_path / "sweep.csv")
    np.testing.assert_allclose(f.points_mm, d, atol=1e-11)
    cal = tmp_path / "cal.json"
    code = main(["calibrate-directions", str(tmp_path / "sweep.csv"), "-o", str(cal), "--fix", "k2=3e-5"])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "stage rotation" in out.out
    c = json.loads(cal.read_text())
    assert abs(c["intrinsics"]["f_mm"] - 8.0) < 5 * c["std"]["f_mm"] and c["std"]["k2"] is None
    (tmp_path / "pts.csv").write_text("x_mm,y_mm\n0.1,0.2\n1.0,-1.0\n")
    assert main(["aoa", str(tmp_path / "pts.csv"), "--calib", str(cal), "-o", str(tmp_path / "a.csv")]) == 0
    assert main(["report", str(cal), "-o", str(tmp_path / "r.html")]) == 0
    # bad input: one line naming file, line and field; nothing written
    bad = tmp_path / "bad.csv"
    bad.write_text("az_deg,el_deg,x_mm,y_mm\n0,0,0.1,0.1\n1,95,0.1,0.2\n")
    capsys.readouterr()
    code = main(["calibrate-directions", str(bad), "-o", str(tmp_path / "x.json")])
    err = capsys.readouterr().err
    assert code == 2 and "bad.csv:3" in err and "el_deg" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.json").exists()


def test_cli_amplitudes_with_fitted_gains(tmp_path, capsys):
    """Raw amplitudes through unequal channel gains: --fit-gains recovers them."""
    from psdcal.model.readout import photocurrents

    az, el = sweep_grid(20, 20, 9, 9)
    g = np.array([1.0, 1.03, 0.98, 1.01])
    d = simulate_sweep(INTR, DIST, RVEC, az, el)
    amps = photocurrents(d) * g
    rows = ["az_deg,el_deg,vx1,vx2,vy1,vy2"] + [f"{a:.10g},{e:.10g}," + ",".join(f"{v:.15g}" for v in amp)
                                                for a, e, amp in zip(az, el, amps)]
    (tmp_path / "amps.csv").write_text("\n".join(rows) + "\n")
    cal = tmp_path / "cal.json"
    code = main(["calibrate-directions", str(tmp_path / "amps.csv"), "--fit-gains", "-o", str(cal), "-q"])
    assert code == 0, capsys.readouterr().err
    c = json.loads(cal.read_text())
    np.testing.assert_allclose(c["gains"], g, rtol=1e-8)
    assert c["intrinsics"]["f_mm"] == pytest.approx(8.0, rel=1e-8)
    # points instead of amplitudes with --fit-gains: refused
    write_directions(tmp_path / "pts.csv", az, el, d)
    code = main(["calibrate-directions", str(tmp_path / "pts.csv"), "--fit-gains", "-o", str(tmp_path / "x.json")])
    assert code == 2 and "amplitudes" in capsys.readouterr().err


# -- the verdict on a direction calibration ------------------------------------------------
def _sweep(rng, dist, noise_mm=2e-3, gains=None):
    from psdcal.calibration import directions as D
    from psdcal.model.params import Intrinsics

    az, el = D.sweep_grid(20, 20, 9, 9)
    pts = D.simulate_sweep(Intrinsics(8.0, 0.5, -0.7, 0.0), dist, [0.01, -0.02, 0.03], az, el, noise_mm=noise_mm,
                           rng=rng, gains=gains)
    return az, el, pts


def test_direction_verdict_false_alarms_and_detection():
    """Correct fits are 'good' (design false-alarm rate 1e-3 per check); a missing k2 and ignored
    channel gains are caught by the residual-structure check, which names the structure."""
    from psdcal.calibration import directions as D
    from psdcal.model.params import Distortion

    rng = np.random.default_rng(11)
    lens = Distortion(k1=1e-2, k2=3e-5)
    bad = 0
    for _ in range(60):
        az, el, pts = _sweep(rng, lens)
        r = D.calibrate_directions(az, el, pts, radial=2, tangential=False, noise_mm=2e-3)
        bad += r.verdict["verdict"] != "good"
    assert bad <= 1
    # a lens with a strong k2 fitted with k1 only: systematic residuals
    for _ in range(10):
        az, el, pts = _sweep(rng, Distortion(k1=1e-2, k2=3e-4))
        r = D.calibrate_directions(az, el, pts, radial=1, tangential=False)
        failed = {c["name"] for c in r.verdict["checks"] if c["passed"] is False}
        assert r.verdict["verdict"] != "good" and "structure" in failed
    # ignored gain imbalance (R 1 %, C 15 % class): a projective misfit
    for _ in range(10):
        az, el, pts = _sweep(rng, lens, gains=[1.0, 1.03, 0.97, 1.02])
        r = D.calibrate_directions(az, el, pts, radial=2, tangential=False)
        assert r.verdict["verdict"] != "good"


def test_direction_verdict_noise_check_uses_the_stated_noise():
    from psdcal.calibration import directions as D
    from psdcal.model.params import Distortion

    rng = np.random.default_rng(5)
    az, el, pts = _sweep(rng, Distortion(k1=1e-2, k2=3e-5), noise_mm=6e-3)
    ok = D.calibrate_directions(az, el, pts, radial=2, tangential=False, noise_mm=6e-3)
    low = D.calibrate_directions(az, el, pts, radial=2, tangential=False, noise_mm=2e-3)
    noise = {c["name"]: c for c in low.verdict["checks"]}["noise"]
    assert ok.verdict["verdict"] == "good"
    assert noise["passed"] is False and low.verdict["verdict"] != "good"
