"""The fast paths of the linear first stage against their numpy references.

The line-straightness cost has a compiled kernel (used when ``psdcal._jit``
is enabled); poses, collinearity tests and Zhang's V matrix are batched over
the views; the template's lines are memoised. Each must give the reference's
result to round-off, and raise the same errors.
"""
import numpy as np
import pytest
from _degenerate_views import spoilt_set

import psdcal._jit
from psdcal.calibration._closed_form import extrinsics_from_homography, poses_from_homographies, poses_from_homographies_reference
from psdcal.calibration._homography import collinearity, collinearity_batch, homographies
from psdcal.calibration._straightness import (
    _line_residuals,
    _radial_line_residuals_jit,
    estimate_radial,
    find_lines,
    find_lines_reference,
)
from psdcal.calibration.core import initial_estimate
from psdcal.model.distortion import undistort
from psdcal.errors import DegenerateViewsError
from psdcal.model.params import Intrinsics
from psdcal.model.projection import R_from_r, nearest_rotation, nearest_rotation_batch, r_from_R, r_from_R_batch
from psdcal.study.simulate import default_template, simulate_set


@pytest.fixture
def numpy_only(monkeypatch):
    """A context in which the compiled kernels are switched off (the numpy reference runs)."""

    def use():
        # what the dispatch reads (use_compiled checks AVAILABLE; enabled() reports it)
        monkeypatch.setattr(psdcal._jit, "AVAILABLE", False)
        monkeypatch.setattr(psdcal._jit, "enabled", lambda: False)

    return use


def _with_missing(points_mm, rng, fraction=0.08):
    pts = np.array(points_mm, dtype=float)
    miss = rng.random(pts.shape[:2]) < fraction
    pts[miss] = np.nan
    return pts


# -- the straightness kernel ------------------------------------------------------------


@pytest.mark.parametrize("n_terms", [1, 2, 3])
def test_straightness_kernel_equals_line_residuals_of_undistort(rng, n_terms):
    for _ in range(5):
        n_groups = int(rng.integers(1, 30))
        group = np.sort(rng.integers(0, n_groups, 400))
        group = np.unique(group, return_inverse=True)[1].astype(np.int64)  # no empty group
        n_groups = int(group.max()) + 1
        # points near lines, so the groups have a direction
        d_mm = rng.uniform(-4, 4, (n_groups, 2))[group] + rng.normal(0, 0.5, (group.size, 1)) * rng.normal(size=(n_groups, 2))[group]
        d_mm += rng.normal(0, 0.01, d_mm.shape)
        c_mm = rng.normal(0, 0.5, 2)
        k = np.array([1e-2, 3e-5, 2e-7])[:n_terms] * rng.uniform(-2, 2, n_terms)
        z_scale = np.array([16.0, 256.0, 4096.0])[:n_terms]
        coef = np.zeros(7)
        coef[:n_terms] = k
        u, _, _, du_dk = undistort(d_mm, coef, c_mm, jacobians=True)
        res_ref, jac_ref = _line_residuals(u, group, n_groups, du_dk[:, :, :n_terms] / z_scale)
        res, jac = _radial_line_residuals_jit(d_mm, group, n_groups, k, c_mm, z_scale, True)
        np.testing.assert_allclose(res, res_ref, rtol=1e-12, atol=1e-14 * np.abs(res_ref).max())
        np.testing.assert_allclose(jac, jac_ref, rtol=1e-12, atol=1e-14 * np.abs(jac_ref).max())
        res_only, jac_none = _radial_line_residuals_jit(d_mm, group, n_groups, k, c_mm, z_scale, False)
        np.testing.assert_array_equal(res_only, res)
        assert jac_none.shape == (0, n_terms)


def test_straightness_kernel_jacobian_by_differences(rng):
    group = np.repeat(np.arange(6), 5).astype(np.int64)
    d_mm = np.repeat(rng.uniform(-3, 3, (6, 2)), 5, axis=0) + np.outer(np.tile(np.linspace(-1, 1, 5), 6), [1.0, 0.4])
    d_mm += rng.normal(0, 0.02, d_mm.shape)
    z_scale = np.array([10.0, 100.0])
    z = np.array([0.3, -0.1])
    _, jac = _radial_line_residuals_jit(d_mm, group, 6, z / z_scale, np.zeros(2), z_scale, True)
    h = 1e-6
    for j in range(2):
        dz = np.zeros(2)
        dz[j] = h
        rp = _radial_line_residuals_jit(d_mm, group, 6, (z + dz) / z_scale, np.zeros(2), z_scale, False)[0]
        rm = _radial_line_residuals_jit(d_mm, group, 6, (z - dz) / z_scale, np.zeros(2), z_scale, False)[0]
        np.testing.assert_allclose(jac[:, j], (rp - rm) / (2 * h), rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize("lens,n_images", [("lens1", 9), ("lens2", 12)])
@pytest.mark.parametrize("n_terms", [1, 2, 3])
def test_estimate_radial_compiled_equals_numpy(lens, n_images, n_terms, numpy_only):
    rng = np.random.default_rng(7)
    runs = []
    for seed in range(4):
        s = simulate_set(lens, n_images=n_images, noise_mm=0.002, seed=seed)
        pts = _with_missing(s.points_mm, rng) if seed % 2 else s.points_mm
        runs.append((pts, find_lines(s.template_mm, max_lines=40), dict(c_mm=rng.normal(0, 0.3, 2) if seed == 3 else (0, 0))))
    fast = [estimate_radial(p, ln, n_terms=n_terms, **kw) for p, ln, kw in runs]
    numpy_only()
    assert not psdcal._jit.enabled()
    ref = [estimate_radial(p, ln, n_terms=n_terms, **kw) for p, ln, kw in runs]
    for a, b in zip(fast, ref):
        np.testing.assert_allclose(a.k, b.k, rtol=1e-9, atol=0)
        assert a.n_lines == b.n_lines and a.success == b.success
        np.testing.assert_allclose(a.rms_rel, b.rms_rel, rtol=1e-9)


def test_estimate_radial_without_usable_lines_is_unchanged(numpy_only):
    s = simulate_set("lens2", n_images=3, noise_mm=0.0, seed=1)
    pts = s.points_mm.copy()
    pts[:, 1:] = np.nan  # no line keeps 3 points
    lines = find_lines(s.template_mm)
    a = estimate_radial(pts, lines)
    numpy_only()
    b = estimate_radial(pts, lines)
    assert a.n_lines == b.n_lines == 0 and not a.success
    np.testing.assert_array_equal(a.k, b.k)


# -- lines of the template ---------------------------------------------------------------


def test_find_lines_memoised_equals_reference(rng):
    grid = np.array([(x, y) for y in range(4) for x in range(5)], dtype=float)
    templates = [default_template(), grid, grid * 3.7 + 1.0, rng.uniform(0, 10, (12, 2)), grid[:2]]
    for T in templates:
        for kw in ({}, dict(max_lines=5), dict(min_points=4), dict(tol_rel=1e-3)):
            ref = find_lines_reference(T, **kw)
            for _ in range(2):  # the second call comes from the cache
                got = find_lines(T, **kw)
                assert len(got) == len(ref)
                for a, b in zip(got, ref):
                    np.testing.assert_array_equal(a, b)
                    assert a.dtype == b.dtype


def test_find_lines_returns_fresh_arrays():
    T = default_template()
    first = find_lines(T)
    first[0][:] = -1
    first.append(np.array([99]))
    again = find_lines(T)
    assert len(again) == len(find_lines_reference(T))
    np.testing.assert_array_equal(again[0], find_lines_reference(T)[0])
    again[0][0] = 5  # writable
    # a modified template is a different key
    T2 = T.copy()
    T2[0] += 0.5
    assert [tuple(x) for x in find_lines(T2)] == [tuple(x) for x in find_lines_reference(T2)]


# -- rotations and poses -----------------------------------------------------------------


def _rotations(rng, n):
    angles = np.concatenate([rng.uniform(0, np.pi, n), [0.0, 1e-10, 1e-6, np.pi - 1e-8, np.pi - 1e-7, np.pi]])
    axes = rng.normal(size=(angles.size, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return np.array([R_from_r(ax * a) for ax, a in zip(axes, angles)])


def test_r_from_R_batch_equals_one_by_one(rng):
    Rs = _rotations(rng, 50)
    got = r_from_R_batch(Rs)
    ref = np.array([r_from_R(R) for R in Rs])
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-15)
    assert r_from_R_batch(np.zeros((0, 3, 3))).shape == (0, 3)


def test_nearest_rotation_batch_equals_one_by_one(rng):
    M = np.concatenate([rng.normal(size=(40, 3, 3)), _rotations(rng, 5) + rng.normal(0, 1e-3, (11, 3, 3))])
    M[0] = -np.eye(3)  # det -1
    got = nearest_rotation_batch(M)
    ref = np.array([nearest_rotation(m) for m in M])
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(got), 1.0, rtol=1e-12)


def test_poses_batched_equal_one_by_one(rng):
    for lens, n in (("lens1", 9), ("lens2", 12)):
        s = simulate_set(lens, n_images=n, noise_mm=0.002, seed=3)
        est = initial_estimate(s.template_mm, s.points_mm)
        for Hs in (est.homographies, -est.homographies, list(est.homographies)):
            rv, tv = poses_from_homographies(Hs, est.intrinsics)
            rv0, tv0 = poses_from_homographies_reference(Hs, est.intrinsics)
            np.testing.assert_allclose(rv, rv0, rtol=1e-12, atol=1e-15)
            np.testing.assert_allclose(tv, tv0, rtol=1e-12, atol=1e-13)
    # arbitrary homographies, an intrinsic matrix with skew and fy, rotations near pi
    intr = Intrinsics(f_mm=7.5, cx_mm=0.3, cy_mm=-0.2, skew=0.05, fy_mm=7.7)
    Rs = _rotations(rng, 20)
    t = np.c_[rng.normal(0, 50, (Rs.shape[0], 2)), rng.uniform(200, 900, Rs.shape[0])]
    Hs = np.einsum("ij,njk->nik", intr.matrix(), np.stack([Rs[:, :, 0], Rs[:, :, 1], t], axis=-1))
    Hs = Hs * rng.uniform(-3, 3, (Hs.shape[0], 1, 1)) + rng.normal(0, 1e-3, Hs.shape)
    rv, tv = poses_from_homographies(Hs, intr)
    rv0, tv0 = poses_from_homographies_reference(Hs, intr)
    np.testing.assert_allclose(rv, rv0, rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(tv, tv0, rtol=1e-11, atol=1e-11)
    r1, t1 = extrinsics_from_homography(Hs[4], intr)
    np.testing.assert_allclose(rv[4], r1, rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(tv[4], t1, rtol=1e-11)
    empty = poses_from_homographies(np.zeros((0, 3, 3)), intr)
    assert empty[0].shape == (0, 3) and empty[1].shape == (0, 3)


# -- homographies: collinearity of all views, errors -------------------------------------


def test_collinearity_batch_equals_one_by_one(rng):
    pts = rng.normal(size=(30, 10, 2))
    pts[::3] = np.outer(rng.normal(size=10), [1.0, 2.0]) + [0.5, -0.2] + rng.normal(0, 1e-9, (10, 2))  # nearly collinear
    pts[1, :, 1] = 0.0  # exactly collinear
    valid = rng.random((30, 10)) > 0.2
    valid[:, :3] = True
    pts[~valid] = np.nan
    got = collinearity_batch(pts, valid)
    ref = np.array([collinearity(p[v]) for p, v in zip(pts, valid)])
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-14)
    assert np.all((got < 1e-6) == (ref < 1e-6))
    # a set without valid points or spread counts as collinear
    assert collinearity_batch(np.zeros((2, 4, 2)), np.array([[False] * 4, [True] * 4])).tolist() == [0.0, 0.0]


def _homography_errors_by_loop(src, dst, labels):
    """The checks of :func:`homographies` as a loop over the views (the former code)."""
    ok = np.all(np.isfinite(dst), axis=-1)
    for i in range(dst.shape[0]):
        cnt = int(ok[i].sum())
        if cnt < 4:
            return f"{labels[i]}: {cnt} points, a homography needs at least 4"
        if collinearity(src[ok[i]]) < 1e-6 or collinearity(dst[i][ok[i]]) < 1e-6:
            return f"{labels[i]}: its points are collinear, a homography needs points spread on the plane"
    return None


@pytest.mark.parametrize(
    "spoil",
    [
        {2: "few"},
        {1: "line"},
        {3: "few", 1: "line"},
        {1: "few", 3: "line"},
        {0: "line-template"},
        {4: "none"},
    ],
)
def test_homography_errors_name_the_first_bad_view(spoil):
    T, pts = spoilt_set(spoil)
    labels = [f"image {i + 10}" for i in range(6)]
    expected = _homography_errors_by_loop(T, pts, labels)
    assert expected is not None
    with pytest.raises(DegenerateViewsError) as info:
        homographies(T, pts, labels=labels)
    assert str(info.value) == expected
    with pytest.raises(DegenerateViewsError) as info:
        initial_estimate(T, pts, image_ids=range(10, 16))
    assert str(info.value) == expected


# -- the whole linear stage --------------------------------------------------------------


def _estimates(cases, **kw):
    return [initial_estimate(T, pts, **kw) for T, pts in cases]


@pytest.mark.parametrize("kw", [dict(radial_terms=2), dict(radial_terms=1), dict(normalize=False), dict(skew=True, aspect=True)])
def test_initial_estimate_fast_equals_numpy(kw, numpy_only):
    rng = np.random.default_rng(11)
    cases = []
    for lens, n in (("lens1", 9), ("lens2", 12)):
        for seed in range(3):
            s = simulate_set(lens, n_images=n, noise_mm=0.002, seed=seed)
            cases.append((s.template_mm, _with_missing(s.points_mm, rng) if seed == 1 else s.points_mm))
    fast = _estimates(cases, **kw)
    numpy_only()
    ref = _estimates(cases, **kw)
    for a, b in zip(fast, ref):
        np.testing.assert_allclose(a.preliminary_k, b.preliminary_k, rtol=1e-9, atol=0)
        assert a.n_lines == b.n_lines
        np.testing.assert_allclose(a.homographies, b.homographies, rtol=1e-9, atol=1e-12)
        for name in ("f_mm", "cx_mm", "cy_mm", "skew", "fy"):
            np.testing.assert_allclose(getattr(a.intrinsics, name), getattr(b.intrinsics, name), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(a.rvecs, b.rvecs, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(a.tvecs_mm, b.tvecs_mm, rtol=1e-9, atol=1e-9)
    # the poses are also those of the one-by-one reference
    for a in fast:
        rv0, tv0 = poses_from_homographies_reference(a.homographies, a.intrinsics)
        np.testing.assert_allclose(a.rvecs, rv0, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(a.tvecs_mm, tv0, rtol=1e-12, atol=1e-12)


def test_initial_estimate_degenerate_views_still_raise(numpy_only):
    s = simulate_set("lens2", n_images=4, noise_mm=0.0, seed=2)
    flat = np.repeat(s.points_mm[:1], 4, axis=0)  # four identical views: no intrinsics
    for _ in range(2):
        with pytest.raises(DegenerateViewsError):
            initial_estimate(s.template_mm, flat)
        numpy_only()


def test_find_lines_in_blocks_equals_the_loop(rng):
    """The blocked search (what find_lines memoises) gives the loop's lines in the loop's order, whatever
    the block: grids (many ties of angle), random and rounded points, coincident points, a near-line."""
    from psdcal.calibration._straightness import _find_lines_blocked

    grid = np.array([(x, y) for y in range(4) for x in range(5)], dtype=float)
    big = np.array([(x, y) for y in range(20) for x in range(20)], dtype=float) * 0.5
    templates = [default_template(), grid, grid * 3.7 + 1.0, rng.uniform(0, 10, (12, 2)), grid[:2], big,
                 np.round(rng.uniform(0, 6, (60, 2))), np.zeros((5, 2)),
                 np.array([[0, 0], [1, 0], [2, 0], [3, 1e-9]], dtype=float)]
    for T in templates:
        for kw in ({}, dict(max_lines=5), dict(min_points=4), dict(tol_rel=1e-3), dict(min_points=2)):
            ref = find_lines_reference(T, **kw)
            opts = dict(dict(min_points=3, tol_rel=1e-6, max_lines=None), **kw)
            for block in (1, 7, 128):
                got = _find_lines_blocked(np.asarray(T, dtype=float), block=block, **opts)
                assert len(got) == len(ref)
                for a, b in zip(got, ref):
                    np.testing.assert_array_equal(a, b)
                    assert a.dtype == b.dtype
