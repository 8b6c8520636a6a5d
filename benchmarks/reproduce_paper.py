#!/usr/bin/env python3
"""The paper's Tables 1-4, 7-8, Figure 9 and the gain remedies, as reproduction.md and gain-calibration.md show them.

Runs ``psdcal reproduce`` (every table, with Figure 9; the command line, in a temporary folder, on
``--workers`` processes: the tables do not depend on their number) and prints its Markdown tables: ``tables34``, the corrected cases of Tables 3-4 (cx, f and k1:
our mean (std) beside the paper's); ``remedies``, the AoA error of each gain remedy on the Tables 5-6
cases (from its ``gains.md``); ``table1``, ``table2`` (the linear stage, noiseless), ``table7``,
``table8`` (PSD distortion, imbalance and noise), each row ours beside the paper's with the agreement
flags of ``table_N.md``; and ``figure9``, the errors at S = 5 m from the mean + 2 std parameters.

    .venv/bin/python benchmarks/reproduce_paper.py [--trials 200] [--gain-trials 25] [--workers 1] [--markdown]
    .venv/bin/python benchmarks/reproduce_paper.py --quick      (3 trials per case, 2 per remedy case)

At the paper's 200 trials per case the whole run takes a few minutes of one core (Tables 1-2 are
linear fits; each other trial is one calibration).
"""
from __future__ import annotations

import argparse
import csv
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/_table.py
from _table import print_table  # noqa: E402


def _g(x: float) -> str:
    return f"{x:.4g}"


def tables34(folder: Path) -> list[list[str]]:
    """Rows ``lens, SNR | cx | f | k1``, each ``ours mean (std) / paper mean (std)``, for the corrected columns."""
    lines = []
    for table, lens in ((3, "Lens 1"), (4, "Lens 2")):
        with open(folder / f"table_{table}.csv", encoding="utf-8") as fh:
            rows = [r for r in csv.DictReader(fh) if r["column"].startswith("with corrections")]
        for col in dict.fromkeys(r["column"] for r in rows):
            cells = []
            for param in ("cx_mm", "f_mm", "k1"):
                r = next(r for r in rows if r["column"] == col and r["param"] == param)
                cells.append(f"{_g(float(r['mean']))} ({float(r['std']):.2g}) / "
                             f"{_g(float(r['paper_mean']))} ({float(r['paper_std']):.2g})")
            lines.append([f"{lens}, {col.split(', ')[1]}", *cells])
    return lines


def _first_table(text: str) -> tuple[list[str], list[list[str]]]:
    """The header and the rows of the first Markdown table of ``text``."""
    lines = text.splitlines()
    start = next(k for k, line in enumerate(lines) if line.startswith("|"))
    end = next((k for k in range(start, len(lines)) if not lines[k].startswith("|")), len(lines))
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in lines[start:end]]
    return rows[0], rows[2:]


def _columns(head: list[str], body: list[list[str]], keep: tuple[str, ...]) -> tuple[list[str], list[list[str]]]:
    idx = [head.index(k) for k in keep]
    return [head[k] for k in idx], [[r[k] for k in idx] for r in body]


def remedies(folder: Path) -> tuple[list[str], list[list[str]]]:
    """The remedies table of ``gains.md``: lens, case, remedy, AoA RMS, ratio to the reference."""
    text = (folder / "gains.md").read_text(encoding="utf-8")
    head, body = _first_table(text[text.index("## Remedies"):])
    return _columns(head, body, ("lens", "case", "remedy", "AoA RMS (deg)", "ratio to reference", "n (failed)"))


def paper_table(folder: Path, table: int, trials: str) -> tuple[list[str], list[list[str]]]:
    """Table N of ``table_N.md``: case, parameter, ideal, ours, the paper's and the agreement flags.

    The paper gives one noiseless set for Tables 1-2 and the noiseless columns of 7-8 (no std to compare:
    ``std agrees`` is n/a there), so Tables 1-2 leave that column out.
    """
    head, body = _first_table((folder / f"table_{table}.md").read_text(encoding="utf-8"))
    keep = ["column", "parameter", "ideal", "ours", "paper", "mean agrees", "std agrees", "unbiased", "n (failed)"]
    if table in (1, 2):
        keep.remove("std agrees")
    head, body = _columns(head, body, tuple(keep))
    head = [f"ours, mean (std) of {trials} trials" if h == "ours" else h for h in head]
    return ["case" if h == "column" else h for h in head], body


def figure9(folder: Path) -> tuple[list[str], list[list[str]]]:
    """The Figure 9 table of ``report.md``: AoA and position errors at S = 5 m per lens and case."""
    text = (folder / "report.md").read_text(encoding="utf-8")
    return _first_table(text[text.index("## Figure 9"):])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--gain-trials", type=int, default=25)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=1, help="worker processes (the same tables for any number)")
    ap.add_argument("--quick", action="store_true", help="3 trials per case, 2 per remedy case")
    ap.add_argument("--markdown", action="store_true",
                    help="(the tables are Markdown; ids tables34, remedies, table1, table2, table7, table8, figure9)")
    a = ap.parse_args(argv)
    exe = Path(sys.executable).with_name("psdcal")
    cmd = [str(exe) if exe.exists() else "psdcal", "reproduce", "--workers", str(a.workers), "--seed", str(a.seed)]
    cmd += ["--quick"] if a.quick else ["--trials", str(a.trials), "--gain-trials", str(a.gain_trials)]
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "repro"
        proc = subprocess.run([*cmd, "--out", str(out)], capture_output=True, text=True)
        if proc.returncode != 0:
            print(proc.stdout + proc.stderr, file=sys.stderr)
            return proc.returncode
        print(proc.stdout.strip().splitlines()[-1])
        print()
        trials = "3" if a.quick else str(a.trials)
        print_table(["lens, SNR", f"cx (mm) ours / paper, mean (std) of {trials} trials", "f (mm) ours / paper",
                     "k1 ours / paper"], tables34(out), True, "tables34")
        print()
        head, body = remedies(out)
        print_table(head, body, True, "remedies")
        for table in (1, 2, 7, 8):
            print()
            head, body = paper_table(out, table, trials)
            print_table(head, body, True, f"table{table}")
        print()
        head, body = figure9(out)
        print_table(head, body, True, "figure9")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
