"""Zhang's real calibration data (tests/data/zhang1998) for the benchmarks: psdcal's and OpenCV's inputs."""
from __future__ import annotations

from pathlib import Path

import numpy as np

ZHANG = Path(__file__).resolve().parent.parent / "tests" / "data" / "zhang1998"
#: Zhang's camera: 6.4 x 4.8 mm sensor (640 x 480 pixels of 10 um, the pitch psdcal's copy assumes)
SENSOR_MM = (6.4, 4.8)


def load_zhang():
    """``(template_mm (M, 2), points_mm (n_views, M, 2), object_points, image_points)``.

    The last two are OpenCV's ``calibrateCamera`` inputs from ``points_px.csv`` (one float32
    ``(m, 3)`` / ``(m, 1, 2)`` array per view, the template's z = 0).
    """
    from psdcal.io import read_points, read_template

    ids, template = read_template(ZHANG / "template.csv")
    points = read_points(ZHANG / "points.csv", ids, sensor_mm=SENSOR_MM).points_mm
    px = np.loadtxt(ZHANG / "points_px.csv", delimiter=",", skiprows=1)
    obj = np.concatenate([template, np.zeros((len(template), 1))], axis=1).astype(np.float32)
    objs, imgs = [], []
    for i in np.unique(px[:, 0]):
        rows = px[px[:, 0] == i]
        objs.append(obj[rows[:, 1].astype(int)])
        imgs.append(rows[:, 2:4].astype(np.float32).reshape(-1, 1, 2))
    return template, points, objs, imgs
