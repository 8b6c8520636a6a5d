"""Closed-form intrinsics and extrinsics from homographies (Zhang; the paper's Eq 19-28).

With one focal length and no skew, ``B = A^-T A^-1`` has ``b12 = 0`` and
``b11 = b22`` (Eq 21), so the unknown is ``b = [b11, b13, b23, b33]`` and each
view gives two equations (Eq 19, 20, 22). The recovery below is the corrected
one of docs/model.md#closed-form-intrinsics (the paper's Eq 23-25 are misprinted):

    Cx = -b13 / b11,  Cy = -b23 / b11,
    lambda = b33 - (b13^2 + b23^2) / b11,  f = sqrt(lambda / b11)

With skew or a separate vertical focal length free, Zhang's general
six-element ``b`` (Zhang, IEEE PAMI 22(11), 2000, Appendix B) is used.
"""
from __future__ import annotations

import math

import numpy as np

from psdcal import _jit
from psdcal.calibration._homography import linear_kernels
from psdcal.errors import DegenerateViewsError
from psdcal.model.params import Intrinsics
from psdcal.model.projection import nearest_rotation, nearest_rotation_batch, r_from_R, r_from_R_batch


# why the closed form has no camera (the compiled and the numpy paths raise the same)
_UNDETERMINED = "the views do not determine the intrinsics (too few distinct orientations of the template)"
_NOT_POSITIVE_DEFINITE = "closed-form intrinsics: B is not positive definite (degenerate or noisy views)"
_NEGATIVE_FOCAL = "closed-form intrinsics: negative focal length squared (degenerate views)"


def _v(Hs, i, j):
    """Zhang's v_ij over the full b = [b11, b12, b22, b13, b23, b33] (Eq 22), per view.

    Hs : (n, 3, 3) homographies; returns (n, 6).
    """
    hi, hj = Hs[:, :, i], Hs[:, :, j]
    return np.stack(
        [
            hi[:, 0] * hj[:, 0],
            hi[:, 0] * hj[:, 1] + hi[:, 1] * hj[:, 0],
            hi[:, 1] * hj[:, 1],
            hi[:, 2] * hj[:, 0] + hi[:, 0] * hj[:, 2],
            hi[:, 2] * hj[:, 1] + hi[:, 1] * hj[:, 2],
            hi[:, 2] * hj[:, 2],
        ],
        axis=-1,
    )


def intrinsics_from_homographies(Hs, *, skew: bool = False, aspect: bool = False) -> Intrinsics:
    """Closed-form intrinsics from n >= 2 (>= 3 with skew or aspect) homographies.

    Parameters
    ----------
    Hs : sequence of (3, 3) arrays
        Template -> sensor homographies (mm -> mm).
    skew : bool
        Leave the skew free (else 0).
    aspect : bool
        Leave a separate vertical focal length free (else fy = f).

    Returns
    -------
    Intrinsics

    Raises
    ------
    DegenerateViewsError
        Too few views, or views that do not constrain the intrinsics (e.g. all
        parallel to the sensor), or a solution that is not a real camera.

    With :func:`psdcal._jit.use_compiled`, one compiled call
    (:func:`psdcal.calibration._linear_kernel.intrinsics_kernel`) does it all;
    the numpy code below is its reference (same errors).
    """
    need = 2 if not (skew or aspect) else 3
    if not isinstance(Hs, np.ndarray):
        Hs = list(Hs)
    if _jit.use_compiled(len(Hs)):
        H = np.asarray(Hs, dtype=float)
        if H.ndim == 3 and H.shape[1:] == (3, 3) and H.shape[0] >= need:
            lk = linear_kernels()
            out, code = lk.intrinsics_kernel(np.ascontiguousarray(H), bool(skew), bool(aspect))
            if code == lk.I_OK:
                alpha, u0, v0, gamma, beta = out.tolist()
                if aspect:
                    return Intrinsics(f_mm=alpha, cx_mm=u0, cy_mm=v0, skew=gamma if skew else 0.0, fy_mm=beta)
                return Intrinsics(f_mm=math.sqrt(alpha * beta), cx_mm=u0, cy_mm=v0, skew=gamma if skew else 0.0)
            if code == lk.I_UNDETERMINED:
                raise DegenerateViewsError(_UNDETERMINED)
            if code == lk.I_NOT_POSITIVE_DEFINITE:
                raise DegenerateViewsError(_NOT_POSITIVE_DEFINITE)
            if code == lk.I_NEGATIVE_FOCAL:
                raise DegenerateViewsError(_NEGATIVE_FOCAL)
            # a non-finite or zero homography, or an SVD that did not converge: the reference below decides
    Hs = [np.asarray(H, dtype=float) / np.linalg.norm(H) for H in Hs]
    if len(Hs) < need:
        raise DegenerateViewsError(f"{len(Hs)} usable views; the closed-form intrinsics need at least {need}")
    # two rows per view, v12 and v11 - v22 (Eq 22), for all views at once
    Hst = np.stack(Hs)
    V = np.stack([_v(Hst, 0, 1), _v(Hst, 0, 0) - _v(Hst, 1, 1)], axis=1).reshape(-1, 6)
    # Map the reduced unknown to the full b: columns of E (6, k).
    cols = [np.array([1.0, 0, 1.0 if not aspect else 0.0, 0, 0, 0])]
    if skew:
        cols.append(np.array([0, 1.0, 0, 0, 0, 0]))
    if aspect:
        cols.append(np.array([0, 0, 1.0, 0, 0, 0]))
    cols += [np.eye(6)[3], np.eye(6)[4], np.eye(6)[5]]
    E = np.stack(cols, axis=1)
    Vr = V @ E
    # column scaling for conditioning
    sc = np.linalg.norm(Vr, axis=0)
    sc[sc == 0] = 1.0
    _, s, Vt = np.linalg.svd(Vr / sc, full_matrices=False)  # U of all views is never used: O(views), not O(views^2)
    k = Vr.shape[1]
    if s.size < k - 1 or s[k - 2] <= 1e-12 * s[0]:
        raise DegenerateViewsError(_UNDETERMINED)
    b = E @ (Vt[-1] / sc)
    if b[0] < 0:
        b = -b
    b11, b12, b22, b13, b23, b33 = b
    den = b11 * b22 - b12 * b12
    if not (b11 > 0 and den > 0):
        raise DegenerateViewsError(_NOT_POSITIVE_DEFINITE)
    v0 = (b12 * b13 - b11 * b23) / den
    lam = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11
    if not lam / b11 > 0:
        raise DegenerateViewsError(_NEGATIVE_FOCAL)
    alpha = np.sqrt(lam / b11)
    beta = np.sqrt(lam * b11 / den)
    gamma = -b12 * alpha * alpha * beta / lam
    u0 = gamma * v0 / beta - b13 * alpha * alpha / lam
    if aspect:
        return Intrinsics(f_mm=float(alpha), cx_mm=float(u0), cy_mm=float(v0), skew=float(gamma) if skew else 0.0, fy_mm=float(beta))
    # one focal length: alpha == beta exactly when b22 == b11 and b12 == 0 (then u0 = -b13/b11)
    f = float(np.sqrt(alpha * beta))
    return Intrinsics(f_mm=f, cx_mm=float(u0), cy_mm=float(v0), skew=float(gamma) if skew else 0.0)


def extrinsics_from_homography(H, intr: Intrinsics):
    """Pose of the template from its homography and the intrinsics (Eq 26-28, docs/model.md#extrinsics).

    ``r1 = l A^-1 h1``, ``r2 = l A^-1 h2``, ``r3 = r1 x r2``, ``t = l A^-1 h3``,
    ``l = 1/|A^-1 h1|``; R is then replaced by the nearest rotation and the
    sign chosen so that ``t_z > 0`` (template in front of the sensor).

    Returns
    -------
    rvec (3,), tvec_mm (3,)
    """
    Ainv = np.linalg.inv(intr.matrix())
    H = np.asarray(H, dtype=float)
    a1 = Ainv @ H[:, 0]
    a2 = Ainv @ H[:, 1]
    a3 = Ainv @ H[:, 2]
    lam = 2.0 / (np.linalg.norm(a1) + np.linalg.norm(a2))
    if a3[2] * lam < 0:
        lam = -lam
    r1, r2, t = lam * a1, lam * a2, lam * a3
    R = nearest_rotation(np.column_stack([r1, r2, np.cross(r1, r2)]))
    return r_from_R(R), t


def poses_from_homographies(Hs, intr: Intrinsics):
    """Poses of all views: :func:`extrinsics_from_homography` of each (Eq 26-28), batched.

    The same steps as the one-view function on a stack of homographies
    (one inverse of A, one batched SVD for the nearest rotations);
    :func:`poses_from_homographies_reference` is the one-by-one loop.

    Parameters
    ----------
    Hs : (n_views, 3, 3) array_like or sequence of (3, 3) arrays
        Template -> sensor homographies (mm -> mm).
    intr : Intrinsics

    Returns
    -------
    rvecs, tvecs_mm : (n_views, 3) arrays (rad, mm)

    With :func:`psdcal._jit.use_compiled`, one compiled call
    (:func:`psdcal.calibration._linear_kernel.poses_kernel`: the nearest
    rotations by a 3 x 3 Jacobi SVD); the numpy code below is its reference.
    """
    H = np.asarray(Hs, dtype=float).reshape(-1, 3, 3)
    if H.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    if _jit.use_compiled(H.shape[0]):
        rv, tv, ok = linear_kernels().poses_kernel(np.ascontiguousarray(H), float(intr.f_mm), float(intr.skew),
                                                   float(intr.cx_mm), float(intr.fy), float(intr.cy_mm))
        if ok:
            return rv, tv
        # non-finite input or a singular A: the reference below decides
    return _poses_numpy(H, intr)


def _poses_numpy(H, intr: Intrinsics):
    """The numpy code of :func:`poses_from_homographies` (its reference), H (n, 3, 3) with n >= 1."""
    Ainv = np.linalg.inv(intr.matrix())
    # a[:, j] = A^-1 h_j (Eq 26-28 before scaling), as matrix-vector products (the one-view
    # function's, which round as a matrix-matrix product need not)
    h_cols = np.ascontiguousarray(H.transpose(0, 2, 1))[..., None]  # (n, 3, 3, 1): h_j as columns
    a = np.matmul(Ainv, h_cols)[..., 0]
    a1, a2, a3 = a[:, 0], a[:, 1], a[:, 2]
    # |a1|, |a2| as (1x3)(3x1) products: the dot product the one-view norm takes, so the same bits
    norm1 = np.sqrt((a1[:, None, :] @ a1[:, :, None])[:, 0, 0])
    norm2 = np.sqrt((a2[:, None, :] @ a2[:, :, None])[:, 0, 0])
    lam = 2.0 / (norm1 + norm2)
    lam = np.where(a3[:, 2] * lam < 0, -lam, lam)  # template in front: t_z > 0
    r1, r2, t = lam[:, None] * a1, lam[:, None] * a2, lam[:, None] * a3
    R = nearest_rotation_batch(np.stack([r1, r2, np.cross(r1, r2)], axis=-1))
    return r_from_R_batch(R), t


def poses_from_homographies_reference(Hs, intr: Intrinsics):
    """:func:`poses_from_homographies` as a loop of :func:`extrinsics_from_homography` (the reference).

    Returns
    -------
    rvecs, tvecs_mm : (n_views, 3) arrays
    """
    poses = [extrinsics_from_homography(H, intr) for H in Hs]
    return np.array([p[0] for p in poses]).reshape(-1, 3), np.array([p[1] for p in poses]).reshape(-1, 3)
