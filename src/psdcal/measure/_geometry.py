"""Small geometry helpers shared by the system-level modules (pose, bundle, planning, the simulator)."""
from __future__ import annotations

import numpy as np

from psdcal.model.distortion import distort
from psdcal.model.projection import R_from_r


def project_world(points_w_mm, rvec, tvec_mm):
    """Normalised coordinates (..., 2) and depth (...) of world points seen from a pose ``Pc = R Pw + t``."""
    P = np.asarray(points_w_mm, dtype=float)
    pc = P @ R_from_r(np.asarray(rvec, dtype=float)).T + np.asarray(tvec_mm, dtype=float)
    z = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        n = pc[..., :2] / z[..., None]
    return n, z


def spot_for_normalised(m, n, *, strict: bool = False):
    """Measured impact point (..., 2), mm, of normalised coordinates ``n`` (..., 2) through model ``m``.

    ``x = A n`` (Eq 4), ``d = distort(x)`` (Eq 7-16); NaN where the distortion
    does not converge (an assertion error with ``strict``).
    """
    n = np.asarray(n, dtype=float)
    A = m.intrinsics.matrix()
    nh = np.concatenate([n, np.ones(n.shape[:-1] + (1,))], axis=-1)
    x = (nh @ A.T)[..., :2]
    res = distort(x, m.distortion, m.intrinsics.c)
    if strict:
        assert np.all(res.converged)
    return np.where(np.asarray(res.converged)[..., None], res.d_mm, np.nan)


def skews(v):
    """``[v]_x`` (N, 3, 3) for each row of ``v`` (N, 3)."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], -1), np.stack([v[:, 2], z, -v[:, 0]], -1),
                     np.stack([-v[:, 1], v[:, 0], z], -1)], -2)
