"""Simulated sensors and recordings with known truth, for the locate tests."""
from __future__ import annotations

import numpy as np

from psdcal.model.distortion import distort
from psdcal.model.readout import photocurrents
from psdcal.measure.sensor_model import SensorModel

#: The paper's Lens 2 with the optical centre offset (docs/model.md#paper-simulation-setup), a little PSD distortion.
BASE = {
    "intrinsics": {"f_mm": 8.0, "cx_mm": 0.5, "cy_mm": -0.7, "skew": 0.0},
    "distortion": {"k1": 1e-2, "k2": 3e-5, "k3": 0.0, "p1": 0.0, "p2": 0.0, "l1": -1.3e-3, "l2": 0.0},
    "sensor": {"lx_mm": 9.0, "ly_mm": 9.0},
}
NAMES = ["f_mm", "cx_mm", "cy_mm", "k1", "k2", "l1"]
STD = [5e-3, 4e-3, 4e-3, 2e-5, 1e-6, 1e-5]


def calib_dict(*, names=NAMES, std=STD, corr=0.3, skew=None, fy=None, gains=None, seed=0):
    """A calibration JSON dict with a random positive-definite correlated covariance."""
    d = {k: dict(v) for k, v in BASE.items()}
    names = list(names)
    std = list(std)
    if skew is not None:
        d["intrinsics"]["skew"] = skew
        names.append("skew")
        std.append(1e-3)
    if fy is not None:
        d["intrinsics"]["fy_mm"] = fy
        names.append("fy_mm")
        std.append(5e-3)
    if gains is not None:
        d["gains"] = list(gains)
        names += ["g_x2", "g_y1", "g_y2"]
        std += [2e-3, 2e-3, 2e-3]
    rng = np.random.default_rng(seed)
    m = len(names)
    c = np.eye(m) * (1 - corr) + corr * np.ones((m, m))
    q = np.linalg.qr(rng.standard_normal((m, m)))[0]
    c = np.diag(np.sqrt(np.diag(c))) @ c @ np.diag(np.sqrt(np.diag(c)))
    # mix the correlation structure a little so it is not uniform
    c = 0.7 * c + 0.3 * (q @ np.diag(rng.uniform(0.5, 1.5, m)) @ q.T)
    dd = 1 / np.sqrt(np.diag(c))
    c = dd[:, None] * c * dd[None]
    s = np.asarray(std)
    d["covariance"] = {"names": names, "matrix": (s[:, None] * c * s[None]).tolist()}
    return d


def model(**kw) -> SensorModel:
    return SensorModel.from_dict(calib_dict(**kw))


def spot_for_angles(m: SensorModel, alpha_rad):
    """Measured impact point (..., 2) of a beam arriving at ``alpha_rad`` (..., 2)."""
    n = np.tan(np.asarray(alpha_rad, dtype=float))
    A = m.intrinsics.matrix()
    nh = np.concatenate([n, np.ones(n.shape[:-1] + (1,))], axis=-1)
    x = (nh @ A.T)[..., :2]
    res = distort(x, m.distortion, m.intrinsics.c)
    assert np.all(res.converged)
    return res.d_mm


def amplitudes(m: SensorModel, d_mm, total=1.0):
    """Channel amplitudes (..., 4) of a spot at d_mm (through the sensor's gains)."""
    return photocurrents(d_mm, total, m.lx_mm, m.ly_mm) * m.gains


def signals(rate_hz, n, emitters, *, t0_s=0.0, noise=0.0, offset=(0.1, 0.12, 0.09, 0.11), rng=None):
    """Four-channel samples (4, n).

    emitters: list of (amplitudes (4,), carrier_hz, phase_rad).
    """
    t = t0_s + np.arange(n) / rate_hz
    x = np.zeros((4, n)) + np.asarray(offset)[:, None]
    for amp, f, ph in emitters:
        x += np.asarray(amp)[:, None] * np.sin(2 * np.pi * f * t + ph)[None]
    if noise:
        rng = rng or np.random.default_rng(0)
        x += noise * rng.standard_normal((4, n))
    return x
