"""The verdict's fast linear algebra and warm-started diagnosis against their references (issue 22, item 1).

The verdict's tests and effects now come from small Gram matrices of the
projected columns (never a tall SVD or QR, never a projected copy of the
fields), its projector from two Cholesky QR passes where the columns are well
conditioned, and the diagnosis refines its alternatives from the fit's own
solution. Each is compared here with the dense computation it replaces,
written out in the test (SVD of the explicitly projected columns, Householder
QR): equal to round-off (relative 1e-8 on statistics, 1e-6 on refitted costs).
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from psdcal.calibration import _verdict_diagnosis as D
from psdcal.calibration import _verdict_fields as VF
from psdcal.calibration import _verdict_linear as L
from psdcal.calibration.core import calibrate
from psdcal.study.faults import random_case
from psdcal.study.simulate import simulate_set


@pytest.fixture(scope="module")
def fit():
    """A chessboard-like fit with a systematic effect (Lens 2 fitted with radial 1: the structure check finds it)."""
    s = simulate_set("lens2", n_images=8, noise_mm=1e-3, seed=4)
    return calibrate(s.template_mm, s.points_mm, radial=1, tangential=False, verdict=False)


def _reference_explained(lin, B):
    """sum of squares of e along span((I - P) B) (singular directions above 1e-2 of the largest), by a tall SVD."""
    Bn = B / np.linalg.norm(B, axis=0)
    Bp = lin.perp(Bn)
    use = np.linalg.norm(Bp, axis=0) > 1e-4
    U, s, _ = np.linalg.svd(Bp[:, use], full_matrices=False)
    U = U[:, s > 1e-2 * s[0]]
    return float(np.sum((U.T @ lin.e) ** 2)), U.shape[1]


def test_gram_of_projected_columns_equals_the_projected_columns_gram(fit):
    lin = L.linearise(fit)
    B = VF.structure_fields(lin, fit)
    Bp = lin.perp(B)
    np.testing.assert_allclose(lin.gram_perp(B), Bp.T @ Bp, rtol=0, atol=1e-9 * np.abs(B.T @ B).max())


def test_explained_and_f_test_equal_the_tall_svd_reference(fit):
    lin = L.linearise(fit)
    for B in (VF.structure_fields(lin, fit), lin.extra):
        ref, dim = _reference_explained(lin, B)
        got, gdim = VF.explained(lin, B)
        assert gdim == dim
        assert got == pytest.approx(ref, rel=1e-8)
    _, p, _, _ = VF.f_test(lin, VF.structure_fields(lin, fit))
    assert p < 1e-3  # the missing k2 shows: the effect branch below is exercised


def test_field_shift_equals_the_qr_svd_reference(fit):
    lin = L.linearise(fit)
    B = VF.structure_fields(lin, fit)
    for vis in (0.0, 0.3):
        c, dth = VF.field_shift(lin, B, min_visible=vis)
        # reference: the dense computation (QR of B, SVD of its projection), as the verdict did before
        scale = np.linalg.norm(B, axis=0)
        Qb, Rb = np.linalg.qr(B / scale)
        U, s, Vt = np.linalg.svd(lin.perp(Qb), full_matrices=False)
        use = s > max(vis, 1e-2 * s[0] if vis <= 0 else 0.0)
        if vis <= 0:  # the unrestricted refit: every direction the parameters leave visible (1e-2 of the largest)
            Bn = B / scale
            Bp = lin.perp(Bn)
            keepc = np.linalg.norm(Bp, axis=0) > 1e-4
            U2, s2, Vt2 = np.linalg.svd(Bp[:, keepc], full_matrices=False)
            k = s2 > 1e-2 * s2[0]
            cref = np.zeros(B.shape[1])
            cref[keepc] = (Vt2[k].T / s2[k]) @ (U2[:, k].T @ lin.e) / scale[keepc]
        else:
            a = Vt[use].T @ ((U[:, use].T @ lin.e) / s[use])
            cref = np.linalg.solve(Rb, a) / scale
        dref = -lin.ninv @ (lin.gt.T @ (B @ cref))
        np.testing.assert_allclose(B @ c, B @ cref, rtol=0, atol=1e-7 * np.abs(B @ cref).max())
        np.testing.assert_allclose(dth, dref, rtol=0, atol=1e-7 * np.abs(dref).max())


def test_cholesky_qr_projector_equals_the_householder_one(fit, monkeypatch):
    lin = L.linearise(fit)
    B = VF.structure_fields(lin, fit)
    monkeypatch.setattr(L, "_cholqr2", lambda A, unit_columns=True: None)  # the Householder path
    monkeypatch.setattr(L, "_compiled_bases", lambda *a: None)  # (the compiled Cholesky QR too)
    ref = L.linearise(fit)
    assert ref.n == lin.n
    np.testing.assert_allclose(lin.h, ref.h, rtol=0, atol=1e-10)
    np.testing.assert_allclose(lin.perp(B), ref.perp(B), rtol=0, atol=1e-10 * np.abs(B).max())
    np.testing.assert_allclose(lin.e, ref.e, rtol=0, atol=1e-10 * np.abs(ref.e).max())


def test_cholesky_qr_refuses_ill_conditioned_columns():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(200, 4))
    Q = L._cholqr2(A)
    np.testing.assert_allclose(Q.T @ Q, np.eye(4), atol=1e-13)
    np.testing.assert_allclose(Q @ (Q.T @ A), A, atol=1e-12)
    A[:, 3] = A[:, 2] + 1e-7 * A[:, 1]  # condition ~1e7
    assert L._cholqr2(A) is None
    blocks = rng.normal(size=(5, 40, 6))
    Qs = L._cholqr2(blocks)
    for q, a in zip(Qs, blocks):
        np.testing.assert_allclose(q.T @ q, np.eye(6), atol=1e-13)
        np.testing.assert_allclose(q @ (q.T @ a), a, atol=1e-12)


def test_field_basis_columns_are_the_documented_fields():
    rng = np.random.default_rng(2)
    pts = rng.uniform(-4, 4, size=(30, 2))
    c, half = np.array([0.2, -0.1]), np.array([4.5, 4.5])
    B = L.field_basis(pts, c, half)
    u = pts / half
    cols = []
    for i in range(L.FIELD_DEGREE + 1):
        for j in range(L.FIELD_DEGREE + 1 - i):
            mono = u[:, 0] ** i * u[:, 1] ** j
            cols += [np.stack([mono, 0 * mono], 1).ravel(), np.stack([0 * mono, mono], 1).ravel()]
    d = (pts - c) / half
    r2 = np.sum(d * d, axis=1)
    cols += [(d * r2[:, None] ** 2).ravel(), (d * r2[:, None] ** 3).ravel()]
    np.testing.assert_allclose(B, np.stack(cols, 1), rtol=1e-14, atol=1e-15)


def test_rerun_of_a_fresh_fit_is_that_fit_and_a_changed_one_is_refitted(fit):
    assert D._refit(fit) is fit  # deterministic: the diagnosis' re-run reuses it
    other = D._refit(fit, radial=2)
    assert other is not None and other is not fit and other.model.radial == 2


def test_warm_refit_reaches_the_full_refits_cost():
    """The diagnosis' alternatives refined from the fit's solution reach the cost of a full calibration."""
    c = random_case(90_003, fault="no_k2")
    r = calibrate(c.template_mm, c.points_mm, **c.model, verdict=False)
    for ch in ({"radial": r.model.radial + 1}, {"tangential": True}, {"aspect": True}):
        warm = D._warm_refit(r, **ch)
        full = D._refit(r, **ch)
        assert warm is not None and full is not None
        assert D._ssr(warm) == pytest.approx(D._ssr(full), rel=1e-6)
        assert warm.intrinsics.f_mm == pytest.approx(full.intrinsics.f_mm, rel=1e-6)
    w = D._warm_refit(r, drop_image=1)
    f = D._refit(r, drop_image=1)
    assert w.sigma_mm == pytest.approx(f.sigma_mm, rel=1e-6)


def test_screened_model_refits_keep_the_diagnosis(fit):
    """The missing k2 is still named by the diagnosis (its linearised refit passes the screen)."""
    from psdcal.calibration.verdict import assess

    v = assess(fit, points_kind="points")
    assert any("--radial 2" in ch.advice for ch in v.failed)


def test_rerun_of_a_failed_fit_fails_the_same_way_without_refitting():
    from psdcal.calibration._refine import SolverOptions
    from psdcal.errors import ConvergenceError

    s = simulate_set("lens2", n_images=6, noise_mm=1e-3, seed=5)
    with pytest.raises(ConvergenceError) as info:
        calibrate(s.template_mm, s.points_mm, solver=SolverOptions(max_iterations=1), verdict=False)
    failed = info.value.result
    assert failed is not None
    assert D._refit(failed) is None  # the re-run raises the same error (a refit that fails names nothing)
    from psdcal.calibration.core import _calibrate_record

    with pytest.raises(ConvergenceError):
        _calibrate_record(failed, reuse=True)
    with pytest.raises(ConvergenceError):  # without the reuse: the calibration itself fails again
        _calibrate_record(failed)


def test_median_without_numpy_ma_is_numpys():
    from psdcal.calibration.verdict import _median

    rng = np.random.default_rng(0)
    for n in (1, 2, 3, 4, 7, 12):
        x = rng.normal(size=n)
        assert _median(x) == float(np.median(x))
    assert np.isnan(_median(np.array([1.0, np.nan, 2.0])))


def test_field_parts_products_equal_the_dense_fields(fit):
    lin = L.linearise(fit)
    fp = VF.structure_fields(lin, fit, parts=True)
    B = fp.dense()
    np.testing.assert_array_equal(B, VF.structure_fields(lin, fit))
    rng = np.random.default_rng(3)
    Q = rng.normal(size=(B.shape[0], 5))
    np.testing.assert_allclose(fp.coords(Q), Q.T @ B, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fp.gram(), B.T @ B, rtol=1e-12, atol=1e-12)
    n_img = int(lin.img.max()) + 1
    Qbt = rng.normal(size=(n_img, 6, B.shape[0] // n_img))
    ref = np.matmul(Qbt, B.reshape(n_img, -1, B.shape[1])).reshape(-1, B.shape[1])
    np.testing.assert_allclose(fp.coords_blocks(Qbt), ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(lin.gram_perp(fp), lin.gram_perp(B), rtol=0, atol=1e-9 * np.abs(B.T @ B).max())
    assert VF.explained(lin, fp) == pytest.approx(VF.explained(lin, B), rel=1e-10)


def _angles_written_out(intr, dist, d):
    """Angles of arrival (K, 2) of sensor points d (K, 2): the ideal point by undistortion, then the ray of
    x = f X/Z + skew Y/Z + cx, y = fy Y/Z + cy."""
    from psdcal.model.distortion import undistort

    x = undistort(d, dist, np.array([intr.cx_mm, intr.cy_mm]))
    ty = (x[:, 1] - intr.cy_mm) / intr.fy
    tx = (x[:, 0] - intr.cx_mm - intr.skew * ty) / intr.f_mm
    return np.stack([np.arctan(tx), np.arctan(ty)], axis=1)


@pytest.mark.parametrize("kw", [{"radial": 1, "tangential": False}, {"skew": True, "psd_radial": 1}, {"aspect": True}])
def test_analytic_angle_sensitivities_equal_central_differences(kw):
    """consequences()' d(angle)/d(parameter) and d(angle)/d(sensor point), analytic, against central differences of
    the angles written out here (relative 1e-6 of each column's largest entry; the differences' own error ~1e-9)."""
    from dataclasses import replace

    s = simulate_set("lens2", n_images=8, noise_mm=1e-3, seed=5)
    res = calibrate(s.template_mm, s.points_mm, verdict=False, **kw)
    lin = L.linearise(res)
    cons = L.consequences(lin, res)
    g = cons.grid
    intr, dist = res.intrinsics, res.distortion
    for k, n in enumerate(cons.names):
        if n in ("f_mm", "fy_mm", "cx_mm", "cy_mm", "skew"):
            v = intr.fy if n == "fy_mm" else getattr(intr, n)
            h = 1e-6 * max(abs(v), 1e-2)
            up = _angles_written_out(replace(intr, **{n: v + h}), dist, g)
            dn = _angles_written_out(replace(intr, **{n: v - h}), dist, g)
        else:
            v = getattr(dist, n)
            h = 1e-7 * max(abs(v), 1e-2)
            up = _angles_written_out(intr, replace(dist, **{n: v + h}), g)
            dn = _angles_written_out(intr, replace(dist, **{n: v - h}), g)
        ref = ((up - dn) / (2 * h)).ravel()
        np.testing.assert_allclose(cons.A[:, k], ref, rtol=0, atol=1e-6 * np.abs(ref).max(), err_msg=n)
    for j in range(2):
        dg = np.zeros(2)
        dg[j] = 1e-6
        ref = (_angles_written_out(intr, dist, g + dg) - _angles_written_out(intr, dist, g - dg)) / 2e-6
        np.testing.assert_allclose(cons.D[:, :, j], ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    # and the previous finite-difference version (one-sided steps of 1e-2 sigma) to its truncation error
    old = L.consequences_reference(lin, res)
    np.testing.assert_allclose(cons.sd, old.sd, rtol=1e-3)


def _numpy_linear(fit, monkeypatch):
    """``linearise(fit)`` on the numpy projector (the reference of the compiled one)."""
    with monkeypatch.context() as m:
        m.setattr(L, "_compiled_bases", lambda *a: None)
        return L.linearise(fit)


@pytest.mark.skipif(not __import__("psdcal._jit", fromlist=["x"]).enabled(), reason="numba not available")
@pytest.mark.parametrize("case", ["structured", "correct"])
def test_compiled_projector_equals_the_numpy_one(fit, case, monkeypatch):
    """The compiled projector (psdcal.calibration._verdict_kernel) against the numpy code it replaces on the dense
    layout: the same rank, leverages, residuals and projections (relative 1e-9 of the largest entry; both are
    orthonormal bases of the same spans to ~1e-13), the same statistics (relative 1e-8) and decisions."""
    from psdcal.calibration.verdict import assess

    monkeypatch.setattr(L, "COMPILED_PROJECTOR_MAX_POINTS", 10 ** 9)  # whatever the fit's size
    if case == "correct":
        s = simulate_set("lens1", n_images=6, noise_mm=2e-3, seed=11)
        fit = calibrate(s.template_mm, s.points_mm, radial=2, tangential=False, verdict=False)
    used = []
    real = L._compiled_bases
    monkeypatch.setattr(L, "_compiled_bases", lambda *a: used.append(1) or real(*a))
    lin = L.linearise(fit)
    assert used, "the dense layout takes the compiled projector"
    ref = _numpy_linear(fit, monkeypatch)
    assert lin.n == ref.n
    fp = VF.structure_fields(lin, fit, parts=True)
    B = fp.dense()
    rng = np.random.default_rng(5)
    R = rng.normal(size=(B.shape[0], 4))

    def close(a, b, tol=1e-9):
        np.testing.assert_allclose(a, b, rtol=0, atol=tol * max(np.abs(b).max(), 1e-300))

    close(lin.h, ref.h)
    close(lin.e, ref.e)
    for M in (B, R, lin.extra):
        close(lin.perp(M), ref.perp(M))
        close(lin.perp_pose(M), ref.perp_pose(M))
        close(lin.gram_perp(M), ref.gram_perp(M))
    close(lin.gram_perp(fp), ref.gram_perp(VF.structure_fields(ref, fit, parts=True)))
    close(lin.gt, ref.gt)
    close(lin.ninv, ref.ninv, 1e-8)
    monkeypatch.setattr(L, "_compiled_bases", real)
    v = assess(fit, diagnose=False)
    with monkeypatch.context() as m:
        m.setattr(L, "_compiled_bases", lambda *a: None)
        vref = assess(fit, diagnose=False)
    assert v.verdict == vref.verdict
    for c, cr in zip(v.checks, vref.checks, strict=True):
        assert (c.name, c.passed, c.severe, c.advice) == (cr.name, cr.passed, cr.severe, cr.advice)
        for a, b in ((c.statistic, cr.statistic), (c.p_value, cr.p_value), (c.effect_sigma, cr.effect_sigma),
                     (c.inflation, cr.inflation)):
            assert (a is None) == (b is None)
            if a is not None and np.isfinite(b):
                assert a == pytest.approx(b, rel=1e-8, abs=1e-300)


@pytest.mark.skipif(not __import__("psdcal._jit", fromlist=["x"]).enabled(), reason="numba not available")
def test_compiled_projector_hands_ill_conditioned_columns_to_the_numpy_code():
    """A view whose pose columns are (nearly) dependent, or a global column the poses absorb, fails the compiled
    path's conditioning test (as the numpy Cholesky QR's): the projector then comes from the numpy code."""
    from psdcal.calibration import _verdict_kernel as vk

    rng = np.random.default_rng(2)
    Jb = rng.normal(size=(4, 30, 6))
    G = rng.normal(size=(120, 3))
    ok, Qb, Qg, h = vk.bases(Jb.reshape(120, 6), 30, G, L.CHOLQR_MAX_COND, L.CHOLQR_ONE_PASS_COND)
    assert ok
    for q, a in zip(Qb.reshape(4, 30, 6), Jb):
        np.testing.assert_allclose(q.T @ q, np.eye(6), atol=1e-12)
        np.testing.assert_allclose(q @ (q.T @ a), a, atol=1e-11)
    np.testing.assert_allclose(Qg.T @ Qg, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(Qb.T @ Qg, np.zeros((6, 3)), atol=1e-12)  # the global basis off the poses
    np.testing.assert_allclose(h, np.sum(Qb * Qb, axis=1) + np.sum(Qg * Qg, axis=1), atol=1e-14)
    bad = Jb.copy()
    bad[2, :, 5] = bad[2, :, 4] + 1e-7 * bad[2, :, 3]  # condition ~1e7 in view 2
    assert not vk.bases(bad.reshape(120, 6), 30, G, L.CHOLQR_MAX_COND, L.CHOLQR_ONE_PASS_COND)[0]
    Gbad = G.copy()
    Gbad[:, 1] = Jb.reshape(120, 6)[:, 0] + 1e-9 * G[:, 1]  # a global column inside the poses' span
    assert not vk.bases(Jb.reshape(120, 6), 30, Gbad, L.CHOLQR_MAX_COND, L.CHOLQR_ONE_PASS_COND)[0]
    row_img = np.repeat(np.arange(4), 30)
    perp = L.projector(Gbad, bad.reshape(120, 6), row_img, 4)[0]  # the numpy path, no error
    B = rng.normal(size=(120, 2))
    Bp = perp(B)
    np.testing.assert_allclose(perp(Bp), Bp, atol=1e-9)  # a projector


def test_pinv_sym_equals_numpys_pinv():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(6, 4)) * np.array([1.0, 1e3, 1e-2, 5.0])
    N = A @ A.T  # rank 4 of 6, badly scaled
    d = np.sqrt(np.diag(N))
    ref = np.linalg.pinv(N / np.outer(d, d), rcond=1e-12, hermitian=True) / np.outer(d, d)
    np.testing.assert_allclose(L._pinv_sym(N), ref, rtol=0, atol=1e-10 * np.abs(ref).max())
    np.testing.assert_allclose(L._pinv_sym(np.zeros((0, 0))), np.zeros((0, 0)))


@pytest.mark.skipif(not __import__("psdcal._jit", fromlist=["x"]).enabled(), reason="numba not available")
def test_compiled_jacobi_eigenproblem_equals_numpys():
    """The compiled projector's small symmetric eigenproblems (cyclic Jacobi) against np.linalg.eigh: eigenvalues
    to 1e-13 of the largest, eigenvectors up to sign to 1e-10 (distinct eigenvalues), orthonormal to 1e-13."""
    from psdcal.calibration import _verdict_kernel as vk

    rng = np.random.default_rng(8)
    for k, scale in ((6, 1.0), (8, 1e4), (3, 1e-6)):
        A = rng.normal(size=(50, k)) * np.logspace(0, 2, k) * scale
        K = A.T @ A
        lam, V = vk._eigh_jacobi(K)
        lref, Vref = np.linalg.eigh(K)
        np.testing.assert_allclose(lam, lref, rtol=0, atol=1e-13 * lref[-1])
        np.testing.assert_allclose(V.T @ V, np.eye(k), atol=1e-13)
        np.testing.assert_allclose(np.abs(np.sum(V * Vref, axis=0)), np.ones(k), atol=1e-10)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-3.0, 3.0)] * 3), min_size=1, max_size=40))
def test_template_normals_are_the_rotated_z_axis_for_few_and_many_views(rvecs):
    """The verdict's template normals (floats for a few views, numpy for many) are R(rvec) e_z (Rodrigues,
    written independently in this file's ``_rot``), and both paths give the same numbers."""
    from psdcal.calibration import _verdict_rules as R

    r = np.array(rvecs, dtype=float)
    n = R._normals(r)
    want = np.array([_rot(v)[:, 2] for v in r])
    np.testing.assert_allclose(n, want, atol=1e-12)
    many = R._normals(np.concatenate([r] * (R._FEW_VIEWS // len(r) + 1)))[: len(r)]  # the numpy path
    np.testing.assert_allclose(n, many, rtol=0, atol=1e-15)


def _rot(r):
    """Rotation matrix of a rotation vector (Rodrigues' formula with the cross-product matrix)."""
    th = float(np.linalg.norm(r))
    if th == 0.0:
        return np.eye(3)
    k = np.asarray(r, float) / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
