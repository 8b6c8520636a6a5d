"""The fast locate path: rows read where they lie, the lock-in on rows, batched rows, the compiled CSV writer.

Each is checked against its reference: the channel-major lock-in
(``MultiCarrierLockin._demodulate``), the checked (4, m) reader, Python's
``%`` formatting.
"""
from __future__ import annotations

import numpy as np
import pytest

from _locate_sim import amplitudes, calib_dict, signals, spot_for_angles
from psdcal.errors import InputError
from psdcal.measure.locate import LocateConfig, locate_to_csv
from psdcal.measure.sensor_model import SensorModel
from psdcal.signal.recording import open_recording
from psdcal.signal.stream import MultiCarrierLockin, _sum_squares, sum_squares_reference

RATE = 125_000.0


def _sig(n, carriers=(1000.0, 1300.0), noise=2e-3, seed=0):
    m = SensorModel.from_dict(calib_dict())
    d = spot_for_angles(m, np.radians([[10.0, -3.0], [-7.0, 12.0], [4.0, 5.0]]))
    parts = [(amplitudes(m, d[i]), f, 0.3 + i) for i, f in enumerate(carriers)]
    return m, signals(RATE, n, parts, noise=noise, rng=np.random.default_rng(seed))


@pytest.mark.parametrize("carriers", [(1000.0,), (1000.0, 1300.0), (1000.0, 1300.0, 1700.0)])
def test_rows_lockin_equals_channel_major_reference(carriers):
    _, x = _sig(40_000, carriers)
    lk = MultiCarrierLockin(RATE, carriers, 0.01)
    n = lk.n_window
    nw = x.shape[1] // n
    lk._origin_s = 0.0
    ref = lk._demodulate(np.ascontiguousarray(x[:, : nw * n]).reshape(4, nw, n))
    lk2 = MultiCarrierLockin(RATE, carriers, 0.01)
    lk2._origin_s = 0.0
    new = lk2._demodulate_rows(np.ascontiguousarray(x[:, : nw * n].T).reshape(nw, n, 4))
    for f in ("amplitude", "t_s", "t_start_s", "index"):
        a, b = getattr(new, f), getattr(ref, f)
        assert a.shape == b.shape, f
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max(), err_msg=f)
    # the residual variance is |x|^2 - fit, a difference of two sums of the signal's energy: both ways
    # agree to rounding of that energy (1e-13 of |x|^2 / dof), not to 1e-12 of the small residual
    xx = sum_squares_reference(np.ascontiguousarray(x[:, : nw * n].T).reshape(nw, n, 4))  # (nw, 4)
    tol_var = 1e-13 * xx / lk._dof
    assert new.var_amplitude.shape == ref.var_amplitude.shape
    assert np.all(np.abs(new.noise_sigma**2 - ref.noise_sigma**2) <= tol_var)
    gain = ref.var_amplitude / (ref.noise_sigma**2)[:, None, :]  # (nw, k, 4): the projection's factor
    assert np.all(np.abs(new.var_amplitude - ref.var_amplitude) <= gain * tol_var[:, None, :] * (1 + 1e-9))
    # phases: equal modulo 2 pi
    np.testing.assert_allclose(np.exp(1j * new.phase_rad), np.exp(1j * ref.phase_rad), rtol=0, atol=1e-12)


def test_process_rows_equals_process_any_chunking_and_strides():
    _, x = _sig(31_111)
    a = MultiCarrierLockin(RATE, (1000.0, 1300.0), 0.01)
    b = MultiCarrierLockin(RATE, (1000.0, 1300.0), 0.01)
    rows = np.ascontiguousarray(x.T)
    out_a, out_b = [], []
    for i in range(0, x.shape[1], 4_567):  # not a multiple of the window: samples wait for the next chunk
        out_a.append(a.process(i / RATE, x[:, i: i + 4_567]))  # (4, m) block: a strided transposed view inside
        out_b.append(b.process_rows(i / RATE, rows[i: i + 4_567]))
    assert a.pending_samples == b.pending_samples == x.shape[1] % a.n_window
    for f in ("amplitude", "var_amplitude", "noise_sigma", "phase_rad"):  # the same windows, the same sums
        np.testing.assert_allclose(np.concatenate([getattr(w, f) for w in out_b]),
                                   np.concatenate([getattr(w, f) for w in out_a]), rtol=1e-9, atol=1e-15)
    with pytest.raises(InputError, match=r"shape \(n, 4\)"):
        b.process_rows(0.0, np.zeros((4, 10)))


def test_sum_squares_equals_reference():
    rng = np.random.default_rng(3)
    xr = rng.standard_normal((7, 1250, 4)) * np.array([1.0, 1e-3, 1e3, 5.0])
    np.testing.assert_allclose(_sum_squares(xr), sum_squares_reference(xr), rtol=1e-13)
    strided = np.ascontiguousarray(xr.transpose(2, 0, 1)).transpose(1, 2, 0)  # a transposed block's layout
    np.testing.assert_allclose(_sum_squares(strided), sum_squares_reference(xr), rtol=1e-13)
    bad = xr.copy()
    bad[3, 100, 2] = np.nan
    bad[5, 7, 0] = np.inf
    s = _sum_squares(bad)
    assert np.isnan(s[3, 2]) and np.isinf(s[5, 0]) and np.isfinite(np.delete(s.ravel(), [3 * 4 + 2, 5 * 4])).all()


@pytest.mark.parametrize("layout", ["rows", "fortran", "cols", "float32"])
def test_rows_chunks_equal_checked_chunks(tmp_path, layout):
    _, x = _sig(10_007)
    arr = {"rows": np.ascontiguousarray(x.T), "fortran": x.T, "cols": x, "float32": x.T.astype(np.float32)}[layout]
    np.save(tmp_path / "r.npy", arr)
    rec = open_recording(tmp_path / "r.npy", RATE)
    ref = list(rec.chunks(3_000))
    fast = list(rec.chunks(3_000, rows=True, check_finite=False))
    assert [t for t, _ in fast] == [t for t, _ in ref]
    for (_, a), (_, b) in zip(fast, ref):
        assert a.shape == b.T.shape and a.dtype == np.float64
        np.testing.assert_array_equal(a, b.T)
    reused = [b.copy() for _, b in rec.chunks(3_000, rows=True, reuse_buffer=True)]
    for a, (_, b) in zip(reused, ref):
        np.testing.assert_array_equal(a, b.T)
    if layout == "rows":  # read straight into one buffer, filled again for every chunk
        it = rec.chunks(3_000, rows=True, reuse_buffer=True)
        first, second = next(it)[1], next(it)[1]
        assert np.shares_memory(first, second)


def test_truncated_npy_is_named(tmp_path):
    _, x = _sig(10_000)
    np.save(tmp_path / "r.npy", np.ascontiguousarray(x.T))
    rec = open_recording(tmp_path / "r.npy", RATE)
    data = (tmp_path / "r.npy").read_bytes()
    (tmp_path / "r.npy").write_bytes(data[: len(data) - 32 * 100])  # the last 100 samples lost after opening
    with pytest.raises(InputError, match=r"r\.npy.*(truncated|not a readable)"):
        list(rec.chunks(3_000, rows=True, check_finite=False))


@pytest.mark.parametrize("where", [5_000, 24_990])  # inside a window; in the tail left waiting (no window)
@pytest.mark.parametrize("bad", [np.nan, np.inf])
@pytest.mark.parametrize("order", ["C", "F"])  # read into a buffer; converted from the memory map
@pytest.mark.filterwarnings("error")  # one error line, no numpy warnings before it
def test_non_finite_sample_named_on_the_fast_path(tmp_path, where, bad, order):
    m, x = _sig(25_000)
    x[2, where] = bad
    np.save(tmp_path / "r.npy", np.asarray(x.T, order=order))
    (tmp_path / "out.csv").write_text("keep\n")
    cfg = LocateConfig(carriers_hz=(1000.0, 1300.0), window_s=0.01, check_carriers=False, chunk_samples=8_192)
    with pytest.raises(InputError, match=rf"sample {where} of channel vy1"):
        locate_to_csv(open_recording(tmp_path / "r.npy", RATE), m, tmp_path / "out.csv", cfg)
    assert (tmp_path / "out.csv").read_text() == "keep\n"


def test_locate_csv_text_equals_python_formatting(tmp_path, monkeypatch):
    import psdcal.measure._csvtext as ct

    m, x = _sig(60_000)
    np.save(tmp_path / "r.npy", np.ascontiguousarray(x.T))
    rec = open_recording(tmp_path / "r.npy", RATE)
    cfg = LocateConfig(carriers_hz=(1000.0, 1300.0), window_s=0.01, distance_mm=5000.0)
    locate_to_csv(rec, m, tmp_path / "fast.csv", cfg)
    monkeypatch.setattr(ct, "rows_bytes", lambda cols: ct.rows_text_reference(cols).encode("utf-8"))
    locate_to_csv(rec, m, tmp_path / "ref.csv", cfg)
    fast, ref = (tmp_path / "fast.csv").read_bytes(), (tmp_path / "ref.csv").read_bytes()
    assert fast.count(b"\n") == 1 + 2 * (60_000 // 1250)
    assert fast == ref


def test_batching_does_not_change_rows(tmp_path):
    m, x = _sig(100_000)
    np.save(tmp_path / "r.npy", np.ascontiguousarray(x.T))
    rec = open_recording(tmp_path / "r.npy", RATE)
    outs = []
    for k, chunk in enumerate((1_250, 16_384, 1 << 20)):  # one window per chunk .. everything in one batch
        cfg = LocateConfig(carriers_hz=(1000.0, 1300.0), window_s=0.01, distance_mm=5000.0, chunk_samples=chunk,
                           output_format="npy")
        s = locate_to_csv(rec, m, tmp_path / f"o{k}.npy", cfg)
        assert s.n_rows == 2 * (100_000 // 1250)
        outs.append(np.load(tmp_path / f"o{k}.npy"))
    for o in outs[1:]:
        assert list(o["emitter"]) == list(outs[0]["emitter"])
        for f in o.dtype.names:
            if f != "emitter":
                np.testing.assert_allclose(o[f], outs[0][f], rtol=1e-12, atol=1e-15, err_msg=f)


def test_window_sums_of_several_chunks_turned_into_windows_at_once():
    _, x = _sig(40_000)
    rows = np.ascontiguousarray(x.T)
    a = MultiCarrierLockin(RATE, (1000.0, 1300.0), 0.01)
    b = MultiCarrierLockin(RATE, (1000.0, 1300.0), 0.01)
    per_chunk = [a.process_rows(i / RATE, rows[i: i + 3_000]) for i in range(0, 40_000, 3_000)]
    sums = [b.fit_rows(i / RATE, rows[i: i + 3_000]) for i in range(0, 40_000, 3_000)]
    # consecutive windows: each chunk's first window follows the previous chunk's last
    assert [j for j, _, _ in sums] == list(np.cumsum([0] + [len(w) for w in per_chunk[:-1]]))
    together = b.windows(sums[0][0], np.concatenate([c for _, c, _ in sums]), np.concatenate([s for _, _, s in sums]))
    for f in ("index", "t_s", "amplitude", "var_amplitude", "noise_sigma", "phase_rad"):
        np.testing.assert_allclose(getattr(together, f), np.concatenate([getattr(w, f) for w in per_chunk]),
                                   rtol=1e-13, atol=1e-15, err_msg=f)


def test_big_endian_npy_gives_the_same_rows(tmp_path):
    _, x = _sig(7_000)
    native = np.ascontiguousarray(x.T)
    np.save(tmp_path / "be.npy", native.astype(">f8"))
    rec = open_recording(tmp_path / "be.npy", RATE)
    got = np.concatenate([b.copy() for _, b in rec.chunks(3_000, rows=True, reuse_buffer=True)])
    np.testing.assert_array_equal(got, native)


@pytest.mark.parametrize("carriers", [(1000.0,), (1000.0, 1300.0), (1000.0, 1300.0, 1700.0),
                                      (1000.0, 1300.0, 1700.0, 2100.0), (1000.0, 1300.0, 1700.0, 2100.0, 2500.0)])
def test_compiled_window_sums_equal_numpy(carriers):
    """The compiled window sums (one pass, reassociated) equal numpy's product and sum of squares to
    rounding: |coef - ref| <= 1e-13 sum_t |P| |x| (a few ulps of the sum's terms), for 1 to 5 carriers
    (the kernel's groups of five and three rows, zero-padded), on rows with any strides."""
    from psdcal import _jit

    if not _jit.enabled():
        pytest.skip("numba disabled")
    rng = np.random.default_rng(3)
    t = np.arange(30_000) / RATE
    x = 0.05 + 1e-3 * rng.standard_normal((4, t.size))
    for f in carriers:
        x += rng.uniform(0.1, 1.0, (4, 1)) * np.sin(2 * np.pi * f * t + rng.uniform(0, 6))
    a = MultiCarrierLockin(RATE, carriers, 0.01, compiled=False)
    b = MultiCarrierLockin(RATE, carriers, 0.01, compiled=True)
    rows = np.asfortranarray(x.T)  # not C-contiguous: the kernel reads any strides
    j0a, ca, xa = a.fit_rows(0.0, rows)
    j0b, cb, xb = b.fit_rows(0.0, rows)
    assert j0a == j0b == 0 and ca.shape == cb.shape == (rows.shape[0] // a.n_window, 2 * len(carriers) + 1, 4)
    n = a.n_window
    xr = np.abs(rows[: ca.shape[0] * n]).reshape(-1, n, 4)
    bound = 1e-13 * np.matmul(np.abs(a._proj_t), xr)  # (nw, J, 4)
    assert np.all(np.abs(cb - ca) <= bound)
    assert np.all(np.abs(xb - xa) <= 1e-13 * xa)


def test_compiled_window_sums_not_finite_on_a_bad_sample():
    """A NaN or inf sample makes its window's sum of squares non-finite on the compiled path too (the
    kernel's fastmath flags exclude nnan/ninf): the fast path's finiteness check relies on it."""
    from psdcal import _jit

    if not _jit.enabled():
        pytest.skip("numba disabled")
    _, x = _sig(12_500)
    rows = np.ascontiguousarray(x.T)
    rows[3 * 1250 + 17, 2] = np.nan
    rows[7 * 1250 + 5, 0] = np.inf
    _, coef, xx = MultiCarrierLockin(RATE, (1000.0, 1300.0), 0.01, compiled=True).fit_rows(0.0, rows)
    bad = ~np.isfinite(xx)
    assert bad[3, 2] and bad[7, 0] and bad.sum() == 2


def test_locate_rows_with_the_compiled_lockin_equal_the_numpy_lockin(tmp_path, monkeypatch):
    """The whole locate output with the compiled window sums against numpy's: the same rows and emitters,
    every number equal to its 10 significant digits up to one unit of the last (the sums differ by
    rounding; the noise variance, a difference of two sums of the signal's energy, by 1e-13 of that
    energy, which moves a sigma by ~1e-10 of itself)."""
    import psdcal.signal.stream as st
    from psdcal import _jit

    if not _jit.enabled():
        pytest.skip("numba disabled")
    m, x = _sig(80_000, noise=1e-4)  # high SNR: the noise variance is the most sensitive to rounding
    np.save(tmp_path / "r.npy", np.ascontiguousarray(x.T))
    rec = open_recording(tmp_path / "r.npy", RATE)
    cfg = LocateConfig(carriers_hz=(1000.0, 1300.0), window_s=0.01, distance_mm=5000.0)
    locate_to_csv(rec, m, tmp_path / "compiled.csv", cfg)
    monkeypatch.setattr(st, "use_compiled_lockin", lambda n_samples=0: False)
    locate_to_csv(rec, m, tmp_path / "numpy.csv", cfg)
    a = np.genfromtxt(tmp_path / "compiled.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    b = np.genfromtxt(tmp_path / "numpy.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert a.shape == b.shape == (2 * (80_000 // 1250),)
    assert list(a["emitter"]) == list(b["emitter"])
    # a sigma's relative change: half that of the noise variance, 1e-13 of the energy per sample over it
    noise = 1e-4
    rtol_sigma = 1e-13 * float(np.mean(x ** 2)) / noise ** 2 + 2e-9
    assert rtol_sigma < 1e-5  # (the bound is a small one)
    for c in a.dtype.names:
        if c != "emitter":
            rtol = rtol_sigma if c.startswith("sigma_") else 2e-9
            np.testing.assert_allclose(a[c], b[c], rtol=rtol, atol=0, err_msg=c)


def test_compiled_window_arithmetic_equals_numpy():
    """The compiled per-window arithmetic (noise, common phase, projected amplitudes) against the numpy
    code on the same sums: equal to rounding, including a window without signal (no phase: amplitudes
    along the in-phase axis), a window of zeros (the noise floor) and non-finite sums (NaN, no warning)."""
    from psdcal import _jit

    if not _jit.enabled():
        pytest.skip("numba disabled")
    _, x = _sig(20_000, (1000.0, 1300.0))
    rows = np.ascontiguousarray(x.T)
    rows[3 * 1250: 4 * 1250] = 0.05  # a constant window: no carrier
    rows[5 * 1250: 6 * 1250] = 0.0  # zeros: the residual floor
    a = MultiCarrierLockin(RATE, (1000.0, 1300.0), 0.01, compiled=False)
    b = MultiCarrierLockin(RATE, (1000.0, 1300.0), 0.01, compiled=True)
    j0, coef, xx = a.fit_rows(0.0, rows)
    b.fit_rows(0.0, rows)
    xx = xx.copy()
    xx[7, 1] = np.nan
    wa, wb = a.windows(j0, coef, xx), b.windows(j0, coef, xx)
    # the noise variance is |x|^2 - fit: equal to rounding of the energy (1e-13 |x|^2 / dof), as above
    tol_var = 1e-13 * xx / a._dof
    ok = np.isfinite(xx)
    assert np.all(np.abs(wb.noise_sigma**2 - wa.noise_sigma**2)[ok] <= tol_var[ok])
    ok &= wa.noise_sigma > 0  # (the window of zeros: no noise, nothing to scale)
    with np.errstate(invalid="ignore", divide="ignore"):
        gain = wa.var_amplitude / (wa.noise_sigma**2)[:, None, :]
    okk = np.broadcast_to(ok[:, None, :], gain.shape)
    assert np.all(wb.var_amplitude[5] == 0) and np.all(wa.var_amplitude[5] == 0)
    assert np.all((np.abs(wb.var_amplitude - wa.var_amplitude) <= gain * tol_var[:, None, :] * (1 + 1e-9))[okk])
    for f in ("amplitude", "t_s", "index"):
        u, v = getattr(wb, f), getattr(wa, f)
        assert u.shape == v.shape
        np.testing.assert_array_equal(np.isnan(u), np.isnan(v), err_msg=f)
        ok = ~np.isnan(v)
        np.testing.assert_allclose(u[ok], v[ok], rtol=1e-12, atol=1e-12 * np.nanmax(np.abs(v)), err_msg=f)
    np.testing.assert_allclose(np.exp(1j * wb.phase_rad), np.exp(1j * wa.phase_rad), rtol=0, atol=1e-12)
    assert np.isnan(wb.noise_sigma[7, 1]) and np.all(np.isfinite(wb.noise_sigma[7, [0, 2, 3]]))
    assert np.array_equal(np.isnan(wb.var_amplitude), np.isnan(wa.var_amplitude))


def test_mapped_rows_equal_read_rows_and_truncation_is_named(tmp_path):
    """``chunks(mapped=True)``: the same rows as the copied reads, as views of the file (no copy); a file
    truncated after it was opened is named as truncated before a block past its end is touched."""
    _, x = _sig(10_000)
    np.save(tmp_path / "r.npy", np.ascontiguousarray(x.T))
    rec = open_recording(tmp_path / "r.npy", RATE)
    a = np.concatenate([b for _, b in rec.chunks(3_000, rows=True)])
    it = rec.chunks(3_000, rows=True, mapped=True)
    t0, first = next(it)
    assert not first.flags.writeable and t0 == 0.0
    b = np.concatenate([first] + [blk for _, blk in it])
    np.testing.assert_array_equal(a, b)
    data = (tmp_path / "r.npy").read_bytes()
    it = rec.chunks(3_000, rows=True, mapped=True)
    next(it)
    with open(tmp_path / "r.npy", "r+b") as fh:  # the same file, shortened (not replaced)
        fh.truncate(len(data) - 32 * 5_000)
    with pytest.raises(InputError, match=r"r\.npy.*truncated"):
        list(it)


def test_median_rows_equals_numpy_median():
    """The pre-scan's noise floor (one-pivot partition) equals ``np.median`` exactly: odd and even counts,
    ties, NaN, one and two columns, spectra of real noise."""
    from psdcal.signal.inspect import _median_rows

    rng = np.random.default_rng(5)
    cases = [rng.random((4, m)) for m in (1, 2, 3, 4, 5, 64, 65, 1000, 32768, 32769)]
    cases += [rng.integers(0, 3, (4, 101)).astype(float), rng.integers(0, 3, (4, 100)).astype(float)]
    p = np.abs(np.fft.rfft(rng.standard_normal((4, 4096)), axis=1)) ** 2
    cases.append(p[:, 1:])
    q = rng.random((4, 50))
    q[2, 7] = np.nan
    cases.append(q)
    for c in cases:
        np.testing.assert_array_equal(_median_rows(c), np.median(c, axis=1))


def test_median_of_long_rows_bracketed_exactly_or_not_at_all():
    """Long rows (a pre-scan spectrum's 32,768 bins) are bracketed by a sample before the partition: the
    same values as ``np.median`` when the bracket holds the middle (spectra, many ties, odd and even
    counts); None, and the full partition's values, when the sample misleads (every 16th value the
    smallest) or a NaN is there."""
    from psdcal.signal import inspect as ins

    rng = np.random.default_rng(11)
    p = (np.abs(np.fft.rfft(rng.standard_normal((4, 1 << 16)), axis=1)) ** 2)[:, 1:]
    cases = [p, p[:, :-1], rng.integers(0, 3, (4, 40_001)).astype(float), rng.integers(0, 3, (4, 40_000)).astype(float),
             rng.random((3, 4096)), rng.random((2, 5001))]
    for c in cases:
        got = ins._median_bracketed(c)
        assert got is not None
        np.testing.assert_array_equal(got, np.median(c, axis=1))
        np.testing.assert_array_equal(ins._median_rows(c), np.median(c, axis=1))
    trap = np.ones((2, 8192))
    trap[:, :: ins._BRACKET_STEP] = 0.0  # the sample sees only zeros: the bracket [0, 0] misses the middle
    trap[1, 5] = 7.0
    assert ins._median_bracketed(trap) is None
    np.testing.assert_array_equal(ins._median_rows(trap), np.median(trap, axis=1))
    p2 = p.copy()
    p2[1, 100] = np.nan
    assert ins._median_bracketed(p2) is None
    np.testing.assert_array_equal(ins._median_rows(p2), np.median(p2, axis=1))


def test_prescan_spectrum_equals_abs_squared_fft():
    """The pre-scan's power spectrum (re^2 + im^2 of the Hann-windowed, mean-removed channels) equals
    ``|rfft|^2`` written independently, to rounding (relative 1e-12 of the largest bin), rows layout too."""
    from psdcal.signal.inspect import spectrum

    rng = np.random.default_rng(9)
    n = 4096
    t = np.arange(n) / 50_000.0
    x = 0.1 + 1e-3 * rng.standard_normal((n, 4)) + np.sin(2 * np.pi * 1234.5 * t)[:, None] * [0.3, 0.2, 0.1, 0.05]
    freq, p, wsum, w2sum = spectrum(x.T, 50_000.0)  # a (4, n) view of rows
    w = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(n) / (n - 1))
    for c in range(4):
        ref = np.abs(np.fft.fft((x[:, c] - x[:, c].mean()) * w)[: n // 2 + 1]) ** 2
        np.testing.assert_allclose(p[c], ref, rtol=0, atol=1e-12 * ref.max())
    assert np.isclose(wsum, w.sum()) and np.isclose(w2sum, (w * w).sum())
    np.testing.assert_allclose(freq, np.arange(n // 2 + 1) * 50_000.0 / n)


def test_prescan_spectrum_buffers_kept_between_calls_change_nothing():
    """The spectrum's buffers are reused from call to call: a spectrum returned earlier is not changed by a
    later call (of another length, channel count or layout), and each equals the spectrum of one channel
    at a time computed independently (numpy's own FFT of each windowed channel), exactly."""
    from psdcal.signal.inspect import spectrum

    rng = np.random.default_rng(11)
    w_of = {}
    results = []
    for n, c, rows in ((4096, 4, True), (4096, 4, False), (1000, 4, True), (4096, 2, False), (4097, 4, True)):
        x = rng.standard_normal((n, c)) * [1.0, 2.0, 0.5, 3.0][:c] + 0.2
        xv = x.T if rows else np.ascontiguousarray(x.T)
        results.append((xv.copy(), spectrum(xv, 10_000.0)))
    for xv, (freq, p, wsum, w2sum) in results:
        n = xv.shape[1]
        w = w_of.setdefault(n, np.hanning(n))
        for c in range(xv.shape[0]):
            row = np.ascontiguousarray(xv[c])
            z = np.fft.rfft((row - row.mean()) * w)
            np.testing.assert_array_equal(p[c], z.real ** 2 + z.imag ** 2)
        assert wsum == float(w.sum()) and w2sum == float((w * w).sum())


def test_read_prefix_rows_view_has_the_same_samples(tmp_path):
    """``read_prefix(rows_view=True)`` (the pre-scan without time multiplexing): the same (4, n) samples as
    the plain read, within one chunk (a read-only view of the file) and over several chunks (a copy), a
    prefix shorter than the file too; the spectrum of either is the same."""
    from psdcal.signal.inspect import read_prefix, spectrum

    _, x = _sig(150_000)
    np.save(tmp_path / "r.npy", np.ascontiguousarray(x.T))
    rec = open_recording(tmp_path / "r.npy", RATE)
    for n in (100, 65_536, 70_000, 150_000, 200_000):
        a = read_prefix(rec, n)
        b = read_prefix(rec, n, rows_view=True)
        assert a.shape == b.shape == (4, min(n, 150_000))
        np.testing.assert_array_equal(a, b)
        assert b.flags.writeable == (n > 65_536)  # a view of the map within one chunk, else a copy
        for u, v in zip(spectrum(a, RATE), spectrum(b, RATE)):
            np.testing.assert_array_equal(u, v)


def test_npy_read_in_chunks_of_any_size_changes_nothing(tmp_path):
    """A ``.npy`` is read chunk by chunk into one reused buffer (windows that straddle two chunks wait in the
    lock-in): the same CSV bytes whatever the chunk size, the same one-line error naming a bad sample late in
    the file; progress is still reported up to every sample; the buffer's reuse leaves no earlier chunk's
    samples in a later window (the rows equal those of the same samples read from a CSV, whose (4, m) blocks
    take the lock-in's other path)."""
    m, x = _sig(120_000)
    rows = np.ascontiguousarray(x.T)
    np.save(tmp_path / "r.npy", rows)
    texts, seen = [], []
    for chunk in (10_000, 37_501, 1 << 16):
        cfg = LocateConfig(carriers_hz=(1000.0, 1300.0), window_s=0.01, distance_mm=5000.0, chunk_samples=chunk)
        progress = []
        locate_to_csv(open_recording(tmp_path / "r.npy", RATE), m, tmp_path / f"o{chunk}.csv", cfg,
                      progress=progress.append)
        texts.append((tmp_path / f"o{chunk}.csv").read_bytes())
        seen.append(progress)
    assert texts[0] == texts[1] == texts[2]
    assert all(p[-1] == 120_000 and p == sorted(p) for p in seen) and len(seen[2]) < len(seen[0])
    np.savetxt(tmp_path / "r.csv", rows, delimiter=",", header="vx1,vx2,vy1,vy2", comments="")
    cfg = LocateConfig(carriers_hz=(1000.0, 1300.0), window_s=0.01, distance_mm=5000.0, chunk_samples=10_000)
    locate_to_csv(open_recording(tmp_path / "r.csv", RATE), m, tmp_path / "ref.csv", cfg)
    a, b = (np.genfromtxt(tmp_path / f, delimiter=",", names=True, dtype=None, encoding="utf-8")
            for f in ("o10000.csv", "ref.csv"))
    assert len(a) == len(b) > 0
    for name in ("alpha_x_deg", "alpha_y_deg", "X_mm", "Y_mm", "sigma_X_mm"):
        np.testing.assert_allclose(a[name], b[name], rtol=1e-9, atol=1e-12)
    bad = rows.copy()
    bad[97_531, 2] = np.nan
    np.save(tmp_path / "bad.npy", bad)
    msgs = []
    for chunk in (10_000, 1 << 16):
        cfg = LocateConfig(carriers_hz=(1000.0, 1300.0), window_s=0.01, distance_mm=5000.0, chunk_samples=chunk)
        with pytest.raises(InputError) as ei:
            locate_to_csv(open_recording(tmp_path / "bad.npy", RATE), m, tmp_path / "b.csv", cfg)
        msgs.append(str(ei.value))
    assert msgs[0] == msgs[1] and "sample 97531 of channel vy1" in msgs[0]
    assert not (tmp_path / "b.csv").exists()
