"""The hostile-input suite: every case exits 2 with one error line and changes no file.

Cases come from :mod:`tests.fuzz.corpus` (classes: text, calib-json,
recording, option, output, resource). Each runs ``psdcal.cli.main``
in-process in a fresh copy of the base files; the whole folder (inputs and
pre-existing outputs) must be byte-identical afterwards, with no temporary
left behind.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import stat

import pytest

from psdcal.cli import main

from . import corpus

_BASE: dict = {}


def _base(tmp_path_factory):
    if "dir" not in _BASE:
        d = tmp_path_factory.mktemp("fuzzbase")
        corpus.build_base(d, main)
        _BASE["dir"] = d
        _BASE["cases"] = {c.id: c for c in corpus.cases(d, tmp_path_factory.mktemp("h5"))}
    return _BASE["dir"]


def _cases_without_base():
    # ids and command lines are computed without the base (the calibration variants' names do not depend on it)
    import json
    import tempfile

    from psdcal.calibration.core import calibrate  # noqa: F401  (warm import outside the timed cases)

    with tempfile.TemporaryDirectory() as d:
        fake = {"intrinsics": {"f_mm": 8, "cx_mm": 0, "cy_mm": 0}, "distortion": {}, "std": {"f_mm": 0.1},
                "covariance": {"names": ["f_mm", "cx_mm"], "matrix": [[1, 0], [0, 1]]}, "sensor": {"lx_mm": 9},
                "gains": [1, 1, 1, 1], "software": {"name": "psdcal", "version": "0"}, "residuals": {},
                "sensor_id": "x"}
        with open(os.path.join(d, "calib.json"), "w") as fh:
            json.dump(fake, fh)
        return corpus.cases(d, d)


_CASES = _cases_without_base()
CASE_IDS = [c.id for c in _CASES]


def snapshot(root):
    out = {}
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        for n in dirnames + filenames:
            p = os.path.join(dirpath, n)
            rel = os.path.relpath(p, root)
            st = os.lstat(p)
            if stat.S_ISLNK(st.st_mode):
                out[rel] = ("link", os.readlink(p))
            elif stat.S_ISDIR(st.st_mode):
                out[rel] = ("dir",)
            else:
                with open(p, "rb") as fh:
                    out[rel] = ("file", hashlib.sha256(fh.read()).hexdigest(), stat.S_IMODE(st.st_mode))
    return out


def _plant(work, case):
    for name, spec in case.plant.items():
        p = os.path.join(work, name)
        os.makedirs(os.path.dirname(p), exist_ok=True)
        if spec == "DIR":
            os.makedirs(p, exist_ok=True)
        elif isinstance(spec, tuple) and spec[0] == "LINK":
            os.symlink(spec[1].replace("{b}", str(work)), p)
        else:
            with open(p, "wb") as fh:
                fh.write(spec)


def _commands():
    """Every command of the CLI (from the click group itself: a new command without a case fails)."""
    from psdcal.cli import OUTPUT_PARAMS, _register, cli

    _register()

    def walk(group, prefix=()):
        for name, cmd in group.commands.items():
            if hasattr(cmd, "commands"):
                yield from walk(cmd, (*prefix, name))
            else:
                yield (*prefix, name), any(p.name in OUTPUT_PARAMS for p in cmd.params)

    return dict(walk(cli))


def _command_of(argv):
    return tuple(argv[:2]) if argv and argv[0] in {c[0] for c in _commands() if len(c) > 1} else tuple(argv[:1])


def test_corpus_is_large_and_covers_every_command():
    assert len(CASE_IDS) >= 400
    assert len(set(CASE_IDS)) == len(CASE_IDS)
    commands = _commands()
    assert len(commands) >= 22
    classes = {cid.split("/")[0] for cid in CASE_IDS}
    assert {"text", "path", "calib-json", "recording", "option", "output", "resource"} <= classes
    by_class: dict = {}
    for c in _CASES:
        by_class.setdefault(c.cls, set()).add(_command_of(c.argv))
    covered = set().union(*by_class.values())
    missing = sorted(" ".join(c) for c in commands if c not in covered)
    assert not missing, f"commands without a hostile case: {missing}"
    # every command that reads a file gets broken files, every command that writes gets the output cases
    groups = {c[0] for c in commands if len(c) > 1}
    unknown = {c for c in covered if c[0] in ("no-such-command", "--no-such-flag") or (c[0] in groups and c not in commands)}
    assert covered - unknown <= set(commands), covered - set(commands)
    no_option = sorted(" ".join(c) for c in commands if c not in by_class["option"])
    assert not no_option, f"commands without a bad-option case: {no_option}"
    writers = {c for c, writes in commands.items() if writes}
    assert not sorted(" ".join(c) for c in writers - by_class["output"]), writers - by_class["output"]


@pytest.mark.parametrize("case_id", CASE_IDS)
def test_hostile_case(case_id, tmp_path_factory, tmp_path, capsys, monkeypatch):
    base = _base(tmp_path_factory)
    case = _BASE["cases"][case_id]
    work = tmp_path / "w"
    shutil.copytree(base, work, symlinks=True)
    _plant(work, case)
    monkeypatch.chdir(work)
    before = snapshot(work)
    argv = [a.replace("{b}", str(work)) for a in case.argv]
    capsys.readouterr()
    code = main(argv)
    out, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, (code, err, out[-500:])
    assert len(lines) == 1 and lines[0].startswith("psdcal: error:"), err
    assert "Traceback" not in err + out
    if case.names_file:
        assert case.names_file in lines[0], lines[0]
    assert snapshot(work) == before
