"""Angles of arrival, their uncertainty, positions (psdcal.measure.aoa, psdcal.measure.positioning, psdcal.measure.sensor_model)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from _locate_sim import amplitudes, calib_dict, model, signals, spot_for_angles
from psdcal.measure.aoa import angles_from_amplitudes, angles_from_points, impact_from_amplitudes
from psdcal.errors import InputError, ZeroSignalError
from psdcal.measure.positioning import error_map, plane_position, plot_error_map, triangulate, triangulate_aoa, SensorPose
from psdcal.model.projection import R_from_r
from psdcal.measure.sensor_model import SensorModel
from psdcal.signal.stream import MultiCarrierLockin

VARIANTS = {
    "plain": {},
    "skew": {"skew": 0.02},
    "fy": {"fy": 8.1},
    "skew+fy+gains": {"skew": -0.01, "fy": 7.9, "gains": [1.0, 1.03, 0.97, 1.01]},
}


@pytest.fixture(params=list(VARIANTS))
def variant(request):
    return model(**VARIANTS[request.param])


def grid_points():
    g = np.linspace(-3.8, 3.8, 5)
    return np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)


def test_param_jacobian_matches_finite_differences(variant):
    m = variant
    a = amplitudes(SensorModel.from_dict({"intrinsics": {"f_mm": 8, "cx_mm": 0, "cy_mm": 0}}), grid_points())
    imp = impact_from_amplitudes(a, m)
    res = angles_from_points(imp.d_mm, m, dd_dgains=imp.dd_dgains)
    for k, name in enumerate(m.names):
        h = 1e-6 * max(1.0, abs(m.value(name)))
        plus = m.with_values({name: m.value(name) + h})
        minus = m.with_values({name: m.value(name) - h})
        n_p = angles_from_amplitudes(a, plus).n
        n_m = angles_from_amplitudes(a, minus).n
        fd = (n_p - n_m) / (2 * h)
        np.testing.assert_allclose(res.dn_dp[..., k], fd, rtol=1e-5, atol=1e-8, err_msg=name)


def test_point_and_amplitude_jacobians(variant):
    m = variant
    d = grid_points() * 0.9
    res = angles_from_points(d, m)
    h = 1e-6
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        fd = (angles_from_points(d + e, m).n - angles_from_points(d - e, m).n) / (2 * h)
        np.testing.assert_allclose(res.dn_dd[..., j], fd, rtol=1e-6, atol=1e-9)
    # amplitude noise -> impact point covariance, against finite differences of Eq 1-2
    a = amplitudes(m, d)
    var = np.array([1e-4, 2e-4, 3e-4, 4e-4])
    imp = impact_from_amplitudes(a, m, var)
    J = np.empty(a.shape[:-1] + (2, 4))
    for c in range(4):
        e = np.zeros(4)
        e[c] = 1e-7
        J[..., c] = (impact_from_amplitudes(a + e, m).d_mm - impact_from_amplitudes(a - e, m).d_mm) / 2e-7
    np.testing.assert_allclose(imp.cov_d_mm2, J @ np.diag(var) @ np.swapaxes(J, -1, -2), rtol=1e-5, atol=1e-14)
    np.testing.assert_allclose(imp.d_mm, d, atol=1e-12)  # the gains are corrected


def test_calibration_covariance_against_monte_carlo():
    m = model(skew=0.01, gains=[1.0, 1.02, 0.99, 1.0])
    a = amplitudes(m, grid_points()[[0, 7, 12, 24]])
    res = angles_from_amplitudes(a, m)
    rng = np.random.default_rng(2)
    draws = rng.multivariate_normal([m.value(n) for n in m.names], m.covariance, size=3000)
    ns = np.stack([angles_from_amplitudes(a, m.with_values(dict(zip(m.names, p)))).n for p in draws])
    emp = np.einsum("sni,snj->nij", ns - ns.mean(0), ns - ns.mean(0)) / (len(draws) - 1)
    np.testing.assert_allclose(np.sqrt(np.diagonal(emp, axis1=1, axis2=2)),
                               np.sqrt(np.diagonal(res.cov_n_calib, axis1=1, axis2=2)), rtol=0.08)


def test_angles_of_known_directions_and_plane_position():
    m = model()
    alpha = np.radians([[0.0, 0.0], [10.0, -5.0], [-18.0, 14.0]])
    d = spot_for_angles(m, alpha)
    res = angles_from_points(d, m)
    np.testing.assert_allclose(res.alpha_rad, alpha, atol=1e-12)
    pos = plane_position(res, 5000.0)
    np.testing.assert_allclose(pos.xy_mm, 5000.0 * np.tan(alpha), atol=1e-8)
    np.testing.assert_allclose(pos.cov_xy_mm2, 5000.0**2 * res.cov_n, rtol=1e-12)
    np.testing.assert_allclose(res.ray, np.concatenate([np.tan(alpha), np.ones((3, 1))], 1)
                               / np.linalg.norm(np.concatenate([np.tan(alpha), np.ones((3, 1))], 1), axis=1)[:, None])
    with pytest.raises(ZeroSignalError):
        angles_from_amplitudes(np.zeros((2, 4)), m)
    assert np.isnan(angles_from_amplitudes(np.zeros((1, 4)), m, on_zero="nan").alpha_rad).all()


def test_recorded_angles_within_3_sigma_of_reported_uncertainty():
    """Simulated recording, known truth, the calibration itself uncertain: each window's error < 3 sigma."""
    truth = calib_dict(gains=[1.0, 1.01, 0.99, 1.02])
    m_true = SensorModel.from_dict(truth)
    # the "calibrated" model: the truth moved by one draw of its own covariance
    rng = np.random.default_rng(5)
    draw = rng.multivariate_normal(np.zeros(len(m_true.names)), m_true.covariance)
    m_cal = m_true.with_values({n: m_true.value(n) + dv for n, dv in zip(m_true.names, draw)})
    alpha = np.radians([[14.0, -9.0], [-6.0, 20.0]])
    d = spot_for_angles(m_true, alpha)
    rate = 125_000.0
    x = signals(rate, 250_000, [(amplitudes(m_true, d[0]), 1000.0, 0.1), (amplitudes(m_true, d[1], 0.7), 1300.0, 2.0)],
                noise=3e-3, rng=rng)
    lk = MultiCarrierLockin(rate, [1000.0, 1300.0], 0.01)
    wb = lk.process(0.0, x)
    res = angles_from_amplitudes(wb.amplitude, m_cal, wb.var_amplitude)
    z = (res.alpha_rad - alpha[None]) / res.sigma_alpha_rad
    assert np.all(np.abs(z) < 3.0)
    # noise only (a perfectly known model): the normalised errors have unit spread
    res0 = angles_from_amplitudes(wb.amplitude, SensorModel.from_dict({**truth, "covariance": None, "std": {}}),
                                  wb.var_amplitude)
    z0 = (res0.alpha_rad - alpha[None]) / res0.sigma_alpha_rad
    assert np.mean(np.abs(z0) < 3.0) > 0.99
    assert 0.75 < z0.std() < 1.25


def _two_sensors():
    m1, m2 = model(seed=1), model(seed=2, fy=8.05)
    # two sensors 2 m apart looking at the same region, 5 m away
    poses = [
        (np.array([0.0, 0.25, 0.0]), np.array([0.0, 0.0, 0.0])),
        (np.array([0.02, -0.25, 0.01]), np.array([0.0, 0.0, 0.0])),
    ]
    centres = [np.array([-1000.0, 0.0, 0.0]), np.array([1000.0, 50.0, 0.0])]
    sensors = []
    for (r, _), c, m, name in zip(poses, centres, (m1, m2), ("left", "right")):
        R = R_from_r(r)
        sensors.append(SensorPose(name, m, r, -R @ c))
    return sensors


def test_two_sensor_triangulation_within_reported_uncertainty():
    sensors = _two_sensors()
    p_true = np.array([120.0, -300.0, 5000.0])
    rng = np.random.default_rng(9)
    rate = 125_000.0
    results = []
    for sp in sensors:
        pc = sp.R @ p_true + sp.tvec_mm
        alpha = np.arctan(pc[:2] / pc[2])
        d = spot_for_angles(sp.model, alpha)
        x = signals(rate, 25_000, [(amplitudes(sp.model, d), 1000.0, 0.5)], noise=2e-3, rng=rng)
        wb = MultiCarrierLockin(rate, [1000.0], 0.02).process(0.0, x)
        results.append(angles_from_amplitudes(wb.amplitude[:, 0], sp.model, wb.var_amplitude[:, 0]))
    tri = triangulate_aoa(results, sensors)
    err = tri.p_w_mm - p_true
    maha = np.einsum("wi,wij,wj->w", err, np.linalg.inv(tri.cov_p_mm2), err)
    assert np.all(maha < 14.16)  # chi2(3) at 3 sigma (99.73 %)
    assert np.all(tri.n_sensors == 2)
    assert np.all(tri.sigma_p_mm[:, 2] > tri.sigma_p_mm[:, 0])  # depth is the least certain
    assert np.all(tri.sigma_p_mm < 200.0)


def test_triangulation_covariance_against_monte_carlo():
    sensors = _two_sensors()
    p_true = np.array([-200.0, 150.0, 4000.0])
    R = np.stack([s.R for s in sensors])
    t = np.stack([s.tvec_mm for s in sensors])
    pc = np.einsum("kij,j->ki", R, p_true) + t
    n_true = pc[:, :2] / pc[:, 2:]
    cov = np.array([[[4e-8, 1e-8], [1e-8, 3e-8]], [[2e-8, 0.0], [0.0, 5e-8]]])
    rng = np.random.default_rng(3)
    noise = np.stack([rng.multivariate_normal(np.zeros(2), c, size=2000) for c in cov])  # (2, 2000, 2)
    tri = triangulate(n_true[:, None] + noise, np.broadcast_to(cov[:, None], (2, 2000, 2, 2)), R, t)
    err = tri.p_w_mm - p_true
    emp = err.T @ err / len(err)
    np.testing.assert_allclose(np.sqrt(np.diag(emp)), np.sqrt(np.diag(tri.cov_p_mm2[0])), rtol=0.08)
    # a sensor that does not see the point: NaN, and the point from the others
    n_missing = n_true.copy()
    n_missing[1] = np.nan
    one = triangulate(n_missing, cov, R, t)
    assert np.isnan(one.p_w_mm).all() and one.n_sensors == 1


def test_sensor_model_loading(tmp_path):
    d = calib_dict(fy=8.1, gains=[1, 1.01, 1.0, 0.99])
    p = tmp_path / "calib.json"
    p.write_text(json.dumps(d))
    m = SensorModel.load(p)
    assert m.intrinsics.fy_mm == 8.1 and m.names[-1] == "g_y2" and m.has_gains
    assert SensorModel.from_dict(m.to_dict()).names == m.names
    # std fallback (no covariance): diagonal from the non-null std entries
    d2 = {k: v for k, v in d.items() if k != "covariance"}
    d2["std"] = {"f_mm": 0.01, "cx_mm": None, "k1": 1e-5}
    m2 = SensorModel.from_dict(d2)
    assert m2.names == ("f_mm", "k1") and np.allclose(m2.std(), [0.01, 1e-5])
    bad = [
        ({"distortion": {}}, "intrinsics"),
        ({**d, "intrinsics": {"f_mm": -1, "cx_mm": 0, "cy_mm": 0}}, "intrinsics.f_mm"),
        ({**d, "covariance": {"names": ["f_mm", "zz"], "matrix": [[1, 0], [0, 1]]}}, "covariance.names"),
        ({**d, "covariance": {"names": ["f_mm"], "matrix": [[1, 0], [0, 1]]}}, "covariance.matrix"),
        ({**d, "gains": [1, 2]}, "gains"),
    ]
    for data, key in bad:
        p.write_text(json.dumps(data))
        with pytest.raises(InputError, match=key.replace(".", r"\.")) as exc:
            SensorModel.load(p)
        assert "calib.json" in str(exc.value)
    p.write_text("{not json")
    with pytest.raises(InputError, match="calib.json:1"):
        SensorModel.load(p)


@pytest.mark.parametrize("mode", ["sigma", "mean+2std"])
def test_error_map(tmp_path, mode):
    m = model()
    emap = error_map(m, 5000.0, mode=mode, grid=9)
    assert emap.aoa_error_deg.shape == (9, 9) and np.all(emap.aoa_error_deg > 0)
    centre = emap.aoa_error_deg[4, 4]
    assert emap.aoa_error_deg.max() > centre  # grows towards the edges
    if mode == "sigma":
        res = angles_from_points(np.array([emap.d_x_mm[0], emap.d_y_mm[0]]), m)
        np.testing.assert_allclose(emap.aoa_error_deg[0, 0], np.degrees(np.hypot(*res.sigma_alpha_rad)))
    plot_error_map(emap, tmp_path / "e.png")
    assert (tmp_path / "e.png").read_bytes()[:4] == b"\x89PNG"


def test_compiled_impact_rows_equal_numpy_reference():
    """The compiled impact points of locate's rows (psdcal.measure._impact_kernel) against
    impact_from_amplitudes: d, its covariance and dd/dgains equal to rounding (1e-12 relative), NaN rows
    where the gain-corrected sum is not positive or a value is not finite."""
    from psdcal import _jit
    from psdcal.measure._impact_kernel import impact_compiled
    from psdcal.measure.aoa import impact_from_amplitudes
    from psdcal.measure.sensor_model import SensorModel

    if not _jit.enabled():
        pytest.skip("numba disabled")
    m = SensorModel.from_dict({"intrinsics": {"f_mm": 8.0, "cx_mm": 0.1, "cy_mm": -0.2},
                               "gains": [1.0, 1.03, 0.97, 1.01]})
    rng = np.random.default_rng(11)
    a = rng.uniform(0.01, 1.0, (500, 4)) * rng.choice([1.0, 1e-3, 1e3], (500, 1))
    var = rng.uniform(1e-8, 1e-5, (500, 4))
    a[7] = [0.2, -0.2, 0.1, -0.1]  # a sum near zero (after the gains: small, either way)
    a[9] = [-0.2, -0.1, -0.1, -0.1]  # negative sum
    a[11, 2] = np.nan
    a[13, 0] = np.inf
    ref = impact_from_amplitudes(a, m, var, on_zero="nan")
    d, cov, ddg, bad = impact_compiled(a, m.gains, var, m.lx_mm, m.ly_mm)
    want_bad = np.isnan(ref.d_mm).any(axis=-1)
    assert set(np.flatnonzero(want_bad)) >= {9, 11, 13}
    np.testing.assert_array_equal(bad, want_bad)
    for got, exp, what in ((d, ref.d_mm, "d"), (cov, ref.cov_d_mm2, "cov"), (ddg, ref.dd_dgains, "dd_dg")):
        assert np.all(np.isnan(got[bad])) and np.all(np.isnan(exp[bad])), what
        ok = ~bad
        scale = np.abs(exp[ok]).reshape(ok.sum(), -1).max(axis=1)
        err = np.abs(got[ok] - exp[ok]).reshape(ok.sum(), -1).max(axis=1)
        assert np.all(err <= 1e-12 * scale), what


def test_compiled_channel_sum_check_equals_numpy():
    """SumCheck.add by the compiled loop against its numpy code: the same rows used, the sums (chi2, its
    gain terms, RMS and largest D) equal to rounding, rows with a non-positive or non-finite sum skipped."""
    from psdcal import _jit
    from psdcal.measure.channel_order import SumCheck

    if not _jit.enabled():
        pytest.skip("numba disabled")
    rng = np.random.default_rng(12)
    a = rng.uniform(0.05, 1.0, (3000, 4))
    var = rng.uniform(1e-8, 1e-5, (3000, 4))
    a[5] = [-0.2, -0.1, -0.1, -0.1]
    a[6, 1] = np.nan
    var[7, 0] = np.inf
    a[8] = 0.0
    gains, cov = [1.0, 1.02, 0.98, 1.01], np.diag([1e-6, 2e-6, 1e-6])
    ref, fast = SumCheck(gains, 9.0, "x", cov), SumCheck(gains, 9.0, "x", cov)
    for part in np.array_split(np.arange(3000), 3):
        with np.errstate(all="ignore"):
            ref.add(a[part], var[part])
        fast.add(a[part], var[part], compiled=True)
    assert fast.n == ref.n and 3000 - 4 <= ref.n < 3000
    for f in ("s0", "sum_d2", "max_abs_d", "chi2"):
        assert abs(getattr(fast, f) - getattr(ref, f)) <= 1e-12 * abs(getattr(ref, f)), f
    np.testing.assert_allclose(fast.u, ref.u, rtol=1e-12, atol=1e-12 * np.abs(ref.u).max())
    np.testing.assert_allclose(fast.m, ref.m, rtol=1e-12, atol=1e-12 * np.abs(ref.m).max())
