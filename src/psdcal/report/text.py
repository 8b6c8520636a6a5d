"""Plain-text (terminal) presentation of results; no numerics here."""
from __future__ import annotations

import numpy as np

_FMT = {"f_mm": "{:.6f}", "cx_mm": "{:.6f}", "cy_mm": "{:.6f}", "skew": "{:.3e}", "fy_mm": "{:.6f}"}


def _fmt(name, v):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    return _FMT.get(name, "{:.5e}").format(v)


def print_calibration(res, truth: dict | None = None, console=None) -> None:
    """Print a calibration's parameters (with standard errors) and residuals as a table.

    ``truth`` (name -> value) adds the true values and the error in standard errors.
    """
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    t = Table(title=f"psdcal calibration ({res.cost} cost, {len(res.image_ids)} images)")
    t.add_column("parameter")
    if truth is not None:
        t.add_column("truth", justify="right")
    t.add_column("estimate", justify="right")
    t.add_column("std error", justify="right")
    if truth is not None:
        t.add_column("error / std", justify="right")
    for name in res.param_names:
        v = res.parameter(name)
        s = res.std.get(name)
        row = [name]
        if truth is not None:
            row.append(_fmt(name, truth.get(name)))
        row += [_fmt(name, v), _fmt(name, s)]
        if truth is not None:
            tv = truth.get(name)
            row.append("-" if tv is None or not s else f"{(v - tv) / s:+.2f}")
        t.add_row(*row)
    console.print(t)
    console.print(
        f"residual RMS {res.rms_mm * 1e3:.4f} um on the sensor (implied noise {res.sigma_mm * 1e3:.4f} um per coordinate); "
        f"{res.iterations} iterations, {'converged' if res.converged else 'NOT converged'}"
    )
    per = np.asarray(res.per_image_rms_mm, dtype=float)
    worst = int(np.nanargmax(per)) if np.any(np.isfinite(per)) else None
    if worst is not None:
        console.print(f"per-image RMS {res.per_image_rms_mm.min() * 1e3:.4f}-{res.per_image_rms_mm.max() * 1e3:.4f} um "
                      f"(worst: image {res.image_ids[worst]})")
    for w in res.warnings():
        console.print(f"[bold yellow]warning:[/] {w}", markup=True)
    print_verdict(res, console)


def print_verdict(res, console=None) -> None:
    """Print a calibration's verdict (good / suspect / wrong) and the failed checks with their advice."""
    if not getattr(res, "verdict", None):
        return
    from rich.console import Console
    from rich.markup import escape

    from psdcal.calibration.verdict import Verdict

    console = console or Console()
    v = Verdict.from_dict(res.verdict)
    colour = {"good": "green", "suspect": "yellow", "wrong": "red"}[v.verdict]
    lines = v.lines()
    console.print(f"[bold {colour}]{escape(lines[0])}[/]", markup=True)
    for line in lines[1:]:
        console.print(escape(line), markup=True, soft_wrap=True)
