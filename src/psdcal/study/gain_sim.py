"""Simulated gain measurements through the signal chain (the studies' and ``simulate``'s side of gains).

:mod:`psdcal.calibration.gains` fits channel gains from measured spots; the
functions here *make* such measurements by running the simulated electronics
(:mod:`psdcal.signal.chain`), which sits above the calibration layer, so they
live in the study layer.
"""
from __future__ import annotations

from dataclasses import asdict

import numpy as np

from psdcal.calibration.gains import GainCalibration, calibrate_gains, calibration_spots
from psdcal.model.readout import impact_point
from psdcal.signal.chain import ChainSettings, channel_gains, measure_amplitudes


def simulate_electrical_calibration(gains, settings=None, rng=None, *, spots_mm=None, l1: float = 0.0,
                                    repeats: int = 1) -> GainCalibration:
    """Simulate remedy (b): read known spots on the bare PSD through the chain, fit the gains.

    Parameters
    ----------
    gains : (4,) array_like
        The true channel gains, V/A.
    settings : psdcal.signal.chain.ChainSettings
        Noise (``snr_db``), demodulation and record of the bench measurement.
    rng : numpy.random.Generator, int or None
    spots_mm : (n, 2), default :func:`calibration_spots` (7 x 7 over +-3.5 mm).
    l1 : float
        PSD distortion of the bare sensor, mm^-2 (the fit assumes none).
    repeats : int
        Records averaged per spot (amplitudes averaged).

    Returns
    -------
    GainCalibration
    """
    s = ChainSettings() if settings is None else settings
    spots = calibration_spots() if spots_mm is None else np.asarray(spots_mm, dtype=float)
    gen = np.random.default_rng(rng)
    amps = np.mean([measure_amplitudes(spots, s, gains, gen, l1) for _ in range(max(1, int(repeats)))], axis=0)
    meas = impact_point(amps, s.lx_mm, s.ly_mm)
    return calibrate_gains(spots, meas, s.lx_mm, s.ly_mm)


def simulate_amplitudes(points_mm, *, snr_db: float | None = None, r_tol: float = 0.0, c_tol: float = 0.0, seed=0):
    """Raw amplitudes of readout points through the paper's signal chain, for an amplitude points file.

    The chain of :meth:`psdcal.signal.chain.ChainSettings.paper` (band-pass,
    Eq 43 gains); the four channels' R and C drawn within ``r_tol``,
    ``c_tol`` (none when both are 0), white noise at ``snr_db``.

    Parameters
    ----------
    points_mm : (..., 2) array_like
        Noiseless readout points (Eq 1-2 with equal gains; PSD distortion
        already included), mm.  NaN rows stay NaN.
    snr_db : float or None
    r_tol, c_tol : float
    seed : int or Generator

    Returns
    -------
    amplitudes : (..., 4) ndarray, V
    gains : (4,) ndarray, V/A (the drawn channel gains)
    chain : dict, the chain settings used (for the truth file)
    """
    chain = ChainSettings.paper(snr_db=snr_db, r_tol=float(r_tol), c_tol=float(c_tol))
    rng = np.random.default_rng(seed)
    g = channel_gains(chain, rng) if (r_tol > 0 or c_tol > 0) else channel_gains(chain)
    amps = measure_amplitudes(points_mm, chain, g, rng)
    return amps, g, asdict(chain)


__all__ = ["simulate_amplitudes", "simulate_electrical_calibration"]
