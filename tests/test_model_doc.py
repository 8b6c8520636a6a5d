"""docs/model.md#calibration-json documents exactly what ``psdcal calibrate`` writes.

Every top-level key of a calibration JSON written by the CLI has a row in the
table, every row names a key the tool writes, and every sub-key of the
dict-valued keys is named in its row. A new JSON field therefore needs its
line in docs/model.md.
"""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def json_table() -> dict[str, str]:
    """Key -> content cell of the calibration JSON table (a row may name several keys)."""
    text = (ROOT / "docs" / "model.md").read_text(encoding="utf-8")
    section = text.split("### Calibration JSON", 1)[1].split("\n#", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 2 or not cells[0].startswith("`"):
            continue
        for key in re.findall(r"`([^`]+)`", cells[0]):
            rows[key] = cells[1]
    return rows


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> dict:
    d = tmp_path_factory.mktemp("cal")
    cli = [sys.executable, "-m", "psdcal.cli"]
    subprocess.run([*cli, "simulate", "--lens", "lens2", "--images", "6", "--noise-mm", "0.002", "--seed", "1",
                    "-o", str(d)], check=True, capture_output=True)
    subprocess.run([*cli, "calibrate", str(d / "points.csv"), "-t", str(d / "template.csv"), "--aspect", "--sensor-id", "lab-1",
                    "-o", str(d / "c.json")], check=True, capture_output=True)
    return json.loads((d / "c.json").read_text())


def test_every_top_level_key_is_documented_and_written(written):
    table = json_table()
    assert set(written) - set(table) == set(), "keys written but not in docs/model.md#calibration-json"
    assert set(table) - set(written) == set(), "keys documented but not written"


@pytest.mark.parametrize("key", ["intrinsics", "distortion", "residuals", "model", "sensor", "stages", "problem", "software"])
def test_sub_keys_are_named_in_their_row(written, key):
    named = set(re.findall(r"`([^`]+)`", json_table()[key]))
    assert set(written[key]) - named == set(), f"{key}: sub-keys not named in docs/model.md#calibration-json"
