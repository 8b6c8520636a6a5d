"""`psdcal export`: a calibration as OpenCV YAML, ROS camera_info, or the JSON Schema of the calibration file."""
from __future__ import annotations

from pathlib import Path

import click

from psdcal.cli import cli


@cli.command("export")
@click.argument("calibration", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--format", "fmt", required=True, type=click.Choice(["opencv-yaml", "ros", "json-schema"]),
              help="opencv-yaml: OpenCV FileStorage YAML (camera_matrix, distortion_coefficients); ros: a ROS "
                   "camera_info YAML; json-schema: the JSON Schema (draft 2020-12) of the calibration file.")
@click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="File to write (written only when the export succeeds).")
@click.option("--pixel-um", type=click.FloatRange(min=0.0, min_open=True), default=1.0, show_default=True,
              help="Pixel pitch of the exported camera matrix, micrometres (a PSD has no pixels; 1: pixel "
                   "coordinates are micrometres from the sensor's corner; 1000: pixels are millimetres).")
@click.option("--coeffs", "n_coeffs", type=click.Choice(["4", "5", "8"]), default="5", show_default=True,
              help="OpenCV distortion coefficients: 4 (k1 k2 p1 p2), 5 (+ k3; ROS plumb_bob), 8 (+ k4 k5 k6, "
                   "OpenCV's rational model; ROS rational_polynomial). Short lenses with strong distortion need 8.")
@click.option("--fixed-k/--refine-k", "fixed_k", default=False, show_default=True,
              help="Keep psdcal's f and C in the camera matrix (--fixed-k) or adjust them in the fit (--refine-k: "
                   "smaller fit error; OpenCV has one distortion centre, psdcal two).")
@click.option("--grid", type=click.IntRange(5, 401), default=61, show_default=True,
              help="Sensor grid points per side for the fit and its error.")
@click.option("--camera-name", default="psd_sensor", show_default=True, help="With --format ros: camera_name.")
def export_command(calibration, fmt, output, pixel_um, n_coeffs, fixed_k, grid, camera_name):
    """Export a calibration for other tools.

    opencv-yaml and ros FIT OpenCV's forward distortion model (k1, k2, p1, p2
    [, k3 [, k4, k5, k6]]) to psdcal's undistortion model over a grid of the
    whole sensor, and state the fit error in the file and here: the forward
    misfit in micrometres on the sensor and the angle between OpenCV's ray
    and psdcal's ray, in degrees (max and RMS). The verdict compares it with
    the calibration's own AoA uncertainty.

    Pixels: u = (x_mm + Lx/2) / pitch - 0.5, v = (y_mm + Ly/2) / pitch - 0.5
    (u along the sensor's +x, v along +y; OpenCV's camera frame is psdcal's
    sensor frame). With strong distortion, give cv2.undistortPoints a
    termination criteria (e.g. COUNT+EPS, 100, 1e-12): its default 5
    iterations do not converge at the sensor's corners.

    json-schema writes the JSON Schema of the calibration file (CALIBRATION
    is then optional; when given it is checked against the schema if the
    `jsonschema` package is installed).

    Examples:

      psdcal export calib.json --format opencv-yaml -o calib.yaml

      psdcal export calib.json --format ros --coeffs 8 --pixel-um 10 -o camera_info.yaml

      psdcal export --format json-schema -o calibration.schema.json
    """
    from psdcal.errors import InputError
    from psdcal.io import write_json

    if fmt == "json-schema":
        from psdcal.schema import calibration_schema

        schema = calibration_schema()
        if calibration is not None:
            _check_against_schema(calibration, schema)
        _write(output, lambda: write_json(output, schema))
        click.echo(f"wrote {output}")
        return
    if calibration is None:
        raise InputError(f"--format {fmt} needs a CALIBRATION file", field="CALIBRATION")
    from psdcal._atomic import write_text_atomic
    from psdcal.io import load_calibration
    from psdcal.report.compare import fov_uncertainty
    from psdcal.report.export import fit_opencv, opencv_yaml, ros_camera_info

    res = load_calibration(calibration)
    m = fit_opencv(res, pixel_um=pixel_um, n_coeffs=int(n_coeffs), n_grid=grid, refine_k=not fixed_k)
    if fmt == "opencv-yaml":
        text = opencv_yaml(m, source=calibration.name)
    else:
        text = ros_camera_info(m, camera_name=camera_name, source=calibration.name)
    _write(output, lambda: write_text_atomic(output, text))
    names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")[: m.dist_coeffs.size]
    K = m.camera_matrix
    click.echo(f"camera matrix (pixels of {m.pixel_um:g} um): fx {K[0, 0]:.6g}, fy {K[1, 1]:.6g}, "
               f"cx {K[0, 2]:.6g}, cy {K[1, 2]:.6g}; image {m.image_size[0]} x {m.image_size[1]}")
    click.echo("distortion: " + ", ".join(f"{n} {v:.6g}" for n, v in zip(names, m.dist_coeffs)))
    click.echo(f"fit error over {m.grid_points} sensor points: on the sensor max {m.fit_max_um:.3g} um, "
               f"RMS {m.fit_rms_um:.3g} um; in angle max {m.fit_max_deg:.3g} deg, RMS {m.fit_rms_deg:.3g} deg")
    calib_sigma = float("nan")
    if res.covariance.size:
        import numpy as np

        calib_sigma = float(np.nanmax(fov_uncertainty(res, n=21).sigma_total_deg))
    click.echo("verdict: " + _verdict(m, calib_sigma, int(n_coeffs)))
    click.echo(f"wrote {output}")


def _verdict(m, calib_sigma_deg: float, n_coeffs: int) -> str:
    import math

    more = " (try --coeffs 8)" if n_coeffs < 8 else ""
    if not math.isfinite(calib_sigma_deg):
        return "no covariance in the calibration: compare the fit error with your accuracy needs"
    if m.fit_max_deg <= calib_sigma_deg:
        return (f"good: the fit error (max {m.fit_max_deg:.3g} deg) is below the calibration's own AoA "
                f"uncertainty (1-sigma up to {calib_sigma_deg:.3g} deg)")
    return (f"LOSES ACCURACY: the fit error (max {m.fit_max_deg:.3g} deg) exceeds the calibration's own AoA "
            f"uncertainty (1-sigma up to {calib_sigma_deg:.3g} deg){more}")


def _write(output, writer):
    from psdcal.errors import InputError

    try:
        writer()
    except OSError as exc:
        raise InputError(f"cannot write: {exc.strerror or exc}", path=output, field="--output") from None


def _check_against_schema(calibration: Path, schema: dict) -> None:
    from psdcal.errors import InputError
    from psdcal.io import read_json

    d = read_json(calibration)
    try:
        import jsonschema
    except ImportError:
        click.echo(f"(not checking {calibration}: install the jsonschema package to validate it)")
        return
    err = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(schema).iter_errors(d))
    if err is not None:
        where = "/".join(str(p) for p in err.absolute_path) or "(top level)"
        raise InputError(f"does not match the calibration schema at {where}: {err.message}", path=calibration)
    click.echo(f"{calibration} matches the calibration schema")
