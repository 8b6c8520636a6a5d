"""Rooms for the pose tests, drawn independently of psdcal (own rotations, own pinhole, own noise).

Nothing here imports psdcal: the rotation (Rodrigues), its logarithm, the
aiming of a sensor, the pinhole projection and the correlated angle noise are
written from their definitions, so a convention error shared by psdcal's own
simulator and its solver cannot pass unseen.

Room frame: right-handed, ``z`` up, origin at a floor corner, the room the box
``[0, W] x [0, D] x [0, H]`` (mm). Camera frame: ``x`` right, ``y`` down,
``z`` forward; ``n = (X / Z, Y / Z)`` of ``R (P - c)``.

Layouts (``KINDS``): ``floor`` (emitters on the floor, a ceiling sensor),
``bumpy`` (the floor with 0-30 mm relief), ``wall`` (one of the four walls,
the sensor in the room), ``ceiling`` (emitters on the ceiling, the sensor below
looking up), ``general`` (anywhere in the room's volume, a high sensor).
Surveys (``SURVEYS``): ``right``, ``swap_xy`` (x and y exchanged), ``flip_x``
(x measured from the far wall: a left-handed frame), ``flip_z`` (z measured
down from the ceiling): each maps the room's box onto itself, so the mistaken
coordinates look as plausible as the right ones.
"""
from __future__ import annotations

import numpy as np

KINDS = ("floor", "bumpy", "wall", "ceiling", "general")
SURVEYS = ("right", "swap_xy", "flip_x", "flip_z")
#: Largest angle of an emitter from the sensor's axis (a lens's field of view), deg.
HALF_FOV_DEG = 65.0


def rodrigues(w):
    """Rotation matrix of the rotation vector ``w`` (3,) (axis * angle, rad)."""
    w = np.asarray(w, dtype=float)
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    a = w / th
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * K @ K


def log_rotation(R):
    """Rotation vector (3,) of a rotation matrix (angles below pi)."""
    th = float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return v * (0.5 if th < 1e-12 else th / (2.0 * np.sin(th)))


def aim(c, target, roll_rad):
    """World -> camera rotation of a sensor at ``c`` looking at ``target``, rolled about its axis."""
    z = np.asarray(target, dtype=float) - c
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.cross(z, [1.0, 0.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)  # x cross y = z: a right-handed camera frame
    return rodrigues([0.0, 0.0, roll_rad]) @ np.stack([x, y, z])


def draw_room(rng, kind):
    """Emitters ``P`` (k, 3) mm, the sensor's rotation ``R`` (world -> camera) and centre ``c`` (mm), the box (W, D, H)."""
    W, D, H = rng.uniform(4000, 8000), rng.uniform(3000, 6000), rng.uniform(2500, 3500)
    for _ in range(10_000):
        k = int(rng.integers(4, 9))
        if kind in ("floor", "bumpy"):
            P = np.c_[rng.uniform(0, W, k), rng.uniform(0, D, k), np.zeros(k)]
            if kind == "bumpy":
                P[:, 2] = rng.uniform(0, 30, k)
            c = np.array([rng.uniform(0.1, 0.9) * W, rng.uniform(0.1, 0.9) * D, H - rng.uniform(20, 300)])
        elif kind == "ceiling":
            P = np.c_[rng.uniform(0, W, k), rng.uniform(0, D, k), np.full(k, H)]
            c = np.array([rng.uniform(0.1, 0.9) * W, rng.uniform(0.1, 0.9) * D, rng.uniform(200, 1400)])
        elif kind == "wall":
            wall = int(rng.integers(4))
            s = rng.uniform(0, (W, D)[wall % 2], k)
            h = rng.uniform(200, H - 200, k)
            P = {0: np.c_[np.zeros(k), s, h], 1: np.c_[s, np.zeros(k), h],
                 2: np.c_[np.full(k, W), s, h], 3: np.c_[s, np.full(k, D), h]}[wall]
            c = np.array([rng.uniform(0.2, 0.8) * W, rng.uniform(0.2, 0.8) * D, rng.uniform(500, H - 100)])
        elif kind == "general":
            P = np.c_[rng.uniform(0, W, k), rng.uniform(0, D, k), rng.uniform(0, H, k)]
            c = np.array([rng.uniform(0.05, 0.95) * W, rng.uniform(0.05, 0.95) * D, H - rng.uniform(20, 500)])
        else:
            raise ValueError(kind)
        R = aim(c, P.mean(0) + rng.normal(0.0, 300.0, 3), rng.uniform(-np.pi, np.pi))
        pc = (P - c) @ R.T
        if np.all(pc[:, 2] > np.cos(np.radians(HALF_FOV_DEG)) * np.linalg.norm(pc, axis=1)) and \
                np.min(np.linalg.norm(P - c, axis=1)) > 300.0:
            return P, R, c, (W, D, H)
    raise RuntimeError("no room drawn")  # pragma: no cover


def observe(rng, P, R, c, sigma_range=(2e-5, 5e-4)):
    """Normalised coordinates (k, 2) with correlated Gaussian noise, and that noise's covariance (k, 2, 2).

    Each emitter's two sigmas are drawn log-uniformly in ``sigma_range``
    (normalised units, ~rad), their correlation uniformly in [-0.5, 0.5].
    """
    pc = (P - c) @ R.T
    n = pc[:, :2] / pc[:, 2:]
    k = len(P)
    lo, hi = np.log10(sigma_range[0]), np.log10(sigma_range[1])
    sig = 10.0 ** rng.uniform(lo, hi, (k, 2))
    rho = rng.uniform(-0.5, 0.5, k)
    cov = np.zeros((k, 2, 2))
    cov[:, 0, 0], cov[:, 1, 1] = sig[:, 0] ** 2, sig[:, 1] ** 2
    cov[:, 0, 1] = cov[:, 1, 0] = rho * sig[:, 0] * sig[:, 1]
    L = np.linalg.cholesky(cov)
    return n + np.einsum("kij,kj->ki", L, rng.standard_normal((k, 2))), cov


def corrupt(P, how, box):
    """The survey as a mistaken surveyor writes it (each maps the room's box onto itself)."""
    W, D, H = box
    if how == "swap_xy":
        return P[:, [1, 0, 2]].copy()
    if how == "flip_x":
        return P * [-1.0, 1.0, 1.0] + [W, 0.0, 0.0]
    if how == "flip_z":
        return P * [1.0, 1.0, -1.0] + [0.0, 0.0, H]
    if how == "right":
        return P.copy()
    raise ValueError(how)


def chi2_of(n, cov, P, R, c):
    """The weighted squared residual of the angles ``n`` (k, 2) for the pose ``(R, c)`` (the likelihood's exponent)."""
    pc = (P - c) @ R.T
    r = n - pc[:, :2] / pc[:, 2:]
    return float(np.einsum("ki,kij,kj->", r, np.linalg.inv(cov), r))


def pose_nees(R_hat, c_hat, cov, R, c):
    """NEES of a pose ``(R_hat, c_hat)`` with covariance ``cov`` over ``(omega, c)``, ``R = exp([omega]) R_hat``."""
    e = np.concatenate([log_rotation(R @ R_hat.T), c - c_hat])
    return float(e @ np.linalg.solve(cov, e))


def run_study(estimate, *, n_right: int, n_wrong: int, seed: int, kinds=KINDS, solve_pnp=None):
    """Draw rooms and pose each with ``estimate(n, cov, P_survey)``; one record per room.

    ``n_right`` rooms per layout with the right survey, ``n_wrong`` per layout and mistaken survey.
    ``estimate`` returns a result with ``R``, ``center_w_mm``, ``cov``, ``usable`` and ``checks``
    (or raises: a refusal). ``solve_pnp(n, P) -> (R, c)`` (e.g. OpenCV's SQPnP) is compared on the
    right surveys when given.

    Returns
    -------
    list of dict: kind, survey, k, outcome ('refused', 'unusable', 'warned', 'clean'), nees and
    dchi2_truth (right surveys: the chi2 at the true pose minus the result's, the likelihood ratio), sqpnp_nees and sqpnp_same (the independent solver's pose against the result's: its NEES
    under the result's covariance, and whether it lies in the same basin: 2 deg, 2 % of the distance).
    """
    rng = np.random.default_rng(seed)
    out = []
    for kind in kinds:
        for how in SURVEYS:
            for _ in range(n_right if how == "right" else n_wrong):
                P, R, c, box = draw_room(rng, kind)
                n, cov = observe(rng, P, R, c)
                Ps = corrupt(P, how, box)
                rec = {"kind": kind, "survey": how, "k": len(P), "nees": None, "sqpnp_nees": None,
                       "sqpnp_same": None, "truth": (n, cov, Ps, R, c)}
                try:
                    r = estimate(n, cov, Ps)
                except Exception as exc:  # a refusal: one of psdcal's errors
                    rec["outcome"] = "refused"
                    rec["error"] = str(exc)
                    out.append(rec)
                    continue
                if not r.usable:
                    rec["outcome"] = "unusable"
                elif any(ch.passed is False for ch in r.checks):
                    rec["outcome"] = "warned"
                else:
                    rec["outcome"] = "clean"
                if how == "right":
                    rec["nees"] = pose_nees(r.R, r.center_w_mm, r.cov, R, c)
                    rec["dchi2_truth"] = chi2_of(n, cov, P, R, c) - chi2_of(n, cov, P, r.R, r.center_w_mm)
                    if solve_pnp is not None:
                        Rq, cq = solve_pnp(n, Ps)
                        rec["sqpnp_nees"] = pose_nees(r.R, r.center_w_mm, r.cov, Rq, cq)
                        rec["sqpnp_dchi2"] = chi2_of(n, cov, Ps, Rq, cq) - chi2_of(n, cov, Ps, r.R, r.center_w_mm)
                        dist = float(np.mean(np.linalg.norm(Ps - c, axis=1)))
                        ang = np.degrees(np.linalg.norm(log_rotation(Rq @ r.R.T)))
                        rec["sqpnp_same"] = bool(ang < 2.0 and np.linalg.norm(cq - r.center_w_mm) < 0.02 * dist)
                out.append(rec)
    return out


def sqpnp(n, P):
    """OpenCV's SQPnP on normalised coordinates (identity camera matrix): ``(R, c)``."""
    import cv2

    ok, rvec, tvec = cv2.solvePnP(np.ascontiguousarray(P, dtype=np.float64),
                                  np.ascontiguousarray(n, dtype=np.float64), np.eye(3), None,
                                  flags=cv2.SOLVEPNP_SQPNP)
    if not ok:  # pragma: no cover
        raise RuntimeError("SQPnP failed")
    R = cv2.Rodrigues(rvec)[0]
    return R, -R.T @ tvec.ravel()
