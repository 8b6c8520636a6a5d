"""Several sensors: ``psdcal locate --sensors`` (triangulated rows and the file's consistency rule).

Split from :mod:`psdcal.measure.locate` (which re-exports these names).  Columns::

    t_s,emitter,X_mm,Y_mm,Z_mm,sigma_X_mm,sigma_Y_mm,sigma_Z_mm,n_sensors,chi2,dof,flagged,left_out,reflection
"""
from __future__ import annotations

import tempfile
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from psdcal._atomic import atomic_path
from psdcal._consistency import ALPHA, extra_variance_on_grid
from psdcal.errors import InputError, ZeroSignalError
from psdcal.measure.aoa import angles_from_amplitudes
from psdcal.measure.positioning import (
    extra_noise_check,
    extra_ray_sums,
    pooled_check,
    ray_inputs,
    triangulate,
)
from psdcal.measure.reflections import FLAGS, reflection_warnings, screen_rays
from psdcal.signal.stream import MultiCarrierLockin

if TYPE_CHECKING:
    from psdcal.measure.locate import LocateConfig, LocateSummary

MULTI_COLUMNS = ("t_s", "emitter", "X_mm", "Y_mm", "Z_mm", "sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm", "n_sensors", "chi2",
                 "dof", "flagged")
#: Appended: the sensor left out as a reflection and the flag (:mod:`psdcal.measure.reflections`).
MULTI_COLUMNS = MULTI_COLUMNS + ("left_out", "reflection")
#: Grid of extra ray variances (normalised coordinates^2) on which the file's residual sums are pooled.
EXTRA_GRID = np.logspace(-20.0, 2.0, 441)
#: Per-row record of the first pass (float64): t, emitter index, X, Y, Z, cov (6), d cov / d s2 (6), n_sensors, chi2, dof,
#: then the sensor left out (-1: none) and the reflection flag's index in :data:`psdcal.measure.reflections.FLAGS`.
_REC = 22
_TRIU = (np.array([0, 1, 2, 0, 0, 1]), np.array([0, 1, 2, 1, 2, 2]))


def locate_multi_to_csv(recordings, sensors, out_path, config: LocateConfig,
                        progress: Callable[[int], None] | None = None) -> LocateSummary:
    """Triangulate emitters seen by several sensors; write 3D positions to CSV.

    The recordings (one per sensor, same sampling rate, started together) are
    demodulated in lockstep; for every window and emitter the rays of the
    sensors that see it (total amplitude above ``min_snr`` sigma) are
    intersected (:func:`psdcal.measure.positioning.triangulate`).

    Sigmas that cover the error (docs/guide/positioning.md#sigmas-that-cover-the-error):
    each row's ``chi2`` is tested against ``chi2(dof)`` at 1e-3 (the
    ``flagged`` column).  All the rows of the file are tested together
    (``sum chi2`` against ``sum dof``); when that fails, one extra isotropic
    ray noise ``s2`` is estimated from every row's residuals
    (``sum r^T (C + s2 I)^-1 r = sum dof``) and every row's sigmas include
    it; one warning gives its size.  On correct data a file is inflated at the
    design rate 1e-3 (measured 0.0007 +- 0.0002 over 20000 files of 20 points,
    benchmarks/study_consistency_rows.py; tests/test_consistency_rows.py).
    The rows are triangulated in a first pass into a temporary file (bounded
    memory) and written with their final sigmas in a second.

    Parameters
    ----------
    recordings : sequence of Recording
    sensors : sequence of SensorPose
    out_path : str or Path
    config : LocateConfig
        ``tdm`` and ``distance_mm`` are not used here.
    progress : callable, optional

    Returns
    -------
    LocateSummary
    """
    from psdcal.measure.locate import LocateConfig, LocateSummary, prescan  # (locate re-exports this module)

    if config.output_format != "csv":
        raise InputError("--format npy is not available with --sensors (several sensors): write CSV", field="format")
    if len(recordings) != len(sensors) or len(sensors) < 2:
        raise InputError("give one recording per sensor and at least two sensors", field="sensors")
    if config.tdm:
        raise InputError("time multiplexing is supported with one sensor only", field="tdm")
    rates = {r.rate_hz for r in recordings}
    if len(rates) != 1:
        raise InputError(f"the recordings have different sampling rates {sorted(rates)}", field="rate_hz")
    rate = rates.pop()
    names = config.emitter_names()
    k = len(names)
    warnings: list[str] = []
    window_s = 0.01 if config.window_s is None else config.window_s
    for r in recordings:
        warnings += prescan(r, LocateConfig(config.carriers_hz, window_s, check_carriers=config.check_carriers))[1]
    lockins = [MultiCarrierLockin(rate, config.carriers_hz, window_s) for _ in sensors]
    nwin = lockins[0].n_window
    chunk = max(1, int(config.chunk_samples) // nwin) * nwin
    R = np.stack([s.R for s in sensors])
    t = np.stack([np.asarray(s.tvec_mm, dtype=float) for s in sensors])
    names_arr = np.array(names, dtype=object)
    n_samples = n_windows = n_rows = n_skipped = 0
    pool = _RowPool()
    refl_codes: list = []
    with atomic_path(out_path, suffix=".csv") as tmp, tempfile.TemporaryFile() as rec_fh:
        iters = [r.chunks(chunk) for r in recordings]
        while True:
            items = [next(it, None) for it in iters]
            if any(item is None for item in items):
                break
            m = min(item[1].shape[1] for item in items)
            blocks = [lk.process(t0, b[:, :m]) for lk, (t0, b) in zip(lockins, items)]
            n_samples += m
            nw = len(blocks[0])
            n_windows += nw
            if nw:
                results, seens = [], []
                for blk, sp in zip(blocks, sensors):
                    a = blk.amplitude.reshape(-1, 4)
                    v = blk.var_amplitude.reshape(-1, 4)
                    seen = (a.sum(-1) > config.min_snr * np.sqrt(v.sum(-1))) & np.all(np.isfinite(a), -1)
                    a_safe = np.where(seen[:, None], a, 1.0)
                    results.append(angles_from_amplitudes(a_safe, sp.model, v, on_zero="nan"))
                    seens.append(seen)
                # the rays with their covariance; poses from `psdcal pose` add theirs (ray_inputs)
                ns, covs, kw = ray_inputs(results, sensors, seens)
                tri = triangulate(ns, covs, R, t, inflate=False, **kw)
                scr = screen_rays(ns, covs, R, t, tri, inflate=False, **kw)  # a disagreeing sensor left out
                tri = scr.tri
                ok = tri.n_sensors >= 2
                n_skipped += int((~ok).sum())
                rec = np.empty((int(ok.sum()), _REC))
                rec[:, 0] = np.repeat(blocks[0].t_s, k)[ok]
                rec[:, 1] = np.tile(np.arange(k), nw)[ok]
                rec[:, 2:5] = tri.p_w_mm[ok]
                rec[:, 5:11] = tri.cov_p_stated_mm2[ok][:, _TRIU[0], _TRIU[1]]
                rec[:, 11:17] = tri.dcov_dextra_mm2[ok][:, _TRIU[0], _TRIU[1]]
                rec[:, 17] = tri.n_sensors[ok]
                rec[:, 18] = tri.chi2[ok]
                rec[:, 19] = tri.dof[ok]
                rec[:, 20] = scr.left_out[ok]
                rec[:, 21] = [FLAGS.index(f) for f in scr.flag[ok]]
                refl_codes.append(rec[:, 20:22].astype(np.int8))
                rec_fh.write(np.ascontiguousarray(rec).tobytes())
                pool.add(tri)
                n_rows += len(rec)
            if progress is not None:
                progress(n_samples)
        if n_windows == 0:
            raise InputError("the recordings are shorter than one window", field="window_s")
        if n_rows == 0:
            raise ZeroSignalError(
                f"no window has a carrier of {list(config.carriers_hz)} Hz seen by two sensors above "
                f"--min-snr {config.min_snr:g}"
            )
        check, s2 = pool.result()
        snames = [sp.name for sp in sensors]
        n_flagged, tr0, tr1 = _write_multi_rows(tmp, rec_fh, n_rows, names_arr, s2, sensor_names=snames)
        if s2 > 0:
            check = extra_noise_check(check, s2, tr0, tr1)
        if check.passed is False:
            warnings.append(f"{out_path}: {check.line()} ({n_flagged} of {n_rows} rows flagged individually)")
    codes = np.concatenate(refl_codes) if refl_codes else np.zeros((0, 2), np.int8)
    lut = np.array([*snames, ""], dtype=object)
    warnings += reflection_warnings(lut[codes[:, 0]], np.array(FLAGS, dtype=object)[codes[:, 1]])
    n_left = int((codes[:, 0] >= 0).sum())
    if s2 > 0 and n_left:  # the test of each sensor used the stated ray noise, which the file's rule found too small
        warnings.append(f"{out_path}: the rays are noisier than stated, and the reflection test used the stated "
                        f"noise: some of the {n_left} rows with a sensor left out may be noise, not reflections "
                        "(the calibration or a pose is off?); 'locate --angles' screens again with the grown noise")
    return LocateSummary(n_samples, n_windows, n_rows, n_skipped, n_samples / rate, MULTI_COLUMNS,
                         warnings=tuple(warnings), window_s=window_s, n_flagged=n_flagged, checks=(check,),
                         extra_var_n=s2)


class _RowPool:
    """The file's pooled chi-squared and residual sums over :data:`EXTRA_GRID` (bounded memory)."""

    def __init__(self, alpha: float = ALPHA):
        self.alpha = alpha
        self.chi2 = 0.0
        self.dof = 0
        self.points = 0
        self.sums = np.zeros(EXTRA_GRID.shape)

    def add(self, tri) -> None:
        good = tri.n_sensors >= 2
        self.chi2 += float(np.nansum(tri.chi2))
        self.dof += int(tri.dof.sum())
        self.points += int(good.sum())
        self.sums += extra_ray_sums(tri, EXTRA_GRID)

    def result(self):
        """``(check, s2)``: the pooled test and the extra ray variance (0 when it passed)."""
        check = pooled_check(self.chi2, self.dof, self.points, self.alpha)
        if check.passed is not False:
            return check, 0.0
        return check, extra_variance_on_grid(EXTRA_GRID, self.sums, self.dof)


def _write_multi_rows(path, rec_fh, n_rows: int, names_arr, s2: float, chunk_rows: int = 65536,
                      sensor_names=()) -> int:
    """Second pass: the first pass's records as CSV rows with the sigmas of extra ray variance ``s2``.

    Returns ``(flagged rows, trace of each row's covariance before, after)``."""
    from psdcal._stats import chi2_isf
    from psdcal.measure.locate import _write_rows

    thr = {}
    n_flagged = 0
    rec_fh.seek(0)
    traces0, traces1 = [], []
    with open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(",".join(MULTI_COLUMNS) + "\n")
        done = 0
        while done < n_rows:
            m = min(chunk_rows, n_rows - done)
            rec = np.frombuffer(rec_fh.read(m * _REC * 8), dtype=np.float64).reshape(m, _REC)
            done += m
            var = rec[:, 5:8] + s2 * rec[:, 11:14]
            traces0.append(rec[:, 5:8].sum(1).astype(np.float32))
            traces1.append(var.sum(1).astype(np.float32))
            dof = rec[:, 19].astype(int)
            flag = np.zeros(m, dtype=int)
            for d in np.unique(dof):
                if d > 0:
                    if d not in thr:
                        thr[d] = chi2_isf(1e-3, float(d))
                    flag[dof == d] = rec[dof == d, 18] > thr[d]
            n_flagged += int(flag.sum())
            sig = np.sqrt(np.clip(var, 0.0, None))
            cols = {
                "t_s": rec[:, 0],
                "emitter": names_arr[rec[:, 1].astype(int)],
                "X_mm": rec[:, 2],
                "Y_mm": rec[:, 3],
                "Z_mm": rec[:, 4],
                "sigma_X_mm": sig[:, 0],
                "sigma_Y_mm": sig[:, 1],
                "sigma_Z_mm": sig[:, 2],
                "n_sensors": rec[:, 17].astype(int),
                "chi2": rec[:, 18],
                "dof": dof,
                "flagged": flag,
                "left_out": np.array([*sensor_names, ""], dtype=object)[rec[:, 20].astype(int)],
                "reflection": np.array(FLAGS, dtype=object)[rec[:, 21].astype(int)],
            }
            _write_rows(fh, cols, MULTI_COLUMNS)
    cat = lambda a: np.concatenate(a) if a else np.zeros(0)
    return n_flagged, cat(traces0), cat(traces1)
