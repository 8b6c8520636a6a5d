"""The verdict's projector from each view's Gram matrix (psdcal.calibration._verdict_blocks) against the QR one.

:func:`~psdcal.calibration._verdict_blocks.normal_bases` builds the bases of the
fit's Jacobian from the per-view Gram matrices (a Schur complement over the pose
blocks) where the QR path (:func:`~psdcal.calibration._verdict_linear.projector`)
factors the tall blocks. Both are compared here: the same spans, leverages,
projections, Gram matrices, ``Gt``, ``Ninv`` and group shifts (to round-off) and
the same verdict; the compiled transforms against their numpy reference; the
hand-over to the QR path on ill-conditioned blocks and other layouts; and the
left-out terms' test that computes only the p-value it needs against all of them.
"""
from __future__ import annotations

import numpy as np
import pytest

from psdcal import _stats
from psdcal.calibration import _verdict_blocks as VB
from psdcal.calibration import _verdict_fields as VF
from psdcal.calibration import _verdict_linear as L

needs_numba = pytest.mark.skipif(not __import__("psdcal._jit", fromlist=["x"]).enabled(),
                                 reason="numba not available")


@pytest.fixture
def fit(lens2_radial1_fit):
    """Lens 2 fitted with radial 1 (conftest): the structure check finds the missing terms."""
    return lens2_radial1_fit


def _pair(fit, monkeypatch):
    """(linearised from the Gram matrices, linearised by QR) of ``fit``."""
    with monkeypatch.context() as m:
        m.setattr(L, "NORMAL_BASES_MIN_POINTS", 0)
        lin = L.linearise(fit)
    with monkeypatch.context() as m:
        m.setattr(L, "NORMAL_BASES_MIN_POINTS", 10 ** 9)
        ref = L.linearise(fit)
    return lin, ref


def _close(a, b, tol=1e-9):
    np.testing.assert_allclose(a, b, rtol=0, atol=tol * max(np.abs(b).max(), 1e-300))


def test_gram_projector_equals_the_qr_one(fit, monkeypatch):
    lin, ref = _pair(fit, monkeypatch)
    assert lin.blocks is not None and ref.blocks is None
    assert lin.n == ref.n
    _close(lin.h, ref.h)
    _close(lin.e, ref.e)
    fp = VF.structure_fields(lin, fit, parts=True)
    B = fp.dense()
    R = np.random.default_rng(3).normal(size=(B.shape[0], 3))
    for M in (B, R, np.ascontiguousarray(lin.extra)):
        _close(lin.perp(M), ref.perp(M))
        _close(lin.perp_pose(M), ref.perp_pose(M))
        _close(lin.gram_perp(M), ref.gram_perp(M))
        _close(lin.gt_t(M), ref.gt.T @ M)
    _close(lin.gram_perp(fp), ref.gram_perp(VF.structure_fields(ref, fit, parts=True)))
    _close(lin.gt_t(fp), ref.gt.T @ B)
    # the left-out terms' Gram matrices and Gt^T E from the per-view Gram matrices alone
    _close(lin.extra_gram[0], ref.extra_gram[0])
    _close(lin.extra_gram[1], ref.extra_gram[1])
    _close(lin.gt_t(lin.extra), ref.gt.T @ ref.extra)
    _close(lin.gt, ref.gt)
    _close(lin.gtg, ref.gt.T @ ref.gt)
    _close(lin.ninv, ref.ninv, 1e-8)
    # each view's Schur complement is that view's Gt_v^T Gt_v
    row_img = np.repeat(lin.img, 2)
    for v in range(len(fit.image_ids)):
        gv = ref.gt[row_img == v]
        _close(lin.blocks.gtg_view[v], gv.T @ gv)
    for rows in (np.repeat(lin.img == 2, 2), np.repeat(lin.led == 5, 2)):
        _close(L.group_shift(lin, rows), L.group_shift(ref, rows), 1e-8)
    for fn in (lambda x: VF.field_shift(x, VF.structure_fields(x, fit, parts=True), min_visible=0.3),
               lambda x: VF.field_shift(x, x.extra)):
        for a, b in zip(fn(lin), fn(ref), strict=True):
            _close(a, b, 1e-8)


def test_gram_projector_gives_the_same_verdict(fit, monkeypatch):
    from psdcal.calibration.verdict import assess

    with monkeypatch.context() as m:
        m.setattr(L, "NORMAL_BASES_MIN_POINTS", 0)
        used = []
        real = L.normal_bases
        m.setattr(L, "normal_bases", lambda *a, **k: used.append(1) or real(*a, **k))
        v = assess(fit, diagnose=False)
        assert used
    with monkeypatch.context() as m:
        m.setattr(L, "NORMAL_BASES_MIN_POINTS", 10 ** 9)
        vref = assess(fit, diagnose=False)
    assert v.verdict == vref.verdict
    assert any(c.passed is False for c in v.checks)  # the effects (field and group shifts) are exercised
    for c, cr in zip(v.checks, vref.checks, strict=True):
        assert (c.name, c.passed, c.severe, c.advice, c.message) == (cr.name, cr.passed, cr.severe, cr.advice,
                                                                     cr.message)
        for a, b in ((c.statistic, cr.statistic), (c.p_value, cr.p_value), (c.effect_sigma, cr.effect_sigma),
                     (c.inflation, cr.inflation)):
            assert (a is None) == (b is None)
            if a is not None and np.isfinite(b):
                assert a == pytest.approx(b, rel=1e-8, abs=1e-300)


def _blocks(rng, v=4, nr=40, g=3, ne=2):
    X = rng.normal(size=(v * nr, 6 + g + ne)) * np.logspace(0, 1, 6 + g + ne)
    Xb = X.reshape(v, nr, -1)
    return X, np.matmul(np.swapaxes(Xb, 1, 2), Xb)


def test_normal_transforms_give_orthonormal_bases_of_the_columns():
    """[Qb_v | Qg_v] = [A_v | G_v] T_v: orthonormal, Qb_v spans A_v, Qg is orthogonal to every view's poses and
    spans Gt (the global columns less their part on the poses), Gt = Qg Rg, gtg_view[v] = Gt_v^T Gt_v."""
    rng = np.random.default_rng(7)
    X, K = _blocks(rng)
    ok, T, Rg, gtg_view = VB.normal_transforms(K, 3)
    assert ok
    Xb = X.reshape(4, 40, -1)
    Q = np.matmul(Xb[:, :, :9], T)
    Qg = Q[:, :, 6:].reshape(-1, 3)
    np.testing.assert_allclose(Qg.T @ Qg, np.eye(3), atol=1e-12)
    Gt = []
    for v in range(4):
        A, G = Xb[v, :, :6], Xb[v, :, 6:9]
        Qb = Q[v, :, :6]
        np.testing.assert_allclose(Qb.T @ Qb, np.eye(6), atol=1e-12)
        np.testing.assert_allclose(Qb @ (Qb.T @ A), A, atol=1e-11 * np.abs(A).max())
        np.testing.assert_allclose(Qb.T @ Q[v, :, 6:], np.zeros((6, 3)), atol=1e-12)
        Gt.append(G - A @ np.linalg.lstsq(A, G, rcond=None)[0])
        np.testing.assert_allclose(gtg_view[v], Gt[-1].T @ Gt[-1], atol=1e-11 * np.abs(G.T @ G).max())
    Gt = np.concatenate(Gt)
    np.testing.assert_allclose(Qg @ Rg, Gt, atol=1e-11 * np.abs(Gt).max())


@needs_numba
def test_compiled_normal_transforms_equal_numpys():
    """The compiled transforms (Jacobi eigenproblems) against the numpy reference (LAPACK): the same Schur
    complements, the same projectors per view (Q Q^T; the eigenvectors may differ in sign), the same Gt = Qg Rg,
    and the same refusals."""
    from psdcal.calibration import _verdict_kernel as vk

    rng = np.random.default_rng(11)
    for g in (0, 1, 3, 8):
        X, K = _blocks(rng, v=5, nr=30, g=g, ne=1)
        ok, T, Rg, gv = VB.normal_transforms(K, g)
        ok2, T2, Rg2, gv2 = vk.normal_transforms(K, g, float(VB.CHOLQR_ONE_PASS_COND))
        assert ok and ok2
        np.testing.assert_allclose(gv2, gv, rtol=0, atol=1e-12 * np.abs(K).max())
        Xb = X.reshape(5, 30, -1)[:, :, :6 + g]
        Q, Q2 = np.matmul(Xb, T), np.matmul(Xb, T2)
        for v in range(5):
            for sl in (slice(0, 6), slice(6, 6 + g)):
                _close(Q2[v, :, sl] @ Q2[v, :, sl].T, Q[v, :, sl] @ Q[v, :, sl].T, 1e-11)
        if g:
            _close(Q2[:, :, 6:].reshape(-1, g) @ Rg2, Q[:, :, 6:].reshape(-1, g) @ Rg, 1e-11)
    # ill conditioned: a view's pose columns nearly dependent (cond ~ 1e4 > the one-pass limit 1e3), a global column
    # inside the poses' span, a zero pose column
    X, K = _blocks(rng)
    for bad in ("pose", "global", "zero"):
        Xb = X.copy().reshape(4, 40, -1)
        if bad == "pose":
            Xb[1, :, 5] = Xb[1, :, 4] + 1e-4 * Xb[1, :, 3]
        elif bad == "global":
            Xb[:, :, 7] = Xb[:, :, 0] + 1e-8 * Xb[:, :, 7]
        else:
            Xb[2, :, 0] = 0.0
        Kb = np.matmul(np.swapaxes(Xb, 1, 2), Xb)
        assert not VB.normal_transforms(Kb, 3)[0]
        assert not vk.normal_transforms(Kb, 3, float(VB.CHOLQR_ONE_PASS_COND))[0]


def test_normal_bases_hands_other_layouts_and_ill_conditioned_blocks_to_qr():
    rng = np.random.default_rng(5)
    X, _ = _blocks(rng)
    row_img = np.repeat(np.arange(4), 40)
    assert VB.normal_bases(X, 3, 2, row_img, 4) is not None
    assert VB.normal_bases(X[:-2], 3, 2, row_img[:-2], 4) is None  # views of unequal row counts
    assert VB.normal_bases(X, 3, 2, row_img[::-1].copy(), 4) is None  # views not in order
    Xbad = X.copy()
    Xbad[:40, 5] = Xbad[:40, 4] * (1 + 1e-9)
    assert VB.normal_bases(Xbad, 3, 2, row_img, 4) is None


def test_terms_test_computes_only_the_p_value_it_needs(fit, monkeypatch):
    """terms_test evaluates one single-term p-value (the largest F's) and returns what evaluating all of them
    returned (written out here)."""
    lin = L.linearise(fit)
    calls = []
    real = _stats.f_sf
    monkeypatch.setattr(_stats, "f_sf", lambda *a: calls.append(a) or real(*a))
    got = VF.terms_test(lin)
    assert sum(1 for a in calls if a[1] == 1) == 1
    monkeypatch.setattr(_stats, "f_sf", real)
    # the reference: every term's test, the smallest p-value (then F, then name) against the joint test's
    F, p, p_dim, _ = VF.f_test(lin, lin.extra)
    btb, K = lin.extra_gram
    norms = np.sqrt(np.diag(btb))
    nb = np.sqrt(np.maximum(np.diag(K), 0.0)) / norms
    bte = (lin.extra.T @ lin.e) / norms
    ssr, dof = float(lin.e @ lin.e), lin.dof
    single = []
    for k, name in enumerate(lin.extra_names):
        if nb[k] > 1e-4:
            ek = float((bte[k] / nb[k]) ** 2)
            Fk = ek / ((ssr - ek) / (dof - 1))
            single.append((real(Fk, 1, dof - 1), Fk, name))
    n = 1 + len(single)
    pk, Fk, name = min(single)
    want = (Fk, min(1.0, n * pk), 1, name) if pk < p else (F, min(1.0, n * p), p_dim, name)
    assert got[2:] == want[2:]
    assert got[0] == pytest.approx(want[0], rel=1e-14) and got[1] == pytest.approx(want[1], rel=1e-14)


@needs_numba
def test_compiled_group_f_equals_numpys_to_the_last_bit(fit, monkeypatch):
    """The per-view and per-LED F statistics in one compiled loop: the same numbers as the numpy code, bit for
    bit, including groups too small to test (NaN) and the choice of the worst group."""
    from psdcal import _jit

    lin = L.linearise(fit)
    ssr, dof = float(lin.e @ lin.e), lin.dof
    small = L.Linear(lin.e, lin.perp, np.where(np.repeat(lin.led, 2) == 3, 0.99, lin.h), lin.pts, lin.img,
                                 lin.led, lin.n)  # LED 3 all but absorbed: too few degrees of freedom to test
    cases = [(lin, lin.img, len(fit.image_ids)), (lin, lin.led, len(fit.point_ids)),
             (small, small.led, len(fit.point_ids))]
    got = [L.group_f(x, g, n, ssr, dof) for x, g, n in cases]
    monkeypatch.setattr(_jit, "use_compiled", lambda *a, **k: False)
    want = [L.group_f(x, g, n, ssr, dof) for x, g, n in cases]
    assert np.isnan(want[2][0][3])
    for (F, pv), (Fr, pvr) in zip(got, want, strict=True):
        assert np.array_equal(F, Fr, equal_nan=True) and np.array_equal(pv, pvr, equal_nan=True)



def test_span_basis_is_orthonormal_on_the_span_by_cholesky_or_eigenproblem():
    """field_shift's basis of span(B): Bn M orthonormal, spanning B (Cholesky where no direction is near-null), and
    with a near-null direction (two equal columns) dropped as the eigenproblem does."""
    rng = np.random.default_rng(12)
    B = rng.normal(size=(200, 6)) @ np.triu(rng.normal(size=(6, 6))) + 0.0
    for Bc, r in ((B, 6), (np.concatenate([B, B[:, :1]], axis=1), 6)):
        Bn = Bc / np.linalg.norm(Bc, axis=0)
        M = VF._span_basis(Bn.T @ Bn)
        assert M.shape == (Bc.shape[1], r)
        Q = Bn @ M
        np.testing.assert_allclose(Q.T @ Q, np.eye(r), atol=1e-9)
        np.testing.assert_allclose(Q @ (Q.T @ Bn), Bn, atol=1e-9)


def test_field_coordinates_memo_belongs_to_its_blocks(fit, monkeypatch):
    """The coordinates of a FieldParts (and their split) are memoised for one Blocks: another Blocks (here the
    bases negated) computes its own."""
    import dataclasses

    lin, _ = _pair(fit, monkeypatch)
    fp = VF.structure_fields(lin, fit, parts=True)
    b1 = lin.blocks
    g1, k1 = b1.gt_t(fp), b1.pgram(fp)
    b2 = dataclasses.replace(b1, Q=-b1.Q)
    np.testing.assert_array_equal(b2.gt_t(fp), -g1)
    np.testing.assert_array_equal(b2.pgram(fp), k1)  # quadratic in the coordinates
    np.testing.assert_array_equal(b1.gt_t(fp), g1)  # the first one's again (the memo now holds the second's)
    np.testing.assert_array_equal(b1.h, b2.h)
    _close(b1.h, np.einsum("vri,vri->vr", b1.Q, b1.Q).reshape(-1), 1e-15)
