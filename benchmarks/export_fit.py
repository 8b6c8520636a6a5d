#!/usr/bin/env python3
"""How well OpenCV's distortion model fits psdcal's, for the paper's lenses (the table of docs/guide/export.md).

Calibrates 12 simulated views (2 um noise) of each case, fits 4, 5 and 8 OpenCV coefficients (K refined), and
prints the stated fit error, the error of cv2.undistortPoints with a converging criteria and with its default
iterations, and the calibration's own worst AoA 1-sigma for scale.

    .venv/bin/python benchmarks/export_fit.py      (a few seconds)
"""
from __future__ import annotations

import numpy as np

from psdcal import calibrate
from psdcal.errors import InputError
from psdcal.measure.aoa import angles_from_points
from psdcal.measure.sensor_model import SensorModel
from psdcal.report.compare import fov_uncertainty, sensor_grid_mm
from psdcal.report.export import fit_opencv, sensor_to_pixels
from psdcal.study.simulate import PAPER_L1, simulate_set


def ray_angle_deg(n1, n2):
    r1 = np.c_[n1, np.ones(len(n1))]
    r2 = np.c_[n2, np.ones(len(n2))]
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(r1, r2), axis=1), np.sum(r1 * r2, axis=1)))


def main(argv=None):
    import argparse

    import cv2

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--markdown", action="store_true", help="(the table is Markdown in any case; for tasks.py bench)")
    ap.add_argument("--quick", action="store_true", help="Lens 1 only (a smoke run)")
    a = ap.parse_args(argv)

    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    print("| case | coefficients | fit max (um on the sensor) | fit max (deg) | fit RMS (deg) | cv2.undistortPoints, "
          "criteria (deg) | cv2.undistortPoints, default (deg) | calibration's worst 1-sigma (deg) |")
    print("|---|---|---|---|---|---|---|---|")
    for lens, psd in (("lens1", 0),) if a.quick else (("lens1", 0), ("lens1", 1), ("lens2", 0), ("lens2", 1)):
        s = simulate_set(lens, n_images=12, noise_mm=0.002, seed=1, psd_l1=PAPER_L1 if psd else 0.0)
        r = calibrate(s.template_mm, s.points_mm, psd_radial=psd)
        sig = float(np.nanmax(fov_uncertainty(r, n=21).sigma_total_deg))
        d = sensor_grid_mm(r.sensor_mm, 41).reshape(-1, 2)
        n = angles_from_points(d, SensorModel(intrinsics=r.intrinsics, distortion=r.distortion)).n
        name = f"{lens}{' + PSD l1' if psd else ''}"
        for nc in (4, 5, 8):
            try:
                m = fit_opencv(r, n_coeffs=nc)
            except InputError:
                print(f"| {name} | {nc} | refused: the fitted model folds over inside the sensor | | | | | {sig:.3g} |")
                continue
            px = sensor_to_pixels(d, r.sensor_mm, m.pixel_um).reshape(-1, 1, 2)
            a1 = ray_angle_deg(cv2.undistortPoints(px, m.camera_matrix, m.dist_coeffs, None, None, None, crit)
                               .reshape(-1, 2), n).max()
            a0 = ray_angle_deg(cv2.undistortPoints(px, m.camera_matrix, m.dist_coeffs).reshape(-1, 2), n).max()
            print(f"| {name} | {nc} | {m.fit_max_um:.3g} | {m.fit_max_deg:.3g} | {m.fit_rms_deg:.2g} | {a1:.3g} | "
                  f"{a0:.3g} | {sig:.3g} |")


if __name__ == "__main__":
    main()
