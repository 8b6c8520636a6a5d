"""`psdcal locate/amplitudes --format npy`: the same rows as the CSV output, at full precision."""
from __future__ import annotations

import json

import numpy as np

from _locate_sim import amplitudes, calib_dict, signals, spot_for_angles
from psdcal.cli import main
from psdcal.measure.sensor_model import SensorModel

RATE = 125_000.0


def _recording(tmp_path):
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps(calib_dict()))
    m = SensorModel.load(calib)
    d = spot_for_angles(m, np.radians([[10.0, -3.0], [-7.0, 12.0]]))
    x = signals(RATE, 25_000, [(amplitudes(m, d[0]), 1000.0, 0.0), (amplitudes(m, d[1]), 1300.0, 1.0)], noise=2e-3)
    np.save(tmp_path / "rec.npy", x.T)
    return calib


def test_locate_npy_equals_csv(tmp_path):
    calib = _recording(tmp_path)
    base = ["locate", str(tmp_path / "rec.npy"), "--calib", str(calib), "--rate-hz", "125000", "--carrier-hz", "1000",
            "--carrier-hz", "1300", "--distance-mm", "5000", "--window-s", "0.02"]
    assert main(base + ["-o", str(tmp_path / "out.csv")]) == 0
    assert main(base + ["--format", "npy", "-o", str(tmp_path / "out.npy")]) == 0
    csv = np.genfromtxt(tmp_path / "out.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    arr = np.load(tmp_path / "out.npy", allow_pickle=False)
    assert arr.dtype.names == csv.dtype.names and len(arr) == len(csv) == 20
    assert list(arr["emitter"]) == list(csv["emitter"])
    for name in arr.dtype.names:
        if name != "emitter":
            assert arr[name].dtype == np.float64
            np.testing.assert_allclose(arr[name], csv[name], rtol=1e-9, atol=1e-12, err_msg=name)


def test_amplitudes_npy_equals_csv(tmp_path):
    _recording(tmp_path)
    base = ["amplitudes", str(tmp_path / "rec.npy"), "--rate-hz", "125000", "--carrier-hz", "1000", "--window-s", "0.02"]
    assert main(base + ["-o", str(tmp_path / "a.csv")]) == 0
    assert main(base + ["--format", "npy", "-o", str(tmp_path / "a.npy")]) == 0
    csv = np.genfromtxt(tmp_path / "a.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    arr = np.load(tmp_path / "a.npy", allow_pickle=False)
    assert len(arr) == len(csv) > 0
    np.testing.assert_allclose(arr["vx1"], csv["vx1"], rtol=1e-9)
