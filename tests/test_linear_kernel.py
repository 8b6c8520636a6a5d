"""The compiled linear stage (psdcal.calibration._linear_kernel) against its numpy reference.

``homographies``, ``intrinsics_from_homographies`` and ``poses_from_homographies``
dispatch to one compiled call when ``psdcal._jit.use_compiled`` says so. The
fixtures below force either path (``use_compiled`` patched), so both are tested
whatever ``PSDCAL_JIT`` says; without numba the kernels run as plain Python,
the same code.

Tolerances: homographies and poses agree to 1e-12 relative (the null vector of
the DLT and the polar factor of a 3 x 3 matrix are well conditioned after
Hartley normalisation; both SVDs are backward stable; about 1e-15 is reached).
The plain DLT (``normalize=False``) is as ill-conditioned as the paper says:
the homographies still agree to 1e-12 of their norm, but their small entries
only to the conditioning times eps (some 1e-11 relative; checked at 1e-9). The
closed-form intrinsics take a square root of a difference (``lambda = b33 -
...``), which can lose digits on poorly conditioned views: checked at 1e-10
relative (about 1e-15 is reached on calibration sets).
"""
import numpy as np
import pytest
from _degenerate_views import spoilt_set
from hypothesis import given, settings
from hypothesis import strategies as st

import psdcal._jit
from psdcal.calibration import _closed_form, _homography
from psdcal.calibration._closed_form import (
    intrinsics_from_homographies,
    poses_from_homographies,
    poses_from_homographies_reference,
)
from psdcal.calibration._homography import homographies, linear_kernels
from psdcal.calibration.core import calibrate, focal_from_homographies
from psdcal.errors import DegenerateViewsError
from psdcal.model.params import Intrinsics
from psdcal.model.projection import R_from_r
from psdcal.study.simulate import simulate_set


@pytest.fixture
def path(monkeypatch):
    """``path("compiled")`` / ``path("numpy")``: the linear stage's dispatch forced one way."""

    def use(which):
        assert which in ("compiled", "numpy")
        monkeypatch.setattr(psdcal._jit, "use_compiled", lambda n: which == "compiled")

    return use


def _both(path, fn):
    """``fn()`` on the compiled path, then on the numpy path."""
    path("compiled")
    a = fn()
    path("numpy")
    return a, fn()


def _outcome(fn):
    try:
        return fn()
    except (DegenerateViewsError, np.linalg.LinAlgError) as exc:
        return exc


def _grid(nx, ny):
    X, Y = np.meshgrid(np.linspace(-60, 60, nx), np.linspace(-40, 40, ny))
    return np.stack([X.ravel(), Y.ravel()], axis=1)


def _sets():
    rng = np.random.default_rng(3)
    out = []
    s = simulate_set("lens2", n_images=5, noise_mm=0.002, seed=0)
    out.append((s.template_mm, s.points_mm))
    s = simulate_set("lens1", n_images=13, noise_mm=0.002, seed=1, template_mm=_grid(6, 4))
    out.append((s.template_mm, s.points_mm))
    s = simulate_set("lens2", n_images=9, noise_mm=0.0, seed=2)
    pts = s.points_mm.copy()
    pts[rng.random(pts.shape[:2]) < 0.15] = np.nan  # missing points
    corners = [0, 4, 9, 13]
    pts[3] = np.nan
    pts[3, corners] = s.points_mm[3, corners]  # a view with exactly 4 points: 8 DLT rows
    pts[5, 2] = [np.inf, 0.0]  # a non-finite coordinate is a missing point too
    out.append((s.template_mm, pts))
    return out


def _zhang():
    from pathlib import Path

    from psdcal.io import read_points, read_template

    z = Path(__file__).parent / "data" / "zhang1998"
    ids, T = read_template(z / "template.csv")
    return T, read_points(z / "points.csv", ids, sensor_mm=(6.4, 4.8)).points_mm


# -- homographies --------------------------------------------------------------------------------


@pytest.mark.parametrize("normalize", [True, False])
def test_homographies_compiled_equal_numpy(path, normalize):
    for T, X in _sets() + [_zhang()]:
        got, ref = _both(path, lambda: homographies(T, X, normalize=normalize))
        assert got.shape == ref.shape == (X.shape[0], 3, 3)
        # unit Frobenius norm: atol is relative to H; the plain DLT's small entries carry its conditioning
        np.testing.assert_allclose(got, ref, rtol=1e-12 if normalize else 1e-9, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(got, axis=(1, 2)), 1.0, rtol=1e-14)
        assert np.all(got[:, 2, 2] >= 0)


def test_homographies_compiled_map_noiseless_points(path):
    s = simulate_set("lens2", n_images=6, noise_mm=0.0, seed=4, psd_l1=0.0)
    # a distortion-free set: the homography maps the template onto the points exactly
    from psdcal.model.params import Distortion

    s = simulate_set((s.intrinsics, Distortion()), n_images=6, noise_mm=0.0, seed=4)
    path("compiled")
    for normalize in (True, False):
        H = homographies(s.template_mm, s.points_mm, normalize=normalize)
        mapped = np.stack([_homography.apply_homography(h, s.template_mm) for h in H])
        np.testing.assert_allclose(mapped, s.points_mm, atol=1e-11)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_views=st.integers(1, 6), n_points=st.integers(4, 30),
       noise=st.sampled_from([0.0, 1e-4, 1e-2]), missing=st.floats(0.0, 0.3))
def test_homographies_property_compiled_equal_numpy(seed, n_views, n_points, noise, missing):
    """Random planes seen by a random projective map: the same homographies, or the same error."""
    rng = np.random.default_rng(seed)
    T = rng.uniform(-50, 50, (n_points, 2))
    Hs = np.eye(3) + rng.normal(0, [[0.3, 0.3, 5.0], [0.3, 0.3, 5.0], [0.004, 0.004, 0.3]], (n_views, 3, 3))
    ph = T @ Hs[:, :, :2].transpose(0, 2, 1) + Hs[:, None, :, 2]
    X = ph[..., :2] / ph[..., 2:3] * 0.05 + rng.normal(0, noise, (n_views, n_points, 2))
    X[rng.random((n_views, n_points)) < missing] = np.nan
    saved = psdcal._jit.use_compiled
    try:
        psdcal._jit.use_compiled = lambda n: True
        got = _outcome(lambda: homographies(T, X, labels=[f"v{i}" for i in range(n_views)]))
        psdcal._jit.use_compiled = lambda n: False
        ref = _outcome(lambda: homographies(T, X, labels=[f"v{i}" for i in range(n_views)]))
    finally:
        psdcal._jit.use_compiled = saved
    if isinstance(ref, Exception) or isinstance(got, Exception):
        assert type(got) is type(ref) and str(got) == str(ref)
        return
    # both null vectors are within eps times the conditioning s0 / (s7 - s8) of the normalised DLT
    # (the 1e-12 factor also covers the de-normalisation; 2826 random sets reached 1e-13)
    tol = 1e-12 * (1.0 + _dlt_conditioning(T, X))
    assert np.all(np.abs(got - ref).max(axis=(1, 2)) <= tol)
    assert np.all(got[:, 2, 2] >= 0)


def _dlt_conditioning(T, X):
    """``s0 / (s7 - s8)`` of each view's Hartley-normalised DLT matrix (numpy's SVD), (n_views,)."""
    out = []
    for x in X:
        ok = np.all(np.isfinite(x), axis=1)

        def normalised(p):
            m = p.mean(axis=0)
            return (p - m) * (np.sqrt(2.0) / np.hypot(*(p - m).T).mean())

        P, Q = normalised(T[ok]), normalised(x[ok])
        M = len(P)
        A = np.zeros((2 * M + 1, 9))  # one zero row: 9 singular values even for 4 points
        A[:M, 0:2], A[:M, 2], A[M:2 * M, 3:5], A[M:2 * M, 5] = P, 1.0, P, 1.0
        A[:M, 6:8], A[:M, 8] = -Q[:, :1] * P, -Q[:, 0]
        A[M:2 * M, 6:8], A[M:2 * M, 8] = -Q[:, 1:] * P, -Q[:, 1]
        s = np.linalg.svd(A, compute_uv=False)
        out.append(s[0] / (s[7] - s[8]))
    return np.array(out)


@pytest.mark.parametrize("spoil", [{2: "few"}, {1: "line"}, {3: "few", 1: "line"}, {1: "few", 3: "line"},
                                   {0: "line-template"}, {4: "none"}, {2: "rank"}, {4: "rank", 5: "few"},
                                   {1: "rank", 3: "rank"}])
def test_homography_errors_same_on_both_paths(path, spoil):
    T, pts = spoilt_set(spoil)
    labels = [f"image {i + 10}" for i in range(6)]
    got, ref = _both(path, lambda: _outcome(lambda: homographies(T, pts, labels=labels)))
    assert isinstance(ref, DegenerateViewsError)
    assert type(got) is type(ref) and str(got) == str(ref)
    # default labels
    got, ref = _both(path, lambda: _outcome(lambda: homographies(T, pts)))
    assert str(got) == str(ref) and str(ref).startswith("image ")


def test_homography_errors_collinear_template_and_nan_template(path):
    s = simulate_set("lens2", n_images=3, noise_mm=0.002, seed=6)
    flat_T = s.template_mm.copy()
    flat_T[:, 1] = 2.0 * flat_T[:, 0] + 1.0  # the template on one line
    bad_T = s.template_mm.copy()
    bad_T[2] = np.nan
    for T in (flat_T, bad_T):
        got, ref = _both(path, lambda: _outcome(lambda: homographies(T, s.points_mm)))
        assert isinstance(ref, DegenerateViewsError) and str(got) == str(ref)


def test_homographies_odd_shapes_use_the_reference(path):
    """Mismatched or empty input goes to the numpy code (the kernel would read out of bounds)."""
    s = simulate_set("lens2", n_images=2, noise_mm=0.0, seed=0)
    path("compiled")
    with pytest.raises(ValueError):
        homographies(s.template_mm[:5], s.points_mm)
    H = homographies(s.template_mm, s.points_mm[0][None])
    path("numpy")
    np.testing.assert_allclose(H, homographies(s.template_mm, s.points_mm[0][None]), rtol=1e-12, atol=1e-14)


# -- closed-form intrinsics ----------------------------------------------------------------------


_VARIANTS = [dict(), dict(skew=True), dict(aspect=True), dict(skew=True, aspect=True)]


def _intr_close(a, b, rtol=1e-10):
    for name in ("f_mm", "cx_mm", "cy_mm", "skew", "fy"):
        x, y = getattr(a, name), getattr(b, name)
        assert abs(x - y) <= rtol * max(abs(y), abs(a.f_mm)), (name, x, y)
    assert (a.fy_mm is None) == (b.fy_mm is None)


@pytest.mark.parametrize("kw", _VARIANTS)
def test_intrinsics_compiled_equal_numpy(path, kw):
    path("numpy")
    cases = [homographies(T, X) for T, X in _sets() + [_zhang()]]
    for Hs in cases:
        for form in (Hs, list(Hs), -Hs * 3.0):  # any scale and sign of each homography
            got, ref = _both(path, lambda: intrinsics_from_homographies(form, **kw))
            _intr_close(got, ref)
            assert type(got.f_mm) is float and type(got.cx_mm) is float
            if not kw.get("skew"):
                assert got.skew == 0.0


def test_intrinsics_compiled_recover_truth(path):
    """Noiseless, distortion-free views: the closed form gives the true camera (both paths)."""
    from psdcal.model.params import Distortion

    truth = Intrinsics(f_mm=8.2, cx_mm=0.3, cy_mm=-0.25, skew=0.02, fy_mm=8.3)
    s = simulate_set((truth, Distortion()), n_images=7, noise_mm=0.0, seed=8)
    path("numpy")
    Hs = homographies(s.template_mm, s.points_mm)
    path("compiled")
    got = intrinsics_from_homographies(Hs, skew=True, aspect=True)
    for name in ("f_mm", "cx_mm", "cy_mm", "skew", "fy"):
        assert abs(getattr(got, name) - getattr(truth, name)) < 1e-7, name


def test_intrinsics_errors_same_on_both_paths(path):
    s = simulate_set("lens2", n_images=4, noise_mm=0.0, seed=2)
    path("numpy")
    Hs = homographies(s.template_mm, s.points_mm)
    rng = np.random.default_rng(9)
    cases = [(np.repeat(Hs[:1], 4, axis=0), {}), (Hs[:1], {}), (Hs[:2], dict(skew=True)), (Hs[:2], dict(aspect=True)),
             (np.repeat(Hs[:1], 4, axis=0), dict(skew=True, aspect=True))]
    cases += [(rng.normal(size=(int(rng.integers(2, 6)), 3, 3)), kw) for kw in _VARIANTS for _ in range(60)]
    kinds = set()
    for H, kw in cases:
        got, ref = _both(path, lambda: _outcome(lambda: intrinsics_from_homographies(H, **kw)))
        if isinstance(ref, Exception):
            assert type(got) is type(ref) and str(got) == str(ref)
            kinds.add(str(ref).split(":")[0][:40])
        else:
            _intr_close(got, ref, rtol=1e-8)  # random matrices: worse conditioned than any camera's
    assert len(kinds) >= 3  # too few views, undetermined, B not positive definite / negative focal


def test_intrinsics_nonfinite_and_zero_homographies_use_the_reference(path):
    Hs = np.repeat(np.eye(3)[None], 3, axis=0)
    for bad in (np.nan, np.inf, 0.0):
        H = Hs.copy()
        H[1] = bad
        with np.errstate(all="ignore"):
            got, ref = _both(path, lambda: _outcome(lambda: intrinsics_from_homographies(H)))
        assert type(got) is type(ref) and str(got) == str(ref)


# -- poses ---------------------------------------------------------------------------------------


def _rotations(rng, n, near_pi=()):
    angles = np.concatenate([rng.uniform(0, np.pi, n), [0.0, 1e-10, 1e-6], [np.pi - d for d in near_pi]])
    axes = rng.normal(size=(angles.size, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return np.array([R_from_r(ax * a) for ax, a in zip(axes, angles)])


def test_poses_compiled_equal_numpy_and_reference(path, rng):
    intrs = [Intrinsics(f_mm=8.0), Intrinsics(f_mm=7.5, cx_mm=0.3, cy_mm=-0.2, skew=0.05, fy_mm=7.7)]
    Rs = _rotations(rng, 60, near_pi=(0.3, 0.1, 0.06, 0.04, 1e-3, 1e-5, 1e-8, 0.0))
    t = np.c_[rng.normal(0, 50, (Rs.shape[0], 2)), rng.uniform(200, 900, Rs.shape[0])]
    for intr in intrs:
        for noise in (0.0, 1e-3):
            Hs = np.einsum("ij,njk->nik", intr.matrix(), np.stack([Rs[:, :, 0], Rs[:, :, 1], t], axis=-1))
            Hs = Hs * rng.uniform(-3, 3, (Hs.shape[0], 1, 1)) + rng.normal(0, noise, Hs.shape)
            (rv, tv), (rv1, tv1) = _both(path, lambda: poses_from_homographies(Hs, intr))
            rv0, tv0 = poses_from_homographies_reference(Hs, intr)
            for got in ((rv, tv), (rv1, tv1)):
                np.testing.assert_allclose(got[0], rv0, rtol=1e-12, atol=1e-14)
                np.testing.assert_allclose(got[1], tv0, rtol=1e-12, atol=1e-12)
            # the rotation vectors are those of rotations: R(r) [r1 r2] close to A^-1 H's columns
            assert np.all(tv[:, 2] > 0)


def test_poses_compiled_from_calibration_sets(path):
    for T, X in _sets() + [_zhang()]:
        path("numpy")
        Hs = homographies(T, X)
        intr = intrinsics_from_homographies(Hs)
        (rv, tv), (rv1, tv1) = _both(path, lambda: poses_from_homographies(Hs, intr))
        np.testing.assert_allclose(rv, rv1, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(tv, tv1, rtol=1e-12, atol=1e-12)


def test_poses_degenerate_input_same_on_both_paths(path):
    intr = Intrinsics(f_mm=8.0)
    H = np.repeat(np.eye(3)[None], 3, axis=0)
    for bad in (0.0, np.nan):
        Hb = H.copy()
        Hb[1] = bad
        with np.errstate(all="ignore"):
            got, ref = _both(path, lambda: _outcome(lambda: poses_from_homographies(Hb, intr)))
        assert type(got) is type(ref)
    with np.errstate(all="ignore"):
        got, ref = _both(path, lambda: _outcome(lambda: poses_from_homographies(H, Intrinsics(f_mm=0.0))))
    assert type(got) is type(ref)
    Hp = H.copy()
    Hp[1, :, 1] = Hp[1, :, 0]  # h1 = h2: no unique nearest rotation, the reference decides
    got, ref = _both(path, lambda: poses_from_homographies(Hp, intr))
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])
    empty, _ = _both(path, lambda: poses_from_homographies(np.zeros((0, 3, 3)), intr))
    assert empty[0].shape == (0, 3) and empty[1].shape == (0, 3)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 8), scale=st.floats(0.01, 100.0))
def test_nearest_rotation_kernel_property(seed, n, scale):
    """The kernel's nearest rotation is orthogonal with det +1 and equal to numpy's (the polar factor)."""
    from psdcal.model.projection import nearest_rotation

    rng = np.random.default_rng(seed)
    lk = linear_kernels()
    M = rng.normal(size=(n, 3, 3)) * scale
    W, V, R = np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3))
    for m in M:
        lk._nearest_rotation(m, W, V, R)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
        assert abs(np.linalg.det(R) - 1.0) < 1e-14
        s = np.linalg.svd(m, compute_uv=False)
        gap = min(s[1] + s[2], s[0] + s[1]) / s[0]  # the polar factor's conditioning
        np.testing.assert_allclose(R, nearest_rotation(m), atol=1e-14 / gap)


# -- the Jacobi SVD and QR -----------------------------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(9, 40), decades=st.integers(0, 14))
def test_qr_jacobi_singular_values_and_null_vector(seed, m, decades):
    rng = np.random.default_rng(seed)
    lk = linear_kernels()
    U, _ = np.linalg.qr(rng.normal(size=(m, 9)))
    Vt, _ = np.linalg.qr(rng.normal(size=(9, 9)))
    s = np.logspace(0, -decades, 9)
    A = (U * s) @ Vt.T
    R = A.copy()
    lk._householder_r(R, m, 9)
    assert np.all(np.tril(R[:9], -1) == 0)
    W, V = R[:9].copy(), np.zeros((9, 9))
    lk._jacobi_svd(W, V, 9)
    got = np.sort(np.linalg.norm(W, axis=0))[::-1]
    np.testing.assert_allclose(got, np.linalg.svd(A, compute_uv=False), rtol=0, atol=1e-14)
    np.testing.assert_allclose(V.T @ V, np.eye(9), atol=1e-14)
    np.testing.assert_allclose(R[:9] @ V, W, atol=1e-14)
    # the smallest singular value's vector, unique up to sign
    if decades == 0:
        return  # all singular values equal: no distinct null vector
    z = V[:, np.argmin(np.linalg.norm(W, axis=0))]
    ref = Vt[:, -1]
    gap = s[7] - s[8]
    assert min(np.abs(z - ref).max(), np.abs(z + ref).max()) < 1e-14 / gap


# -- per-view focal lengths and the whole calibration --------------------------------------------


def test_focal_kernel_equals_core(rng, monkeypatch):
    import psdcal._jit

    lk = linear_kernels()
    monkeypatch.setattr(psdcal._jit, "use_compiled", lambda n: False)  # core's numpy lines, the reference
    path_H = [homographies(T, X) for T, X in _sets()]
    Hs = np.concatenate(path_H + [rng.normal(size=(40, 3, 3))])
    Hs[3, 2, :2] = 0.0  # parallel to the sensor: NaN
    Hs[4] = 0.0  # nothing: NaN
    for c in ((0.0, 0.0), (0.3, -0.2)):
        with np.errstate(all="ignore"):
            ref = focal_from_homographies(Hs, c)
        got = lk.focal_from_homographies_kernel(np.ascontiguousarray(Hs), *c)
        assert np.array_equal(np.isnan(got), np.isnan(ref))
        np.testing.assert_allclose(got, ref, rtol=1e-13)
    assert np.isnan(got[3]) and np.isnan(got[4])
    monkeypatch.undo()
    if psdcal._jit.use_compiled(len(Hs)):  # and core dispatches to the kernel (when the dispatch would)
        np.testing.assert_array_equal(focal_from_homographies(Hs, (0.3, -0.2)), got)
    monkeypatch.setattr(psdcal._jit, "use_compiled", lambda n: True)
    np.testing.assert_array_equal(focal_from_homographies(Hs, (0.3, -0.2)), got)


def test_calibrate_same_solution_with_the_compiled_linear_stage(monkeypatch):
    """Only the linear stage's dispatch switched: the refined calibration is the same."""
    import types

    s = simulate_set("lens2", n_images=5, noise_mm=0.002, seed=0)
    fits = []
    for compiled in (True, False):
        shim = types.SimpleNamespace(use_compiled=lambda n, c=compiled: c)
        monkeypatch.setattr(_homography, "_jit", shim)
        monkeypatch.setattr(_closed_form, "_jit", shim)
        fits.append(calibrate(s.template_mm, s.points_mm, cost="image", radial=2, tangential=False, verdict=False))
    a, b = fits
    for name in ("f_mm", "cx_mm", "cy_mm"):
        np.testing.assert_allclose(getattr(a.intrinsics, name), getattr(b.intrinsics, name), rtol=1e-9)
    np.testing.assert_allclose(a.distortion.k1, b.distortion.k1, rtol=1e-8)
    np.testing.assert_allclose(a.rvecs, b.rvecs, rtol=1e-8, atol=1e-10)


# -- an SVD that does not converge is handed to the reference ------------------------------------


def test_jacobi_reports_non_convergence_on_nan():
    lk = linear_kernels()
    W = np.eye(3)
    W[0, 1] = np.nan
    assert not lk._jacobi_svd(W, np.zeros((3, 3)), 3)
    assert lk._jacobi_svd(np.diag([3.0, 1.0, 2.0]), np.zeros((3, 3)), 3)


def test_unconverged_kernels_fall_back_to_the_reference(path, monkeypatch):
    s = simulate_set("lens2", n_images=4, noise_mm=0.002, seed=1)
    path("numpy")
    H_ref = homographies(s.template_mm, s.points_mm)
    intr_ref = intrinsics_from_homographies(H_ref)
    lk = linear_kernels()
    monkeypatch.setattr(lk, "homographies_kernel", lambda *a: (np.zeros((4, 3, 3)), lk.H_USE_REFERENCE, 2, 14))
    monkeypatch.setattr(lk, "intrinsics_kernel", lambda *a: (np.zeros(5), lk.I_USE_REFERENCE))
    monkeypatch.setattr(lk, "poses_kernel", lambda H, *a: (np.zeros((len(H), 3)),) * 2 + (False,))
    path("compiled")
    np.testing.assert_array_equal(homographies(s.template_mm, s.points_mm), H_ref)
    assert intrinsics_from_homographies(H_ref) == intr_ref
    rv, tv = poses_from_homographies(H_ref, intr_ref)
    path("numpy")
    rv0, tv0 = poses_from_homographies(H_ref, intr_ref)
    np.testing.assert_array_equal(rv, rv0)
    np.testing.assert_array_equal(tv, tv0)
