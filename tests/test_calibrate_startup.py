"""What a fresh `psdcal calibrate` loads and starts on a small real set, and that the shortcuts change no output.

The CPU time itself is measured by benchmarks/bench_default.py (its
command-line table); these tests check the mechanisms behind it: no numba,
scipy, matplotlib or rich (the table is written without rich when the output
is not styled), no difflib (click's suggestions for a short option), no
tempfile, OpenSSL's hashlib or the priors module; one BLAS thread from the
start unless the user set the count (and then threadpoolctl's limit, not
needed otherwise); the same bytes on stdout as rich writes.
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parent / "data"
SETS = [DATA / "zhang1998", DATA / "chessboards" / "opencv_left"]
NOT_LOADED = ("numba", "scipy", "matplotlib", "rich", "difflib", "tempfile", "_hashlib",
              "psdcal.calibration.priors", "psdcal.calibration._image_kernel", "threadpoolctl")


def _fresh(args, env=None, probe="BLAS"):
    """Run `psdcal calibrate ARGS` in a fresh interpreter: (exit status, the modules of NOT_LOADED it loaded,
    the BLAS thread variables it ran with)."""
    code = ("import sys, os, json, contextlib, io\nfrom psdcal.cli import main\n"
            f"with contextlib.redirect_stdout(io.StringIO()):\n    rc = main({[str(a) for a in args]!r})\n"
            f"print(json.dumps([rc, sorted(m for m in {NOT_LOADED!r} if m in sys.modules), "
            "[os.environ.get(v) for v in ('OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS')]]))")
    run_env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    run_env.update(env or {})
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True, env=run_env).stdout
    return json.loads(out.strip().splitlines()[-1])


@pytest.mark.parametrize("folder", SETS, ids=lambda p: p.name)
def test_a_small_real_calibration_loads_only_what_it_uses(folder, tmp_path):
    rc, loaded, blas = _fresh(["calibrate", folder / "points.csv", "-t", folder / "template.csv",
                               "-o", tmp_path / "c.json"])
    assert rc == 0 and (tmp_path / "c.json").exists()
    assert loaded == []
    assert blas == ["1", "1"]  # OpenBLAS started with one thread (its idle threads spin on the CPU)


def test_a_users_blas_thread_count_is_kept_and_priors_load_when_asked(tmp_path):
    d = SETS[0]
    rc, loaded, blas = _fresh(["calibrate", d / "points.csv", "-t", d / "template.csv", "--fix", "p2=0", "-q"],
                              env={"OPENBLAS_NUM_THREADS": "2"})
    assert rc == 0 and blas == ["2", "1"] and loaded == ["psdcal.calibration.priors", "threadpoolctl"]


def test_option_errors_are_unchanged(capsys):
    """Short options skip click's suggestions; a mistyped long option still gets them, a bad short one the error."""
    from psdcal.cli import main

    d = SETS[0]
    for args, expect in ((["--templat", "x"], "No such option '--templat'. Did you mean '--template'?"),
                         (["-x", "1"], "No such option '-x'."),
                         (["-tx", "--outpt", "y"], "No such option '--outpt'. (Did you mean one of: '--cost', '--output'?)"),
                         (["-q=1"], "No such option '-='.")):
        assert main(["calibrate", str(d / "points.csv"), *args]) == 2
        err = capsys.readouterr().err
        assert expect in err and err.count("\n") == 1, (args, err)


def test_short_options_read_as_before(tmp_path, capsys):
    from psdcal.cli import main

    d = SETS[0]
    assert main(["calibrate", str(d / "points.csv"), f"-t{d / 'template.csv'}", "-q", "-o", str(tmp_path / "a.json")]) == 0
    assert main(["calibrate", str(d / "points.csv"), "--template", str(d / "template.csv"), "--quiet",
                 "--output", str(tmp_path / "b.json")]) == 0
    a, b = (json.loads((tmp_path / n).read_text()) for n in ("a.json", "b.json"))
    for x in (a, b):
        x.pop("created")
        x["problem"].pop("files")
    assert a == b and capsys.readouterr().out == ""


def test_checksums_are_hashlibs(tmp_path):
    from psdcal.cli.calibrate_cmd import _sha256

    rng = __import__("random").Random(3)
    for n in (0, 1, 55, 56, 64, 1000, 100_003):
        data = bytes(rng.randrange(256) for _ in range(n))
        assert _sha256(data).hexdigest() == hashlib.sha256(data).hexdigest()


@pytest.mark.parametrize("folder", SETS, ids=lambda p: p.name)
def test_the_printout_is_what_rich_prints(folder, tmp_path, capsys, monkeypatch):
    """The whole `psdcal calibrate` printout, written without rich, is rich's (same run, rich forced)."""
    from psdcal.cli import main
    from psdcal.report import text

    monkeypatch.setenv("COLUMNS", "80")
    args = ["calibrate", str(folder / "points.csv"), "-t", str(folder / "template.csv"), "-o", str(tmp_path / "c.json"),
            "--force"]
    assert main(args) == 0
    plain = capsys.readouterr().out
    monkeypatch.setattr(text, "_plain_width", lambda: None)  # rich lays it out
    assert main(args) == 0
    assert plain == capsys.readouterr().out
    assert "verdict:" in plain and "┏" in plain
