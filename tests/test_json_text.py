"""psdcal.io.json_text (the writer of every JSON file) is json.dumps(..., indent=2) byte for byte, NaN as null."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from psdcal.io import json_text, write_json

DATA = Path(__file__).resolve().parent / "data"


def _nulls(o):
    """NaN and infinities as None (written out here, independently of the module's own helper)."""
    if isinstance(o, float):
        return None if math.isnan(o) or math.isinf(o) else o
    if isinstance(o, dict):
        return {k: _nulls(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_nulls(v) for v in o]
    return o


CASES = [
    {"a": [1.0, float("nan"), float("inf"), -0.0, 1e-300, 5e20, 1, True, False, None, "\u00e9\n\"x"], "b": {}, "c": [],
     "d": [[1.5, 2], [3.0]], "e": (1.0, 2.0), "f": {"g": [float("-inf")]}, "h": np.float64(2.5), "i": [np.float64(1.0)]},
    {"k": 1, 1: 2, None: 3},
    [], {}, 3.0, float("nan"), "s", None, True, 7, [[0, 1, 0.25, -1e-9]] * 3, {"rows": [[1, 2.0, None, "x", [], {}]]},
    # tables of numeric rows (written a row at a time) and what leaves that path: NaN, bools, empty or nested rows
    [[1.0, 2], [3, -4.5e-300]], [[1.0, float("nan")], [2, 3.0]], [[1.0, float("-inf")]], [[1, True], [2, 3]],
    [[1.0], []], [[1.0], [[2.0]]], [[[1.0, 2.0], [3.0, 4.0]], [[5.0, 6.0]]], {"t": [[0, 0, 1e-3, -2e-3]] * 4},
]


@pytest.mark.parametrize("obj", CASES)
def test_json_text_is_the_json_modules_indented_text(obj):
    assert json_text(obj) == json.dumps(_nulls(obj), indent=2)


def test_json_text_of_a_calibration_file_and_a_refused_value(tmp_path):
    from psdcal.calibration.core import calibrate
    from psdcal.io import read_points, read_template

    ids, T = read_template(DATA / "zhang1998" / "template.csv")
    pts = read_points(DATA / "zhang1998" / "points.csv", ids, sensor_mm=(6.4, 4.8)).points_mm
    d = calibrate(T, pts, aspect=True, sensor_mm=(6.4, 4.8)).to_dict()
    write_json(tmp_path / "c.json", d)
    assert (tmp_path / "c.json").read_text() == json.dumps(_nulls(d), indent=2) + "\n"
    with pytest.raises(TypeError):
        json_text({"x": [np.int64(3)]})  # what json.dumps refuses is refused
