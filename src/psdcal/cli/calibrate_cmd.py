"""`psdcal calibrate`: points + template -> calibration JSON."""
from __future__ import annotations

from pathlib import Path

import click

from psdcal.cli import cli


def model_options(f):
    """The model switches shared by calibrate-like commands."""
    opts = [
        click.option("--cost", type=click.Choice(["image", "template"]), default="image", show_default=True,
                     help="image: maximum-likelihood residual on the sensor; template: the paper's Eq 29 on the plate."),
        click.option("--radial", type=click.IntRange(0, 3), default=2, show_default=True, help="Lens radial terms k1..k3."),
        click.option("--tangential/--no-tangential", default=True, show_default=True, help="Lens tangential terms p1, p2."),
        click.option("--psd-radial", type=click.IntRange(0, 2), default=0, show_default=True, help="PSD radial terms l1, l2."),
        click.option("--skew/--no-skew", default=False, show_default=True, help="Estimate the skew."),
        click.option("--aspect/--no-aspect", default=False, show_default=True, help="Separate vertical focal length fy_mm."),
        click.option("--preliminary/--no-preliminary", default=True, show_default=True,
                     help="Line-straightness preliminary distortion estimate (Section 3.2)."),
        click.option("--normalize/--no-normalize", default=True, show_default=True,
                     help="Hartley normalisation of the DLT (Section 3.3)."),
        click.option("--sensor-mm", type=(float, float), default=(9.0, 9.0), show_default=True,
                     help="PSD active lengths Lx Ly, mm (S5991-01: 9 9)."),
        click.option("--max-iterations", type=click.IntRange(1, 100000), default=200, show_default=True,
                     help="LM iteration limit; more is a convergence failure (exit 2)."),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


@cli.command("calibrate")
@click.argument("points", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--template", "-t", "template", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Template CSV: point_id,X_mm,Y_mm.")
@click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Calibration JSON to write (only written when the calibration succeeds).")
@model_options
@click.option("--fit-gains", is_flag=True, default=False,
              help="Estimate the three relative channel gains jointly (POINTS must carry raw amplitudes vx1,vx2,vy1,vy2).")
@click.option("--reject", "reject_k", type=click.FloatRange(min=0.0, min_open=True), default=None, metavar="K",
              help="Remove points whose residual exceeds K robust noise sigmas, refit, and list them (e.g. 5).")
@click.option("--quiet", "-q", is_flag=True, help="Print nothing but errors.")
def calibrate_command(points, template, output, cost, radial, tangential, psd_radial, skew, aspect, preliminary,
                      normalize, sensor_mm, max_iterations, fit_gains, quiet, reject_k=None):
    """Calibrate a PSD + lens sensor from views of a planar LED template.

    POINTS is a CSV of impact points, `image_id,point_id,x_mm,y_mm` (a missing
    point is a missing row), or of raw amplitudes `image_id,point_id,vx1,vx2,vy1,vy2`.
    Prints the parameters with standard errors and the residual RMS, and
    writes the calibration JSON to --output.

    Example: psdcal calibrate points.csv -t template.csv -o calib.json --psd-radial 1
    """
    from psdcal.calibration.core import calibrate
    from psdcal.errors import DegenerateViewsError, InputError
    from psdcal.io import read_points, read_template, save_calibration
    from psdcal.report.text import print_calibration

    tids, txy = read_template(template)
    pf = read_points(points, tids, sensor_mm=sensor_mm)
    if fit_gains and pf.kind != "amplitudes":
        raise InputError("--fit-gains needs raw amplitudes (header image_id,point_id,vx1,vx2,vy1,vy2)", path=points, line=1)
    from psdcal.calibration._refine import SolverOptions

    _kernels_for(pf.points_mm, quiet)
    try:
        res = calibrate(
            txy, pf.points_mm, cost=cost, radial=radial, tangential=tangential, psd_radial=psd_radial, skew=skew,
            preliminary=preliminary, normalize=normalize, aspect=aspect, fit_gains=fit_gains,
            image_ids=pf.image_ids, point_ids=tids, sensor_mm=tuple(sensor_mm),
            solver=SolverOptions(max_iterations=max_iterations),
        )
    except DegenerateViewsError as exc:
        raise DegenerateViewsError(f"{points}: {exc}") from None
    if reject_k is not None:
        from psdcal.calibration.outliers import reject_outliers

        rej = reject_outliers(res, reject_k, line_numbers=pf.line_numbers)
        res = rej.result
        if not quiet:
            click.echo(f"--reject {reject_k:g}: removed {len(rej.removed)} point(s) above {reject_k:g} x "
                       f"{rej.sigma_mm * 1e3:.3f} um (robust noise sigma), {rej.rounds} refit(s)")
            for p in rej.removed:
                click.echo(f"  {points}:{p.line}: image {p.image_id}, point {p.point_id} at ({p.x_mm:.4f}, {p.y_mm:.4f}) mm, "
                           f"residual {p.residual_mm * 1e3:.2f} um = {p.ratio:.1f} sigma")
            for iid, pid in rej.kept_flagged:
                click.echo(f"  kept (too few points left to remove it): image {iid}, point {pid}")
    res = _with_inputs(res, template, points)
    if output is not None:
        save_calibration(output, res)
    if not quiet:
        print_calibration(res)
        if output is not None:
            click.echo(f"wrote {output}")


def _kernels_for(points_mm, quiet: bool) -> None:
    """One-shot run: the compiled kernels only where they pay for their loading (psdcal._jit, "auto").

    When they are needed and not yet compiled on this machine, say so on one line
    (compiling takes some seconds, once) instead of stalling silently.
    """
    import numpy as np

    from psdcal import _jit

    _jit.set_mode("auto")
    n_obs = int(np.all(np.isfinite(points_mm), axis=-1).sum())
    if _jit.use_compiled(n_obs) and not _jit.cache_is_warm() and not quiet:
        click.echo("psdcal: compiling the numerical kernels (first use on this machine, some seconds; "
                   "`python3 tasks.py` set-up does it ahead) ...", err=True)


def _with_inputs(res, template, points):
    """Record the input files and their checksums in the result's problem record."""
    import dataclasses
    import hashlib

    files = {}
    for role, p in (("template", template), ("points", points)):
        files[role] = {"path": str(p), "sha256": hashlib.sha256(Path(p).read_bytes()).hexdigest()}
    return dataclasses.replace(res, problem={**res.problem, "files": files})
