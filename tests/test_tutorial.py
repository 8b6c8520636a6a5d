"""docs/tutorial.md and docs/guide/positioning.md run as written.

The runnable-documentation convention: every fenced block preceded by the
line ``<!-- run -->`` runs, in order, in one fresh folder (bash with
``-euo pipefail`` and the venv's ``psdcal`` first on PATH; python with this
interpreter).  When the project-wide runner (tests/test_docs_examples.py)
is present it covers these pages and this test steps aside.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = ["docs/tutorial.md", "docs/guide/positioning.md"]


def _blocks(text):
    return re.findall(r"^<!-- run -->\n```(bash|python)\n(.*?)^```", text, flags=re.S | re.M)


@pytest.mark.skipif((ROOT / "tests" / "test_docs_examples.py").exists(), reason="the docs runner covers the pages")
@pytest.mark.parametrize("page", PAGES)
def test_page_runs(page, tmp_path):
    blocks = _blocks((ROOT / page).read_text(encoding="utf-8"))
    assert len(blocks) >= 3
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    for lang, code in blocks:
        cmd = ["bash", "-euo", "pipefail", "-c", code] if lang == "bash" else [sys.executable, "-c", code]
        p = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, f"{page}: block failed:\n{code}\n--- stderr:\n{p.stderr[-3000:]}"
