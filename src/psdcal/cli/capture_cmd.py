"""`psdcal next-view`: which template pose to take next, and when to stop."""
from __future__ import annotations

from pathlib import Path

import click

from psdcal.cli import cli


@cli.command("next-view")
@click.argument("views", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--template", "-t", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Template CSV (needed when VIEWS is a points CSV; the views are then calibrated first).")
@click.option("--noise-um", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="Impact-point noise per coordinate, um [default: the calibration's implied noise sigma_mm].")
@click.option("--min-gain", type=click.FloatRange(0.0, 1.0), default=0.05, show_default=True,
              help="Stop when the best next view lowers the worst AoA uncertainty by less than this fraction.")
@click.option("--target-deg", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="Also stop when the worst AoA 1-sigma over the sensor is at or below this, degrees.")
@click.option("--top", type=click.IntRange(1, 100), default=5, show_default=True, help="How many candidates to list.")
@click.option("--grid", type=click.IntRange(3, 41), default=11, show_default=True,
              help="Sensor grid points per side where the worst AoA uncertainty is taken.")
@click.option("--max-tilt-deg", type=click.FloatRange(0.0, 89.0), default=50.0, show_default=True,
              help="Largest tilt your set-up can make; candidates use the tilts 0, 20, 35, 50 deg up to it.")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the ranking as JSON (current_deg, gain, stop, candidates with pose and instruction).")
def next_view_command(views, template, noise_um, min_gain, target_deg, top, grid, max_tilt_deg=50.0, json_out=None):
    """Suggest the next calibration view: the template pose that lowers the worst AoA uncertainty most.

    VIEWS is a calibration JSON, or a points CSV of the views taken so far
    (with --template; calibrated with the default model). For every candidate
    pose (tilts 0-50 deg about 8 in-plane axes, template centre on a 5 x 5 grid
    of the sensor, three distances) the calibration's information matrix is
    updated with the candidate's Jacobian (no refit) and the worst 1-sigma AoA
    uncertainty over the sensor is predicted. Prints the best candidates as
    instructions and whether more views still help (--min-gain, --target-deg).

    Tilt: the template plane is rotated by the angle about the stated axis in
    the sensor plane (right-hand rule, sensor x/y as in the points files): a
    positive tilt about +x moves the template edge imaged at +y away from the
    lens; about +y, the edge imaged at -x. Centre: where the centroid of the
    template's LEDs is imaged on the PSD. Distance: from the lens to the
    template's centre along the optical axis.

    Example: psdcal next-view calib.json --target-deg 0.05
    """
    from psdcal.errors import InputError
    from psdcal.study.capture import information_of_calibration, next_view

    if views.suffix.lower() == ".json":
        from psdcal.io import load_calibration

        res = load_calibration(views)
    else:
        if template is None:
            raise InputError("a points CSV needs --template", path=views, field="--template")
        from psdcal.calibration.core import calibrate
        from psdcal.io import read_points, read_template

        tids, txy = read_template(template)
        pf = read_points(views, tids)
        res = calibrate(txy, pf.points_mm, image_ids=pf.image_ids, point_ids=tids)
    if res.problem and res.problem.get("kind") == "directions":
        raise InputError("a direction (rotation-stage) calibration has no template views: next-view plans "
                         "template views only", path=views)
    if not res.problem or "template" not in res.problem:
        raise InputError("the calibration has no problem record (template and points): cannot add views to it",
                         path=views)
    if res.model.fit_gains:
        raise InputError("next-view does not handle calibrations with fitted channel gains", path=views)
    noise_mm = res.sigma_mm if noise_um is None else noise_um * 1e-3
    import numpy as np

    S = information_of_calibration(res)
    P = np.asarray(res.problem["template"]["xy_mm"], dtype=float)
    from psdcal.study.capture import candidate_views

    tilts = tuple(t for t in (0.0, 20.0, 35.0, 50.0) if t <= max_tilt_deg)
    cands = candidate_views(P, res.intrinsics, res.distortion, tilts_deg=tilts, sensor_mm=tuple(res.sensor_mm))
    # parameters held fixed (calibrate --fix) are not in the covariance: predict over the free ones only
    free = tuple(n for n in res.model.global_names if n in res.param_names) if res.param_names else None
    nv = next_view(P, res.intrinsics, res.distortion, res.model, S, noise_mm, candidates=cands, grid=grid,
                   sensor_mm=tuple(res.sensor_mm), min_gain=min_gain, free=free)
    click.echo(f"{len(res.image_ids)} views taken; noise {noise_mm * 1e3:.3g} um per coordinate; worst AoA 1-sigma over "
               f"the sensor now {nv.current_deg:.3g} deg")
    for k, (c, w) in enumerate(nv.ranked[:top], start=1):
        click.echo(f"{k}. {c.instruction()}  ->  worst 1-sigma {w:.3g} deg")
    met = target_deg is not None and nv.current_deg <= target_deg
    if met:
        verdict = f"stop: the worst AoA 1-sigma ({nv.current_deg:.3g} deg) meets the target ({target_deg:g} deg)"
    else:
        verdict = nv.verdict()
    click.echo("verdict: " + verdict)
    if json_out is not None:
        from psdcal.io import write_json

        rows = [{"rank": k, "instruction": c.instruction(), "tilt_deg": c.tilt_deg, "axis_deg": c.axis_deg,
                 "centre_mm": list(c.centre_mm), "distance_mm": c.distance_mm, "rvec": c.rvec.tolist(),
                 "tvec_mm": c.tvec_mm.tolist(), "worst_sigma_deg": w}
                for k, (c, w) in enumerate(nv.ranked[:top], start=1)]
        doc = {"views": len(res.image_ids), "noise_mm": noise_mm, "current_deg": nv.current_deg, "gain": nv.gain,
               "min_gain": min_gain, "target_deg": target_deg, "stop": bool(nv.stop or met), "verdict": verdict,
               "candidates": rows}
        try:
            write_json(json_out, doc)
        except OSError as exc:
            raise InputError(f"cannot write: {exc.strerror or exc}", path=json_out, field="--json") from None
        click.echo(f"wrote {json_out}")
