"""Fixed parameters and Gaussian priors in the template calibration (issue 13.4).

The truths tested: an infinitely wide prior is the free fit, an infinitely
tight one the fixed fit; in between the covariance is the information sum of
the two Gaussian estimates (Cov^-1 = Cov_free^-1 + C^-1, exact when the prior
is centred on the free estimate because the solution and Jacobian do not
move), for one parameter and for a joint prior with correlations.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from psdcal.calibration.core import calibrate, recalibrate
from psdcal.calibration.priors import GaussianPrior, parse_fix, parse_prior, read_prior_file
from psdcal.cli import main
from psdcal.errors import InputError
from psdcal.study.simulate import simulate_set


@pytest.fixture(scope="module")
def data():
    s = simulate_set("lens2", n_images=8, noise_mm=0.002, seed=11)
    free = calibrate(s.template_mm, s.points_mm)
    return s, free


def _fit(s, **kw):
    return calibrate(s.template_mm, s.points_mm, **kw)


def _cov(res, names):
    idx = [res.param_names.index(n) for n in names]
    return res.covariance[np.ix_(idx, idx)]


def test_infinitely_wide_prior_is_the_free_fit(data):
    s, lm_free = data
    # an infinite std is no prior: the free fit (polished by Gauss-Newton steps to round-off;
    # the LM alone stops ~1e-5 standard errors from the optimum)
    free = _fit(s, priors={"f_mm": (7.0, np.inf)})
    assert free.problem["options"]["priors"] == []
    for n in free.param_names:
        assert abs(free.parameter(n) - lm_free.parameter(n)) < 1e-4 * lm_free.std[n]
    res = _fit(s, priors={"f_mm": (7.0, 1e12), "k1": (0.0, 1e12)})
    for n in free.param_names:
        assert res.parameter(n) == pytest.approx(free.parameter(n), rel=1e-9, abs=1e-9 * free.std[n])
        assert res.std[n] == pytest.approx(free.std[n], rel=1e-9)
    assert res.sigma_mm == pytest.approx(free.sigma_mm, rel=1e-9)


def test_zero_width_prior_is_the_fixed_fit(data):
    s, free = data
    fixed = _fit(s, fix={"f_mm": 8.0})
    assert fixed.intrinsics.f_mm == 8.0 and fixed.std["f_mm"] is None
    assert "f_mm" not in fixed.param_names
    zero = _fit(s, priors={"f_mm": (8.0, 0.0)})  # std 0 is "fixed", exactly
    tight = _fit(s, priors={"f_mm": (8.0, 1e-7 * free.std["f_mm"])})
    for n in fixed.param_names:
        assert zero.parameter(n) == fixed.parameter(n)
        assert tight.parameter(n) == pytest.approx(fixed.parameter(n), rel=1e-9, abs=1e-9 * free.std[n])
        assert tight.std[n] == pytest.approx(fixed.std[n], rel=1e-9)
    assert tight.intrinsics.f_mm == pytest.approx(8.0, abs=1e-9 * free.std["f_mm"])
    # degrees of freedom: the tight prior removes one parameter, like fixing it
    assert tight.problem["prior_fit"]["prior_dof"] == pytest.approx(1.0, abs=1e-9)
    assert tight.sigma_mm == pytest.approx(fixed.sigma_mm, rel=1e-9)


def test_fixed_fit_degrees_of_freedom(data):
    s, free = data
    fixed = _fit(s, fix={"f_mm": float(free.intrinsics.f_mm), "k2": float(free.distortion.k2)})
    # fixed at the free optimum: the same residuals, two fewer parameters
    m = 2 * int(np.sum(np.isfinite(s.points_mm[..., 0])))
    n_free = len(free.param_names) + 6 * s.points_mm.shape[0]
    assert fixed.sigma_mm**2 == pytest.approx(free.sigma_mm**2 * (m - n_free) / (m - n_free + 2), rel=1e-6)
    # conditional covariance: what is left of the free covariance once f, k2 are known
    keep = list(fixed.param_names)
    C = free.covariance
    ia = [free.param_names.index(n) for n in keep]
    ib = [free.param_names.index(n) for n in ("f_mm", "k2")]
    cond = C[np.ix_(ia, ia)] - C[np.ix_(ia, ib)] @ np.linalg.solve(C[np.ix_(ib, ib)], C[np.ix_(ib, ia)])
    scale = fixed.sigma_mm**2 / free.sigma_mm**2
    np.testing.assert_allclose(fixed.covariance, cond * scale, rtol=1e-5)


def test_prior_combines_like_two_gaussian_estimates(data):
    s, free = data
    sf = free.std["f_mm"]
    res = _fit(s, priors={"f_mm": (free.intrinsics.f_mm, sf)})  # centred on the free estimate
    assert res.intrinsics.f_mm == pytest.approx(free.intrinsics.f_mm, abs=1e-6 * sf)
    s2_ratio = res.sigma_mm**2 / free.sigma_mm**2
    assert abs(s2_ratio - 1) < 0.01  # only the degrees of freedom moved (by 1/2)
    P = np.zeros((len(free.param_names),) * 2)
    P[0, 0] = 1 / sf**2
    expect = np.linalg.inv(np.linalg.inv(free.covariance) / s2_ratio + P)
    np.testing.assert_allclose(res.covariance, expect, rtol=1e-6, atol=1e-12 * np.max(np.abs(expect)))
    # one parameter: 1/s^2 = 1/s_free^2 + 1/s_prior^2 (f is the parameter the prior acts on)
    assert 1 / res.std["f_mm"] ** 2 == pytest.approx(1 / (sf**2 * s2_ratio) + 1 / sf**2, rel=1e-6)
    assert res.std["f_mm"] < sf
    # effective prior degrees of freedom t = tr(P Cov) = 1/2 for a prior as informative as the data
    assert res.problem["prior_fit"]["prior_dof"] == pytest.approx(0.5, abs=0.01)


def test_joint_prior_full_matrix_and_mean(data):
    s, free = data
    names = ("f_mm", "cx_mm", "cy_mm")
    Cf = _cov(free, names)
    rng = np.random.default_rng(3)
    Q = rng.normal(size=(3, 3))
    C = 0.5 * Cf + 0.2 * (Q @ Q.T) * np.sqrt(np.outer(np.diag(Cf), np.diag(Cf)))
    mu_f = np.array([free.parameter(n) for n in names])
    prior = GaussianPrior(names, mu_f, C)
    res = _fit(s, priors=prior)
    s2_ratio = res.sigma_mm**2 / free.sigma_mm**2
    P = np.zeros((len(free.param_names),) * 2)
    P[:3, :3] = np.linalg.inv(C)
    expect = np.linalg.inv(np.linalg.inv(free.covariance) / s2_ratio + P)
    np.testing.assert_allclose(res.covariance, expect, rtol=1e-6, atol=1e-9 * np.max(np.abs(np.diag(expect))))
    # a prior mean away from the estimate: the MAP estimate is the information-weighted mean
    # (exact for a linear model; here within a small fraction of a standard error)
    shift = np.sqrt(np.diag(C)) * np.array([1.0, -1.0, 0.5])
    res2 = _fit(s, priors=GaussianPrior(names, mu_f + shift, C))
    theta_free = np.array([free.parameter(n) for n in free.param_names])
    Icomb = np.linalg.inv(free.covariance) / s2_ratio + P
    mu_full = theta_free.copy()
    mu_full[:3] += shift
    expect_mean = np.linalg.solve(Icomb, np.linalg.inv(free.covariance) / s2_ratio @ theta_free + P @ mu_full)
    got = np.array([res2.parameter(n) for n in free.param_names])
    std = np.sqrt(np.diag(res2.covariance))
    assert np.all(np.abs(got - expect_mean) < 0.05 * std)
    assert np.all(np.sqrt(np.diag(_cov(res2, names))) < np.sqrt(np.diag(Cf)))


def test_standard_errors_shrink_monotonically(data):
    s, free = data
    sf = free.std["cx_mm"]
    stds = [_fit(s, priors={"cx_mm": (free.intrinsics.cx_mm, k * sf)}).std["cx_mm"] for k in (100.0, 3.0, 1.0, 0.3)]
    assert all(a > b for a, b in zip(stds, stds[1:]))
    assert stds[0] == pytest.approx(sf, rel=1e-3)


def test_fix_outside_the_model_and_record_reruns(data, tmp_path):
    s, free = data
    res = _fit(s, fix={"k3": 0.0, "skew": 0.0, "fy_mm": float(free.intrinsics.f_mm)},
               priors={"k1": (free.distortion.k1, 10 * free.std["k1"])})
    assert res.std["skew"] is None and res.std["fy_mm"] is None and res.std["k3"] is None
    assert res.intrinsics.fy_mm == float(free.intrinsics.f_mm)
    d = json.loads(json.dumps(res.to_dict()))
    assert d["problem"]["options"]["fix"]["fy_mm"] == float(free.intrinsics.f_mm)
    assert d["problem"]["options"]["priors"][0]["names"] == ["k1"]
    assert d["std"]["fy_mm"] is None
    again = recalibrate(d)
    assert again.param_names == res.param_names and again.model == res.model
    for n in res.param_names:
        assert again.parameter(n) == pytest.approx(res.parameter(n), rel=1e-12, abs=1e-15)
        assert again.std[n] == pytest.approx(res.std[n], rel=1e-10)


def test_bad_fixes_and_priors():
    with pytest.raises(InputError, match="NAME=VALUE"):
        parse_fix(["f=8"])
    with pytest.raises(InputError, match="not a number"):
        parse_fix(["f_mm=eight"])
    with pytest.raises(InputError, match="NAME=VALUE,STD"):
        parse_prior("f_mm=8.0")
    assert parse_prior("f_mm=8.0,0.1").covariance[0, 0] == pytest.approx(0.01)
    with pytest.raises(InputError, match="symmetric"):
        GaussianPrior(("f_mm", "k1"), [8, 0], [[1, 0.5], [0.1, 1]])
    s = simulate_set("lens2", n_images=4, noise_mm=0.002, seed=2)
    with pytest.raises(InputError, match="does not estimate"):
        calibrate(s.template_mm, s.points_mm, priors={"k3": (0.0, 1e-4)})
    with pytest.raises(InputError, match="both fixed"):
        calibrate(s.template_mm, s.points_mm, fix={"f_mm": 8.0}, priors={"f_mm": (8.0, 0.1)})


def test_prior_file_formats(tmp_path):
    p = tmp_path / "gains.json"
    cov = [[1e-6, 1e-7, 0], [1e-7, 2e-6, 0], [0, 0, 3e-6]]
    p.write_text(json.dumps({"gains": [1.0, 1.01, 0.99, 1.02], "covariance": cov, "names": ["g_x2", "g_y1", "g_y2"]}))
    pr = read_prior_file(p)
    assert pr.names == ("g_x2", "g_y1", "g_y2")
    np.testing.assert_allclose(pr.mean, [1.01, 0.99, 1.02])
    np.testing.assert_allclose(pr.covariance, cov)
    q = tmp_path / "std.json"
    q.write_text(json.dumps({"gains": [1.0, 1.01, 0.99, 1.02], "std": {"g_x2": 1e-3, "g_y1": 2e-3, "g_y2": 3e-3}}))
    np.testing.assert_allclose(np.diag(read_prior_file(q).covariance), [1e-6, 4e-6, 9e-6])
    r = tmp_path / "generic.json"
    r.write_text(json.dumps({"names": ["f_mm", "cx_mm"], "values": [8.0, 0.5], "covariance": [[1e-4, 0], [0, 1e-4]]}))
    assert read_prior_file(r).names == ("f_mm", "cx_mm")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"names": ["f_mm"], "values": [8.0]}))
    with pytest.raises(InputError, match="bad.json.*covariance"):
        read_prior_file(bad)


def test_gain_prior_file_combines_with_fitted_gains(tmp_path):
    """The bench (electrical) gains enter the template fit as a prior: the gains' errors shrink."""
    from psdcal.model.readout import gain_map

    s = simulate_set("lens2", n_images=8, noise_mm=0.002, seed=5)
    g = np.array([1.0, 1.02, 0.97, 1.01])
    X = gain_map(s.points_mm, g)
    free = calibrate(s.template_mm, X, fit_gains=True)
    sd = np.array([free.std[n] for n in ("g_x2", "g_y1", "g_y2")])
    p = tmp_path / "gains.json"
    p.write_text(json.dumps({"gains": g.tolist(), "names": ["g_x2", "g_y1", "g_y2"], "covariance": np.diag(sd**2).tolist()}))
    res = calibrate(s.template_mm, X, fit_gains=True, priors=str(p))
    got = np.array([res.std[n] for n in ("g_x2", "g_y1", "g_y2")])
    assert np.all(got < 0.9 * sd)
    # centred on the free estimate (solution and Jacobian unchanged): exactly the information
    # sum with the (correlated) free covariance of the gains
    gf = np.concatenate([[1.0], [free.parameter(n) for n in ("g_x2", "g_y1", "g_y2")]])
    p.write_text(json.dumps({"gains": gf.tolist(), "names": ["g_x2", "g_y1", "g_y2"], "covariance": np.diag(sd**2).tolist()}))
    res = calibrate(s.template_mm, X, fit_gains=True, priors=str(p))
    got = np.array([res.std[n] for n in ("g_x2", "g_y1", "g_y2")])
    P = np.zeros((len(free.param_names),) * 2)
    gi = [free.param_names.index(n) for n in ("g_x2", "g_y1", "g_y2")]
    P[np.ix_(gi, gi)] = np.diag(1 / sd**2)
    s2_ratio = res.sigma_mm**2 / free.sigma_mm**2
    expect = np.linalg.inv(np.linalg.inv(free.covariance) / s2_ratio + P)
    np.testing.assert_allclose(got, np.sqrt(np.diag(expect)[gi]), rtol=1e-5)


def test_cli_fix_and_prior(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", "--images", "6", "--noise-mm", "0.002", "--seed", "4", "-o", str(out)]) == 0
    cal = tmp_path / "cal.json"
    code = main(["calibrate", str(out / "points.csv"), "-t", str(out / "template.csv"), "-o", str(cal),
                 "--fix", "f_mm=8.0", "--fix", "k2=0", "--prior", "k1=0.01,0.001", "-q"])
    assert code == 0, capsys.readouterr().err
    d = json.loads(cal.read_text())
    assert d["intrinsics"]["f_mm"] == 8.0 and d["std"]["f_mm"] is None and d["std"]["k2"] is None
    assert d["problem"]["options"]["fix"] == {"f_mm": 8.0, "k2": 0.0}
    assert d["problem"]["options"]["priors"][0]["mean"] == [0.01]
    # the constrained calibration is an ordinary calibration file for the other commands
    assert main(["report", str(cal), "-o", str(tmp_path / "r.html")]) == 0
    assert main(["compare", str(cal), str(cal)]) == 0
    capsys.readouterr()
    code = main(["calibrate", str(out / "points.csv"), "-t", str(out / "template.csv"), "-o", str(tmp_path / "x.json"),
                 "--fix", "focal=8"])
    err = capsys.readouterr().err
    assert code == 2 and "NAME=VALUE" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.json").exists()


def test_template_cost_prior_and_fix(data):
    """The plate-plane cost (Eq 29): s^2 in plate mm^2; a wide prior is the free fit, a fix removes the parameter."""
    s, _ = data
    free = _fit(s, cost="template", priors={"f_mm": (8.0, np.inf)})
    wide = _fit(s, cost="template", priors={"f_mm": (8.0, 1e12)})
    for n in free.param_names:
        assert wide.parameter(n) == pytest.approx(free.parameter(n), rel=1e-9, abs=1e-9 * free.std[n])
    sf = free.std["f_mm"]
    mid = _fit(s, cost="template", priors={"f_mm": (free.intrinsics.f_mm, sf)})
    assert mid.std["f_mm"] == pytest.approx(sf / np.sqrt(2), rel=0.01)
    fixed = _fit(s, cost="template", fix={"cx_mm": 0.5})
    assert fixed.cost == "template" and fixed.std["cx_mm"] is None and fixed.intrinsics.cx_mm == 0.5


def test_reads_the_electrical_calibration_json(tmp_path):
    """The gains JSON of the electrical calibration (GainCalibration.to_dict) is a prior file as it is."""
    from psdcal.calibration.gains import calibrate_gains
    from psdcal.model.readout import gain_map

    rng = np.random.default_rng(1)
    spots = np.stack(np.meshgrid(np.linspace(-3.5, 3.5, 7), np.linspace(-3.5, 3.5, 7)), -1).reshape(-1, 2)
    g = np.array([1.0, 1.02, 0.97, 1.01])
    gc = calibrate_gains(spots, gain_map(spots, g) + rng.normal(0, 0.002, spots.shape))
    p = tmp_path / "gains.json"
    d = gc.to_dict()
    p.write_text(json.dumps(d))
    pr = read_prior_file(p)
    assert pr.names == ("g_x2", "g_y1", "g_y2")
    np.testing.assert_allclose(pr.mean, gc.gains[1:])
    np.testing.assert_allclose(np.sqrt(np.diag(pr.covariance)), gc.std)
    # with the full covariance and names (the 'gains' command's file), the covariance is used as it is
    d.update(names=["g_x2", "g_y1", "g_y2"], covariance=gc.covariance.tolist())
    p.write_text(json.dumps(d))
    np.testing.assert_allclose(read_prior_file(p).covariance, gc.covariance)
    # a 4 x 4 covariance over (g_x1, ...) with g_x1 exactly 1: its first row and column dropped
    C4 = np.zeros((4, 4))
    C4[1:, 1:] = gc.covariance
    p.write_text(json.dumps({"names": ["g_x1", "g_x2", "g_y1", "g_y2"], "values": gc.gains.tolist(), "covariance": C4.tolist()}))
    np.testing.assert_allclose(read_prior_file(p).covariance, gc.covariance)
