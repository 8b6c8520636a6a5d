#!/usr/bin/env python3
"""Project tasks for a fresh machine with only Python 3.11 and pip.

    python3 tasks.py demo    # calibrate the bundled default data (main job)
    python3 tasks.py test    # run the test suite
    python3 tasks.py bench   # run the benchmarks, write their tables into README/docs (--quick: smoke run)
    python3 tasks.py docs    # build the documentation site into site/ (strict)

Each task creates the virtual environment ``.venv`` at the repository root
when it is missing and installs psdcal into it (editable; with the test
extras, except for ``demo``, which needs psdcal's own dependencies only), then
compiles the numerical kernels once, in two processes (``demo`` prints its
table meanwhile: it needs none of them).
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
PY = BIN / ("python.exe" if os.name == "nt" else "python")
STAMP = VENV / ".psdcal-installed"  # psdcal with its test extras installed for this pyproject.toml
CORE_STAMP = VENV / ".psdcal-installed-core"  # psdcal and its own dependencies only (what the demo needs)

#: The kernel warm-up's parts (psdcal.study.warmup.PARTS), compiled in parallel processes.
WARM_UP_PARTS = ("calibration", "measure")


#: Writes the bytecode of the packages ``psdcal --help`` imports (found without importing them).
_COMPILE_STARTUP = (
    "import compileall, importlib.util as u, os, sys\n"
    "for name in ('click', 'psdcal'):\n"
    "    spec = u.find_spec(name)\n"
    "    ok = spec is not None and spec.origin and compileall.compile_dir(os.path.dirname(spec.origin), quiet=1)\n"
    "    if not ok:\n"
    "        sys.exit(f'psdcal set-up: could not compile {name}')\n"
)


def ensure_venv(extras: bool = True) -> tuple[list[subprocess.Popen], Path | None]:
    """Create .venv and install the package when missing or when pyproject changed.

    ``extras``: with the test extras (tests, benchmarks, docs); without them (the demo)
    psdcal and its own dependencies only, fewer packages to install. After an install,
    the numerical kernels are compiled once, in the background, one process per part of
    :data:`WARM_UP_PARTS`. Returns those processes and the stamp to write once they are
    done (none and None when the set-up was already done): see :func:`finish_set_up`.
    """
    if not PY.exists():
        print(f"creating virtual environment in {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    pyproject = (ROOT / "pyproject.toml").read_bytes()
    if any(st.exists() and st.read_bytes() == pyproject for st in ((STAMP,) if extras else (STAMP, CORE_STAMP))):
        return [], None
    t0 = time.perf_counter()
    subprocess.check_call([str(PY), "-m", "pip", "install", "-q", "--upgrade", "pip"])
    # --no-compile: no bytecode for the thousands of modules of the dependencies now (most of pip's time);
    # each module gets its bytecode when first imported (the demo imports a few dozen)
    subprocess.check_call([str(PY), "-m", "pip", "install", "-q", "--no-compile", "-e",
                           f"{ROOT}[test]" if extras else str(ROOT)])
    # ... except the few the command line's start needs (click and psdcal itself): their bytecode is written
    # now, so that the very first `psdcal --help` does not pay for compiling them (about 0.3 s)
    subprocess.check_call([str(PY), "-c", _COMPILE_STARTUP])
    what = "with the test extras" if extras else "psdcal and its dependencies"
    print(f"psdcal set-up: venv + pip install {time.perf_counter() - t0:.1f} s ({what})", file=sys.stderr, flush=True)
    # compile the numerical kernels now (once per machine), so that no later run stalls on it; the parts
    # compile different kernels, in parallel (the demo itself needs none: it runs beside them)
    print(f"psdcal: compiling the numerical kernels in the background ({len(WARM_UP_PARTS)} processes) ...",
          file=sys.stderr, flush=True)
    lower = (lambda: os.nice(10)) if hasattr(os, "nice") else None  # the demo first; the kernels with what is left
    warming = [subprocess.Popen([str(PY), "-c", f"from psdcal.study.warmup import warm_up; warm_up(False, part={p!r})"],
                                preexec_fn=lower)
               for p in WARM_UP_PARTS]
    return warming, STAMP if extras else CORE_STAMP


def finish_set_up(warming: list[subprocess.Popen], stamp: Path | None, t0: float) -> None:
    """Wait for the kernel warm-up (if one runs), then mark the set-up as done."""
    if stamp is None:
        return
    for proc in warming:
        proc.wait()
    print(f"psdcal set-up: kernels compiled {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    stamp.write_bytes((ROOT / "pyproject.toml").read_bytes())


def run(args: list[str]) -> int:
    return subprocess.call(args, cwd=ROOT)


def main(argv: list[str]) -> int:
    task = argv[1] if len(argv) > 1 else "help"
    extra = argv[2:]
    if task not in {"demo", "test", "bench", "docs"}:
        print(__doc__)
        return 0 if task == "help" else 2
    warming, stamp = ensure_venv(extras=task != "demo")
    t0 = time.perf_counter()
    if task == "demo":  # the demo (12 views x 14 points, numpy path) needs no kernel: it runs beside the warm-up
        try:
            return run([str(BIN / "psdcal"), "demo", *extra])
        finally:
            finish_set_up(warming, stamp, t0)
    finish_set_up(warming, stamp, t0)
    if task == "test":
        return run([str(PY), "-m", "pytest", "-n", "2", "-q", *extra])
    if task == "docs":
        # Strict: a broken link, a missing anchor or a docstring mkdocstrings cannot read fails the build.
        os.environ.setdefault("NO_MKDOCS_2_WARNING", "1")
        return run([str(PY), "-m", "mkdocs", "build", "--strict", "--site-dir", str(ROOT / "site"), *extra])
    return run([str(PY), str(ROOT / "benchmarks" / "run_all.py"), *extra])


if __name__ == "__main__":
    sys.exit(main(sys.argv))
