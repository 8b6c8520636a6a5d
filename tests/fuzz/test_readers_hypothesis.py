"""Property: every public reader, on any bytes, returns or raises the project's InputError naming the file."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from psdcal.errors import InputError, PsdcalError


def _readers():
    from psdcal.io import load_calibration, read_json, read_points, read_template
    from psdcal.measure.pose import read_emitters
    from psdcal.measure.positioning import load_sensors
    from psdcal.measure.sensor_model import SensorModel
    from psdcal.calibration.bench import read_bench_amplitudes, read_positions
    from psdcal.signal.module import read_module
    from psdcal.signal.recording import open_recording
    from psdcal.signal.stream import load_schedule

    def rec(p):
        r = open_recording(p, 20000.0)
        for _ in r.chunks(256):
            pass

    return {
        "template.csv": read_template,
        "points.csv": lambda p: read_points(p, list(range(14))),
        "calib.json": load_calibration,
        "model.json": SensorModel.load,
        "any.json": read_json,
        "schedule.csv": load_schedule,
        "sensors.json": load_sensors,
        "emitters.csv": read_emitters,
        "rec.csv": rec,
        "rec.npy": rec,
        "spots.csv": read_positions,
        "bench.csv": lambda p: read_bench_amplitudes(p, {"s0": np.zeros(2), "s1": np.ones(2)}),
        "module.txt": lambda p: read_module(p, "t,x,y,sum"),
    }


READERS = _readers()

# text that looks like the files: headers, numbers, separators, odd characters
_TOKENS = st.sampled_from(["point_id", "X_mm", "sum", "t", "Y_mm", "image_id", "x_mm", "y_mm", "vx1", "vx2", "vy1", "vy2",
                           "emitter", "t_start_s", "t_end_s", "X_m", "Y_m", "Z_m", ",", ",", "\n", "\n", "0", "1",
                           "-2.5", "1e308", "nan", "inf", "\"", "\ufeff", "\x00", "é", "{", "}", "[", "]", ":",
                           "\"intrinsics\"", "\"f_mm\"", "\"covariance\"", "\"sensors\"", "null", "true", "  "])
_CSVISH = st.lists(_TOKENS, max_size=60).map(lambda t: "".join(t).encode("utf-8", "surrogatepass"))
_CONTENT = st.one_of(st.binary(max_size=400), _CSVISH)


@pytest.mark.parametrize("name", sorted(READERS))
@settings(max_examples=30, deadline=None)
@given(data=_CONTENT)
def test_reader_raises_only_input_errors(name, data, tmp_path_factory):
    d = tmp_path_factory.mktemp("h")
    p = d / name
    p.write_bytes(data)
    try:
        READERS[name](p)
    except PsdcalError as exc:
        # bad bytes are bad input: the project's InputError (not a solver's error), naming THIS file
        assert isinstance(exc, InputError), (type(exc).__name__, str(exc))
        assert exc.path is not None and Path(exc.path).name == p.name, str(exc)
        assert str(exc).startswith(exc.path), str(exc)
        # one line a user can act on: no newline, and a message beyond the location
        assert "\n" not in str(exc) and "\r" not in str(exc), repr(str(exc))
        assert exc.detail.strip(), repr(str(exc))


@settings(max_examples=40, deadline=None)
@given(f=st.one_of(st.floats(allow_nan=True), st.text(max_size=3), st.none(), st.lists(st.floats(), max_size=2),
                   st.booleans()),
       cov=st.lists(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=2, max_size=2),
                    min_size=2, max_size=2))
def test_calibration_values_are_checked(f, cov, tmp_path_factory):
    """Any f_mm and any 2x2 covariance: accepted only when f > 0 finite and the covariance is a covariance."""
    from psdcal.io import load_calibration

    p = tmp_path_factory.mktemp("c") / "c.json"
    d = {"intrinsics": {"f_mm": f, "cx_mm": 0.0, "cy_mm": 0.0}, "covariance": {"names": ["f_mm", "cx_mm"], "matrix": cov}}
    p.write_text(json.dumps(d))
    m = np.array(cov, dtype=float)
    f_ok = isinstance(f, float) and np.isfinite(f) and f > 0
    cov_ok = bool(np.all(np.isfinite(m)) and np.allclose(m, m.T) and np.all(np.diag(m) >= 0)
                  and np.linalg.eigvalsh(0.5 * (m + m.T)).min() >= -1e-8 * max(1.0, np.abs(m).max()))
    try:
        load_calibration(p)
        accepted = True
    except InputError:
        accepted = False
    if not f_ok:
        assert not accepted
    if accepted:
        assert cov_ok
