"""A small positioning room written directly as files (no recording, no numba): for the dashboard's tests,
its benchmark and its screenshots.

The sensors look from the ceiling at the middle of a 6 x 4 x 3 m room. The
rows are what ``psdcal locate --sensors`` writes (``MULTI_COLUMNS``): a fixed
emitter ``a1`` and a tag on a circle, 100 windows per second, with per-axis
sigmas and chi2 values drawn from chi2(3); three windows of ``a1`` in a row
have a chi2 of 500 at ``t_s`` = 1.00, 1.01, 1.02 (a reflection).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

ROWS_HEADER = "t_s,emitter,X_mm,Y_mm,Z_mm,sigma_X_mm,sigma_Y_mm,sigma_Z_mm,n_sensors,chi2"
BAD_T = (1.0, 1.01, 1.02)


def rotvec(R) -> list:
    """Rotation vector of a rotation matrix (axis * angle), written out here rather than borrowed."""
    angle = math.acos(max(-1.0, min(1.0, (np.trace(R) - 1) / 2)))
    if angle < 1e-12:
        return [0.0, 0.0, 0.0]
    if abs(angle - math.pi) < 1e-6:  # R = 2 a a^T - I: the axis is the largest column of (R + I) / 2
        B = (np.asarray(R) + np.eye(3)) / 2
        a = B[:, int(np.argmax(np.diag(B)))]
        return (a / np.linalg.norm(a) * math.pi).tolist()
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2 * math.sin(angle))
    return (axis * angle).tolist()


def look_at(center_mm, aim_mm):
    """World -> camera rotation of a sensor at ``center_mm`` whose optical axis (+Z) points at ``aim_mm``."""
    z = np.asarray(aim_mm, float) - np.asarray(center_mm, float)
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.array([x, y, z])


SENSORS = {"s1": (5800.0, 3800.0, 2800.0), "s2": (200.0, 3800.0, 2800.0), "s3": (3000.0, 200.0, 2800.0)}
AIM = (3000.0, 2000.0, 800.0)
SURVEYED = {"a1": (2000.0, 1500.0, 800.0), "b1": (4200.0, 2600.0, 500.0), "b2": (3300.0, 1200.0, 1200.0)}


def tag_position(t):
    """The tag's true position (mm) at time ``t`` (s): a circle of 800 mm in 4 s at Z = 1000 mm."""
    w = 2 * math.pi / 4.0
    return 3000.0 + 800.0 * math.cos(w * t), 2000.0 + 800.0 * math.sin(w * t), 1000.0


REFLECTION = ("s2", "a1", 2.0, 2.1)  # sensor, emitter, from, to (s): its angles 1 deg off


def write_room(d, *, duration_s: float = 30.0, rate_hz: float = 100.0, seed: int = 1, sensor_rows: bool = False) -> dict:
    """Write calib.json, sensors.json, emitters.csv and rows.csv into ``d``; returns their paths.

    With ``sensor_rows`` also each sensor's angles (``<s>_angles.csv``, the
    columns of a single-sensor `locate`, angle noise 0.05 deg stated as 0.1 deg;
    :data:`REFLECTION` puts one sensor's angles of one emitter 1 deg off for
    0.1 s) and amplitudes (``<s>_amp.csv``, SNR about 200, 120 and 40).
    """
    d = Path(d)
    rng = np.random.default_rng(seed)
    (d / "calib.json").write_text(json.dumps({
        "intrinsics": {"f_mm": 8.0, "cx_mm": 0.0, "cy_mm": 0.0, "skew": 0.0},
        "distortion": {"k1": 0.0, "k2": 0.0, "k3": 0.0, "p1": 0.0, "p2": 0.0, "l1": 0.0, "l2": 0.0},
        "sensor": {"lx_mm": 9.0, "ly_mm": 9.0}, "gains": [1.0, 1.0, 1.0, 1.0], "verdict": "good"}))
    sensors = []
    for name, c in SENSORS.items():
        R = look_at(c, AIM)
        sensors.append({"name": name, "calib": "calib.json", "rvec": rotvec(R), "tvec_mm": (-R @ np.array(c)).tolist()})
    (d / "sensors.json").write_text(json.dumps({"sensors": sensors}, indent=1))
    (d / "emitters.csv").write_text("emitter,X_m,Y_m,Z_m\n" + "".join(
        f"{n},{p[0] / 1000:.4f},{p[1] / 1000:.4f},{p[2] / 1000:.4f}\n" for n, p in SURVEYED.items()))
    lines = [ROWS_HEADER]
    n = int(round(duration_s * rate_hz))
    for i in range(n):
        t = 0.005 + i / rate_hz
        for em in ("a1", "tag"):
            truth = SURVEYED["a1"] if em == "a1" else tag_position(t)
            sig = np.array([3.0, 4.0, 5.0]) if em == "a1" else np.array([1.5, 1.5, 2.5])
            p = np.asarray(truth) + sig * rng.standard_normal(3)
            chi2 = float(rng.chisquare(3))
            if em == "a1" and any(abs(t - 0.005 - b) < 1e-9 for b in BAD_T):
                chi2 = 500.0
            lines.append(f"{t:.6f},{em},{p[0]:.4f},{p[1]:.4f},{p[2]:.4f},{sig[0]:.3f},{sig[1]:.3f},{sig[2]:.3f},3,{chi2:.5g}")
    (d / "rows.csv").write_text("\n".join(lines) + "\n")
    out = {k: d / f for k, f in (("calib", "calib.json"), ("sensors", "sensors.json"), ("emitters", "emitters.csv"),
                                 ("rows", "rows.csv"))}
    if sensor_rows:
        for k, (name, c) in enumerate(SENSORS.items()):
            R = look_at(c, AIM)
            ang = ["t_s,emitter,x_mm,y_mm,alpha_x_deg,alpha_y_deg,sigma_x_mm,sigma_y_mm,sigma_alpha_x_deg,sigma_alpha_y_deg"]
            amp = ["t_s,emitter,vx1,vx2,vy1,vy2,sigma_vx1,sigma_vx2,sigma_vy1,sigma_vy2"]
            noise = (0.005, 0.008, 0.025)[k]
            for i in range(n):
                t = 0.005 + i / rate_hz
                for em in ("a1", "tag"):
                    truth = SURVEYED["a1"] if em == "a1" else tag_position(t)
                    pc = R @ (np.asarray(truth) - np.asarray(c))
                    a = np.degrees(np.arctan(pc[:2] / pc[2])) + 0.05 * rng.standard_normal(2)
                    if (name, em) == REFLECTION[:2] and REFLECTION[2] <= t < REFLECTION[3]:
                        a = a + 1.0
                    ang.append(f"{t:.6f},{em},0,0,{a[0]:.6f},{a[1]:.6f},0.001,0.001,0.1,0.1")
                    v = 1.0 + noise * rng.standard_normal(4)
                    amp.append(f"{t:.6f},{em}," + ",".join(f"{x:.5f}" for x in v) + "," + ",".join([f"{noise:g}"] * 4))
            (d / f"{name}_angles.csv").write_text("\n".join(ang) + "\n")
            (d / f"{name}_amp.csv").write_text("\n".join(amp) + "\n")
            out[f"{name}_angles"] = d / f"{name}_angles.csv"
            out[f"{name}_amp"] = d / f"{name}_amp.csv"
    return out


def read_rows(path) -> list:
    """The rows CSV back as ``(t_s, emitter, X_mm, Y_mm)`` tuples (read here, not by the dashboard's parser)."""
    out = []
    with open(path) as fh:
        next(fh)
        for line in fh:
            c = line.strip().split(",")
            out.append((float(c[0]), c[1], float(c[2]), float(c[3])))
    return out
