"""`psdcal calibrate-directions`: spots at known stage directions -> calibration JSON."""
from __future__ import annotations

from pathlib import Path

import click

from psdcal.cli import cli


@cli.command("calibrate-directions")
@click.argument("directions", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Calibration JSON to write (only written when the calibration succeeds).")
@click.option("--distance-mm", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="Distance of the source from the stage's axes, mm: also fits the offsets of the lens' projection "
                   "centre from the axes (offset_x_mm, offset_y_mm, offset_z_mm). Default: a source at infinity "
                   "(collimated), no offsets.")
@click.option("--radial", type=click.IntRange(0, 3), default=2, show_default=True, help="Lens radial terms k1..k3.")
@click.option("--tangential/--no-tangential", default=True, show_default=True, help="Lens tangential terms p1, p2.")
@click.option("--psd-radial", type=click.IntRange(0, 2), default=0, show_default=True, help="PSD radial terms l1, l2.")
@click.option("--skew/--no-skew", default=False, show_default=True, help="Estimate the skew.")
@click.option("--aspect/--no-aspect", default=False, show_default=True, help="Separate vertical focal length fy_mm.")
@click.option("--fit-gains", is_flag=True, default=False,
              help="Estimate the three relative channel gains (DIRECTIONS must carry raw amplitudes vx1,vx2,vy1,vy2).")
@click.option("--sensor-mm", type=(float, float), default=(9.0, 9.0), show_default=True,
              help="PSD active lengths Lx Ly, mm (S5991-01: 9 9).")
@click.option("--max-iterations", type=click.IntRange(1, 100000), default=200, show_default=True,
              help="LM iteration limit; more is a convergence failure (exit 2).")
@click.option("--fix", "fix_items", multiple=True, metavar="NAME=VALUE",
              help="Hold a parameter at VALUE (repeatable): any global parameter (f_mm, cx_mm, k2, g_x2 ...) or "
                   "stage_rx/stage_ry/stage_rz (rad), offset_x_mm/offset_y_mm/offset_z_mm.")
@click.option("--prior", "prior_items", multiple=True, metavar="NAME=VALUE,STD",
              help="Gaussian prior VALUE +- STD on a free global parameter (repeatable).")
@click.option("--prior-file", "prior_files", multiple=True, type=click.Path(dir_okay=False, path_type=Path),
              help="JSON prior with names, values and covariance (e.g. the gains JSON of `psdcal gains`).")
@click.option("--noise-um", "noise_um", type=click.FloatRange(min=0.0, min_open=True), default=None, metavar="SIGMA_UM",
              help="Known noise standard deviation per coordinate of the points, um: the verdict then also tests "
                   "the residual RMS against it.")
@click.option("--quiet", "-q", is_flag=True, help="Print nothing but errors.")
def calibrate_directions_command(directions, output, distance_mm, radial, tangential, psd_radial, skew, aspect, fit_gains,
                                 sensor_mm, max_iterations, fix_items, prior_items, prior_files, quiet, noise_um=None):
    """Calibrate a PSD + lens sensor from spots at known directions (rotation stage, goniometer).

    DIRECTIONS is a CSV `az_deg,el_deg,x_mm,y_mm` (impact points) or
    `az_deg,el_deg,vx1,vx2,vy1,vy2` (raw amplitudes), one row per stage
    position. The direction to the source in the stage frame is
    u = (cos el sin az, sin el, cos el cos az): az turns about the stage's
    vertical (y) axis from +z towards +x, el then raises it towards +y.

    Fits the intrinsics, distortion (same switches as `calibrate`), the
    stage-to-sensor rotation and, with --distance-mm, the offsets of the
    projection centre from the stage's axes, with standard errors. The JSON
    is a calibration file (`locate`, `aoa`, `report`, `compare` read it) whose
    only pose ("stage") is the stage rotation; `problem.stage` holds the
    stage fit.

    Example: psdcal calibrate-directions sweep.csv -o calib.json
    """
    from psdcal.calibration._refine import SolverOptions
    from psdcal.calibration.directions import calibrate_directions, check_result, direction_warnings, read_directions
    from psdcal.calibration.priors import parse_fix, parse_prior, read_prior_file
    from psdcal.errors import DegenerateViewsError, InputError
    from psdcal.io import save_calibration
    from psdcal.report.text import print_calibration

    fix = parse_fix_stage(fix_items, parse_fix)
    priors = [parse_prior(t) for t in prior_items] + [read_prior_file(f) for f in prior_files]
    df = read_directions(directions, sensor_mm=tuple(sensor_mm))
    if fit_gains and df.kind != "amplitudes":
        raise InputError("--fit-gains needs raw amplitudes (header az_deg,el_deg,vx1,vx2,vy1,vy2)", path=directions, line=1)
    try:
        res = calibrate_directions(
            df.az_deg, df.el_deg, df.points_mm, radial=radial, tangential=tangential, psd_radial=psd_radial, skew=skew,
            aspect=aspect, fit_gains=fit_gains, distance_mm=distance_mm, fix=fix or None, priors=priors or None,
            sensor_mm=tuple(sensor_mm), solver=SolverOptions(max_iterations=max_iterations),
            point_ids=[int(v) for v in df.line_numbers],
            noise_mm=None if noise_um is None else noise_um * 1e-3,
        )
    except DegenerateViewsError as exc:
        raise DegenerateViewsError(f"{directions}: {exc}") from None
    check_result(res)
    res = _with_input(res, directions)
    if output is not None:
        save_calibration(output, res)
    if not quiet:
        print_calibration(res)
        st = res.problem["stage"]
        std = st["std"]
        click.echo("stage rotation (rad): " + ", ".join(
            f"{n} {v:.6g} +- {std[n]:.2g}" if std.get(n) is not None else f"{n} {v:.6g} (fixed)"
            for n, v in zip(("stage_rx", "stage_ry", "stage_rz"), st["rvec"])))
        if st.get("offset_mm") is not None:
            click.echo("offsets (mm): " + ", ".join(
                f"{n} {v:.4g} +- {std[n]:.2g}" if std.get(n) is not None else f"{n} {v:.4g} (fixed)"
                for n, v in zip(("offset_x_mm", "offset_y_mm", "offset_z_mm"), st["offset_mm"])))
        for w in direction_warnings(res):
            if w not in res.warnings():  # print_calibration showed those
                click.echo(f"warning: {w}")
        if output is not None:
            click.echo(f"wrote {output}")


def parse_fix_stage(items, parse_fix):
    """``--fix`` values: global parameters by :func:`parse_fix`, plus the stage rotation and offsets."""
    from psdcal.calibration.directions import OFFSET_NAMES, STAGE_NAMES
    from psdcal.errors import InputError

    out, rest = {}, []
    for it in items:
        name, sep, value = str(it).partition("=")
        if name.strip() in STAGE_NAMES + OFFSET_NAMES:
            try:
                out[name.strip()] = float(value)
            except ValueError:
                raise InputError(f"--fix {it!r}: {value!r} is not a number") from None
        else:
            rest.append(it)
    out.update(parse_fix(rest))
    return out


def _with_input(res, path):
    import dataclasses
    import hashlib

    files = {"directions": {"path": str(path), "sha256": hashlib.sha256(Path(path).read_bytes()).hexdigest()}}
    return dataclasses.replace(res, problem={**res.problem, "files": files})
