"""Start-up: light commands import no heavy module; one-shot small calibrations skip the kernels.

Times are in benchmarks/bench_startup.py; these tests check the mechanisms
behind them in fresh interpreters.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
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



def test_unknown_command_suggestions_as_with_every_command_loaded():
    """`psdcal locat` suggests 'locate' although no command module is loaded (click >= 8.4 suggests)."""
    for name in ("locat", "simulat", "no-such-command", "calibrat-directions"):
        fresh, loaded = (subprocess.run([sys.executable, "-c", f"from psdcal.cli import main, _register\n{pre}"
                                         f"raise SystemExit(main([{name!r}]))"],
                                        capture_output=True, text=True).stderr
                         for pre in ("", "_register()\n"))
        assert fresh == loaded and fresh.startswith("psdcal: error: No such command"), (fresh, loaded)

# ----------------------------------------------------------------- cold processes: no numba for small work
def _probe(code: str) -> dict:
    probe = code + "\nimport sys, json\nfrom psdcal import _jit\nprint(json.dumps({'numba': 'numba' in sys.modules, " \
                   "'scipy': 'scipy' in sys.modules, 'mode': _jit._MODE}))"
    out = subprocess.run([sys.executable, "-c", probe], check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def test_deferred_kernels_import_no_numba_until_called():
    from psdcal import _jit

    got = _probe("import psdcal.measure._csvtext, psdcal.measure.locate")
    assert got["numba"] is False
    if not _jit.enabled():
        pytest.skip("numba disabled")
    got = _probe("import numpy as np\nfrom psdcal.measure._csvtext import rows_text, format_rows\n"
                 "rows_text([np.arange(3.0)])\nimport psdcal.measure._csvtext as m\n"
                 "assert type(m.format_rows).__module__.startswith('numba'), type(m.format_rows)\n"
                 "assert type(m._scaled).__module__.startswith('numba'), type(m._scaled)")
    assert got["numba"] is True


def test_deferred_kernel_equals_its_python_function():
    from psdcal import _jit

    def poly(x, n):  # pragma: no cover - compiled
        s = 0.0
        for k in range(n):
            s = s * x + k
        return s

    lazy = _jit.deferred_njit(poly)
    assert lazy(1.5, 7) == poly(1.5, 7)
    if _jit.enabled():
        assert lazy.py_func is poly


def _short_recording(tmp_path):
    from _locate_sim import amplitudes, calib_dict, signals, spot_for_angles
    from psdcal.measure.sensor_model import SensorModel

    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps(calib_dict()))
    m = SensorModel.load(calib)
    d = spot_for_angles(m, np.radians(np.array([[10.0, -3.0], [-7.0, 12.0]])))
    x = signals(50_000.0, 50_000, [(amplitudes(m, d[0]), 1000.0, 0.0), (amplitudes(m, d[1]), 1300.0, 1.0)],
                noise=2e-3, rng=np.random.default_rng(4))
    np.save(tmp_path / "rec.npy", x.T)
    return calib, tmp_path / "rec.npy"



def test_short_locate_aoa_pose_import_no_numba_and_match_the_compiled_path(tmp_path):
    """A 1 s recording: locate and aoa take the numpy path in a fresh process (numba never imported), and
    write what the compiled kernels write (angles to 1e-9 relative; the CSV writer is byte-exact by design)."""
    from psdcal import _jit

    calib, rec = _short_recording(tmp_path)
    loc = ["locate", str(rec), "--calib", str(calib), "--rate-hz", "50000", "--carrier-hz", "1000",
           "--carrier-hz", "1300", "-o", str(tmp_path / "numpy.csv")]
    aoa = ["aoa", str(tmp_path / "numpy.csv"), "--calib", str(calib), "--sigma-d-mm", "0.001",
           "-o", str(tmp_path / "aoa_numpy.csv")]
    got = _probe(f"from psdcal.cli import main\nassert main({loc!r}) == 0\nassert main({aoa!r}) == 0")
    assert got == {"numba": False, "scipy": False, "mode": "auto"}
    if not _jit.enabled():
        pytest.skip("numba disabled: no compiled path to compare")
    forced = ("from psdcal import _jit\n_jit.set_mode = _jit.set_mode_for = lambda *a: None\n"
              "from psdcal.cli import main\n"
              f"assert main({[*loc[:-1], str(tmp_path / 'jit.csv')]!r}) == 0\n"
              f"assert main({[*aoa[:1], str(tmp_path / 'jit.csv'), *aoa[2:-1], str(tmp_path / 'aoa_jit.csv')]!r}) == 0")
    got = _probe(forced)
    assert got["numba"] is True and got["mode"] == "always"
    for a, b in (("numpy.csv", "jit.csv"), ("aoa_numpy.csv", "aoa_jit.csv")):
        ta, tb = (np.genfromtxt(tmp_path / f, delimiter=",", names=True, dtype=None, encoding="utf-8") for f in (a, b))
        assert ta.dtype.names == tb.dtype.names and len(ta) == len(tb) > 50
        for name in ta.dtype.names:
            if ta[name].dtype.kind == "f":
                np.testing.assert_allclose(ta[name], tb[name], rtol=1e-9, atol=1e-12, err_msg=name)
            else:
                assert (ta[name] == tb[name]).all(), name


def test_one_shot_mode_follows_the_size_of_the_whole_run(monkeypatch):
    from psdcal import _jit

    _jit.set_mode_for(1000)
    assert _jit._MODE == "auto"
    _jit.set_mode_for(min(_jit.AUTO_MIN_ANGLES, _jit.AUTO_MIN_CSV_ROWS))
    assert _jit._MODE == "always"
    _jit.set_mode_for(None)  # size unknown (a stream): the kernels, loaded once
    assert _jit._MODE == "always"
    if not _jit.enabled():
        return
    monkeypatch.setattr(_jit, "_MODE", "auto")
    monkeypatch.setattr(_jit, "_numba", None)
    assert not _jit.use_compiled(_jit.AUTO_MIN_ANGLES - 1, _jit.AUTO_MIN_ANGLES)
    assert _jit.use_compiled(_jit.AUTO_MIN_ANGLES, _jit.AUTO_MIN_ANGLES)
    monkeypatch.setattr(_jit, "_numba", object())  # numba loaded already: the kernels cost little more
    assert _jit.use_compiled(1, _jit.AUTO_MIN_ANGLES)


def test_locate_mode_counts_windows_emitters_and_recordings(monkeypatch):
    from types import SimpleNamespace

    from psdcal import _jit
    from psdcal.cli import locate_cmd

    seen = []
    monkeypatch.setattr(_jit, "set_mode_for", seen.append)
    cfg = SimpleNamespace(window_s=0.01, carriers_hz=(1000.0, 1300.0), n_emitters=None, emitters=None)
    rec = SimpleNamespace(n_samples=125_000 * 60, rate_hz=125_000.0, path="x.npy")
    locate_cmd._one_shot_mode([rec, rec], cfg)
    assert seen == [60 * 100 * 2 * 2]


def test_warm_up_parts():
    from psdcal.study.warmup import PARTS, warm_up

    assert PARTS == ("calibration", "measure")
    with pytest.raises(ValueError):
        warm_up(False, part="everything")
