"""The verdict's compiled field tests (psdcal.calibration._fields_kernel) against the numpy code they replace.

The F-test's and the restricted refit's small-matrix steps (:func:`psdcal.calibration._verdict_fields._basis`,
:func:`psdcal.calibration._verdict_fields.field_shift`), their symmetric eigensolver, the angles' shifts of
:func:`psdcal.calibration._verdict_linear.effect` and the fields' products from their parts side by side
(:class:`psdcal.calibration._verdict_blocks.FieldParts`): equal to rounding (relative 1e-10 on statistics and
coefficients), the same dimensions, on a fit whose structure check finds a field and on constructed matrices.
"""
from __future__ import annotations

import numpy as np
import pytest

from psdcal import _jit
from psdcal.calibration import _verdict_blocks as VB
from psdcal.calibration import _verdict_fields as VF
from psdcal.calibration import _verdict_linear as L

pytestmark = pytest.mark.skipif(not _jit.AVAILABLE, reason="numba not installed")


@pytest.fixture
def fit(lens2_radial1_fit):
    """Lens 2 fitted with radial 1 (conftest): the structure check finds the missing terms."""
    return lens2_radial1_fit


def _numpy(monkeypatch, fn):
    """``fn()`` on the numpy path (the compiled kernels switched off for its duration)."""
    with monkeypatch.context() as m:
        m.setattr(_jit, "use_compiled", lambda *a, **k: False)
        return fn()


def _matrices(rng):
    """Symmetric test matrices: random Gram matrices, graded ones, rank-deficient ones, clustered eigenvalues."""
    out = []
    for n in (1, 2, 3, 6, 14, 22, 29):
        A = rng.standard_normal((n + 3, n))
        out.append(A.T @ A)
        out.append((A * np.logspace(0, -7, n)).T @ (A * np.logspace(0, -7, n)))
        B = A[: max(1, n // 2)]
        out.append(B.T @ B)
        Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
        lam = np.repeat(rng.standard_normal(n // 3 + 1), 3)[:n]
        K = (Q * lam) @ Q.T
        out.append((K + K.T) / 2)
    out.append(np.diag([3.0, 1.0, 2.0, 2.0]))  # already diagonal: no rotation
    return out


def test_eigh_equals_lapack():
    from psdcal.calibration._fields_kernel import _eigh_apply, eigh

    for K in _matrices(np.random.default_rng(5)):
        ok, lam, V = eigh(K)
        assert ok
        ref = np.linalg.eigvalsh(K)
        scale = max(np.abs(ref).max(), 1e-300)
        n = K.shape[0]
        assert np.all(np.diff(lam) >= 0)
        np.testing.assert_allclose(lam, ref, rtol=0, atol=1e-14 * n * scale)
        np.testing.assert_allclose(K @ V, V * lam, rtol=0, atol=1e-14 * n * scale)
        np.testing.assert_allclose(V.T @ V, np.eye(n), rtol=0, atol=1e-14 * n)
        y = np.random.default_rng(n).standard_normal((n, 1))
        z = y.copy()
        assert _eigh_apply(K, z)[0]  # a vector's coordinates on the eigenvectors, without them
        np.testing.assert_allclose(z, V.T @ y, rtol=0, atol=1e-13 * n * np.abs(y).max())
    assert not eigh(np.array([[1.0, np.nan], [np.nan, 1.0]]))[0]


def test_field_coords_and_visible_fit_equal_numpys_on_constructed_columns(monkeypatch):
    """_basis and field_shift's restricted refit on columns with absorbed and nearly dependent ones (the eigenproblem
    path of _span_basis) and on well conditioned ones (its Cholesky path)."""
    from psdcal.calibration import _fields_kernel as fk

    rng = np.random.default_rng(11)
    n_used = 0
    for trial in range(40):
        m, k = 200, int(rng.integers(2, 12))
        B = rng.standard_normal((m, k)) * rng.uniform(0.1, 10, k)
        if trial % 2:
            B[:, -1] = B[:, 0] * 2 + 1e-9 * rng.standard_normal(m)  # nearly dependent: the eigenproblem path
        Jq, _ = np.linalg.qr(np.concatenate([B[:, :1] + 1e-3 * rng.standard_normal((m, 1)),
                                             rng.standard_normal((m, 3))], axis=1))
        Bp = B - Jq @ (Jq.T @ B)  # the first column mostly absorbed
        e = rng.standard_normal(m)
        e -= Jq @ (Jq.T @ e)
        btb, K, bte = B.T @ B, Bp.T @ Bp, B.T @ e
        lin = L.Linear(e, lambda X: X - Jq @ (Jq.T @ X), np.zeros(m), np.zeros((m // 2, 2)), np.zeros(m // 2, int),
                       np.zeros(m // 2, int), 4, names=("a", "b", "c", "d"), g=Jq, perp_pose=lambda X: X)
        ute, W = _numpy(monkeypatch, lambda: VF._basis(lin, B))
        ok, ute_c, W_c = fk.field_coords(btb, K, bte, True)
        assert ok and ute_c.size == ute.size
        assert ute_c @ ute_c == pytest.approx(ute @ ute, rel=1e-10, abs=1e-12 * (e @ e))
        np.testing.assert_allclose(W_c @ ute_c, W @ ute, rtol=0, atol=1e-10 * np.abs(W @ ute).max())
        ok, ute_v, _ = fk.field_coords(btb, K, bte, False)  # the coordinates without the eigenvectors
        assert ok and ute_v.size == ute.size
        np.testing.assert_allclose(np.abs(ute_v), np.abs(ute_c), rtol=0, atol=1e-10 * np.abs(ute_c).max())
        for vis in (0.05, 0.3, 0.9):
            c0, dth0 = _numpy(monkeypatch, lambda: VF.field_shift(lin, B, min_visible=vis))
            c, dth = VF.field_shift(lin, B, min_visible=vis)
            np.testing.assert_allclose(c, c0, rtol=0, atol=1e-9 * max(np.abs(c0).max(), 1e-300))
            np.testing.assert_allclose(dth, dth0, rtol=0, atol=1e-9 * max(np.abs(dth0).max(), 1e-300))
            n_used += bool(np.any(c0))
    assert n_used > 40  # most refits keep some combination


def test_field_tests_and_effect_equal_numpys_on_a_fit(fit, monkeypatch):
    lin = L.linearise(fit)
    cov = lin.s2 * lin.ninv
    cons = L.consequences(lin, fit, cov)
    fields = lambda: VF.structure_fields(lin, fit, parts=True)  # noqa: E731 (a fresh one: no memo shared)
    for B in (fields, lambda: lin.extra):
        got = VF.f_test(lin, B())
        ref = _numpy(monkeypatch, lambda: VF.f_test(lin, B()))
        assert got[2] == ref[2] and got[2] > 0
        np.testing.assert_allclose(got[0], ref[0], rtol=1e-10)
        np.testing.assert_allclose(got[1], ref[1], rtol=1e-8)
    assert VF.f_test(lin, fields())[1] < 1e-3  # the field is found: the shift below is the verdict's
    for vis in (0.0, 0.3):
        c, dth = VF.field_shift(lin, fields(), min_visible=vis)
        c0, dth0 = _numpy(monkeypatch, lambda: VF.field_shift(lin, fields(), min_visible=vis))
        np.testing.assert_allclose(c, c0, rtol=0, atol=1e-9 * np.abs(c0).max())
        np.testing.assert_allclose(dth, dth0, rtol=0, atol=1e-9 * np.abs(dth0).max())
    got, ref = VF.terms_test(lin), _numpy(monkeypatch, lambda: VF.terms_test(lin))
    assert got[2:] == ref[2:] and got[:2] == pytest.approx(ref[:2], rel=1e-10)
    c, dth = VF.field_shift(lin, fields(), min_visible=0.3)
    at = VB.field_parts(cons.grid, fit.intrinsics.c, np.asarray(fit.sensor_mm, float) / 2).field(c)
    dense = (VB.field_basis(cons.grid, fit.intrinsics.c, np.asarray(fit.sensor_mm, float) / 2) @ c).reshape(-1, 2)
    np.testing.assert_allclose(at, dense, rtol=0, atol=1e-12 * np.abs(dense).max())
    for kw in ({"field_at_grid": at}, {"dextra": np.full(len(lin.extra_names), 1e-4)}, {}):
        got = L.effect(cons, dth, **kw)
        ref = _numpy(monkeypatch, lambda: L.effect(cons, dth, **kw))
        assert got.what == ref.what and got.params == pytest.approx(ref.params, rel=1e-12)
        assert (got.sigma, got.angle_rad, got.angle_sigma) == pytest.approx(
            (ref.sigma, ref.angle_rad, ref.angle_sigma), rel=1e-10)


def test_angle_shifts_skip_zero_errors_and_keep_nan():
    from psdcal.calibration._fields_kernel import angle_shifts

    rng = np.random.default_rng(2)
    A = rng.standard_normal((8, 3))
    D = rng.standard_normal((4, 2, 2))
    f = rng.standard_normal((4, 2))
    full = rng.standard_normal(3)
    da = A @ full - np.einsum("kij,kj->ki", D, f).ravel()
    sd = np.array([1.0, 0.0, 2.0, 0.5, 0.0, 1.0, 3.0, 1.0])
    sig, rad, sdp = angle_shifts(A, full, D, f, sd, np.diag([4.0, -1.0, 9.0]))
    ok = sd > 0
    assert sig == pytest.approx(np.max(np.abs(da[ok]) / sd[ok]), rel=1e-13)
    assert rad == pytest.approx(np.max(np.abs(da)), rel=1e-13)
    assert np.array_equal(sdp, [2.0, 0.0, 3.0])
    assert angle_shifts(A, full, D, f, np.zeros(8), np.eye(3))[0] == 0.0  # no standard error: no sigma
    D[1, 0, 0] = np.nan  # row 2: sd 2
    sig, rad, _ = angle_shifts(A, full, D, f, sd, np.eye(3))
    assert np.isnan(sig) and np.isnan(rad)
    D[1, 0, 0] = 1.0
    D[0, 1, 0] = np.nan  # row 1: sd 0, not in the sigma's maximum
    sig, rad, _ = angle_shifts(A, full, D, f, sd, np.eye(3))
    assert np.isfinite(sig) and np.isnan(rad)


def test_field_parts_products_equal_the_dense_fields(fit, monkeypatch):
    lin = L.linearise(fit)
    c, half = fit.intrinsics.c, np.asarray(fit.sensor_mm, float) / 2
    fp = VB.field_parts(lin.pts, c, half)
    ref = _numpy(monkeypatch, lambda: VB.field_parts(lin.pts, c, half))
    assert np.array_equal(fp.mono, ref.mono) and np.array_equal(fp.R, ref.R)
    assert np.array_equal(fp._ext(), ref._ext())  # the kernel's side-by-side parts, numpy's concatenation
    D = fp.dense()
    tol = 1e-13 * np.abs(D).max() ** 2 * D.shape[0]
    np.testing.assert_allclose(fp.gram(), D.T @ D, rtol=0, atol=tol)
    assert np.array_equal(fp.gram(), fp.gram().T)
    np.testing.assert_allclose(fp.t_dot(lin.e), D.T @ lin.e, rtol=0, atol=tol)
    Q = np.random.default_rng(0).standard_normal((D.shape[0], 5))
    np.testing.assert_allclose(fp.coords(Q), Q.T @ D, rtol=0, atol=tol * 10)
    v = 4
    Qv = Q[: D.shape[0] // v * v].reshape(v, -1, 5)
    fp4 = VB.field_parts(lin.pts[: D.shape[0] // v * v // 2], c, half)
    D4 = fp4.dense().reshape(v, -1, D.shape[1])
    np.testing.assert_allclose(fp4.coords_views(Qv), np.swapaxes(Qv, 1, 2) @ D4, rtol=0, atol=tol * 10)
    coef = np.random.default_rng(1).standard_normal(D.shape[1])
    np.testing.assert_allclose(fp.field(coef), (D @ coef).reshape(-1, 2), rtol=0, atol=tol)
