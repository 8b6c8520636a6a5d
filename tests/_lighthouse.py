"""Loader of the real Lighthouse V1 data set (``lighthouse-lh1`` of the shared data folder beside the repository, see its README).

Two Lighthouse V1 base stations are angle-of-arrival sensors with known poses
(``geometry.json``); the four photodiodes of the Crazyflie's deck are the
emitters; motion capture is the truth; ``crazyflie_estimate.csv`` is the
Crazyflie's own crossing-beam position.  This module only reads and converts:

- the station angles ``(h, v)`` into psdcal's normalised directions
  ``n = (xn, yn)`` of a camera frame whose axes are the base station's
  ``(y, z, x)`` (left, up, forward: a right-handed frame with ``z`` along the
  optical axis), so that ``n = (tan h, tan v)``, and each station's pose as
  psdcal's ``(R, t_mm)`` with ``Pc = R Pw + t`` (mm);
- the motion capture, interpolated at given times (NaN over gaps);
- the rigid transform lighthouse -> mocap fitted on alternate 10 s blocks and
  scored on the other blocks, as the README describes.

Nothing here is psdcal code: the data are read with numpy only, so the tests
built on them are an independent oracle.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
ROOT = REPO.parent / "shared" / "data" / "lighthouse-lh1"
FLIGHTS = ("lh1_crossingBeam_flight_00", "lh1_crossingBeam_flight_01")
STATIC = tuple(f"lh1_crossingBeam_jitter_{i:02d}" for i in range(5))

#: Angle noise at rest (README, RMS over sensors and logs, 64-74 urad), rad.
SIGMA_ANGLE_RAD = 70e-6
#: Mean correlation of that noise between the four sensors of one station and sweep (README).
RHO_SENSORS = 0.73
#: Camera axes (x, y, z) = base station (y, z, x): rows pick them out of base-station coordinates.
BS_TO_CAM = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


def available() -> bool:
    return (ROOT / "geometry.json").is_file()


@dataclass(frozen=True)
class Geometry:
    origin_mm: np.ndarray  # (2, 3) station origins, lighthouse frame, mm
    R_w2c: np.ndarray  # (2, 3, 3) psdcal rotation world -> camera
    t_mm: np.ndarray  # (2, 3) psdcal translation, Pc = R Pw + t
    sensors_mm: np.ndarray  # (4, 3) deck sensors in the body frame, mm


def geometry() -> Geometry:
    g = json.loads((ROOT / "geometry.json").read_text())
    o = np.array([b["origin_m"] for b in g["base_stations"]]) * 1000.0
    Rb = np.array([b["rotation_bs_to_world"] for b in g["base_stations"]])
    R = np.einsum("ij,bkj->bik", BS_TO_CAM, Rb)  # P @ Rb^T
    t = -np.einsum("bij,bj->bi", R, o)
    pos = g["deck_sensors"]["positions_m"]
    s = np.array([pos[str(i)] for i in range(4)]) * 1000.0
    return Geometry(o, R, t, s)


def _csv(path):
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


@dataclass(frozen=True)
class Log:
    name: str
    angles: np.ndarray  # (N, 5) t_s, station, sensor, h_rad, v_rad
    mocap: np.ndarray  # (M, 4) t_s, X_m, Y_m, Z_m
    estimate: np.ndarray  # (E, 5) t_s, X_m, Y_m, Z_m, delta_m


def load(name: str) -> Log:
    d = ROOT / name
    return Log(name, _csv(d / "angles.csv"), _csv(d / "mocap.csv"), _csv(d / "crazyflie_estimate.csv"))


def frames(log: Log):
    """Each station's frames: ``{station: (times (F,), h (F, 4), v (F, 4))}`` with NaN for unseen sensors."""
    out = {}
    a = log.angles
    for b in (0, 1):
        m = a[:, 1] == b
        t_all = a[m, 0]
        times, inv = np.unique(t_all, return_inverse=True)
        h = np.full((len(times), 4), np.nan)
        v = np.full((len(times), 4), np.nan)
        s = a[m, 2].astype(int)
        h[inv, s] = a[m, 3]
        v[inv, s] = a[m, 4]
        out[b] = (times, h, v)
    return out


def steps(log: Log):
    """The Crazyflie's steps: for each estimate row, each station's latest frame at or before it.

    Returns
    -------
    t_s : (E,) times of the estimate rows
    n : (2, E, 4, 2) psdcal normalised directions ``(tan h, tan v)`` per station and sensor (NaN: unseen)
    age_s : (2, E) age of each station's frame at the row
    estimate_m : (E, 3) the Crazyflie's own position, lighthouse frame, m
    """
    fr = frames(log)
    t = log.estimate[:, 0]
    E = len(t)
    n = np.full((2, E, 4, 2), np.nan)
    age = np.full((2, E), np.nan)
    for b in (0, 1):
        times, h, v = fr[b]
        k = np.searchsorted(times, t + 1e-9, side="right") - 1
        ok = k >= 0
        n[b, ok, :, 0] = np.tan(h[k[ok]])
        n[b, ok, :, 1] = np.tan(v[k[ok]])
        age[b, ok] = t[ok] - times[k[ok]]
    return t, n, age, log.estimate[:, 1:4]


def mocap_at(log: Log, t_s, max_gap_s: float = np.inf):
    """Motion capture position (mm) linearly interpolated at ``t_s``; NaN outside it (or across a gap > max_gap_s)."""
    tm = log.mocap[:, 0]
    t = np.asarray(t_s, dtype=float)
    out = np.full((len(t), 3), np.nan)
    k = np.searchsorted(tm, t)
    ok = (k > 0) & (k < len(tm))
    kk = np.clip(k, 1, len(tm) - 1)
    ok &= (tm[kk] - tm[kk - 1]) <= max_gap_s
    for j in range(3):
        out[:, j] = np.interp(t, tm, log.mocap[:, 1 + j] * 1000.0)
    out[~ok] = np.nan
    return out


def rigid_fit(a_mm, b_mm):
    """``(R, t)`` minimising ``sum |R a + t - b|^2`` (Kabsch, proper rotation)."""
    ca, cb = a_mm.mean(0), b_mm.mean(0)
    H = (a_mm - ca).T @ (b_mm - cb)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


def halves(t_s, block_s: float = 10.0):
    """Fit (even 10 s blocks) and score (odd blocks) masks of the alternate-blocks scheme."""
    blk = np.floor(np.asarray(t_s) / block_s).astype(int)
    return blk % 2 == 0, blk % 2 == 1


def scored_errors(t_s, p_lh_mm, truth_mm, fit_mask, score_mask):
    """Distances (mm) on the score rows after the rigid lighthouse -> mocap fit on the fit rows.

    Returns ``(errors (n,), R, t, rows)``: ``rows`` the indices of the scored rows."""
    ok = np.all(np.isfinite(p_lh_mm), 1) & np.all(np.isfinite(truth_mm), 1)
    f = ok & fit_mask
    R, t = rigid_fit(p_lh_mm[f], truth_mm[f])
    s = np.flatnonzero(ok & score_mask)
    e = np.linalg.norm(p_lh_mm[s] @ R.T + t - truth_mm[s], axis=1)
    return e, R, t, s


def station_directions(n_bs, sigma_rad: float = SIGMA_ANGLE_RAD):
    """psdcal rays and covariances from one station's ``(tan h, tan v)`` (..., 2).

    The angle noise ``sigma_rad`` (independent between h and v) becomes
    ``cov(n) = diag(sigma^2 (1 + n^2)^2)`` (``dn/dangle = 1 + tan^2``)."""
    n_bs = np.asarray(n_bs, dtype=float)
    cov = np.zeros(n_bs.shape + (2,))
    cov[..., 0, 0] = sigma_rad**2 * (1 + n_bs[..., 0] ** 2) ** 2
    cov[..., 1, 1] = sigma_rad**2 * (1 + n_bs[..., 1] ** 2) ** 2
    return cov


def nees(err, cov):
    """``e^T C^-1 e`` per row."""
    return np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov), err)
