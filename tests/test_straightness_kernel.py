"""The compiled line-straightness solve against its numpy reference.

:func:`psdcal.calibration._straightness.estimate_radial` runs as one compiled
call (:func:`psdcal.calibration._straightness_kernel.solve_radial`: grouping,
cost, Jacobian and Levenberg-Marquardt); the reference is the numpy cost
(``_line_residuals`` of ``undistort``) minimised by
:func:`psdcal.calibration._lm.levenberg_marquardt`. The compiled solver
must take the reference's steps: the same status, the same numbers of
residual and Jacobian evaluations, the same k, number of lines, RMS and
convergence flag to round-off.

Tolerances: the residuals agree to ~1e-15 relative (the C library's ``atan2``,
``sin``, ``cos`` and plain loops here, numpy's own functions and BLAS there);
the solver's steps solve the damped normal equations, whose conditioning
multiplies those differences: the reference's own k moves by 1e-12 .. 3e-11
relative when the points are perturbed by half an ulp (5 views x 14 points,
Lens 2, k1 and k2). So k is compared at 5e-11 relative (the largest
difference seen over 432 sets of Lens 1 and 2, 3-13 views, n = 1-3, with and
without noise and missing points: 5.3e-12), the RMS at 1e-13.
"""
import numpy as np
import pytest

import psdcal._jit
from psdcal.calibration._refine import SolverOptions, levenberg_marquardt
from psdcal.calibration._straightness import _SOLVER, _line_residuals, _radial_line_residuals_jit, estimate_radial, find_lines
from psdcal.calibration.core import _straightness_lines
from psdcal.model.distortion import distort, undistort
from psdcal.study.simulate import simulate_set

K_RTOL = 5e-11
RMS_RTOL = 1e-13

compiled_only = pytest.mark.skipif(not psdcal._jit.AVAILABLE, reason="numba not available: no compiled path to compare")


@pytest.fixture
def numpy_only(monkeypatch):
    """Call it to switch the compiled kernels off (``use_compiled`` then answers False)."""

    def use():
        monkeypatch.setattr(psdcal._jit, "AVAILABLE", False)
        assert not psdcal._jit.use_compiled(10**9)

    return use


def _sets(lens, n_terms):
    """(points, lines, c) cases: 5 x 14 and 9-13 views, noise or none, missing points, an off-centre c."""
    rng = np.random.default_rng(11 + n_terms)
    out = []
    for seed, (n_images, noise) in enumerate([(5, 0.002), (5, 0.0), (9, 0.002), (13, 0.02)]):
        s = simulate_set(lens, n_images=n_images, noise_mm=noise, seed=seed)
        pts = s.points_mm.copy()
        if seed % 2:
            pts[rng.random(pts.shape[:2]) < 0.12] = np.nan
        lines = _straightness_lines(s.template_mm) if seed < 2 else find_lines(s.template_mm)
        out.append((pts, lines, np.zeros(2) if seed != 2 else rng.normal(0, 0.3, 2)))
    return out


def _assert_same(a, b):
    assert a.n_lines == b.n_lines
    assert a.success == b.success
    assert a.k.shape == b.k.shape
    np.testing.assert_allclose(a.k, b.k, rtol=K_RTOL, atol=0)
    np.testing.assert_allclose(a.rms_rel, b.rms_rel, rtol=RMS_RTOL)


@compiled_only
@pytest.mark.parametrize("lens", ["lens1", "lens2"])
@pytest.mark.parametrize("n_terms", [1, 2, 3])
def test_estimate_radial_compiled_equals_numpy_reference(lens, n_terms, numpy_only):
    cases = _sets(lens, n_terms)
    fast = [estimate_radial(p, ln, c_mm=c, n_terms=n_terms) for p, ln, c in cases]
    numpy_only()
    ref = [estimate_radial(p, ln, c_mm=c, n_terms=n_terms) for p, ln, c in cases]
    for a, b in zip(fast, ref):
        assert a.success and a.n_lines > 10
        _assert_same(a, b)


def _reference_solve(pts, lines, c, n_terms):
    """The straightness problem built independently (plain loops over views and lines), solved by
    ``levenberg_marquardt`` on the numpy cost: (LMResult, scale, points)."""
    flat, group = [], []
    n_groups = 0
    for view in pts:
        for ln in lines:
            p = view[np.asarray(ln)]
            p = p[np.isfinite(p).all(axis=1)]
            if len(p) >= 3:
                group += [n_groups] * len(p)
                flat.append(p)
                n_groups += 1
    flat = np.concatenate(flat)
    group = np.array(group)
    rmax2 = float(np.max(np.sum((flat - c) ** 2, axis=1)))
    scale = np.array([rmax2 ** (i + 1) for i in range(n_terms)])

    def coef(z):
        out = np.zeros(7)
        out[:n_terms] = z / scale
        return out

    def fun(z):
        return _line_residuals(undistort(flat, coef(z), c), group, n_groups)

    def jac(z):
        u, _, _, du = undistort(flat, coef(z), c, jacobians=True)
        return _line_residuals(u, group, n_groups, du[:, :, :n_terms] / scale)[1]

    return levenberg_marquardt(fun, jac, np.zeros(n_terms), SolverOptions(**_SOLVER)), scale, len(flat), n_groups


def _kernel_solve(pts, lines, c, n_terms):
    from psdcal.calibration._straightness_kernel import solve_radial

    return solve_radial(
        np.ascontiguousarray(pts, dtype=float), np.concatenate(lines).astype(np.int64),
        np.array([len(ln) for ln in lines], dtype=np.int64), np.asarray(c, dtype=float), n_terms,
        _SOLVER["ftol"], _SOLVER["xtol"], _SOLVER["gtol"], _SOLVER["max_iterations"],
    )


@pytest.mark.parametrize("lens", ["lens1", "lens2"])
@pytest.mark.parametrize("n_terms", [1, 2, 3])
def test_compiled_solver_takes_the_steps_of_levenberg_marquardt(lens, n_terms):
    for pts, lines, c in _sets(lens, n_terms):
        sol, scale, n_points, n_groups = _reference_solve(pts, lines, c, n_terms)
        k, cost, status, overflow, groups, points, njev, nfev = _kernel_solve(pts, lines, c, n_terms)
        assert (groups, points) == (n_groups, n_points)
        assert (status, njev, nfev) == (sol.status, sol.njev, sol.nfev)
        assert overflow == ("overflow" in sol.message)
        np.testing.assert_allclose(k, sol.x / scale, rtol=K_RTOL, atol=0)
        np.testing.assert_allclose(cost, sol.cost, rtol=2 * RMS_RTOL)


def _distorted_lines(rng, k, c, n_views=5, per_line=6):
    """Measured points whose undistortion by radial ``k`` about ``c`` lies on straight lines, (n_views, M, 2)."""
    n_lines = 4
    t = np.linspace(-1.0, 1.0, per_line)
    pts = []
    for _ in range(n_views):
        view = []
        for _ in range(n_lines):
            p0 = rng.uniform(-1.5, 1.5, 2)
            u = rng.normal(size=2)
            view.append(p0 + np.outer(t * rng.uniform(1.5, 2.5), u / np.linalg.norm(u)))
        pts.append(np.concatenate(view))
    coef = np.zeros(7)
    coef[: len(k)] = k
    ideal = np.array(pts)
    d = distort(ideal, coef, c).d_mm
    np.testing.assert_allclose(undistort(d, coef, c), ideal, atol=1e-12)
    lines = [np.arange(j * per_line, (j + 1) * per_line) for j in range(n_lines)]
    return d, lines


@pytest.mark.parametrize("k_true", [(-8e-3,), (-1e-2, 4e-4), (6e-3, -2e-4, 1e-5)])
def test_noiseless_lines_give_the_true_k_on_both_paths(rng, k_true, numpy_only):
    c = np.array([0.2, -0.1])
    pts, lines = _distorted_lines(rng, k_true, c)
    n = len(k_true)
    fast = estimate_radial(pts, lines, c_mm=c, n_terms=n)
    numpy_only()
    ref = estimate_radial(pts, lines, c_mm=c, n_terms=n)
    for st in (fast, ref):
        assert st.success and st.n_lines == 5 * 4
        np.testing.assert_allclose(st.k, k_true, rtol=1e-7)
        assert st.rms_rel < 1e-10
    np.testing.assert_allclose(fast.k, ref.k, rtol=1e-9)  # both at the truth to round-off


def test_straight_lines_stop_on_a_zero_residual(numpy_only):
    # points exactly on horizontal lines: the residual at k = 0 is exactly zero (status 4 at once)
    xs = np.array([-3.0, -1.0, 0.5, 2.0, 4.0])
    view = np.array([(x, y) for y in (-2.0, 0.0, 1.5) for x in xs])
    pts = np.stack([view, view * 0.5, view + [0.25, -0.5]])
    lines = [np.arange(5 * j, 5 * j + 5) for j in range(3)]
    for n_terms in (1, 2, 3):
        sol, scale, _, _ = _reference_solve(pts, lines, np.zeros(2), n_terms)
        out = _kernel_solve(pts, lines, np.zeros(2), n_terms)
        assert sol.status == out[2] == 4 and sol.njev == out[6] == 1 and sol.nfev == out[7] == 1
        fast = estimate_radial(pts, lines, n_terms=n_terms)
        assert fast.success and fast.rms_rel == 0.0 and fast.n_lines == 9
        np.testing.assert_array_equal(fast.k, np.zeros(n_terms))
    numpy_only()
    ref = estimate_radial(pts, lines, n_terms=2)
    assert ref.success and ref.rms_rel == 0.0 and np.all(ref.k == 0.0)


def test_no_usable_line_gives_zeros_on_both_paths(numpy_only):
    s = simulate_set("lens2", n_images=4, noise_mm=0.001, seed=3)
    lines = find_lines(s.template_mm)
    sparse = s.points_mm.copy()
    sparse[:, 2:] = np.nan  # no line keeps 3 points
    cases = [(s.points_mm, [], 2), (sparse, lines, 2), (sparse, lines, 1), (s.points_mm, lines, 0)]
    fast = [estimate_radial(p, ln, n_terms=n) for p, ln, n in cases]
    numpy_only()
    ref = [estimate_radial(p, ln, n_terms=n) for p, ln, n in cases]
    for (_, _, n), a, b in zip(cases, fast, ref):
        for st in (a, b):
            assert st.n_lines == 0 and not st.success and np.isnan(st.rms_rel)
            np.testing.assert_array_equal(st.k, np.zeros(n))


def test_line_indices_as_numpy_takes_them(numpy_only):
    s = simulate_set("lens1", n_images=5, noise_mm=0.002, seed=4)
    M = s.template_mm.shape[0]
    lines = find_lines(s.template_mm)
    negative = [ln - M for ln in lines]  # numpy's negative indices: the same points
    a, b = estimate_radial(s.points_mm, lines), estimate_radial(s.points_mm, negative)
    np.testing.assert_array_equal(a.k, b.k)
    bad = lines + [np.array([0, 1, M])]
    with pytest.raises(IndexError):
        estimate_radial(s.points_mm, bad)
    numpy_only()
    with pytest.raises(IndexError):
        estimate_radial(s.points_mm, bad)
    _assert_same(estimate_radial(s.points_mm, negative), a)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the numpy path (numba missing) divides by a zero spread
def test_coincident_points_end_without_a_step():
    # a group of three equal points has no line (its residuals are NaN): the solver must stop, k stays 0
    pts = np.zeros((1, 6, 2))
    pts[0, 3:] = [[0.0, 0.0], [1.0, 1.0], [2.0, 2.1]]
    st = estimate_radial(pts, [np.array([0, 1, 2]), np.array([3, 4, 5])])
    assert st.n_lines == 2 and np.isnan(st.rms_rel)
    np.testing.assert_array_equal(st.k, np.zeros(2))
    assert not st.success  # a NaN cost is no solution (it used to say success)


def test_coincident_points_fail_the_same_on_the_numpy_path(monkeypatch):
    import psdcal._jit

    monkeypatch.setattr(psdcal._jit, "AVAILABLE", False)
    pts = np.zeros((1, 6, 2))
    pts[0, 3:] = [[0.0, 0.0], [1.0, 1.0], [2.0, 2.1]]
    st = estimate_radial(pts, [np.array([0, 1, 2]), np.array([3, 4, 5])])
    assert np.isnan(st.rms_rel) and not st.success


def test_lm_ends_when_no_damping_makes_the_system_positive_definite():
    from psdcal.calibration._refine import SolverOptions, levenberg_marquardt

    # a NaN in the normal matrix: every damped solve fails; the loop must end (it used to spin forever
    # with a LAPACK that rejects NaN pivots), with the damping-overflow status, not a solution
    def normal(J, r):
        A = np.array([[np.nan, 0.0], [0.0, 1.0]])
        return A, np.array([1.0, 1.0])

    class _NoSolve:  # as DenseNormal, with a Cholesky that rejects the NaN
        def __init__(self, A, g):
            self.A, self.g = A, g

        def diagonal(self):
            return np.array([1.0, 1.0])

        def solve(self, damp):
            return None

    sol = levenberg_marquardt(lambda x: np.array([1.0, 2.0, 3.0]), lambda x: np.ones((3, 2)), np.zeros(2),
                              SolverOptions(max_iterations=20), normal=lambda J, r: _NoSolve(*normal(J, r)))
    assert sol.status == 2 and "overflow" in sol.message


@pytest.mark.parametrize("n_terms", [1, 2, 3])
def test_residuals_kernel_takes_groups_in_any_order(rng, n_terms):
    n_groups = 12
    group = rng.permutation(np.repeat(np.arange(n_groups), rng.integers(3, 9, n_groups)))
    u = rng.normal(size=(n_groups, 2))
    d_mm = rng.uniform(-4, 4, (n_groups, 2))[group] + rng.uniform(-1, 1, (group.size, 1)) * u[group]
    d_mm += rng.normal(0, 0.01, d_mm.shape)
    c_mm = rng.normal(0, 0.3, 2)
    k = np.array([1e-2, -3e-4, 2e-6])[:n_terms]
    z_scale = np.array([16.0, 256.0, 4096.0])[:n_terms]
    coef = np.zeros(7)
    coef[:n_terms] = k
    x, _, _, du = undistort(d_mm, coef, c_mm, jacobians=True)
    res_ref, jac_ref = _line_residuals(x, group, n_groups, du[:, :, :n_terms] / z_scale)
    res, jac = _radial_line_residuals_jit(d_mm, group, n_groups, k, c_mm, z_scale, True)
    np.testing.assert_allclose(res, res_ref, rtol=1e-12, atol=1e-14 * np.abs(res_ref).max())
    np.testing.assert_allclose(jac, jac_ref, rtol=1e-12, atol=1e-14 * np.abs(jac_ref).max())


def test_damped_cholesky_solve_equals_numpy(rng):
    from psdcal.calibration._straightness_kernel import _damped_solve

    for n in (1, 2, 3):
        for _ in range(20):
            J = rng.normal(size=(8, n)) * 10.0 ** rng.uniform(-3, 3, n)
            A, g, damp = J.T @ J, rng.normal(size=n), 10.0 ** rng.uniform(-8, 0, n)
            h = np.empty(n)
            assert _damped_solve(A, damp, g, h)
            np.testing.assert_allclose(h, np.linalg.solve(A + np.diag(damp), g), rtol=1e-10)
        # not positive definite: numpy's Cholesky refuses it, and so does the kernel
        A = np.diag(np.r_[1.0, -np.ones(n - 1)]) if n > 1 else np.array([[-1.0]])
        with pytest.raises(np.linalg.LinAlgError):
            np.linalg.cholesky(A + np.diag(np.full(n, 1e-3)))
        assert not _damped_solve(A, np.full(n, 1e-3), np.ones(n), np.empty(n))


def test_line_normals_of_axis_aligned_and_diagonal_lines():
    # the kernel's half-angle normals against numpy's atan2 / sin / cos where the angle formula has its
    # special cases: vertical (b = 0, a < c), horizontal (b = 0, a > c), +-45 degrees (a = c), steep and flat
    t = np.array([-2.0, -0.5, 1.0, 3.0])
    dirs = [(0.0, 1.0), (1.0, 0.0), (1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (1e-9, 1.0), (1.0, 1e-9), (0.3, -2.0), (-2.0, 0.3)]
    noise = np.array([0.0, 1e-3, -2e-3, 1e-3])
    d_mm = np.concatenate([np.outer(t, u) + np.outer(noise, (-u[1], u[0])) + [0.5 * j, -0.25 * j] for j, u in enumerate(dirs)])
    group = np.repeat(np.arange(len(dirs)), t.size)
    z_scale = np.array([10.0, 100.0])
    for k in (np.zeros(2), np.array([1e-3, -2e-5])):
        coef = np.zeros(7)
        coef[:2] = k
        x, _, _, du = undistort(d_mm, coef, np.zeros(2), jacobians=True)
        res_ref, jac_ref = _line_residuals(x, group, len(dirs), du[:, :, :2] / z_scale)
        res, jac = _radial_line_residuals_jit(d_mm, group, len(dirs), k, np.zeros(2), z_scale, True)
        np.testing.assert_allclose(res, res_ref, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(jac, jac_ref, rtol=1e-12, atol=1e-15 * np.abs(jac_ref).max())


@compiled_only
def test_auto_mode_decides_on_the_grouped_points(monkeypatch):
    # psdcal._jit's "auto" mode (kernels not loaded) compiles from 3000 observations: those the
    # straightness cost uses, i.e. the points of (view, line) pairs with >= 3 valid ones
    import sys

    from psdcal.calibration import _straightness

    monkeypatch.setattr(psdcal._jit, "_MODE", "auto")
    monkeypatch.delitem(sys.modules, "psdcal.calibration._image_kernel", raising=False)
    assert not psdcal._jit.use_compiled(0)
    s = simulate_set("lens2", n_images=80, noise_mm=0.001, seed=2)
    lines = find_lines(s.template_mm)
    members = np.concatenate(lines)
    lengths = np.array([len(ln) for ln in lines] + [0])  # an empty line counts for nothing
    rng = np.random.default_rng(5)
    seen = set()
    for fraction in (0.0, 0.1, 0.3, 1.0):
        pts = s.points_mm.copy()
        pts[rng.random(pts.shape[:2]) < fraction] = np.nan
        n = sum(
            len(p) for view in pts for ln in lines
            for p in [view[ln][np.isfinite(view[ln]).all(axis=1)]] if len(p) >= 3
        )
        assert _straightness._compiled_for(pts, members, lengths) == (n >= psdcal._jit.AUTO_MIN_OBSERVATIONS)
        seen.add(n >= psdcal._jit.AUTO_MIN_OBSERVATIONS)
    assert seen == {True, False}
    assert pts.shape[0] * members.size >= psdcal._jit.AUTO_MIN_OBSERVATIONS  # the bound alone would compile
