"""Start-up: light commands import no heavy module; one-shot small calibrations skip the kernels.

Times are in benchmarks/bench_startup.py; these tests check the mechanisms
behind them in fresh interpreters.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parent.parent / "src" / "psdcal" / "data"


def _modules_after(code: str) -> list[str]:
    probe = code + "\nimport sys, json\nprint(json.dumps(sorted(m for m in ('numba', 'scipy', 'matplotlib', 'cv2') if m in sys.modules)))"
    out = subprocess.run([sys.executable, "-c", probe], check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def test_help_imports_no_heavy_module():
    assert _modules_after("from psdcal.cli import main\nmain(['--help'])\nmain(['calibrate', '--help'])") == []


def test_small_cli_calibration_stays_on_the_numpy_path(tmp_path):
    code = (f"from psdcal.cli import main\nassert main(['calibrate', {str(DATA / 'default_points.csv')!r}, '-t', "
            f"{str(DATA / 'default_template.csv')!r}, '-o', {str(tmp_path / 'c.json')!r}, '-q']) == 0")
    assert _modules_after(code) == []
    assert json.loads((tmp_path / "c.json").read_text())["intrinsics"]["f_mm"] > 0


def test_auto_mode_uses_kernels_for_large_problems_only(monkeypatch):
    from psdcal import _jit

    if not _jit.enabled():
        pytest.skip("numba disabled")
    monkeypatch.setattr(_jit, "_MODE", "auto")
    monkeypatch.delitem(sys.modules, "psdcal.calibration._image_kernel", raising=False)
    assert not _jit.use_compiled(100)
    assert _jit.use_compiled(_jit.AUTO_MIN_OBSERVATIONS)
    monkeypatch.setattr(_jit, "_MODE", "always")
    assert _jit.use_compiled(1)
    with pytest.raises(ValueError):
        _jit.set_mode("sometimes")


def test_cache_check_and_first_compile_notice(tmp_path, monkeypatch, capsys):
    import numpy as np

    from psdcal import _jit
    from psdcal.cli import calibrate_cmd

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))  # an empty cache: nothing compiled there
    assert not _jit.cache_is_warm()
    if not _jit.enabled():
        pytest.skip("numba disabled")
    monkeypatch.setattr(_jit, "_MODE", "always")
    monkeypatch.setattr(_jit, "set_mode", lambda mode: None)  # keep "always": the kernels are wanted
    calibrate_cmd._kernels_for(np.zeros((2, 3, 2)), quiet=False)
    assert "compiling the numerical kernels" in capsys.readouterr().err
    calibrate_cmd._kernels_for(np.zeros((2, 3, 2)), quiet=True)
    assert capsys.readouterr().err == ""


def test_help_imports_neither_numpy_nor_a_command_module():
    probe = ("from psdcal.cli import main\nmain(['--help'])\nimport sys, json\n"
             "print(json.dumps(sorted(m for m in sys.modules if m == 'numpy' or m.startswith('psdcal.cli.') "
             "or m.startswith('importlib.metadata'))))")
    out = subprocess.run([sys.executable, "-c", probe], check=True, capture_output=True, text=True).stdout
    assert json.loads(out.strip().splitlines()[-1]) == []


def test_a_command_imports_only_its_own_module():
    probe = ("from psdcal.cli import main\nmain(['gains', '--help'])\nimport sys, json\n"
             "print(json.dumps(sorted(m for m in sys.modules if m.startswith('psdcal.cli.'))))")
    out = subprocess.run([sys.executable, "-c", probe], check=True, capture_output=True, text=True).stdout
    assert json.loads(out.strip().splitlines()[-1]) == ["psdcal.cli.gains_cmd"]


def test_static_command_table_matches_the_commands():
    """LAZY_COMMANDS (what `psdcal --help` lists without importing) is what the command modules define."""
    import click

    from psdcal.cli import LAZY_COMMANDS, _register, cli

    _register()
    assert set(LAZY_COMMANDS) == set(cli.commands)
    for name, (module, _) in LAZY_COMMANDS.items():
        cmd = cli.commands[name]
        assert cmd.callback.__module__ == f"psdcal.cli.{module}", name
        stand_in = click.Command(name, help=LAZY_COMMANDS[name][1])
        assert not cmd.hidden and not cmd.deprecated and cmd.short_help is None, name
        for limit in (10, 25, 45, 60, 72, 80, 100, 200):
            assert stand_in.get_short_help_str(limit) == cmd.get_short_help_str(limit), (name, limit)


def test_lazy_help_listing_equals_the_loaded_one():
    """`psdcal --help` with nothing imported prints what the fully loaded group prints (several widths)."""
    import os

    for columns in ("60", "80", "200"):
        env = {**os.environ, "COLUMNS": columns}
        fresh, loaded = (subprocess.run([sys.executable, "-c", f"from psdcal.cli import main, _register\n{pre}main(['--help'])"],
                                        check=True, capture_output=True, text=True, env=env).stdout
                         for pre in ("", "_register()\n"))
        assert "Commands:" in fresh and "  locate " in fresh
        assert fresh == loaded, columns
