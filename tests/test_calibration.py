"""The calibration pipeline (docs/model.md#calibration) on synthetic data with known truth."""
from dataclasses import replace

import numpy as np
import pytest

import psdcal
from psdcal.calibration._closed_form import extrinsics_from_homography, intrinsics_from_homographies
from psdcal.calibration._homography import homography
from psdcal.calibration._refine import Evaluator, Problem, SolverOptions
from psdcal.calibration._straightness import estimate_radial, find_lines
from psdcal.calibration.core import initial_estimate, recalibrate
from psdcal.errors import ConvergenceError, DegenerateViewsError, InputError
from psdcal.model.params import Distortion, Intrinsics, ModelSpec
from psdcal.model.projection import R_from_r, homography_from_pose
from psdcal.study.simulate import LENSES, PAPER_L1, default_template, simulate_set

CASES = {
    # name: (lens, extra distortion, intrinsics change, calibrate kwargs)
    "lens1-tang-psd": ("lens1", dict(p1=2e-4, p2=-1e-4, l1=PAPER_L1), {}, dict(radial=2, tangential=True, psd_radial=1)),
    "lens2-tang-psd": ("lens2", dict(p1=2e-4, p2=-1e-4, l1=PAPER_L1), {}, dict(radial=2, tangential=True, psd_radial=1)),
    "lens2-k3": ("lens2", dict(k3=2e-7), {}, dict(radial=3, tangential=False)),
    "lens2-psd2": ("lens2", dict(l1=PAPER_L1, l2=3e-6), {}, dict(radial=2, tangential=False, psd_radial=2)),
    "lens1-skew": ("lens1", {}, dict(skew=0.02), dict(radial=1, tangential=False, skew=True)),
    "lens2-aspect": ("lens2", {}, dict(fy_mm=8.1), dict(radial=2, tangential=False, aspect=True)),
    "pinhole": ("lens1", dict(k1=0.0), {}, dict(radial=0, tangential=False)),
}


def _truth(case):
    lens, dextra, iextra, kw = CASES[case]
    intr, dist = LENSES[lens]
    return replace(intr, **iextra), replace(dist, **dextra), kw


def _check_recovery(res, intr, dist, rel=1e-7, abs_zero=1e-9):
    truth = {**intr.to_dict(), **dist.to_dict()}
    if intr.fy_mm is not None:
        truth["fy_mm"] = intr.fy_mm
    for name in res.param_names:
        t = truth.get(name, 0.0)
        v = res.parameter(name)
        if t == 0.0:
            assert abs(v) < abs_zero, (name, v)
        else:
            assert abs(v - t) <= rel * abs(t), (name, v, t)


@pytest.mark.parametrize("cost", ["image", "template"])
@pytest.mark.parametrize("case", list(CASES))
def test_noiseless_recovery(case, cost):
    intr, dist, kw = _truth(case)
    s = simulate_set((intr, dist), n_images=12, noise_mm=0.0, seed=7)
    res = psdcal.calibrate(s.template_mm, s.points_mm, cost=cost, **kw)
    assert res.converged
    _check_recovery(res, intr, dist)
    assert res.rms_mm < 1e-9
    # poses too
    for i in range(12):
        np.testing.assert_allclose(R_from_r(res.rvecs[i]), R_from_r(s.rvecs[i]), atol=1e-8)
        np.testing.assert_allclose(res.tvecs_mm[i], s.tvecs_mm[i], rtol=1e-7)


@pytest.mark.parametrize("cost", ["image", "template"])
def test_noiseless_recovery_with_missing_points(cost):
    s = simulate_set("lens2", n_images=10, noise_mm=0.0, seed=11)
    pts = s.points_mm.copy()
    pts[0, 3] = np.nan
    pts[4, [0, 7, 13]] = np.nan
    res = psdcal.calibrate(s.template_mm, pts, cost=cost, tangential=False)
    _check_recovery(res, s.intrinsics, s.distortion)
    assert np.isnan(res.residuals_mm[0, 3]).all() and np.isfinite(res.residuals_mm[0, 2]).all()


SPECS = [
    ModelSpec(radial=2, tangential=True, psd_radial=1, skew=True),
    ModelSpec(radial=3, tangential=True, psd_radial=2, aspect=True),
    ModelSpec(radial=1, tangential=False, psd_radial=0, fit_gains=True),
]


@pytest.mark.parametrize("cost", ["image", "template"])
@pytest.mark.parametrize("spec", SPECS, ids=["skew", "aspect-all", "gains"])
def test_analytic_jacobian_matches_finite_differences(spec, cost):
    if spec.fit_gains and cost == "template":
        pytest.skip("gains are fitted with the image cost only")
    s = simulate_set("lens2", n_images=4, noise_mm=0.001, seed=3, psd_l1=PAPER_L1, tangential=(1e-4, -2e-4))
    prob = Problem(s.template_mm, s.points_mm, spec, cost=cost)
    intr = replace(s.intrinsics, skew=0.01, fy_mm=8.05 if spec.aspect else None)
    dist = replace(s.distortion, k3=1e-7, l2=1e-6)
    gains = np.array([1.0, 1.03, 0.97, 1.05])
    ev = Evaluator(prob, intr, dist, gains)
    z = prob.pack(intr, dist, gains, s.rvecs, s.tvecs_mm)
    J = ev.jacobian(z)
    num = np.empty_like(J)
    for k in range(z.size):
        h = 1e-6 * max(abs(z[k]), 1e-3)
        zp, zm = z.copy(), z.copy()
        zp[k] += h
        zm[k] -= h
        num[:, k] = (ev.residuals(zp) - ev.residuals(zm)) / (2 * h)
    scale = np.abs(num).max(axis=0) + 1e-300
    err = np.abs(J - num).max(axis=0) / scale
    assert err.max() < 1e-5, (np.argmax(err), err.max())


def test_closed_form_recovers_intrinsics_from_exact_homographies(rng):
    intr = Intrinsics(f_mm=12.0, cx_mm=0.3, cy_mm=-0.4)
    Hs = []
    for _ in range(4):
        r = rng.normal(0, 0.4, 3)
        t = np.array([rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(400, 800)])
        Hs.append(homography_from_pose(intr, r, t) * rng.uniform(-3, 3))
        rr, tt = extrinsics_from_homography(Hs[-1], intr)
        np.testing.assert_allclose(R_from_r(rr), R_from_r(r), atol=1e-9)
        np.testing.assert_allclose(tt, t, rtol=1e-9)
    got = intrinsics_from_homographies(Hs)
    assert got.f_mm == pytest.approx(12.0, rel=1e-9)
    assert got.cx_mm == pytest.approx(0.3, abs=1e-9) and got.cy_mm == pytest.approx(-0.4, abs=1e-9)
    skewed = Intrinsics(f_mm=12.0, cx_mm=0.3, cy_mm=-0.4, skew=0.05, fy_mm=11.5)
    Hs = [homography_from_pose(skewed, rng.normal(0, 0.4, 3), [0, 0, 600.0]) for _ in range(5)]
    got = intrinsics_from_homographies(Hs, skew=True, aspect=True)
    np.testing.assert_allclose([got.f_mm, got.fy_mm, got.skew, got.cx_mm, got.cy_mm], [12, 11.5, 0.05, 0.3, -0.4], atol=1e-8)


@pytest.mark.parametrize("normalize", [True, False])
def test_dlt_is_exact_on_exact_points(normalize, rng):
    H = np.array([[8.0, 0.1, 0.5], [0.2, 7.5, -0.7], [1e-4, -2e-4, 1.0]])
    P = rng.uniform(-80, 80, (14, 2))
    ph = np.c_[P, np.ones(14)] @ H.T
    x = ph[:, :2] / ph[:, 2:]
    got = homography(P, x, normalize=normalize)
    np.testing.assert_allclose(got / got[2, 2], H, rtol=1e-8, atol=1e-11)


def test_normalised_dlt_is_more_accurate_with_noise():
    # Hartley's point: with noise, the normalised DLT gives better homographies
    s = simulate_set(("lens1" and (Intrinsics(25.0, 0.5, -0.7), Distortion())), n_images=30, noise_mm=0.01, seed=5)
    errs = {True: [], False: []}
    for i in range(30):
        H_true = homography_from_pose(s.intrinsics, s.rvecs[i], s.tvecs_mm[i])
        for norm in (True, False):
            H = homography(s.template_mm, s.points_mm[i], normalize=norm)
            ph = np.c_[s.template_mm, np.ones(14)] @ H.T
            pt = np.c_[s.template_mm, np.ones(14)] @ H_true.T
            errs[norm].append(np.sqrt(np.mean(np.sum((ph[:, :2] / ph[:, 2:] - pt[:, :2] / pt[:, 2:]) ** 2, 1))))
    assert np.mean(errs[True]) <= np.mean(errs[False])


def test_find_lines_on_the_default_template():
    lines = find_lines(default_template())
    sets = {tuple(ln) for ln in lines}
    assert (0, 1, 2, 3, 4) in sets and (5, 6, 7, 8) in sets and (9, 10, 11, 12, 13) in sets
    assert all(len(ln) >= 3 for ln in lines)
    P = default_template()
    for ln in lines:  # really collinear
        q = P[ln] - P[ln].mean(0)
        assert np.linalg.svd(q, compute_uv=False)[1] < 1e-9
    # a template with no three collinear points has no line
    assert find_lines(np.array([[0, 0], [1, 0.1], [2, 0.5], [3, 1.4], [4, 2.9]])) == []


def test_straightness_recovers_radial_distortion_about_the_centre():
    # lens distortion centred on the electrical centre: the preliminary step is exact
    intr, dist = Intrinsics(8.0, 0.0, 0.0), Distortion(k1=1e-2, k2=3e-5)
    s = simulate_set((intr, dist), n_images=9, noise_mm=0.0, seed=2)
    st = estimate_radial(s.points_mm, find_lines(s.template_mm), c_mm=(0, 0), n_terms=2)
    np.testing.assert_allclose(st.k, [1e-2, 3e-5], rtol=1e-7)


@pytest.mark.parametrize("lens", ["lens1", "lens2"])
def test_tables_1_2_preliminary_correction_improves_the_start(lens):
    """The paper's Tables 1-2: 9 ideal images; with preliminary correction and
    normalisation the first-stage intrinsics are closer to the truth than without."""
    wins = 0
    for seed in range(5):
        s = simulate_set(lens, n_images=9, noise_mm=0.0, seed=100 + seed)
        t = s.intrinsics

        def err(ie):
            return abs(ie.intrinsics.f_mm - t.f_mm) / t.f_mm + np.hypot(ie.intrinsics.cx_mm - t.cx_mm, ie.intrinsics.cy_mm - t.cy_mm) / t.f_mm

        with_both = err(initial_estimate(s.template_mm, s.points_mm, preliminary=True, normalize=True))
        without = err(initial_estimate(s.template_mm, s.points_mm, preliminary=False, normalize=True))
        plain = err(initial_estimate(s.template_mm, s.points_mm, preliminary=False, normalize=False))
        wins += with_both < without and with_both < plain
    assert wins >= 4


def test_result_json_contract():
    s = simulate_set("lens2", n_images=9, noise_mm=0.002, seed=1)
    res = psdcal.calibrate(s.template_mm, s.points_mm, psd_radial=1)
    d = res.to_dict()
    for key in ("intrinsics", "distortion", "std", "extrinsics", "residuals", "cost", "iterations", "converged", "model", "software"):
        assert key in d
    assert set(d["intrinsics"]) >= {"f_mm", "cx_mm", "cy_mm", "skew"}
    assert set(d["distortion"]) == {"k1", "k2", "k3", "p1", "p2", "l1", "l2"}
    assert set(d["std"]) >= {"f_mm", "cx_mm", "cy_mm", "skew", "k1", "k2", "k3", "p1", "p2", "l1", "l2"}
    assert d["std"]["k3"] is None and d["std"]["skew"] is None and d["std"]["l1"] > 0
    assert d["model"] == {**d["model"], "radial": 2, "tangential": True, "psd_radial": 1, "skew": False}
    assert d["software"]["name"] == "psdcal"
    assert len(d["extrinsics"]) == 9 and set(d["extrinsics"][0]) >= {"image_id", "rvec", "tvec_mm"}
    assert len(d["residuals"]["per_image_rms_mm"]) == 9
    # rms_mm is the sensor RMS distance between measured and modelled points
    r = res.residuals_mm
    assert d["residuals"]["rms_mm"] == pytest.approx(np.sqrt(np.nanmean(np.sum(r**2, -1))))
    back = psdcal.CalibrationResult.from_dict(d)
    assert back.intrinsics == res.intrinsics and back.distortion == res.distortion
    np.testing.assert_allclose(back.covariance, res.covariance)
    np.testing.assert_allclose(back.residuals_mm, res.residuals_mm)
    # the saved problem re-runs exactly
    again = recalibrate(d)
    assert again.intrinsics == res.intrinsics and again.distortion == res.distortion


def test_template_cost_rms_is_reported_on_the_sensor():
    s = simulate_set("lens2", n_images=9, noise_mm=0.003, seed=4)
    a = psdcal.calibrate(s.template_mm, s.points_mm, cost="image")
    b = psdcal.calibrate(s.template_mm, s.points_mm, cost="template")
    # both near the noise level on the sensor; the ML fit has the smaller sensor RMS
    assert 0.5 * 0.003 * np.sqrt(2) < a.rms_mm <= b.rms_mm < 2 * 0.003 * np.sqrt(2)


def test_degenerate_and_bad_inputs():
    s = simulate_set("lens2", n_images=3, noise_mm=0.0, seed=1)
    with pytest.raises(DegenerateViewsError, match="at least 2"):
        psdcal.calibrate(s.template_mm, s.points_mm[:1])
    pts = s.points_mm.copy()
    pts[1, 4:] = np.nan  # 4 points left: rows 0..3 of the template are collinear
    with pytest.raises(DegenerateViewsError, match="image 1.*collinear"):
        psdcal.calibrate(s.template_mm, pts)
    pts = s.points_mm.copy()
    pts[2, 3:] = np.nan
    with pytest.raises(DegenerateViewsError, match="image 2: 3 points"):
        psdcal.calibrate(s.template_mm, pts)
    with pytest.raises(InputError, match="shape"):
        psdcal.calibrate(s.template_mm, s.points_mm[:, :5])
    pts = s.points_mm.copy()
    pts[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="two NaN"):
        psdcal.calibrate(s.template_mm, pts)
    with pytest.raises(InputError, match="cost"):
        psdcal.calibrate(s.template_mm, s.points_mm, cost="plate")


def test_parallel_views_are_degenerate():
    # every view fronto-parallel with the same orientation: the closed form cannot work
    intr, dist = LENSES["lens1"]
    P = default_template()
    from psdcal.study.simulate import measured_points

    rv = np.zeros((4, 3))
    tv = np.array([[0, 0, 900.0], [20, 10, 950.0], [-15, 5, 1000.0], [5, -20, 920.0]])
    pts = measured_points(P, intr, Distortion(), rv, tv)
    with pytest.raises(DegenerateViewsError):
        psdcal.calibrate(P, pts, radial=0, tangential=False, preliminary=False)


def test_non_convergence_is_an_error_carrying_the_last_iterate():
    s = simulate_set("lens2", n_images=9, noise_mm=0.003, seed=4)
    with pytest.raises(ConvergenceError) as info:
        psdcal.calibrate(s.template_mm, s.points_mm, solver=SolverOptions(max_iterations=1))
    assert info.value.result is not None and not info.value.result.converged


@pytest.mark.parametrize("normalize", [True, False])
def test_batched_homographies_equal_one_by_one(normalize):
    from psdcal.calibration._homography import homographies

    s = simulate_set("lens2", n_images=5, noise_mm=0.003, seed=8)
    pts = s.points_mm.copy()
    pts[1, [2, 9]] = np.nan
    Hb = homographies(s.template_mm, pts, normalize=normalize)
    for i in range(5):
        ok = np.all(np.isfinite(pts[i]), axis=1)
        np.testing.assert_allclose(Hb[i], homography(s.template_mm[ok], pts[i][ok], normalize=normalize), rtol=1e-9, atol=1e-13)


def test_find_lines_on_a_grid_is_complete_and_unique():
    # 5 x 4 grid: 4 rows of 5, 5 columns of 4, and diagonals of >= 3 points
    g = np.array([(x, y) for y in range(4) for x in range(5)], dtype=float)
    lines = find_lines(g)
    sets = [tuple(ln) for ln in lines]
    assert len(sets) == len(set(sets))  # each line once
    for r in range(4):
        assert tuple(range(5 * r, 5 * r + 5)) in sets
    for c in range(5):
        assert tuple(range(c, 20, 5)) in sets
    # brute force: every collinear triple lies on exactly one found line
    import itertools

    for a, b, c in itertools.combinations(range(20), 3):
        u, v = g[b] - g[a], g[c] - g[a]
        if abs(u[0] * v[1] - u[1] * v[0]) < 1e-12:
            assert sum({a, b, c} <= set(ln) for ln in sets) == 1
    longest = find_lines(g, max_lines=9)
    assert len(longest) == 9 and min(len(ln) for ln in longest) >= 4


@pytest.mark.parametrize("lens", ["lens1", "lens2"])
def test_psd_term_fit_reaches_the_truth_with_noise(lens):
    """With l1 free the cost has valleys where k1, l1 and C trade; the
    multi-start must still find the maximum-likelihood fit (C near the truth,
    residual at the noise level) on every set."""
    bad = []
    for seed in range(6):
        s = simulate_set(lens, n_images=9, noise_mm=0.0005, seed=seed, psd_l1=PAPER_L1)
        r = psdcal.calibrate(s.template_mm, s.points_mm, radial=2, tangential=False, psd_radial=1)
        c_err = np.hypot(*(r.intrinsics.c - s.intrinsics.c))
        if c_err > 5 * max(r.std["cx_mm"], r.std["cy_mm"]) or r.rms_mm > 1.5 * np.sqrt(2) * 0.0005:
            bad.append((seed, c_err, r.rms_mm))
        assert abs(r.distortion.l1 - PAPER_L1) < 5 * r.std["l1"] or (seed, "l1") in bad
    assert not bad, bad


def test_implausible_solutions_are_refused():
    from psdcal.calibration.core import implausible

    s = simulate_set("lens2", n_images=9, noise_mm=0.002, seed=1)
    res = psdcal.calibrate(s.template_mm, s.points_mm)
    assert implausible(res) == ""
    from dataclasses import replace as rp

    assert "focal length" in implausible(rp(res, intrinsics=rp(res.intrinsics, f_mm=-3e10)))
    tv = res.tvecs_mm.copy()
    tv[2, 2] = -5.0
    assert "image 2 behind the sensor" in implausible(rp(res, tvecs_mm=tv))
    assert "non-finite" in implausible(rp(res, distortion=rp(res.distortion, k1=np.nan)))
