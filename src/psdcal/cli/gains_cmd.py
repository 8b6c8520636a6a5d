"""``psdcal gains``: the electrical calibration of the channel gains (a thin layer over
:mod:`psdcal.calibration.bench`)."""
from __future__ import annotations

import click

from psdcal.cli import cli


@cli.command("gains")
@click.argument("amplitudes", type=click.Path(dir_okay=False))
@click.option("--positions", required=True, type=click.Path(dir_okay=False),
              help="Known spot positions on the bare PSD: CSV point_id,x_mm,y_mm.")
@click.option("--lx-mm", type=float, default=9.0, show_default=True, help="PSD active length along x, mm.")
@click.option("--ly-mm", type=float, default=9.0, show_default=True, help="PSD active length along y, mm.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Output gains JSON.")
def gains_command(amplitudes, positions, lx_mm, ly_mm, output):
    """Fit the three relative channel gains from spots at known positions (bench, lens removed).

    \b
    AMPLITUDES: CSV with vx1,vx2,vy1,vy2 and point_id (or emitter) naming the
    spot, e.g. the output of 'psdcal amplitudes --tdm --image-id bench'; an
    optional carrier_hz column gives one set of gains per carrier (FDM: the
    amplifier's gain depends on frequency).  Rows of one spot are averaged.
    \b
    Writes the gains [1, g_x2, g_y1, g_y2], their covariance and standard
    errors (from the fit residual), the RMS residual in mm.  Use it with
    'psdcal locate --gains FILE' and 'psdcal aoa --gains FILE': the channels
    are corrected and the gains' covariance enters every angle's sigma.
    \b
    Example:
      psdcal gains bench_amplitudes.csv --positions spots.csv -o gains.json
    """
    import json

    from psdcal._atomic import write_text_atomic
    from psdcal.calibration.bench import (check_gains_entry, check_spot_positions, fit_bench, gains_document,
                                         read_bench_amplitudes, read_positions)
    from psdcal.errors import InputError

    for name, v in (("lx_mm", lx_mm), ("ly_mm", ly_mm)):
        if not (v > 0 and v < 1e4):
            raise InputError(f"--{name.replace('_', '-')} must be positive, got {v}", field=name)
    pos = read_positions(positions)
    groups = read_bench_amplitudes(amplitudes, pos)
    for spots, amps in groups.values():  # metres, x/y swapped, a mirrored axis: refused before the fit
        check_spot_positions(spots, amps, lx_mm, ly_mm, positions)
    fits = {car: fit_bench(spots, amps, lx_mm, ly_mm) for car, (spots, amps) in groups.items()}
    doc = gains_document(fits, lx_mm, ly_mm)
    # what is written is what 'locate/aoa --gains' will read
    for entry in [doc, *doc.get("per_carrier", [])]:
        label = "" if "carrier_hz" not in entry else f" at {entry['carrier_hz']:g} Hz"
        try:
            check_gains_entry(entry, output)
        except InputError as exc:
            raise InputError(f"the fit{label} gives gains that 'locate/aoa --gains' would refuse ({exc.detail}); "
                             "nothing written: check the positions against the amplitudes", path=positions,
                             field=exc.field) from None
    write_text_atomic(output, json.dumps(doc, indent=2) + "\n")
    for car in sorted(fits, key=lambda k: -1.0 if k is None else k):
        gc = fits[car]
        label = "" if car is None else f" at {car:g} Hz"
        std = ", ".join(f"{n} {g:.6f} +- {s:.2g}" for n, g, s in zip(("g_x2", "g_y1", "g_y2"), gc.gains[1:], gc.std))
        click.echo(f"gains{label}: {std} (g_x1 = 1; {gc.n_spots} spots, RMS {gc.rms_mm:.3g} mm)")
    click.echo(f"wrote {output}")
