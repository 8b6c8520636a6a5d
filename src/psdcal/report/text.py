"""Plain-text (terminal) presentation of results; no numerics here.

The tables and lines are laid out by rich on a terminal (with colour). When
the output is not styled (a pipe or a file, rich's own rule), a few lines of
plain Python write the very same bytes without loading rich (some 40 ms of a
fresh ``psdcal calibrate``); anything those lines do not reproduce exactly
(a table wider than the console, markup, non-ASCII text) goes through rich.
"""
from __future__ import annotations

import os
import re
import sys

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
    title = f"psdcal calibration ({res.cost} cost, {len(res.image_ids)} images)"
    header = ["parameter"] + (["truth"] if truth is not None else []) + ["estimate", "std error"] \
        + (["error / std"] if truth is not None else [])
    rows = []
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
        rows.append(row)
    lines = [f"residual RMS {res.rms_mm * 1e3:.4f} um on the sensor (implied noise {res.sigma_mm * 1e3:.4f} um per "
             f"coordinate); {res.iterations} iterations, {'converged' if res.converged else 'NOT converged'}"]
    per = np.asarray(res.per_image_rms_mm, dtype=float)
    worst = int(np.nanargmax(per)) if np.any(np.isfinite(per)) else None
    if worst is not None:
        lines.append(f"per-image RMS {res.per_image_rms_mm.min() * 1e3:.4f}-{res.per_image_rms_mm.max() * 1e3:.4f} um "
                     f"(worst: image {res.image_ids[worst]})")
    warnings = list(res.warnings())
    verdict = _verdict_lines(res)
    if console is None:
        width = _plain_width()
        if width is not None:
            text = _plain_table(title, header, rows, width)
            plain = [(line, False) for line in lines] + [(f"warning: {w}", False) for w in warnings] + verdict
            if text is not None and all(_plain_ok(t) for t, _ in plain):
                sys.stdout.write(text + "".join(_plain_lines(t, width, soft) for t, soft in plain))
                sys.stdout.flush()
                return
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    t = Table(title=title)
    for h in header:
        t.add_column(h, **({} if h == "parameter" else {"justify": "right"}))
    for row in rows:
        t.add_row(*row)
    console.print(t)
    for line in lines:
        console.print(line)
    for w in warnings:
        console.print(f"[bold yellow]warning:[/] {w}", markup=True)
    print_verdict(res, console)


def _verdict_lines(res) -> list[tuple[str, bool]]:
    """The verdict's lines as ``(text, soft_wrap)``: the first wraps at the console's width, the others do not."""
    if not getattr(res, "verdict", None):
        return []
    from psdcal.calibration.verdict import Verdict

    lines = Verdict.from_dict(res.verdict).lines()
    return [(lines[0], False)] + [(line, True) for line in lines[1:]]


def print_verdict(res, console=None) -> None:
    """Print a calibration's verdict (good / suspect / wrong) and the failed checks with their advice."""
    if not getattr(res, "verdict", None):
        return
    if console is None:
        width = _plain_width()
        lines = _verdict_lines(res)
        if width is not None and all(_plain_ok(t) for t, _ in lines):
            sys.stdout.write("".join(_plain_lines(t, width, soft) for t, soft in lines))
            sys.stdout.flush()
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


# --- the output of rich's Console() where it styles nothing, written without rich -----------------------------------

#: Text rich would print differently from its characters: markup, escapes, emoji codes (``:name:``), control
#: characters, tabs and anything but printable ASCII (whose cell widths differ).
_NOT_PLAIN = re.compile(r"[^\x20-\x7e]|[\[\\]|:\S*?:")


def _plain_ok(text: str) -> bool:
    return _NOT_PLAIN.search(text) is None


def _plain_width() -> int | None:
    """The width of rich's ``Console()`` on ``sys.stdout`` where it writes no escape codes; None where it would
    style the output (a terminal, ``FORCE_COLOR``, ``TTY_COMPATIBLE=1``), write ASCII boxes (a non-UTF encoding),
    or runs where this function does not follow rich (Windows, Jupyter, IDLE)."""
    out = sys.stdout
    env = os.environ
    if out is None or sys.platform == "win32" or "IPython" in sys.modules or "idlelib" in sys.modules:
        return None
    if not (getattr(out, "encoding", None) or "utf-8").lower().startswith("utf"):
        return None
    tty = env.get("TTY_COMPATIBLE", "")
    if tty == "1":
        return None
    if tty != "0":
        force = env.get("FORCE_COLOR")
        if force is not None:
            if force != "":
                return None
        else:
            isatty = getattr(out, "isatty", None)
            try:
                if isatty is not None and isatty():
                    return None
            except ValueError:
                return None
    columns = env.get("COLUMNS")
    if columns is not None and columns.isdigit():
        width = int(columns)
    else:
        width = None
        for fd in (0, 1, 2):
            try:
                width = os.get_terminal_size(fd)[0]
            except (AttributeError, ValueError, OSError):
                continue
            break
        width = width or 80
    return width if width >= 20 else None


def _wrap(text: str, width: int) -> list[str]:
    """``text`` (printable ASCII) word-wrapped as rich wraps it: break before a word that does not fit, fold a
    word longer than a line, keep a line's trailing spaces up to the width, crop what is beyond."""
    breaks = []
    offset = 0
    for m in re.finditer(r"\s*\S+\s*", text):
        start, word = m.start(), m.group()
        length = len(word.rstrip())
        if width - offset >= length:
            offset += len(word)
        elif length > width:
            pieces = [word[i:i + width] for i in range(0, len(word), width)]
            for k, piece in enumerate(pieces):
                if start:
                    breaks.append(start)
                if k == len(pieces) - 1:
                    offset = len(piece)
                else:
                    start += len(piece)
        elif offset and start:
            breaks.append(start)
            offset = len(word)
    out = []
    for a, b in zip([0, *breaks], [*breaks, len(text)]):
        line = text[a:b]
        if len(line) > width:
            excess = len(line) - width
            spaces = len(line) - len(line.rstrip())
            line = line[:len(line) - min(spaces, excess)][:width]
        out.append(line)
    return out


def _plain_lines(text: str, width: int, soft: bool) -> str:
    """``Console().print(text)`` (``soft_wrap=soft``) of unstyled printable ASCII text."""
    if soft:
        return text + "\n"
    return "\n".join(_wrap(text, width)) + "\n"


def _plain_table(title: str, header: list[str], rows: list[list[str]], width: int) -> str | None:
    """rich's default ``Table(title=title)`` (heavy head, the first column left, the others right-justified) of
    printable ASCII cells; None where rich would lay it out otherwise (wider than the console) or restyle a cell."""
    cells = [*header, *(c for r in rows for c in r)]
    if not all(_plain_ok(c) for c in [title, *cells]) or any(c != c.strip() for c in cells):
        return None
    widths = [max(len(c) for c in col) for col in zip(header, *rows)]
    table_width = sum(widths) + 3 * len(widths) + 1
    if table_width > width:
        return None

    def row(cells, edge):
        inner = f" {edge} ".join(c.ljust(w) if j == 0 else c.rjust(w) for j, (c, w) in enumerate(zip(cells, widths)))
        return f"{edge} {inner} {edge}"

    def rule(left, mid, right, fill):
        return left + mid.join(fill * (w + 2) for w in widths) + right

    out = []
    for line in _wrap(title, table_width):
        line = line.rstrip()[:table_width]
        pad = (table_width - len(line)) // 2
        out.append((" " * pad + line).ljust(table_width))
    out += [rule("┏", "┳", "┓", "━"), row(header, "┃"), rule("┡", "╇", "┩", "━")]
    out += [row(r, "│") for r in rows]
    out.append(rule("└", "┴", "┘", "─"))
    return "\n".join(out) + "\n"
