"""``psdcal module``: recordings of a position-processing module (X, Y, SUM), a thin layer over
:mod:`psdcal.signal.module`."""
from __future__ import annotations

import click

from psdcal.cli import cli


@cli.command("module")
@click.argument("recording", type=click.Path(dir_okay=False))
@click.option("--channels", default="t,x,y,sum", show_default=True,
              help="Role of each column in file order: t, x, y, sum, or - to skip a column.")
@click.option("--rate-hz", type=float, help="Sampling rate (needed without a 't' column).")
@click.option("--mm-per-unit", type=float, default=1.0, show_default=True,
              help="Scale of the module's X, Y outputs: mm on the PSD per volt (per module unit).")
@click.option("--n-emitters", type=int, help="Expected number of LEDs: another count is refused (exit 2).")
@click.option("--calib", type=click.Path(dir_okay=False), help="Calibration JSON: also write angles of arrival.")
@click.option("--image-id", help="Write a calibration points CSV image_id,point_id,x_mm,y_mm for this view.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Output CSV.")
def module_command(recording, channels, rate_hz, mm_per_unit, n_emitters, calib, image_id, output):
    """Split a module RECORDING (X, Y, SUM of time-multiplexed LEDs) into LEDs.

    \b
    The LEDs are found from the signals alone: dark samples (SUM level),
    dense places of (X, Y, SUM) for the LEDs' plateaus, mixtures of two LEDs
    (the sample that straddles a switch) dropped.  LEDs are named 1, 2, ...
    in the order they first appear.  One row per LED:
      emitter,n_samples,x_mm,y_mm,sum,scatter_x_mm,scatter_y_mm,sigma_x_mm,sigma_y_mm
    (scatter: of one sample; sigma: of the median position), and with --calib
      alpha_x_deg,alpha_y_deg,sigma_alpha_x_deg,sigma_alpha_y_deg.
    With --image-id: a calibration points CSV image_id,point_id,x_mm,y_mm.
    \b
    Example (a text file 't_s , x , y , sum' without header):
      psdcal module tri_blink.Dat --channels t,x,y,sum --mm-per-unit 2.0 --n-emitters 3 -o leds.csv
    """
    import math

    import numpy as np

    from psdcal._atomic import atomic_path
    from psdcal.errors import InputError
    from psdcal.signal.module import read_module, segment_module

    if not (mm_per_unit > 0 and math.isfinite(mm_per_unit)):
        raise InputError(f"--mm-per-unit must be positive, got {mm_per_unit}", field="mm_per_unit")
    if n_emitters is not None and n_emitters < 1:
        raise InputError(f"--n-emitters must be at least 1, got {n_emitters}", field="n_emitters")
    if image_id is not None and any(c in str(image_id) for c in ',\n\r"'):
        raise InputError("--image-id must not contain a comma, quote or newline", field="image_id")
    model = None
    if calib is not None:
        from psdcal.measure.sensor_model import SensorModel

        model = SensorModel.load(calib)
    rec = read_module(recording, channels, rate_hz)
    seg = segment_module(rec.x, rec.y, rec.sum, n_emitters=n_emitters)
    em = seg.emitters
    k = mm_per_unit
    d = np.array([[e.x * k, e.y * k] for e in em])
    sc = np.array([[e.scatter_x * k, e.scatter_y * k] for e in em])
    # the median of n samples: sigma ~ 1.2533 scatter / sqrt(n) (Gaussian scatter)
    sig = sc * 1.2533 / np.sqrt(np.array([max(e.n_samples, 1) for e in em]))[:, None]
    if image_id is not None:
        header = ["image_id", "point_id", "x_mm", "y_mm"]
        rows = [[str(image_id), e.emitter, f"{p[0]:.10g}", f"{p[1]:.10g}"] for e, p in zip(em, d)]
    else:
        header = ["emitter", "n_samples", "x_mm", "y_mm", "sum", "scatter_x_mm", "scatter_y_mm", "sigma_x_mm",
                  "sigma_y_mm"]
        rows = [[e.emitter, str(e.n_samples), *(f"{v:.10g}" for v in (*p, e.sum, *s, *g))]
                for e, p, s, g in zip(em, d, sc, sig)]
        if model is not None:
            from psdcal.measure.aoa import angles_from_points

            cov = np.zeros((len(em), 2, 2))
            cov[:, 0, 0], cov[:, 1, 1] = sig[:, 0] ** 2, sig[:, 1] ** 2
            res = angles_from_points(d, model, cov, derivatives=False)
            a = np.degrees(res.alpha_rad)
            sa = np.degrees(res.sigma_alpha_rad)
            header += ["alpha_x_deg", "alpha_y_deg", "sigma_alpha_x_deg", "sigma_alpha_y_deg"]
            rows = [r + [f"{v:.10g}" for v in (*aa, *ss)] for r, aa, ss in zip(rows, a, sa)]
    with atomic_path(output, suffix=".csv") as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(",".join(header) + "\n")
            for r in rows:
                fh.write(",".join(r) + "\n")
    n = len(seg.labels)
    click.echo(f"found {len(em)} emitters in {n} samples ({rec.rate_hz:.6g} Hz): {seg.n_dark} dark, "
               f"{seg.n_transition} transition samples dropped; wrote {output}")
    for e, p, s in zip(em, d, sc):
        click.echo(f"  {e.emitter}: x {p[0]:.5g} mm, y {p[1]:.5g} mm (scatter {s[0]:.2g}, {s[1]:.2g} mm), "
                   f"SUM {e.sum:.4g}, {e.n_samples} samples")
