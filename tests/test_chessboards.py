"""Real chessboard sets (tests/data/chessboards): psdcal against OpenCV's stored calibrations.

Five cameras (OpenCV's and BoofCV's sample images; provenance and licences
in ``tests/data/chessboards/README.md`` and each folder's README). Each set's
corners are calibrated with psdcal as a camera: pixels put on a nominal 10 um
pitch about the image centre (``points.csv``; ``checks.json`` gives the pitch
and origin), the models that match OpenCV's (one f, k1 k2 p1 p2; with k3;
with a separate fy) and compared with ``cv2.calibrateCamera``'s stored
results on the same corners: f within ``f_rel`` (0.5 %), the centre within
``centre_px`` (2 px, about two standard errors), the RMS at most
``rms_max_ratio`` times OpenCV's. The two distortion models differ (psdcal
undistorts, OpenCV distorts), which is why the tolerances are not tighter.
"""
from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

from psdcal.calibration.core import calibrate
from psdcal.io import read_points, read_template

DATA = Path(__file__).parent / "data" / "chessboards"
SETS = sorted(p.name for p in DATA.iterdir() if p.is_dir()) if DATA.exists() else []

#: the command-line options of a check, as calibrate() keywords (only those the gates use here)
_OPTIONS = {(): {}, ("--radial", "3"): {"radial": 3}, ("--aspect",): {"aspect": True}}


def _cases():
    for name in SETS:
        checks = json.loads((DATA / name / "checks.json").read_text())
        for chk in checks["checks"]:
            if chk.get("gate") and chk["name"].startswith("opencv_") and tuple(chk["args"]) in _OPTIONS:
                yield pytest.param(name, chk["name"], id=f"{name}-{chk['name']}")


@lru_cache(maxsize=None)
def _data(name):
    ids, template = read_template(DATA / name / "template.csv")
    pts = read_points(DATA / name / "points.csv", ids)
    return template, pts


@pytest.mark.parametrize("name,check", list(_cases()))
def test_psdcal_matches_opencv_on_real_chessboards(name, check):
    meta = json.loads((DATA / name / "checks.json").read_text())
    chk = next(c for c in meta["checks"] if c["name"] == check)
    pitch = meta["pixel_pitch_mm"]
    origin = np.array(meta["origin_px"], dtype=float)
    tol = meta["tolerances"]
    template, pts = _data(name)
    res = calibrate(template, pts.points_mm, image_ids=pts.image_ids, **_OPTIONS[tuple(chk["args"])])
    intr = res.intrinsics
    f_px = intr.f_mm / pitch
    assert abs(f_px / chk["f_px"] - 1) <= tol["f_rel"], (f_px, chk["f_px"])
    if "fy_px" in chk:
        assert abs(intr.fy / pitch / chk["fy_px"] - 1) <= tol["f_rel"], (intr.fy / pitch, chk["fy_px"])
    c_px = np.asarray(intr.c) / pitch + origin
    assert np.hypot(*(c_px - [chk["cx_px"], chk["cy_px"]])) <= tol["centre_px"], (c_px, chk["cx_px"], chk["cy_px"])
    if "rms_max_ratio" in chk:
        assert res.rms_mm / pitch <= chk["rms_max_ratio"] * chk["rms_px"], (res.rms_mm / pitch, chk["rms_px"])
    assert res.converged
