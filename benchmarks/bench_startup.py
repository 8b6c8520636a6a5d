#!/usr/bin/env python3
"""Start-up: what a fresh ``psdcal`` process costs, against ``psdcal --help`` and an OpenCV script.

Every command runs ``--repeats`` times in a new interpreter; the tables give the
median process CPU time (user + system of the child, ``RUSAGE_CHILDREN``),
which another job on the machine disturbs less than the wall-clock time, and
the differences and ratios within this one run.

Table 1, ``psdcal calibrate`` on the bundled default data (12 views x 14
points; the command keeps such a problem on the numpy path) against a
Python script that reads the same CSV files, runs ``cv2.calibrateCamera``
(one f, C, k1, k2, p1, p2) and writes a JSON file.

Table 2, light commands and a 1 s recording:

- ``python -c pass``: the interpreter alone;
- ``psdcal --help``: with the bytecode caches as installed (the reference of
  the differences), without psdcal's own bytecode (a fresh copy of ``src``
  and ``PYTHONDONTWRITEBYTECODE=1``: a fresh clone's first run), and without
  any bytecode at all (``PYTHONPYCACHEPREFIX`` an empty folder: the standard
  library and click compiled from source too);
- ``psdcal locate`` (one sensor with ``--calib``, and two sensors with
  ``--sensors``), ``aoa`` on its output and ``pose`` on a 1 s, 20 kS/s
  recording of ``simulate-recording room`` (2 sensors, 5 emitters, 2
  carriers located): as shipped (small work on the numpy path, numba not
  imported) and with the compiled kernels forced (``psdcal._jit`` mode
  "always", kernels loaded from a warm disk cache).

``--clone`` adds table 3: ``git clone`` of this repository (its committed
HEAD) into a temporary folder and ``python3 tasks.py demo`` there (which
creates ``.venv``, pip-installs psdcal and compiles the kernels), wall-clock:
to the demo's table and to the end of the command, with the set-up's phases
as ``tasks.py`` reports them; the pip part depends on the network and pip's
cache.

Usage::

    .venv/bin/python benchmarks/bench_startup.py [--repeats 5] [--markdown] [--clone]
"""
from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import print_table  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "src" / "psdcal" / "data"

_OPENCV = r"""
import json, sys
import numpy as np, cv2
T = np.loadtxt(sys.argv[1], delimiter=",", skiprows=1, usecols=(1, 2))
P = np.loadtxt(sys.argv[2], delimiter=",", skiprows=1)
obj = np.concatenate([T, np.zeros((len(T), 1))], 1).astype(np.float32)
imgs = [(P[P[:, 0] == i][:, 2:4] / 0.01 + 450).astype(np.float32).reshape(-1, 1, 2) for i in np.unique(P[:, 0])]
rms, K, dist, rv, tv = cv2.calibrateCamera([obj] * len(imgs), imgs, (900, 900), np.eye(3), np.zeros(5),
                                           flags=cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_K3)
json.dump({"K": K.tolist(), "dist": dist.ravel().tolist(), "rms": rms}, open(sys.argv[3], "w"))
"""

#: psdcal's command line with the compiled kernels forced (mode "always" whatever the command sets).
_FORCED = r"""
import sys
from psdcal import _jit
_jit.set_mode = _jit.set_mode_for = lambda *a: None  # keep mode "always": compiled kernels from the disk cache
from psdcal.cli import main
sys.exit(main(sys.argv[1:]))
"""

_PSDCAL = "import sys\nfrom psdcal.cli import main\nsys.exit(main(sys.argv[1:]))"


def cpu_seconds(cmd, repeats: int, env=None, cwd=None, fresh_src: bool = False, no_bytecode: bool = False) -> float:
    """Median process CPU seconds (user + system) of ``cmd`` run ``repeats`` times in fresh processes.

    ``fresh_src``: psdcal imported from a fresh copy of ``src`` (no ``__pycache__``) and no bytecode
    written; ``no_bytecode``: no bytecode read or written at all (``PYTHONPYCACHEPREFIX`` empty).
    """
    ts = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            e = dict(env or os.environ)
            if fresh_src:
                shutil.copytree(ROOT / "src", Path(tmp) / "src", ignore=shutil.ignore_patterns("__pycache__", "*.nb?"))
                e["PYTHONPATH"] = str(Path(tmp) / "src")
                e["PYTHONDONTWRITEBYTECODE"] = "1"
            if no_bytecode:
                e["PYTHONDONTWRITEBYTECODE"] = "1"
                e["PYTHONPYCACHEPREFIX"] = str(Path(tmp) / "pycache")
            r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            p = subprocess.run(cmd, capture_output=True, env=e, cwd=cwd)
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            if p.returncode != 0:
                raise RuntimeError(f"{' '.join(map(str, cmd))} failed: {p.stderr.decode(errors='replace')[-500:]}")
            ts.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
    return float(np.median(ts))


def _load() -> str:
    return "load {:.2f} {:.2f} {:.2f}".format(*os.getloadavg())


def _room(tmp: Path, env) -> dict:
    """A calibration of the bundled data and a 1 s room recording; the command lines of table 1."""
    py = [sys.executable, "-c", _PSDCAL]
    calib = tmp / "calib.json"
    subprocess.run([*py, "calibrate", str(DATA / "default_points.csv"), "-t", str(DATA / "default_template.csv"),
                    "-o", str(calib), "-q"], check=True, env=env, capture_output=True)
    subprocess.run([*py, "simulate-recording", "room", "--sensors", "2", "--anchors", "5", "--calib", str(calib),
                    "--duration-s", "1", "-o", str(tmp / "room")], check=True, env=env, capture_output=True)
    room = tmp / "room"
    carriers = ["--carrier-hz", "1000", "--carrier-hz", "1150"]
    return {
        "locate, 1 sensor (--calib), 2 carriers": ["locate", str(room / "s1.npy"), "--calib", str(calib),
                                                   "--rate-hz", "20000", *carriers, "-o", str(tmp / "l1.csv"),
                                                   "--force"],
        "locate, 2 sensors (--sensors), 2 carriers": ["locate", "--sensors", str(room / "sensors.json"),
                                                      "--rate-hz", "20000", *carriers, "-o", str(tmp / "l2.csv"),
                                                      "--force"],
        "aoa (150 rows of locate's output)": ["aoa", str(tmp / "l1.csv"), "--calib", str(calib), "-o",
                                              str(tmp / "a.csv"), "--force"],
        "pose (5 emitters)": ["pose", str(room / "s1.npy"), "--rate-hz", "20000", "--calib", str(calib),
                              "--emitters", str(room / "emitters.csv"), "--name", "s1", "-o", str(tmp / "p.json"),
                              "--force"],
    }


def startup_table(repeats: int, env) -> list[tuple[str, str, str]]:
    py = sys.executable
    rows = []
    t_pass = cpu_seconds([py, "-c", "pass"], repeats, env)
    t_help = cpu_seconds([py, "-c", _PSDCAL, "--help"], repeats, env)
    t_help_src = cpu_seconds([py, "-c", _PSDCAL, "--help"], repeats, env, fresh_src=True)
    t_help_none = cpu_seconds([py, "-c", _PSDCAL, "--help"], repeats, env, no_bytecode=True)
    t_click_none = cpu_seconds([py, "-c", "import click"], repeats, env, no_bytecode=True)
    rows.append(("python -c pass (the interpreter alone)", t_pass, None))
    rows.append(("psdcal --help (bytecode cached): the reference", t_help, None))
    rows.append(("psdcal --help without psdcal's bytecode (fresh clone)", t_help_src, None))
    rows.append(("psdcal --help without any bytecode (stdlib and click compiled too)", t_help_none, None))
    rows.append(("python -c 'import click' without any bytecode (that floor)", t_click_none, None))
    with tempfile.TemporaryDirectory() as tmp:
        cmds = _room(Path(tmp), env)
        cmds_list = list(cmds.items())
        cmds_list.insert(2, cmds_list.pop(2))  # aoa reads the first locate's output: keep it after
        for name, args in cmds_list:
            t = cpu_seconds([py, "-c", _PSDCAL, *args], repeats, env)
            rows.append((f"{name}, 1 s recording", t, t - t_help))
        for name, args in cmds_list:
            t = cpu_seconds([py, "-c", _FORCED, *args], repeats, env)
            rows.append((f"{name}, compiled kernels forced", t, t - t_help))
    return [(n, f"{t:.3f}", "" if d is None else f"{d:+.3f}") for n, t, d in rows]


def calibrate_table(repeats: int, env) -> list[tuple[str, str, str]]:
    py = sys.executable
    pts, tpl = str(DATA / "default_points.csv"), str(DATA / "default_template.csv")
    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "c.json")
        try:
            import cv2  # noqa: F401

            t_cv = cpu_seconds([py, "-c", _OPENCV, tpl, pts, out], repeats, env)
        except ImportError:
            t_cv = float("nan")
        rows = [
            ("psdcal --help", cpu_seconds([py, "-c", _PSDCAL, "--help"], repeats, env)),
            ("psdcal calibrate (bundled data)", cpu_seconds(
                [py, "-c", _PSDCAL, "calibrate", pts, "-t", tpl, "-o", out, "-q", "--force"], repeats, env)),
            ("psdcal calibrate, compiled kernels forced", cpu_seconds(
                [py, "-c", _FORCED, "calibrate", pts, "-t", tpl, "-o", out, "-q", "--force"], repeats, env)),
            ("OpenCV script (same data, reads CSV, writes JSON)", t_cv),
        ]
    return [(n, f"{t:.3f}", f"{t / t_cv:.2f}") for n, t in rows]


def clone_table() -> list[tuple[str, str]]:
    """``git clone`` + ``python3 tasks.py demo``: wall-clock seconds of each phase (``tasks.py`` prints them).

    The demo's table is out when its last line (``wrote demo_out/calibration.json``) is.
    """
    with tempfile.TemporaryDirectory() as tmp:
        dest = Path(tmp) / "psdcal"
        t0 = time.perf_counter()
        subprocess.run(["git", "clone", "-q", str(ROOT), str(dest)], check=True)
        t_clone = time.perf_counter() - t0
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
        with tempfile.TemporaryFile("w+") as err:
            proc = subprocess.Popen(["python3", "tasks.py", "demo"], cwd=dest, stdout=subprocess.PIPE, stderr=err,
                                    text=True, env=env)
            t_table = None
            for line in proc.stdout:
                if t_table is None and line.startswith("wrote ") and "calibration.json" in line:
                    t_table = time.perf_counter() - t0
            rc = proc.wait()
            t_all = time.perf_counter() - t0
            err.seek(0)
            log = err.read()
        if rc != 0 or t_table is None:
            raise RuntimeError(f"tasks.py demo failed: {log[-800:]}")
        phases = re.findall(r"psdcal set-up: ([a-z ,+]+?) ([0-9.]+) s", log)
    rows = [("git clone", f"{t_clone:.1f}")]
    rows += [(f"{k} (tasks.py)", v) for k, v in phases]
    rows.append(("clone to the demo's table", f"{t_table:.1f}"))
    rows.append(("clone to the end of `tasks.py demo` (kernels compiled)", f"{t_all:.1f}"))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--clone", action="store_true", help="also time a fresh clone to the demo's table (minutes)")
    a = ap.parse_args(argv)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    subprocess.run([sys.executable, "-c", "from psdcal.study.warmup import warm_up; warm_up(False)"], check=True, env=env)
    print(f"psdcal calibrate against an OpenCV script, median of {a.repeats}, process CPU seconds; {_load()} "
          f"({os.cpu_count()} CPUs)")
    print_table(("command", "CPU s", "ratio to OpenCV"), calibrate_table(a.repeats, env), a.markdown)
    print()
    print(f"fresh processes, median of {a.repeats}, process CPU seconds; {_load()}")
    print_table(("command", "CPU s", "above psdcal --help"), startup_table(a.repeats, env), a.markdown)
    if a.clone:
        print()
        print(f"fresh clone to the demo's table (wall-clock seconds, {os.cpu_count()} CPUs); {_load()}")
        rows = clone_table()
        print(f"after: {_load()}")
        print_table(("phase", "seconds"), rows, a.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
