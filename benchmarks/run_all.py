#!/usr/bin/env python3
"""Run every ``benchmarks/bench_*.py`` in turn with this interpreter.

Each benchmark runs in its own process; its output is printed as it comes.
Names before ``--`` select benchmarks (a substring of the file name:
``opencv`` runs ``bench_opencv.py``); arguments after ``--`` are passed to
every selected benchmark. The exit status is non-zero when any benchmark
fails (the others still run) or when a name matches none.

Usage::

    python3 tasks.py bench [NAME ...] [-- ARGS...]
    .venv/bin/python benchmarks/run_all.py opencv -- --sets 5
"""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv: list[str]) -> int:
    """Run the benchmarks; return 0 when all succeed, 1 otherwise."""
    if argv and argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0
    split = argv.index("--") if "--" in argv else len(argv)
    names, passthrough = argv[:split], argv[split + 1 :]
    options = [n for n in names if n.startswith("-")]
    if options:
        print(f"options {options} must follow '--' (run_all.py [NAME ...] -- ARGS)", file=sys.stderr)
        return 2
    scripts = sorted(HERE.glob("bench_*.py"))
    if names:
        unknown = [n for n in names if not any(n in s.stem for s in scripts)]
        if unknown:
            print(f"no benchmark matches {unknown}; have {[s.stem for s in scripts]}", file=sys.stderr)
            return 2
        scripts = [s for s in scripts if any(n in s.stem for n in names)]
    if not scripts:
        print(f"no bench_*.py in {HERE}", file=sys.stderr)
        return 1
    failed = []
    for script in scripts:
        print(f"=== {script.name} ===", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call([sys.executable, str(script), *passthrough], cwd=HERE.parent)
        print(f"=== {script.name}: {'ok' if rc == 0 else f'FAILED (exit {rc})'} in {time.perf_counter() - t0:.1f} s ===\n", flush=True)
        if rc != 0:
            failed.append(script.name)
    if failed:
        print(f"{len(failed)} benchmark(s) failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    print(f"all {len(scripts)} benchmark(s) passed")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
