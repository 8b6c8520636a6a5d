"""The calibration table and lines without rich (unstyled output) are rich's own output byte for byte.

Each case prints once through rich's ``Console()`` and once through the plain
writer of :mod:`psdcal.report.text`, at several console widths (``COLUMNS``),
and compares the bytes; the word wrapping and the table are also compared on
random text and cells against rich's ``Text`` and ``Table``.
"""
from __future__ import annotations

import dataclasses
import io
import random
import string
import sys
from pathlib import Path

import pytest

rich_console = pytest.importorskip("rich.console")
from rich.table import Table  # noqa: E402
from rich.text import Text  # noqa: E402

from psdcal.report import text as rt  # noqa: E402

DATA = Path(__file__).resolve().parent / "data"


@pytest.fixture(scope="module")
def zhang():
    from psdcal.calibration.core import calibrate
    from psdcal.io import read_points, read_template

    ids, T = read_template(DATA / "zhang1998" / "template.csv")
    pf = read_points(DATA / "zhang1998" / "points.csv", ids)
    return calibrate(T, pf.points_mm, image_ids=pf.image_ids, point_ids=ids)


def _both(capsys, monkeypatch, columns, fn, plain=True):
    """(what rich's Console() prints, what fn(None) prints: without rich where ``plain``) for fn(console)."""
    monkeypatch.setenv("COLUMNS", str(columns))
    for k in ("FORCE_COLOR", "TTY_COMPATIBLE", "NO_COLOR"):
        monkeypatch.delenv(k, raising=False)
    capsys.readouterr()
    fn(rich_console.Console())
    via_rich = capsys.readouterr().out
    with monkeypatch.context() as m:
        if plain:  # the plain writer must not need rich
            for name in [k for k in sys.modules if k == "rich" or k.startswith("rich.")]:
                m.setitem(sys.modules, name, None)
        fn(None)
    return via_rich, capsys.readouterr().out


@pytest.mark.parametrize("columns", [44, 60, 80, 100, 137, 250])
def test_calibration_printout_is_riches_byte_for_byte(zhang, capsys, monkeypatch, columns):
    assert rt._plain_width() is not None or columns < 20
    via_rich, plain = _both(capsys, monkeypatch, columns, lambda c: rt.print_calibration(zhang, console=c))
    assert "psdcal calibration" in plain and "verdict:" in plain
    assert plain == via_rich


def test_truth_columns_warnings_and_verdict_lines(zhang, capsys, monkeypatch):
    truth = {"f_mm": zhang.intrinsics.f_mm * 1.001, "k1": None}
    v = dict(zhang.verdict)
    long_advice = "advice " + "x" * 130 + " and some words, " * 9  # a word longer than the line, then words
    v["checks"] = [*v["checks"], {**v["checks"][-1], "name": "extra", "passed": False, "severe": False,
                                  "message": "m " * 70, "advice": long_advice}]
    v["verdict"] = "suspect"
    res = dataclasses.replace(zhang, verdict=v)
    object.__setattr__(res, "warnings", lambda: ["a warning that is long enough to be wrapped " * 4, "short"])
    for columns in (50, 80, 120):  # at 50 the table is wider than the console: rich lays it out
        via_rich, plain = _both(capsys, monkeypatch, columns, lambda c: rt.print_calibration(res, truth=truth, console=c),
                                plain=columns > 50)
        assert "truth" in plain and "warning: a warning" in plain and "extra" in plain
        assert plain == via_rich, columns
        via_rich, plain = _both(capsys, monkeypatch, columns, lambda c: rt.print_verdict(res, console=c))
        assert plain == via_rich, columns


def test_markup_and_wide_tables_go_through_rich(zhang, capsys, monkeypatch):
    """Text with markup or emoji codes, and a table wider than the console, are left to rich (which it renders)."""
    res = dataclasses.replace(zhang)
    object.__setattr__(res, "warnings", lambda: ["a [bold]marked[/bold] :smile: warning"])
    via_rich, out = _both(capsys, monkeypatch, 80, lambda c: rt.print_calibration(res, console=c), plain=False)
    assert out == via_rich and "[bold]" not in out
    assert rt._plain_table("t", ["a", "b"], [["x" * 30, "y" * 30]], 40) is None
    assert rt._plain_table("t", ["a", "b"], [["x ", "y"]], 40) is None  # rich strips a cell's outer spaces
    assert not rt._plain_ok("[red]x") and not rt._plain_ok("a :smile: b") and not rt._plain_ok("caf\u00e9")
    assert rt._plain_ok("worst: image 3 (F = 2.1, p = 0.01)")


def test_styled_output_is_left_to_rich(monkeypatch):
    monkeypatch.setenv("FORCE_COLOR", "1")
    assert rt._plain_width() is None
    monkeypatch.delenv("FORCE_COLOR")
    monkeypatch.setenv("TTY_COMPATIBLE", "1")
    assert rt._plain_width() is None
    monkeypatch.setenv("TTY_COMPATIBLE", "0")
    monkeypatch.setenv("COLUMNS", "91")
    assert rt._plain_width() == 91
    monkeypatch.setenv("TTY_COMPATIBLE", "")

    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(sys, "stdout", Tty())
    assert rt._plain_width() is None


def _random_text(rng):
    pieces = []
    for _ in range(rng.randrange(0, 30)):
        word = "".join(rng.choice(string.ascii_letters + string.digits + ".,;=()-+%")
                       for _ in range(rng.choice([1, 2, 5, 9, 15, 40, 95])))
        pieces.append(word + " " * rng.choice([0, 1, 1, 1, 2, 3]))
    return " " * rng.choice([0, 0, 2]) + "".join(pieces)


def test_wrapping_is_riches_on_random_text():
    rng = random.Random(20261126)
    for _ in range(1500):
        s = _random_text(rng)
        width = rng.choice([20, 21, 33, 40, 57, 80, 101])
        buf = io.StringIO()
        rich_console.Console(file=buf, width=width, color_system=None).print(Text(s))
        assert rt._plain_lines(s, width, soft=False) == buf.getvalue(), (s, width)


def test_table_is_riches_on_random_cells():
    rng = random.Random(7)
    for _ in range(300):
        ncol = rng.randrange(1, 6)
        header = [_random_text(rng).strip()[:rng.randrange(1, 12)].strip() or "h" for _ in range(ncol)]
        rows = [[rng.choice(["-", "1.5e-03", "f_mm", "", _random_text(rng).strip()[:rng.randrange(0, 14)].strip()])
                 for _ in range(ncol)] for _ in range(rng.randrange(0, 8))]
        title = _random_text(rng).strip()[:rng.randrange(0, 90)] or "t"
        width = rng.choice([30, 50, 80, 120])
        plain = rt._plain_table(title, header, rows, width)
        if plain is None:
            continue
        t = Table(title=title)
        for j, h in enumerate(header):
            t.add_column(h, **({} if j == 0 else {"justify": "right"}))
        for r in rows:
            t.add_row(*r)
        buf = io.StringIO()
        rich_console.Console(file=buf, width=width, color_system=None).print(t)
        assert plain == buf.getvalue(), (title, header, rows, width)


@pytest.mark.parametrize("columns", [None, "100", "abc", "25"])
@pytest.mark.parametrize("terminal", [None, (0, 0), (123, 40)])
def test_width_is_riches(monkeypatch, columns, terminal):
    """The console width (COLUMNS, else a terminal on stdin/stdout/stderr, else 80) is rich's Console().width."""
    import os

    for k in ("COLUMNS", "FORCE_COLOR", "TTY_COMPATIBLE", "LINES"):
        monkeypatch.delenv(k, raising=False)
    if columns is not None:
        monkeypatch.setenv("COLUMNS", columns)

    def size(fd=1):
        if terminal is None or fd != 0:
            raise OSError("not a terminal")
        return os.terminal_size(terminal)

    monkeypatch.setattr(os, "get_terminal_size", size)
    assert rt._plain_width() == rich_console.Console().width
