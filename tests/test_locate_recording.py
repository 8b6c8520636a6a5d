"""Recording readers (psdcal.signal.recording) and constant-memory streaming."""
from __future__ import annotations

import sys
import tracemalloc

import numpy as np
import pytest

from _locate_sim import amplitudes, calib_dict, model, signals, spot_for_angles
from psdcal.errors import InputError
from psdcal.measure.locate import LocateConfig, locate_to_csv
from psdcal.signal.recording import MissingDependencyError, open_recording
from psdcal.measure.sensor_model import SensorModel

RATE = 50_000.0


@pytest.fixture(scope="module")
def sig():
    return signals(RATE, 5_003, [(np.array([0.2, 0.3, 0.25, 0.15]), 1000.0, 0.0)], noise=1e-3)


def _collect(rec, chunk=1_000):
    parts = list(rec.chunks(chunk))
    assert all(b.shape[0] == 4 and b.dtype == np.float64 for _, b in parts)
    t0 = [t for t, _ in parts]
    return np.concatenate([b for _, b in parts], axis=1), t0


def _write_csv(path, x, t=None, order=("vx1", "vx2", "vy1", "vy2")):
    cols = list(order) + (["t_s"] if t is not None else [])
    rows = [",".join(cols)]
    idx = {"vx1": 0, "vx2": 1, "vy1": 2, "vy2": 3}
    for i in range(x.shape[1]):
        vals = [repr(float(x[idx[c], i])) for c in order] + ([repr(float(t[i]))] if t is not None else [])
        rows.append(",".join(vals))
    path.write_text("\n".join(rows) + "\n")


def test_npy_both_layouts(tmp_path, sig):
    np.save(tmp_path / "a.npy", sig.T)
    np.save(tmp_path / "b.npy", sig.astype(np.float32))
    for name, tol in (("a.npy", 0), ("b.npy", 1e-6)):
        rec = open_recording(tmp_path / name, RATE)
        assert rec.n_samples == sig.shape[1] and rec.rate_hz == RATE
        x, t0 = _collect(rec)
        np.testing.assert_allclose(x, sig, atol=tol)
        np.testing.assert_allclose(t0, np.arange(0, sig.shape[1], 1_000) / RATE)


def test_csv_with_and_without_time(tmp_path, sig):
    t = 2.0 + np.arange(sig.shape[1]) / RATE
    _write_csv(tmp_path / "t.csv", sig, t, order=("vy2", "vx1", "vx2", "vy1"))
    rec = open_recording(tmp_path / "t.csv")
    assert rec.rate_hz == pytest.approx(RATE) and rec.t0_s == 2.0
    x, t0 = _collect(rec, 777)
    np.testing.assert_allclose(x, sig, rtol=1e-15)
    assert t0[1] == pytest.approx(2.0 + 777 / RATE)
    _write_csv(tmp_path / "n.csv", sig[:, :100])
    with pytest.raises(InputError, match="rate-hz"):
        open_recording(tmp_path / "n.csv")
    with pytest.raises(InputError, match="disagrees"):
        open_recording(tmp_path / "t.csv", 1000.0)
    # time stamps rounded to 1 us at 48 kS/s: the rate still comes out right
    t48 = np.round(np.arange(5000) / 48_000.0, 6)
    _write_csv(tmp_path / "r.csv", np.ones((4, 5000)), t48)
    assert open_recording(tmp_path / "r.csv", 48_000.0).rate_hz == pytest.approx(48_000.0, rel=1e-5)


def test_hdf5_layouts(tmp_path, sig):
    h5py = pytest.importorskip("h5py")
    with h5py.File(tmp_path / "a.h5", "w") as f:
        for i, n in enumerate(("vx1", "vx2", "vy1", "vy2")):
            f[n] = sig[i]
        f.attrs["rate_hz"] = RATE
    with h5py.File(tmp_path / "b.hdf5", "w") as f:
        g = f.create_group("daq")
        ds = g.create_dataset("signals", data=sig.T)
        ds.attrs["sample_rate"] = RATE
    rec = open_recording(tmp_path / "a.h5")
    assert rec.rate_hz == RATE
    np.testing.assert_array_equal(_collect(rec)[0], sig)
    rec = open_recording(tmp_path / "b.hdf5", group="daq")
    np.testing.assert_array_equal(_collect(rec, 4096)[0], sig)
    with pytest.raises(InputError, match="no dataset 'zz'"):
        open_recording(tmp_path / "b.hdf5", group="daq", dataset="zz")


def test_tdms(tmp_path, sig):
    nptdms = pytest.importorskip("nptdms")
    with nptdms.TdmsWriter(tmp_path / "a.tdms") as w:
        # two segments, as a DAQ writes them
        for part in (sig[:, :3000], sig[:, 3000:]):
            w.write_segment([nptdms.ChannelObject("psd", n, part[i], properties={"wf_increment": 1 / RATE})
                             for i, n in enumerate(("ax1", "ax2", "ay1", "ay2"))])
    rec = open_recording(tmp_path / "a.tdms", channels=("ax1", "ax2", "ay1", "ay2"))
    assert rec.rate_hz == pytest.approx(RATE) and rec.n_samples == sig.shape[1]
    np.testing.assert_array_equal(_collect(rec, 2048)[0], sig)
    with pytest.raises(InputError, match=r"a\.tdms, field 'vx1': no group holds the channels"):
        open_recording(tmp_path / "a.tdms")
    (tmp_path / "bad.tdms").write_bytes(b"not a tdms file at all")
    with pytest.raises(InputError, match="not a readable TDMS"):
        open_recording(tmp_path / "bad.tdms", RATE)


def test_bad_recordings(tmp_path, sig, monkeypatch):
    (tmp_path / "a.wav").write_bytes(b"RIFF")
    with pytest.raises(InputError, match="unknown recording format '.wav'"):
        open_recording(tmp_path / "a.wav", RATE)
    with pytest.raises(InputError, match="not found"):
        open_recording(tmp_path / "none.npy", RATE)
    with pytest.raises(InputError, match="rate-hz"):
        np.save(tmp_path / "a.npy", sig.T)
        open_recording(tmp_path / "a.npy")
    (tmp_path / "m.csv").write_text("vx1,vx2,vy1\n1,2,3\n")
    with pytest.raises(InputError, match=r"m\.csv:1.*vy2"):
        open_recording(tmp_path / "m.csv", RATE)
    x = sig[:, :50].copy()
    x[2, 17] = np.nan
    _write_csv(tmp_path / "nan.csv", x)
    with pytest.raises(InputError, match=r"nan\.csv:19, field 'vy1'.*sample 17"):
        _collect(open_recording(tmp_path / "nan.csv", RATE), 10)
    np.save(tmp_path / "nan.npy", x.T)
    with pytest.raises(InputError, match="sample 17 of channel vy1"):
        _collect(open_recording(tmp_path / "nan.npy", RATE), 10)
    (tmp_path / "bad.csv").write_text("vx1,vx2,vy1,vy2\n1,2,3,4\n1,2,x,4\n")
    with pytest.raises(InputError, match=r"bad\.csv:3"):
        _collect(open_recording(tmp_path / "bad.csv", RATE))
    # a missing optional package: a one-line message saying what to install
    (tmp_path / "a.h5").write_bytes(b"")
    monkeypatch.setitem(sys.modules, "h5py", None)
    with pytest.raises(MissingDependencyError, match=r"install psdcal\[hdf5\]"):
        open_recording(tmp_path / "a.h5", RATE)
    monkeypatch.setitem(sys.modules, "nptdms", None)
    (tmp_path / "a.tdms").write_bytes(b"")
    with pytest.raises(MissingDependencyError, match=r"install psdcal\[tdms\]"):
        open_recording(tmp_path / "a.tdms", RATE)


def test_recording_10x_the_memory_budget_streams_in_constant_memory(tmp_path):
    """A ~24 MB recording through the whole pipeline with a 2 MB working budget."""
    budget = 2 * 1024 * 1024
    rate = 125_000.0
    n = 768_000  # 4 channels x 8 bytes x n = 24.6 MB: 12x the budget
    m = model()
    d = spot_for_angles(m, np.radians([[8.0, -4.0], [-12.0, 6.0]]))
    path = tmp_path / "big.npy"
    mm = np.lib.format.open_memmap(path, mode="w+", dtype=np.float64, shape=(n, 4))
    step = 64_000
    rng = np.random.default_rng(0)
    for i in range(0, n, step):
        mm[i : i + step] = signals(rate, step, [(amplitudes(m, d[0]), 1000.0, 0.2), (amplitudes(m, d[1]), 1300.0, 1.0)],
                                   t0_s=i / rate, noise=2e-3, rng=rng).T
    mm.flush()
    del mm
    assert path.stat().st_size > 10 * budget
    rec = open_recording(path, rate)
    config = LocateConfig(carriers_hz=(1000.0, 1300.0), window_s=0.01, distance_mm=5000.0, chunk_samples=16_384)
    # once untraced: loading the compiled kernels (numba's objects, once per process) is not streaming memory
    locate_to_csv(rec, m, tmp_path / "warm.csv", config)
    seen = []
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        summary = locate_to_csv(rec, m, tmp_path / "out.csv", config,
                                progress=lambda k: seen.append(tracemalloc.get_traced_memory()[0] - base))
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert summary.n_samples == n and summary.n_rows == 2 * (n // 1250)
    assert peak < budget, f"peak {peak} B over the {budget} B budget"
    # no growth: the memory held after the last chunk is that after the first ones
    assert seen[-1] - seen[2] < 64 * 1024
    out = np.genfromtxt(tmp_path / "out.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    z = (out["alpha_x_deg"][::2] - 8.0) / out["sigma_alpha_x_deg"][::2]
    assert np.all(np.abs(z) < 3)


def test_locate_is_atomic(tmp_path):
    m = SensorModel.from_dict(calib_dict())
    (tmp_path / "out.csv").write_text("keep me\n")
    x = signals(RATE, 2000, [(np.array([0.2, 0.3, 0.25, 0.15]), 1000.0, 0.0)])
    x[1, 1500] = np.nan
    np.save(tmp_path / "r.npy", x.T)
    with pytest.raises(InputError, match="sample 1500"):
        locate_to_csv(open_recording(tmp_path / "r.npy", RATE), m, tmp_path / "out.csv",
                      LocateConfig(carriers_hz=(1000.0,), chunk_samples=1000))
    assert (tmp_path / "out.csv").read_text() == "keep me\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.csv", "r.npy"]
