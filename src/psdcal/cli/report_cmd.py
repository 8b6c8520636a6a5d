"""`psdcal report` (the calibration report as one HTML page) and `psdcal compare` (two calibrations)."""
from __future__ import annotations

import sys
from pathlib import Path

import click

from psdcal.cli import cli


@cli.command("report")
@click.argument("calibration", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--points", "-p", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The points CSV the calibration was made from (checksum, line numbers of outliers).")
@click.option("--template", "-t", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The template CSV (needed with --points).")
@click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="HTML file to write (self-contained: open it in any browser, offline).")
@click.option("--outlier-k", "k", type=click.FloatRange(min=0.0, min_open=True), default=5.0, show_default=True,
              help="Outlier threshold in robust standard deviations of the residuals.")
@click.option("--cells", type=click.IntRange(1, 100), default=6, show_default=True,
              help="Coverage cells per side of the sensor.")
@click.option("--region-mm", type=(float, float, float, float), default=None,
              help="Measurement region x0 x1 y0 y1 in mm (default: the whole sensor).")
@click.option("--title", default=None, help="Title of the page.")
def report_command(calibration, points, template, output, k, cells, region_mm, title):
    """Write the calibration report: one self-contained HTML page.

    Parameters with standard errors and correlations, residuals (all images,
    per image, histogram), outliers, coverage of the sensor, distortion field,
    AoA uncertainty over the field of view, and provenance (files with
    SHA-256, options, versions, dates).

    Example: psdcal report calib.json --points points.csv -t template.csv -o report.html
    """
    from psdcal.io import load_calibration
    from psdcal.report.page import ReportInputs, write_report

    res = load_calibration(calibration)
    from psdcal.io import read_json

    sid = read_json(calibration).get("sensor_id")
    if sid is not None:
        click.echo(f"sensor: {sid}")
        title = title or f"Calibration of sensor {sid}"
    inputs = ReportInputs(calibration=str(calibration), points=None if points is None else str(points),
                          template=None if template is None else str(template),
                          command="psdcal " + " ".join(sys.argv[1:]) if sys.argv and "psdcal" in Path(sys.argv[0]).name else None)
    from psdcal.report.page import report_verdict

    v = report_verdict(res)
    if v is not None:
        for line in v.lines():
            click.echo(line)
    write_report(output, res, inputs, k=k, n_cells=cells, region_mm=region_mm, title=title)
    click.echo(f"wrote {output}")


@cli.command("compare")
@click.argument("calib_a", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("calib_b", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Figure to write (PNG, SVG or PDF by its suffix): the difference maps.")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the numbers as JSON.")
@click.option("--distance-mm", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="Also give the position difference on a plane at this distance (mm), parallel to the sensor.")
@click.option("--grid", type=click.IntRange(3, 401), default=41, show_default=True, help="Grid points per side of the sensor.")
@click.option("--margin-mm", type=click.FloatRange(min=0.0), default=0.0, show_default=True,
              help="Leave this much of the sensor's edges out.")
def compare_command(calib_a, calib_b, output, json_out, distance_mm, grid, margin_mm):
    """Compare two calibrations of one sensor in angle of arrival over the field of view.

    For each point of a grid over the sensor, the angle between the rays the
    two calibrations give, in degrees and in units of their combined
    uncertainty (from both covariances). Exit status 0 either way; read the
    verdict: is a re-calibration needed, is a lens change visible?

    Example: psdcal compare old.json new.json -o diff.png --distance-mm 5000
    """
    from rich.console import Console
    from rich.table import Table

    from psdcal.report.compare import compare
    from psdcal.io import load_calibration, write_json

    if output is not None and output.suffix.lower() not in (".png", ".svg", ".pdf"):
        from psdcal.errors import InputError

        raise InputError("the figure's suffix must be .png, .svg or .pdf", path=output, field="--output")
    a, b = load_calibration(calib_a), load_calibration(calib_b)
    c = compare(a, b, n=grid, margin_mm=margin_mm, distance_mm=distance_mm, names=(calib_a.name, calib_b.name))
    s = c.summary()
    t = Table(title=f"AoA difference: {calib_a.name} vs {calib_b.name} ({s['grid_points']} sensor points)")
    t.add_column("")
    t.add_column("max", justify="right")
    t.add_column("RMS", justify="right")
    t.add_row("ray difference (deg)", f"{s['max_deg']:.4g}", f"{s['rms_deg']:.4g}")
    t.add_row("in combined sigma", f"{s['max_sigma']:.3g}", f"{s['rms_sigma']:.3g}")
    if distance_mm is not None:
        t.add_row(f"position at {distance_mm:g} mm (mm)", f"{s['position_max_mm']:.4g}", f"{s['position_rms_mm']:.4g}")
    con = Console()
    con.print(t)
    con.print(f"combined 1-sigma AoA uncertainty (median over the sensor): {s['combined_sigma_deg_median']:.3g} deg")
    con.print(f"verdict: {c.verdict()}")
    if output is not None:
        from psdcal._atomic import atomic_path
        from psdcal.report.plots import compare_maps

        from psdcal.errors import InputError

        fig = compare_maps(c)
        try:
            with atomic_path(output) as tmp:
                fig.savefig(tmp, format=output.suffix.lower().lstrip("."), dpi=100)
        except OSError as exc:
            raise InputError(f"cannot write the figure: {exc.strerror or exc}", path=output, field="--output") from None
        click.echo(f"wrote {output}")
    if json_out is not None:
        from psdcal.errors import InputError

        try:
            write_json(json_out, {"a": str(calib_a), "b": str(calib_b), **s, "verdict": c.verdict()})
        except OSError as exc:
            raise InputError(f"cannot write: {exc.strerror or exc}", path=json_out, field="--json") from None
        click.echo(f"wrote {json_out}")
