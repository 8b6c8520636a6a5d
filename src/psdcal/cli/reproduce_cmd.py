"""``psdcal reproduce``: the paper's simulation study (Tables 1-10, Figure 9) and the gain remedies."""
from __future__ import annotations

from pathlib import Path

import click

from psdcal.cli import cli
from psdcal.cli._cluster import scheduler_option, trial_executor

#: ``--quick``: trials per case and per remedy case (a smoke run for CI, under a minute).
QUICK_TRIALS = (3, 2)


@cli.command("reproduce")
@click.option("--table", "tables", type=click.IntRange(1, 10), multiple=True, metavar="N",
              help="A table of the paper to regenerate (1-10); repeat for several. Default: all, with Figure 9.")
@click.option("--trials", type=click.IntRange(min=2), default=200, show_default=True,
              help="Monte Carlo trials per case (the paper: 200).")
@click.option("--gain-trials", type=click.IntRange(min=2), default=None,
              help="Trials per gain-remedy case (Tables 5-6).  [default: trials / 8, at least 4]")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=Path("reproduce_out"),
              show_default=True, help="Folder for table_N.csv/.md, report.md, gains.md, figure_9.png.")
@click.option("--quick", is_flag=True, default=False,
              help=f"Smoke run for CI: {QUICK_TRIALS[0]} trials per case, {QUICK_TRIALS[1]} per remedy case.")
@click.option("--seed", type=int, default=0, show_default=True, help="Root random seed (same seed, same tables).")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Worker processes on this machine.  [default: CPU count]")
@scheduler_option
def reproduce_command(tables, trials, gain_trials, out_dir, quick, seed, workers, scheduler):
    """Regenerate the paper's Tables 1-10 and Figure 9 beside the paper's numbers.

    Each table is written as CSV and Markdown with the paper's values, an
    agreement flag (within 3 combined Monte Carlo standard errors) and the
    reasons where they disagree; report.md gathers them, gains.md compares
    the gain remedies (paper's model, electrical calibration, joint
    calibration, general intrinsic matrix) on held-out emitters.

    Example: psdcal reproduce --table 3 --table 4 --trials 200 --out repro/

    On a cluster: psdcal reproduce --scheduler tcp://10.0.0.5:8786 --out repro/
    """
    import time

    from psdcal.study.reproduce import PAPER_TRIALS, run_study, write_outputs

    chosen = tuple(tables) if tables else tuple(range(1, 11))
    n, g = (QUICK_TRIALS if quick else (trials, gain_trials if gain_trials is not None else max(4, trials // 8)))
    if not quick and trials < PAPER_TRIALS:
        click.echo(f"note: {trials} trials per case (the paper ran {PAPER_TRIALS})", err=True)
    t0 = time.perf_counter()
    with trial_executor(scheduler) as executor:
        study = run_study(chosen, n, seed, gain_trials=g, workers=workers, executor=executor, progress=True,
                          log=lambda msg: click.echo(f"  {msg}", err=True))
    paths = write_outputs(study, out_dir)
    click.echo(f"wrote {len(paths)} files to {out_dir} in {time.perf_counter() - t0:.0f} s "
               f"(tables {', '.join(str(t) for t in study.tables)}; {n} trials per case, {g} per remedy case)")
