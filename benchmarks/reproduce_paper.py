#!/usr/bin/env python3
"""The paper's Tables 3-4 and the gain remedies, as docs/reproduction.md and docs/guide/gain-calibration.md show them.

Runs ``psdcal reproduce --table 3 --table 4 --table 5 --table 6`` (the command line, in a temporary folder,
one worker) and prints two Markdown tables: ``tables34``, the corrected cases of Tables 3-4 (cx,
f and k1: our mean (std) beside the paper's), and ``remedies``, the AoA error of each gain remedy
on the Tables 5-6 cases (from its ``gains.md``).

    .venv/bin/python benchmarks/reproduce_paper.py [--trials 200] [--gain-trials 25] [--markdown]
    .venv/bin/python benchmarks/reproduce_paper.py --quick      (3 trials per case, 2 per remedy case)
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


def remedies(folder: Path) -> tuple[list[str], list[list[str]]]:
    """The remedies table of ``gains.md``: lens, case, remedy, AoA RMS, ratio to the reference."""
    text = (folder / "gains.md").read_text(encoding="utf-8")
    part = text[text.index("## Remedies"):]
    lines = part.splitlines()
    start = next(k for k, line in enumerate(lines) if line.startswith("|"))
    end = next((k for k in range(start, len(lines)) if not lines[k].startswith("|")), len(lines))
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in lines[start:end]]  # the first table
    head, body = rows[0], rows[2:]
    keep = [head.index(k) for k in ("lens", "case", "remedy", "AoA RMS (deg)", "ratio to reference", "n (failed)")]
    return [head[k] for k in keep], [[r[k] for k in keep] for r in body]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--gain-trials", type=int, default=25)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="3 trials per case, 2 per remedy case")
    ap.add_argument("--markdown", action="store_true", help="(the tables are Markdown; ids tables34, remedies)")
    a = ap.parse_args(argv)
    exe = Path(sys.executable).with_name("psdcal")
    cmd = [str(exe) if exe.exists() else "psdcal", "reproduce", "--table", "3", "--table", "4", "--table", "5", "--table", "6",
           "--workers", "1", "--seed", str(a.seed)]
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
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
