"""Usage errors are one line; the kernel cache never crashes an import."""
import subprocess
import sys

import pytest

from psdcal.cli import main


@pytest.mark.parametrize("args, frag", [
    (["simulate", "--bogus"], "--bogus"),
    (["simulate", "--images", "1"], "--images"),
    (["calibrate", "."], "directory"),
    (["calibrate"], "POINTS"),
    (["calibrate", "p.csv", "-t", "t.csv", "--radial", "9"], "--radial"),
    (["calibrate", "p.csv", "-t", "t.csv", "--reject", "-1"], "--reject"),
    (["reproduce", "--workers", "0"], "--workers"),
    (["no-such-command"], "no-such-command"),
    (["locate", "r.npy", "--rate-hz", "abc", "-o", "x.csv"], "--rate-hz"),
])
def test_usage_error_is_one_line(args, frag, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code = main(args)
    out, err = capsys.readouterr()
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("psdcal: error:") and frag in lines[0], err
    assert "Usage:" not in err and "Try " not in err


def test_no_cache_locator_falls_back_to_an_uncached_compile():
    from psdcal import _jit

    if not _jit.enabled():
        pytest.skip("numba disabled")
    ns = {"njit": _jit.njit}
    exec("@njit\ndef twice(x):\n    return 2.0 * x\n", ns)  # no source file: numba has no cache locator
    assert ns["twice"](3.5) == 7.0


def test_unwritable_cache_dir_does_not_crash_the_import(tmp_path):
    code = ("from psdcal.calibration._straightness import *\nimport psdcal._jit as j\n"
            "from psdcal.cli import main\nprint('ok')")
    env = {"NUMBA_CACHE_DIR": "/dev/null/cache", "HOME": "/nonexistent", "PATH": "/usr/bin:/bin"}
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "ok" in p.stdout, p.stderr[-2000:]
