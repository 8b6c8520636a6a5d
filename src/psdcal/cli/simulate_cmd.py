"""`psdcal simulate` and `psdcal demo`."""
from __future__ import annotations

from pathlib import Path

import click

from psdcal.cli import cli


@cli.command("simulate")
@click.option("--lens", type=click.Choice(["lens1", "lens2"]), default="lens2", show_default=True,
              help="The paper's lens presets (lens1: f 25 mm, k1 2e-3; lens2: f 8 mm, k1 1e-2, k2 3e-5; C = (0.5, -0.7) mm).")
@click.option("--f-mm", type=float, default=None, help="Override the focal length, mm.")
@click.option("--cx-mm", type=float, default=None, help="Override the optical centre x, mm.")
@click.option("--cy-mm", type=float, default=None, help="Override the optical centre y, mm.")
@click.option("--k1", type=float, default=None, help="Override k1 [mm^-2].")
@click.option("--k2", type=float, default=None, help="Override k2 [mm^-4].")
@click.option("--k3", type=float, default=None, help="Override k3 [mm^-6].")
@click.option("--p1", type=float, default=None, help="Tangential p1 [mm^-1].")
@click.option("--p2", type=float, default=None, help="Tangential p2 [mm^-1].")
@click.option("--l1", type=float, default=None, help="PSD radial l1 [mm^-2] (the paper: -1.3058e-3).")
@click.option("--l2", type=float, default=None, help="PSD radial l2 [mm^-4].")
@click.option("--images", "-n", type=click.IntRange(2, 10000), default=12, show_default=True, help="Number of template views.")
@click.option("--noise-mm", type=click.FloatRange(0.0), default=0.003, show_default=True,
              help="Gaussian noise on each impact-point coordinate, mm.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (the same seed gives the same files).")
@click.option("--template", "template_in", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Use this template CSV instead of the built-in 14-LED one.")
@click.option("--out-dir", "-o", type=click.Path(file_okay=False, path_type=Path), default=Path("."), show_default=True,
              help="Folder for template.csv, points.csv and truth.json.")
@click.option("--amplitudes", is_flag=True, default=False,
              help="Write raw amplitudes (image_id,point_id,vx1,vx2,vy1,vy2) through the simulated signal chain "
                   "(paper's band-pass, Eq 43 gains) instead of points with --noise-mm.")
@click.option("--snr-db", type=float, default=None, help="With --amplitudes: SNR in dB (docs/model.md#snr-definition). [default: no noise]")
@click.option("--r-tol", type=click.FloatRange(0.0, 1.0, max_open=True), default=0.0, show_default=True,
              help="With --amplitudes: resistor tolerance of the channel gains (the paper: 0.01).")
@click.option("--c-tol", type=click.FloatRange(0.0, 1.0, max_open=True), default=0.0, show_default=True,
              help="With --amplitudes: capacitor tolerance of the channel gains (the paper: 0.15).")
def simulate_command(lens, f_mm, cx_mm, cy_mm, k1, k2, k3, p1, p2, l1, l2, images, noise_mm, seed, template_in, out_dir,
                     amplitudes=False, snr_db=None, r_tol=0.0, c_tol=0.0):
    """Simulate a calibration set (geometry only) with known truth.

    Writes OUT_DIR/template.csv, OUT_DIR/points.csv and OUT_DIR/truth.json.

    Example: psdcal simulate --lens lens1 --images 9 --noise-mm 0.002 --seed 3 -o sim/
    """
    from dataclasses import replace

    from psdcal.io import read_template, write_json, write_points, write_template
    from psdcal.study.simulate import LENSES, simulate_set

    from psdcal.errors import InputError

    if f_mm is not None and not f_mm > 0:
        raise InputError(f"the focal length must be positive, got {f_mm}", field="--f-mm")
    intr, dist = LENSES[lens]
    intr = replace(intr, **{k: v for k, v in dict(f_mm=f_mm, cx_mm=cx_mm, cy_mm=cy_mm).items() if v is not None})
    dist = replace(dist, **{k: v for k, v in dict(k1=k1, k2=k2, k3=k3, p1=p1, p2=p2, l1=l1, l2=l2).items() if v is not None})
    if template_in is not None:
        tids, txy = read_template(template_in)
    else:
        tids, txy = None, None
    s = simulate_set((intr, dist), n_images=images, noise_mm=0.0 if amplitudes else noise_mm, seed=seed, template_mm=txy)
    tids = list(range(len(s.template_mm))) if tids is None else tids
    out_dir.mkdir(parents=True, exist_ok=True)
    write_template(out_dir / "template.csv", tids, s.template_mm)
    truth = s.truth_dict()
    if amplitudes:
        from psdcal.study.gain_sim import simulate_amplitudes

        amps, gains, chain = simulate_amplitudes(s.ideal_points_mm, snr_db=snr_db, r_tol=r_tol, c_tol=c_tol, seed=seed)
        from psdcal.io import write_amplitudes

        write_amplitudes(out_dir / "points.csv", list(range(images)), tids, amps)
        truth.update(noise_mm=None, snr_db=snr_db, gains=[float(g) for g in gains],
                     relative_gains=[float(g / gains[0]) for g in gains], chain=chain)
        noise_mm = 0.0
    else:
        write_points(out_dir / "points.csv", list(range(images)), tids, s.points_mm)
    truth["seed"] = seed
    truth["lens"] = lens
    write_json(out_dir / "truth.json", truth)
    click.echo(f"wrote {out_dir / 'template.csv'}, {out_dir / 'points.csv'}, {out_dir / 'truth.json'} "
               f"({images} images x {len(tids)} points, noise {noise_mm * 1e3:g} um)")


@cli.command("demo")
@click.option("--cost", type=click.Choice(["image", "template"]), default="image", show_default=True)
@click.option("--out", "-o", type=click.Path(dir_okay=False, path_type=Path), default=Path("demo_out/calibration.json"),
              show_default=True, help="Where to write the calibration JSON (replaced on every run).")
def demo_command(cost, out):
    """Calibrate the bundled default data and show the truth beside the estimate.

    The bundled set is simulated: the paper's Lens 2 (f = 8 mm, k1 = 1e-2,
    k2 = 3e-5, C = (0.5, -0.7) mm), 12 views of the 14-LED template, 3 um
    Gaussian noise on the impact points.
    """
    import json
    from importlib.resources import files

    from psdcal.calibration.core import calibrate
    from psdcal.io import read_points, read_template, save_calibration
    from psdcal.report.text import print_calibration

    data = files("psdcal") / "data"
    from psdcal._atomic import guard_outputs

    # the bundled files are this command's inputs: never overwritten, whatever --out says
    guard_outputs([("bundled data", data / n) for n in ("default_template.csv", "default_points.csv",
                                                         "default_truth.json")], [("--out", out)], force=True)
    tids, txy = read_template(data / "default_template.csv")
    pf = read_points(data / "default_points.csv", tids)
    truth_d = json.loads((data / "default_truth.json").read_text())
    from psdcal import _jit

    _jit.set_mode("auto")  # as `psdcal calibrate`: 12 x 14 points take the numpy path (no numba, nothing compiled)
    res = calibrate(txy, pf.points_mm, cost=cost, radial=2, tangential=True, image_ids=pf.image_ids, point_ids=tids)
    truth = {**truth_d["intrinsics"], **truth_d["distortion"]}
    click.echo(f"bundled data: {data / 'default_points.csv'} ({len(pf.image_ids)} images, noise "
               f"{truth_d['noise_mm'] * 1e3:g} um)")
    print_calibration(res, truth=truth)
    save_calibration(out, res)
    click.echo(f"wrote {out}")
