#!/usr/bin/env python3
"""Project tasks for a fresh machine with only Python 3.11 and pip.

    python3 tasks.py demo    # calibrate the bundled default data (main job)
    python3 tasks.py test    # run the test suite
    python3 tasks.py bench   # run the benchmarks, write their tables into README/docs (--quick: smoke run)
    python3 tasks.py docs    # build the documentation site into site/ (strict)

Each task creates the virtual environment ``.venv`` at the repository root
when it is missing and installs psdcal into it (editable, with test extras).
"""
from __future__ import annotations

import os
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
PY = BIN / ("python.exe" if os.name == "nt" else "python")
STAMP = VENV / ".psdcal-installed"


def ensure_venv() -> None:
    """Create .venv and install the package when missing or when pyproject changed."""
    if not PY.exists():
        print(f"creating virtual environment in {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    pyproject = (ROOT / "pyproject.toml").read_bytes()
    if STAMP.exists() and STAMP.read_bytes() == pyproject:
        return
    subprocess.check_call([str(PY), "-m", "pip", "install", "-q", "--upgrade", "pip"])
    subprocess.check_call([str(PY), "-m", "pip", "install", "-q", "-e", f"{ROOT}[test]"])
    # compile the numerical kernels now (once per machine), so that no later run stalls on it
    subprocess.call([str(PY), "-c", "from psdcal.study.warmup import warm_up; warm_up()"])
    STAMP.write_bytes(pyproject)


def run(args: list[str]) -> int:
    return subprocess.call(args, cwd=ROOT)


def main(argv: list[str]) -> int:
    task = argv[1] if len(argv) > 1 else "help"
    extra = argv[2:]
    if task not in {"demo", "test", "bench", "docs"}:
        print(__doc__)
        return 0 if task == "help" else 2
    ensure_venv()
    if task == "demo":
        return run([str(BIN / "psdcal"), "demo", *extra])
    if task == "test":
        return run([str(PY), "-m", "pytest", "-n", "2", "-q", *extra])
    if task == "docs":
        # Strict: a broken link, a missing anchor or a docstring mkdocstrings cannot read fails the build.
        os.environ.setdefault("NO_MKDOCS_2_WARNING", "1")
        return run([str(PY), "-m", "mkdocs", "build", "--strict", "--site-dir", str(ROOT / "site"), *extra])
    return run([str(PY), str(ROOT / "benchmarks" / "run_all.py"), *extra])


if __name__ == "__main__":
    sys.exit(main(sys.argv))
