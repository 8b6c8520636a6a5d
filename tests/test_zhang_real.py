"""Real measured data: Zhang's five views of a planar target (tests/data/zhang1998).

Provenance and licence are in ``tests/data/zhang1998/README.md``. Zhang
(IEEE TPAMI 22, 2000; MSR-TR-98-71) published, for these 256 corners x 5
images of a 640 x 480 camera: alpha = 832.5, beta = 832.53, gamma = 0.204494,
u0 = 303.959, v0 = 206.585 (pixels), k1 = -0.228601, k2 = 0.190353
(forward distortion of normalised coordinates), RMS residual about 0.34 px.
``points.csv`` puts the points on a nominal 10 um pitch, origin at pixel
(320, 240): a 6.4 x 4.8 mm sensor.

psdcal fits the same data with one focal length, the skew free, two radial
terms of its *undistortion* model (docs/model.md#distortion: the correction from the
measured to the ideal point, in mm about C), no tangential terms, image
cost. Both are maximum-likelihood fits of the same points; only the
distortion models differ, so f, C and the skew must agree to a small
fraction of their standard errors (f 0.0135 mm, C 0.007 mm, skew 0.0008 mm
here). Measured agreement (psdcal 0.1.0): f 8.32672 vs 8.32515 mm
(0.0016 mm = 0.16 px, 0.12 sigma), Cx -0.160410 vs -0.160410 mm, Cy
-0.334222 vs -0.334150 mm (0.007 px), skew 0.002094 vs 0.002045 mm
(0.06 sigma), RMS 0.003365 mm = 0.336 px. The tolerances below leave a
margin of about three over that and stay far below one standard error.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

from psdcal.calibration.core import calibrate
from psdcal.io import read_points, read_template

DATA = Path(__file__).parent / "data" / "zhang1998"
SENSOR_MM = (6.4, 4.8)
PITCH_MM = 0.010
ORIGIN_PX = (320.0, 240.0)

# Zhang's published result, pixels
ALPHA, BETA, GAMMA, U0, V0 = 832.5, 832.53, 0.204494, 303.959, 206.585
K1_ZHANG, K2_ZHANG = -0.228601, 0.190353

F_MM = 0.5 * (ALPHA + BETA) * PITCH_MM
CX_MM = (U0 - ORIGIN_PX[0]) * PITCH_MM
CY_MM = (V0 - ORIGIN_PX[1]) * PITCH_MM
SKEW_MM = GAMMA * PITCH_MM

TOL_F_MM = 0.005  # 0.5 px, 0.06 %
TOL_C_MM = 0.002  # 0.2 px
TOL_SKEW_MM = 0.0005
RMS_RANGE_MM = (0.0032, 0.0036)  # "about 0.34 px"


@lru_cache(maxsize=None)
def _data():
    ids, template = read_template(DATA / "template.csv")
    pts = read_points(DATA / "points.csv", ids, sensor_mm=SENSOR_MM)
    return ids, template, pts


@lru_cache(maxsize=None)
def _calibration(cost: str = "image"):
    ids, template, pts = _data()
    return calibrate(
        template,
        pts.points_mm,
        cost=cost,
        radial=2,
        tangential=False,
        skew=True,
        image_ids=pts.image_ids,
        point_ids=ids,
        sensor_mm=SENSOR_MM,
    )


def test_data_files_are_complete_and_consistent():
    ids, template, pts = _data()
    assert template.shape == (256, 2)
    assert pts.points_mm.shape == (5, 256, 2)
    assert np.all(np.isfinite(pts.points_mm))
    assert (DATA / "README.md").read_text().count("BSD") >= 1
    # points.csv is the published pixel file on the nominal pitch
    px = np.loadtxt(DATA / "points_px.csv", delimiter=",", skiprows=1)
    mm = np.loadtxt(DATA / "points.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(px[:, :2], mm[:, :2])
    np.testing.assert_allclose((px[:, 2:] - ORIGIN_PX) * PITCH_MM, mm[:, 2:], atol=1e-8)


def test_image_cost_agrees_with_zhangs_published_intrinsics():
    res = _calibration("image")
    intr = res.intrinsics
    assert res.converged
    assert abs(intr.f_mm - F_MM) < TOL_F_MM, intr.f_mm
    assert abs(intr.cx_mm - CX_MM) < TOL_C_MM, intr.cx_mm
    assert abs(intr.cy_mm - CY_MM) < TOL_C_MM, intr.cy_mm
    assert abs(intr.skew - SKEW_MM) < TOL_SKEW_MM, intr.skew
    # the published values lie well inside psdcal's own standard errors
    for name, published in (("f_mm", F_MM), ("cx_mm", CX_MM), ("cy_mm", CY_MM), ("skew", SKEW_MM)):
        assert abs(getattr(intr, name) - published) < 0.5 * res.std[name], name
    assert RMS_RANGE_MM[0] < res.rms_mm < RMS_RANGE_MM[1], res.rms_mm


def test_undistortion_k1_matches_zhangs_forward_k1_to_first_order():
    """Zhang: x_d = x (1 + k1 rn^2 + ...), rn normalised; ours: x = d + e (k1' r^2 + ...), r in mm.

    To first order the inverse of the forward model gives k1' = -k1 / f^2
    (mm^-2); the higher-order terms, absorbed differently by the two k2,
    leave a few per cent (measured: 1.7 %).
    """
    res = _calibration("image")
    k1_expected = -K1_ZHANG / (0.5 * (ALPHA + BETA) * PITCH_MM) ** 2
    assert res.distortion.k1 == pytest.approx(k1_expected, rel=0.05)
    assert res.distortion.k2 != 0.0


def test_template_cost_on_real_data_is_close_but_not_better():
    """The paper's template cost on the same data: recorded, within a standard error."""
    img = _calibration("image")
    tpl = _calibration("template")
    print(f"template cost: f {tpl.intrinsics.f_mm:.5f} C ({tpl.intrinsics.cx_mm:.5f}, {tpl.intrinsics.cy_mm:.5f}) "
          f"skew {tpl.intrinsics.skew:.6f} rms {tpl.rms_mm:.6f} mm")
    for name in ("f_mm", "cx_mm", "cy_mm", "skew"):
        assert abs(tpl.parameter(name) - img.parameter(name)) < img.std[name], name
    # the image cost minimises the sensor-plane RMS, so no other fit of the same model beats it
    assert img.rms_mm <= tpl.rms_mm * (1 + 1e-9)
