"""`psdcal gains` (issue 13.3): bench gains, their covariance, and their use in locate/aoa."""
from __future__ import annotations

import json

import numpy as np
import pytest

from _locate_sim import calib_dict, signals, spot_for_angles
from psdcal.calibration.bench import fit_bench, load_gains, with_gains
from psdcal.calibration.gains import calibration_spots
from psdcal.cli import main
from psdcal.errors import InputError
from psdcal.measure.aoa import angles_from_amplitudes
from psdcal.measure.sensor_model import SensorModel
from psdcal.model.readout import photocurrents

G_TRUE = np.array([1.0, 1.04, 0.96, 1.02])
NOISE = 1e-3  # per channel, total photocurrent 1


def bench(rng, gains=G_TRUE, spots=None, noise=NOISE):
    spots = calibration_spots() if spots is None else spots
    a = photocurrents(spots, 1.0) * gains
    return spots, a + noise * rng.standard_normal(a.shape)


def test_bench_gains_recover_the_truth_to_their_stated_std():
    """Seeded Monte Carlo (150 benches): unbiased, scatter equal to the stated std, z-scores ~ N(0, 1)."""
    rng = np.random.default_rng(1)
    est, std = [], []
    for _ in range(150):
        gc = fit_bench(*bench(rng))
        est.append(gc.gains[1:])
        std.append(gc.std)
    est, std = np.array(est), np.array(std)
    err = est - G_TRUE[1:]
    stated = np.median(std, axis=0)
    assert np.all(np.abs(err.mean(0)) < 3 * stated / np.sqrt(len(est)))
    np.testing.assert_allclose(err.std(0, ddof=1), stated, rtol=0.2)  # 3.5 x the 5.8 % sampling spread
    z = err / std
    assert 0.92 < np.mean(np.abs(z) < 2) < 0.98


def angle_errors(model, amplitudes, alpha_true_deg):
    res = angles_from_amplitudes(amplitudes, model, np.full(amplitudes.shape, NOISE**2))
    return np.degrees(res.alpha_rad) - alpha_true_deg, np.degrees(res.sigma_alpha_rad)


def test_angles_with_bench_gains_on_imbalanced_electronics_match_balanced_ones():
    rng = np.random.default_rng(2)
    m = SensorModel.from_dict(calib_dict())
    g = np.linspace(-15, 15, 7)
    alpha = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    d = spot_for_angles(m, np.radians(alpha))
    reps = 20
    e_bal, e_raw, e_fix = [], [], []
    gc = fit_bench(*bench(np.random.default_rng(3), noise=2e-4))  # a bench measurement, averaged longer
    fixed = with_gains(m, gc.gains, gc.covariance)
    for _ in range(reps):
        noise = NOISE * rng.standard_normal((len(d), 4))
        e_bal.append(angle_errors(m, photocurrents(d, 1.0) + noise, alpha)[0])
        e_raw.append(angle_errors(m, photocurrents(d, 1.0) * G_TRUE + noise, alpha)[0])
        e, s = angle_errors(fixed, photocurrents(d, 1.0) * G_TRUE + noise, alpha)
        e_fix.append(e)
    rms = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    assert rms(e_fix) <= 1.5 * rms(e_bal)
    assert rms(e_raw) > 5 * rms(e_bal)  # without the gains the imbalance dominates
    # the gains' covariance is in the sigma: larger than without it, and the errors are within 3 sigma
    clean = photocurrents(d, 1.0) * G_TRUE
    _, s_cov = angle_errors(fixed, clean, alpha)
    _, s_nocov = angle_errors(with_gains(m, gc.gains, np.zeros((3, 3))), clean, alpha)
    assert np.all(s_cov >= s_nocov - 1e-15) and np.any(s_cov > s_nocov * (1 + 1e-6))
    assert np.mean(np.abs(np.array(e_fix)) < 3 * s) > 0.98


def write_bench(tmp_path, spots, amps, carriers=None):
    pos = tmp_path / "spots.csv"
    pos.write_text("point_id,x_mm,y_mm\n" + "".join(f"p{i},{float(x)!r},{float(y)!r}\n" for i, (x, y) in enumerate(spots)))
    amp = tmp_path / "bench.csv"
    head = "point_id,vx1,vx2,vy1,vy2" + (",carrier_hz" if carriers is not None else "")
    lines = [head]
    for k, block in enumerate(amps):
        for i, a in enumerate(block):
            extra = f",{carriers[k]!r}" if carriers is not None else ""
            lines.append(f"p{i}," + ",".join(repr(float(v)) for v in a) + extra)
    amp.write_text("\n".join(lines) + "\n")
    return pos, amp


def test_cli_gains_and_aoa_with_gains(tmp_path, capsys):
    rng = np.random.default_rng(4)
    spots, a = bench(rng)
    pos, amp = write_bench(tmp_path, spots, [a])
    out = tmp_path / "gains.json"
    assert main(["gains", str(amp), "--positions", str(pos), "-o", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["kind"] == "psdcal-gains" and doc["covariance"]["names"] == ["g_x2", "g_y1", "g_y2"]
    assert np.all(np.abs(np.array(doc["gains"][1:]) - G_TRUE[1:]) < 4 * np.array(list(doc["std"].values())))
    g, cov = load_gains(out)
    assert cov.shape == (3, 3) and g[0] == 1.0
    # aoa on amplitudes read through the imbalanced electronics
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps(calib_dict()))
    m = SensorModel.load(calib)
    alpha = np.array([[10.0, -5.0], [-8.0, 12.0], [3.0, 3.0]])
    d = spot_for_angles(m, np.radians(alpha))
    amps = photocurrents(d, 1.0) * G_TRUE
    pts = tmp_path / "pts.csv"
    pts.write_text("point_id,vx1,vx2,vy1,vy2\n" + "".join(f"q{i}," + ",".join(map(repr, map(float, r))) + "\n"
                                                         for i, r in enumerate(amps)))
    capsys.readouterr()
    for gains_opt, tol in (([], None), (["--gains", str(out)], 0.05)):
        o = tmp_path / f"aoa{len(gains_opt)}.csv"
        assert main(["aoa", str(pts), "--calib", str(calib), *gains_opt, "-o", str(o)]) == 0
        r = np.genfromtxt(o, delimiter=",", names=True, dtype=None, encoding="utf-8")
        err = np.abs(np.c_[r["alpha_x_deg"], r["alpha_y_deg"]] - alpha)
        if tol is None:
            assert err.max() > 0.5  # the imbalance biases the angles by degrees
        else:
            assert err.max() < tol
            assert np.all(err < 4 * np.c_[r["sigma_alpha_x_deg"], r["sigma_alpha_y_deg"]])


def test_gains_per_carrier_and_locate_with_them(tmp_path, capsys):
    rng = np.random.default_rng(5)
    g1 = G_TRUE
    g2 = np.array([1.0, 0.97, 1.05, 0.99])  # the TIA's gains at the second carrier
    spots = calibration_spots()
    a1 = bench(rng, g1, spots)[1]
    a2 = bench(rng, g2, spots)[1]
    pos, amp = write_bench(tmp_path, spots, [a1, a2], carriers=[1000.0, 1300.0])
    out = tmp_path / "gains.json"
    assert main(["gains", str(amp), "--positions", str(pos), "-o", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert [e["carrier_hz"] for e in doc["per_carrier"]] == [1000.0, 1300.0]
    for f, gt in ((1000.0, g1), (1300.0, g2)):
        g, cov = load_gains(out, f)
        assert np.all(np.abs(g[1:] - gt[1:]) < 4 * np.sqrt(np.diag(cov)))
    with pytest.raises(InputError, match="no gains for the 2000 Hz"):
        load_gains(out, 2000.0)
    # a recording of two emitters (FDM) through carrier-dependent gains
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps(calib_dict()))
    m = SensorModel.load(calib)
    alpha = np.array([[10.0, -3.0], [-7.0, 12.0]])
    d = spot_for_angles(m, np.radians(alpha))
    rate = 125_000.0
    x = signals(rate, 62_500, [(photocurrents(d[0], 1.0) * g1, 1000.0, 0.0), (photocurrents(d[1], 1.0) * g2, 1300.0, 1.0)],
                noise=2e-4)
    np.save(tmp_path / "rec.npy", x.T)
    res = {}
    for opt in ([], ["--gains", str(out)]):
        o = tmp_path / f"loc{len(opt)}.csv"
        rc = main(["locate", str(tmp_path / "rec.npy"), "--calib", str(calib), "--rate-hz", str(rate),
                   "--carrier-hz", "1000", "--carrier-hz", "1300", "--window-s", "0.02", *opt, "-o", str(o)])
        assert rc == 0, capsys.readouterr().err
        r = np.genfromtxt(o, delimiter=",", names=True, dtype=None, encoding="utf-8")
        res[len(opt)] = r
    r = res[2]
    for k, name in enumerate(("1000Hz", "1300Hz")):
        sel = r["emitter"] == name
        err = np.abs(np.c_[r["alpha_x_deg"][sel], r["alpha_y_deg"][sel]] - alpha[k])
        assert np.all(err < 4 * np.c_[r["sigma_alpha_x_deg"][sel], r["sigma_alpha_y_deg"][sel]])
        sel0 = res[0]["emitter"] == name
        err0 = np.abs(np.c_[res[0]["alpha_x_deg"][sel0], res[0]["alpha_y_deg"][sel0]] - alpha[k])
        assert err0.mean() > 10 * err.mean()


def test_calibrate_with_bench_gains(tmp_path, capsys):
    """Template views read through imbalanced channels: --gains gives back the optical centre."""
    from psdcal.model.readout import gain_map

    sim = tmp_path / "sim"
    assert main(["simulate", "--images", "8", "--noise-mm", "0.001", "--seed", "2", "-o", str(sim)]) == 0
    truth = json.loads((sim / "truth.json").read_text())
    lines = (sim / "points.csv").read_text().splitlines()
    rows = [ln.split(",") for ln in lines[1:]]
    xy = np.array([[float(r[2]), float(r[3])] for r in rows])
    raw = gain_map(xy, G_TRUE)
    (tmp_path / "raw.csv").write_text(lines[0] + "\n" + "".join(
        f"{r[0]},{r[1]},{p[0]!r},{p[1]!r}\n" for r, p in zip(rows, raw.tolist())))
    spots, a = bench(np.random.default_rng(6), noise=2e-4)
    pos, amp = write_bench(tmp_path, spots, [a])
    gains = tmp_path / "gains.json"
    assert main(["gains", str(amp), "--positions", str(pos), "-o", str(gains)]) == 0
    out = {}
    for opt in ([], ["--gains", str(gains)]):
        o = tmp_path / f"calib{len(opt)}.json"
        assert main(["calibrate", str(tmp_path / "raw.csv"), "-t", str(sim / "template.csv"), "--psd-radial", "1",
                     *opt, "-q", "-o", str(o)]) == 0, capsys.readouterr().err
        out[len(opt)] = json.loads(o.read_text())
    c_true = np.array([truth["intrinsics"]["cx_mm"], truth["intrinsics"]["cy_mm"]])
    err = {k: np.hypot(*(np.array([d["intrinsics"]["cx_mm"], d["intrinsics"]["cy_mm"]]) - c_true))
           for k, d in out.items()}
    assert err[2] < 0.1 * err[0]
    np.testing.assert_allclose(out[2]["gains"], load_gains(gains)[0], rtol=1e-12)


def test_bench_gains_as_a_prior_combine_with_the_template_views(tmp_path, capsys):
    """`calibrate --fit-gains --prior-file gains.json` (issue 13.4 with 13.3): the bench's gains and their
    covariance combine with what the template views say; the combined std is below both, the estimate
    stays within its std of the truth, and the covariance equals the closed-form combination of the
    two Gaussian estimates (information adds up)."""
    sim = tmp_path / "sim"
    assert main(["simulate", "--images", "10", "--noise-mm", "0.002", "--seed", "4", "-o", str(sim)]) == 0
    lines = (sim / "points.csv").read_text().splitlines()
    rows = [ln.split(",") for ln in lines[1:]]
    amps = photocurrents(np.array([[float(r[2]), float(r[3])] for r in rows]), 1.0) * G_TRUE  # through the channels
    (tmp_path / "raw.csv").write_text("image_id,point_id,vx1,vx2,vy1,vy2\n" + "".join(
        f"{r[0]},{r[1]}," + ",".join(repr(float(v)) for v in a) + "\n" for r, a in zip(rows, amps)))
    spots, a = bench(np.random.default_rng(8), noise=3e-3)
    pos, amp = write_bench(tmp_path, spots, [a])
    gains = tmp_path / "gains.json"
    assert main(["gains", str(amp), "--positions", str(pos), "-o", str(gains)]) == 0
    g_bench, cov_bench = load_gains(gains)[0][1:], np.array(json.loads(gains.read_text())["covariance"]["matrix"])
    out = {}
    for tag, opt in (("free", []), ("prior", ["--prior-file", str(gains)])):
        o = tmp_path / f"{tag}.json"
        assert main(["calibrate", str(tmp_path / "raw.csv"), "-t", str(sim / "template.csv"), "--fit-gains",
                     *opt, "-q", "-o", str(o)]) == 0, capsys.readouterr().err
        out[tag] = json.loads(o.read_text())
    names = ["g_x2", "g_y1", "g_y2"]

    def block(d):
        n = d["covariance"]["names"]
        idx = [n.index(k) for k in names]
        return np.array(d["covariance"]["matrix"])[np.ix_(idx, idx)]

    s_free, s_prior = [np.array([out[t]["std"][k] for k in names]) for t in ("free", "prior")]
    s_bench = np.sqrt(np.diag(cov_bench))
    assert np.all(s_prior < s_free) and np.all(s_prior < s_bench)
    # information adds: the gains' marginal information of the views (the inverse of their block of the free
    # covariance, rescaled to the constrained fit's noise estimate s^2) plus the bench's
    r = (out["free"]["residuals"]["sigma_mm"] / out["prior"]["residuals"]["sigma_mm"]) ** 2
    combined = np.linalg.inv(r * np.linalg.inv(block(out["free"])) + np.linalg.inv(cov_bench))
    # (to first order: the bench's estimate is about 1 sigma from the views', where the model's Jacobian differs a
    # little; a prior centred on the free estimate matches to 1e-6, tests/test_priors.py)
    np.testing.assert_allclose(np.sqrt(np.diag(block(out["prior"]))), np.sqrt(np.diag(combined)), rtol=0.2)
    assert np.all(np.abs(np.array(out["prior"]["gains"][1:]) - G_TRUE[1:]) < 4 * s_prior)
    assert out["prior"]["verdict"] == "good"
    assert np.all(np.abs(g_bench - G_TRUE[1:]) < 4 * s_bench)
