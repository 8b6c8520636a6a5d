"""Rigid poses and the pinhole model (docs/model.md#pinhole-model, the paper's Eq 3-6).

Rotation vectors (axis * angle, rad) parametrise rotations; ``R_from_r``
gives R and, on request, its derivatives (Gallego & Yezzi 2015, J Math
Imaging Vis 51:378).  Points are (..., 3) in mm in the template frame; image
points (..., 2) in mm on the sensor.
"""
from __future__ import annotations

import numpy as np

from psdcal.model.params import Intrinsics


def skew3(v) -> np.ndarray:
    """Cross-product matrix [v]x of a (3,) vector."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def R_from_r(rvec, *, jacobian: bool = False):
    """Rotation matrix from a rotation vector (Rodrigues' formula).

    Returns
    -------
    R : (3, 3); with ``jacobian``, also ``dR_dr`` (3, 3, 3): ``dR_dr[i] = dR/dr_i``.
    """
    r = np.asarray(rvec, dtype=float)
    theta = float(np.linalg.norm(r))
    K = skew3(r)
    if theta < 1e-12:
        R = np.eye(3) + K
    else:
        R = np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta**2 * (K @ K)
    if not jacobian:
        return R
    dR = np.empty((3, 3, 3))
    eye = np.eye(3)
    if theta < 1e-12:
        for i in range(3):
            dR[i] = skew3(eye[i])
        return R, dR
    IR = eye - R
    for i in range(3):
        dR[i] = (r[i] * K + skew3(np.cross(r, IR[:, i]))) / theta**2 @ R
    return R, dR


def r_from_R(R) -> np.ndarray:
    """Rotation vector (3,) of a rotation matrix (inverse of :func:`R_from_r`); :func:`r_from_R_batch` of one."""
    return r_from_R_batch(np.asarray(R, dtype=float).reshape(1, 3, 3))[0]


def nearest_rotation(M) -> np.ndarray:
    """Closest rotation matrix to M in the Frobenius norm (SVD, det = +1)."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def nearest_rotation_batch(M) -> np.ndarray:
    """:func:`nearest_rotation` of each of a stack of matrices, (n, 3, 3) -> (n, 3, 3).

    One batched SVD; the same LAPACK routine per matrix as the one-by-one
    function, so the same result.
    """
    M = np.asarray(M, dtype=float)
    U, _, Vt = np.linalg.svd(M)
    sign = np.sign(np.linalg.det(U @ Vt))
    # U @ diag(1, 1, sign): scale U's last column
    UD = U.copy()
    UD[:, :, 2] *= sign[:, None]
    return UD @ Vt


def r_from_R_batch(R) -> np.ndarray:
    """Rotation vectors (n, 3) rad of a stack of rotation matrices (n, 3, 3), accurate at every angle.

    With ``w = (R32 - R23, R13 - R31, R21 - R12) = 2 sin(theta) u`` and
    ``cos(theta) = (tr R - 1) / 2``, the angle is ``theta = atan2(|w| / 2, cos)``
    (well conditioned everywhere, unlike the arccos of the trace near 0 and pi);
    the axis is ``w / |w|`` up to 120 degrees, and beyond (where ``w`` shrinks to
    round-off as theta nears pi) the column of largest norm of the symmetric part
    ``(R + R^T) / 2 - cos(theta) I = (1 - cos(theta)) u u^T``, signed like ``w``;
    ``w / 2`` below 1e-8 rad. Relative error about 1e-15 at every angle (the
    arccos formula lost up to 5e-4 within 1e-6 rad of a half turn).
    """
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=-1)
    s = 0.5 * np.sqrt(np.sum(w * w, axis=-1))  # sin(theta)
    c = 0.5 * (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0)  # cos(theta)
    theta = np.arctan2(s, c)
    small = theta < 1e-8
    r = np.where(small[:, None], 0.5 * w, w * (theta / (2.0 * np.where(small, 1.0, s)))[:, None])
    big = ~small & (c < -0.5)  # beyond 120 degrees: the axis from the symmetric part
    if np.any(big):
        Rb, cb = R[big], c[big]
        S = 0.5 * (Rb + Rb.transpose(0, 2, 1)) - cb[:, None, None] * np.eye(3)
        k = np.argmax(np.einsum("nii->ni", S), axis=1)
        col = S[np.arange(k.size), :, k]  # (m, 3): column k of each
        u = col / np.sqrt(np.sum(col * col, axis=-1))[:, None]
        u = np.where((np.sum(u * w[big], axis=-1) < 0)[:, None], -u, u)
        r[big] = u * theta[big][:, None]
    return r


def transform(P, rvec, tvec, *, jacobians: bool = False):
    """Points in the sensor frame, ``Pc = R P + t`` (Eq 3).

    Parameters
    ----------
    P : (..., 3) or (..., 2) array_like
        Template points, mm; 2 columns mean Z = 0.
    Returns
    -------
    Pc : (..., 3); with ``jacobians`` also ``dPc_dr`` (..., 3, 3) and ``dPc_dt`` (3, 3).
    """
    P = np.asarray(P, dtype=float)
    if P.shape[-1] == 2:
        P = np.concatenate([P, np.zeros(P.shape[:-1] + (1,))], axis=-1)
    if jacobians:
        R, dR = R_from_r(rvec, jacobian=True)
    else:
        R = R_from_r(rvec)
    Pc = P @ R.T + np.asarray(tvec, dtype=float)
    if not jacobians:
        return Pc
    dPc_dr = np.einsum("kij,...j->...ik", dR, P)
    return Pc, dPc_dr, np.eye(3)


def pinhole(Pc, intr: Intrinsics, *, jacobians: bool = False):
    """Ideal image point of camera-frame points (Eq 4, docs/model.md#pinhole-model).

    ``x = f Xc/Zc + skew Yc/Zc + cx``, ``y = fy Yc/Zc + cy``.

    Returns
    -------
    x : (..., 2) mm; with ``jacobians``: ``dx_dPc`` (..., 2, 3) and
    ``dx_dintr`` (..., 2, 5) over ``(f, cx, cy, skew, fy)`` where ``fy``'s
    column is zero unless ``intr.fy_mm`` is set (then ``f`` acts on x only).
    """
    Pc = np.asarray(Pc, dtype=float)
    Z = Pc[..., 2]
    xn = Pc[..., 0] / Z
    yn = Pc[..., 1] / Z
    f, fy, s = intr.f_mm, intr.fy, intr.skew
    x = np.stack([f * xn + s * yn + intr.cx_mm, fy * yn + intr.cy_mm], axis=-1)
    if not jacobians:
        return x
    zero = np.zeros_like(Z)
    inv_z = 1.0 / Z
    dxn = np.stack([inv_z, zero, -xn * inv_z], axis=-1)
    dyn = np.stack([zero, inv_z, -yn * inv_z], axis=-1)
    dx_dPc = np.stack([f * dxn + s * dyn, fy * dyn], axis=-2)
    one = np.ones_like(Z)
    separate_fy = intr.fy_mm is not None
    df = np.stack([xn, zero if separate_fy else yn], axis=-1)
    dcx = np.stack([one, zero], axis=-1)
    dcy = np.stack([zero, one], axis=-1)
    ds = np.stack([yn, zero], axis=-1)
    dfy = np.stack([zero, yn if separate_fy else zero], axis=-1)
    dx_dintr = np.stack([df, dcx, dcy, ds, dfy], axis=-1)
    return x, dx_dPc, dx_dintr


def project(P, intr: Intrinsics, rvec, tvec):
    """Ideal image points (..., 2) mm of template points P (..., 2|3) mm (Eq 5-6)."""
    return pinhole(transform(P, rvec, tvec), intr)


def homography_from_pose(intr: Intrinsics, rvec, tvec) -> np.ndarray:
    """H = A [r1 r2 t] mapping template (X, Y, 1) to image (x, y, 1) (Eq 18)."""
    R = R_from_r(rvec)
    return intr.matrix() @ np.column_stack([R[:, 0], R[:, 1], np.asarray(tvec, dtype=float)])


def backproject_to_plane(x_mm, intr: Intrinsics, rvec, tvec):
    """Point on the template plane (Z = 0) seen at ideal image point ``x_mm``.

    Intersects the ray through ``A^-1 (x, y, 1)`` with the plane of the pose.

    Returns
    -------
    (..., 2) ndarray, template-plane coordinates (X, Y) in mm.
    """
    H = homography_from_pose(intr, rvec, tvec)
    x = np.asarray(x_mm, dtype=float)
    xh = np.concatenate([x, np.ones(x.shape[:-1] + (1,))], axis=-1)
    q = np.linalg.solve(H, xh.reshape(-1, 3).T).T.reshape(xh.shape)
    return q[..., :2] / q[..., 2:3]


def rays(x_mm, intr: Intrinsics) -> np.ndarray:
    """Unit ray directions (..., 3) in the sensor frame of ideal image points (docs/model.md#angle-of-arrival-and-position)."""
    x = np.asarray(x_mm, dtype=float)
    xh = np.concatenate([x, np.ones(x.shape[:-1] + (1,))], axis=-1)
    n = np.linalg.solve(intr.matrix(), xh.reshape(-1, 3).T).T.reshape(xh.shape)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)
