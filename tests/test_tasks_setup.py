"""tasks.py's set-up writes the bytecode of what ``psdcal --help`` imports (click and psdcal).

pip installs the dependencies with ``--no-compile`` (most of its time otherwise); without this step
the first ``psdcal --help`` after a fresh set-up would compile click from source (about 0.3 s).
"""
from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _startup_snippet() -> str:
    tree = ast.parse((REPO / "tasks.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", None) == "_COMPILE_STARTUP":
            return ast.literal_eval(node.value)
    raise AssertionError("tasks.py has no _COMPILE_STARTUP")


def _imported_by_help(env) -> set[str]:
    code = ("import sys\nfrom psdcal.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "print('\\n'.join(m.__file__ for m in list(sys.modules.values()) if getattr(m, '__file__', None)))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    return {line for line in out.splitlines() if line.endswith(".py")}


def test_set_up_writes_the_bytecode_that_help_reads(tmp_path):
    prefix = tmp_path / "pycache"
    env = {**os.environ, "PYTHONPYCACHEPREFIX": str(prefix), "PYTHONPATH": str(REPO / "src")}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    subprocess.run([sys.executable, "-c", _startup_snippet()], env=env, check=True)
    written = {p.name.split(".")[0] + "@" + str(p.parent) for p in prefix.rglob("*.pyc")}
    needed = [f for f in _imported_by_help({**env, "PYTHONDONTWRITEBYTECODE": "1"}) if "/click/" in f or "/psdcal/" in f]
    assert any("/click/" in f for f in needed) and any("/psdcal/" in f for f in needed)
    for f in needed:
        src = Path(f).resolve()
        key = src.stem + "@" + str(prefix) + str(src.parent)
        assert key in written, f"no bytecode written for {src}"
