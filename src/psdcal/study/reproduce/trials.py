"""One Monte Carlo trial of each kind: simulate a set of views through the signal chain, calibrate, score.

The trial functions (:func:`case_trial`, :func:`gain_trial`, :func:`initial_trial`) are top level and
picklable for :func:`psdcal.study.montecarlo.run_trials`; each returns a flat ``dict[str, float]``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from psdcal.calibration.core import calibrate, implausible
from psdcal.calibration.gains import correct_points
from psdcal.study.gain_sim import simulate_electrical_calibration
from psdcal.errors import ConvergenceError, PsdcalError
from psdcal.model.distortion import distort, undistort
from psdcal.model.params import Distortion, Intrinsics
from psdcal.model.projection import project
from psdcal.model.readout import impact_point
from psdcal.signal.chain import ChainSettings, channel_gains, signal_amplitudes
from psdcal.study.simulate import LENSES, PAPER_L1, default_template, random_poses


#: Errors the study catches per calibration (a failed calibration is a NaN row, counted).
_CAL_ERRORS = (PsdcalError, np.linalg.LinAlgError, FloatingPointError)


@dataclass(frozen=True)
class TrialData:
    """The views of one trial through the signal chain.

    Attributes
    ----------
    template_mm : (M, 2)
    spots_mm : (n_images, M, 2) true spot positions on the PSD (lens distortion only), mm
    amplitudes : (n_images, M, 4) raw channel amplitudes, V
    points_mm : (n_images, M, 2) raw readout (Eq 1-2), mm
    gains : (4,) channel gains used, V/A
    settings : ChainSettings
    l1 : float, PSD distortion, mm^-2
    """

    template_mm: np.ndarray
    spots_mm: np.ndarray
    amplitudes: np.ndarray
    points_mm: np.ndarray
    gains: np.ndarray
    settings: ChainSettings
    l1: float


def chain_settings(snr_db: float) -> ChainSettings:
    """The paper's chain (band-pass, Eq 43 gains) at an SNR (NaN: noiseless)."""
    return ChainSettings.paper(snr_db=None if (snr_db is None or math.isnan(snr_db)) else float(snr_db))


def simulate_trial(rng, lens: str, snr_db: float | None, gains, psd: bool, *, n_images: int = 9,
                   rvecs=None, tvecs=None) -> TrialData:
    """Views of the template through the lens and the signal chain (one Monte Carlo trial).

    Parameters
    ----------
    rng : numpy.random.Generator
        Poses (unless given), then the noise.
    lens : "lens1" | "lens2"
    snr_db : float; None or NaN for no noise
    gains : (4,) channel gains, V/A
    psd : bool, PSD distortion l1 (Section 4.5)
    n_images : int
    rvecs, tvecs : (n_images, 3), optional fixed poses
    """
    intr, dist = LENSES[lens]
    T = default_template()
    l1 = PAPER_L1 if psd else 0.0
    if rvecs is None:
        # poses chosen so that the readout (with the PSD distortion) covers the sensor
        rvecs, tvecs = random_poses(T, intr, replace(dist, l1=l1), n_images, rng)
    x = np.stack([project(T, intr, r, t) for r, t in zip(rvecs, tvecs)])
    spots = distort(x, dist, intr.c).d_mm  # where the light lands (lens distortion, Eq 7-16)
    s = chain_settings(snr_db)
    from psdcal.signal.chain import measure_amplitudes

    if s.snr_db is None:
        # noiseless: the demodulated amplitudes equal the clean ones up to a factor common to
        # the four channels, which cancels in Eq 1-2 (docs/guide/signal-chain.md); skip the records
        amps = signal_amplitudes(spots, s, gains, l1)
    else:
        # the demodulator's outputs drawn from their exact law (chain.measure_amplitudes, noise=)
        amps = measure_amplitudes(spots, s, gains, rng, l1, noise="closed-form")
    ok = np.all(np.isfinite(amps), axis=-1)
    pts = np.full(spots.shape, np.nan)
    pts[ok] = impact_point(amps[ok], s.lx_mm, s.ly_mm)
    return TrialData(T, spots, amps, pts, np.asarray(gains, dtype=float), s, l1)


def heldout_emitters(lens: str, n_per_side: int = 11, extent_mm: float = 4.0):
    """Emitters not used in any calibration, spread over the field of view.

    Directions whose ideal image points form a square grid of ``n_per_side``
    points over ``+-extent_mm`` about the optical centre.

    Returns
    -------
    rays : (n, 3) ndarray
        Unit directions in the true camera frame.
    spots_mm : (n, 2) ndarray
        Where their light lands on the PSD (lens distortion applied), mm.
    """
    intr, dist = LENSES[lens]
    s = np.linspace(-extent_mm, extent_mm, n_per_side)
    X, Y = np.meshgrid(s, s)
    x = np.stack([X.ravel() + intr.cx_mm, Y.ravel() + intr.cy_mm], axis=1)
    spots = distort(x, dist, intr.c).d_mm
    inside = np.all(np.abs(spots) <= 4.4, axis=1) & np.all(np.isfinite(spots), axis=1)
    n = np.stack([(x[:, 0] - intr.cx_mm) / intr.f_mm, (x[:, 1] - intr.cy_mm) / intr.f_mm, np.ones(len(x))], axis=1)
    rays = n / np.linalg.norm(n, axis=1, keepdims=True)
    return rays[inside], spots[inside]


def rays_from_points(d_mm, intrinsics: Intrinsics, distortion: Distortion) -> np.ndarray:
    """Unit rays (n, 3) of measured points (n, 2) through a calibration (docs/model.md#angle-of-arrival-and-position: undistort, A^-1)."""
    x = undistort(np.asarray(d_mm, dtype=float), distortion, intrinsics.c)
    h = np.concatenate([x, np.ones((x.shape[0], 1))], axis=1) @ np.linalg.inv(intrinsics.matrix()).T
    return h / np.linalg.norm(h, axis=1, keepdims=True)


def aoa_error_deg(rays_true, rays_est) -> np.ndarray:
    """Angle between true and estimated rays, degrees, (n,)."""
    a = np.asarray(rays_true, dtype=float)
    b = np.asarray(rays_est, dtype=float)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)))


def heldout_readout(lens: str, gains, l1: float, settings: ChainSettings):
    """Held-out emitters: true rays, their noiseless raw amplitudes (n, 4) and readout points (n, 2)."""
    rays, spots = heldout_emitters(lens)
    amps = signal_amplitudes(spots, replace(settings, snr_db=None), gains, l1)
    return rays, amps, impact_point(amps, settings.lx_mm, settings.ly_mm)


def _params(res, prefix: str, rays=None, points=None) -> dict:
    out = {
        f"{prefix}cx_mm": res.intrinsics.cx_mm,
        f"{prefix}cy_mm": res.intrinsics.cy_mm,
        f"{prefix}f_mm": res.intrinsics.f_mm,
        f"{prefix}k1": res.distortion.k1,
        f"{prefix}k2": res.distortion.k2,
        # the paper's "residual": error between template points and re-projected image
        # points (Section 4.3); ours: RMS distance on the plate (template cost) or sensor
        f"{prefix}residual_mm": res.cost_rms,
        f"{prefix}rms_mm": res.rms_mm,
        f"{prefix}iterations": float(res.iterations),
    }
    if res.model.aspect:
        out[f"{prefix}fy_mm"] = res.intrinsics.fy
        out[f"{prefix}skew"] = res.intrinsics.skew
    if res.model.fit_gains:
        out.update({f"{prefix}g_x2": res.gains[1], f"{prefix}g_y1": res.gains[2], f"{prefix}g_y2": res.gains[3]})
    if rays is not None:
        err = aoa_error_deg(rays, rays_from_points(points, res.intrinsics, res.distortion))
        out[f"{prefix}aoa_rms_deg"] = float(np.sqrt(np.mean(err**2)))
    return out


def _nan_params(prefix: str, names) -> dict:
    return {f"{prefix}{n}": float("nan") for n in names}


_BASE_NAMES = ("cx_mm", "cy_mm", "f_mm", "k1", "k2", "residual_mm", "rms_mm", "iterations", "aoa_rms_deg")


def _calibrate(data_points, prefix, rays, heldout_points, names=_BASE_NAMES, **kw) -> dict:
    kw.setdefault("cost", "template")
    try:
        res = calibrate(default_template(), data_points, radial=2, tangential=False, **kw)
    except ConvergenceError as exc:  # keep the last iterate, flagged by its iteration count,
        if exc.result is None or implausible(exc.result):  # unless it is not a camera at all
            return _nan_params(prefix, names)
        res = exc.result
    except _CAL_ERRORS:
        return _nan_params(prefix, names)
    return _params(res, prefix, rays, heldout_points)


def case_trial(rng, *, lens: str, snr_db: float | None, imbalance: bool, psd: bool, kind: str = "plain") -> dict:
    """One trial of a case (:class:`Case`): simulate 9 views, calibrate with the paper's model.

    Returns a flat dict ``"<variant>.<parameter>" -> value`` with variants
    ``paper`` (template cost, preliminary corrections and normalisation),
    for ``kind="noise"`` also ``without`` (no preliminary correction, no
    normalisation) and ``image`` (image cost), and for ``kind="gain"`` the
    remedies of :func:`gain_trial`.  Parameters: ``cx_mm, cy_mm, f_mm, k1,
    k2, residual_mm`` (RMS of the minimised cost), ``rms_mm`` (sensor RMS),
    ``iterations`` (of the last LM stage), ``aoa_rms_deg`` (RMS angle error of
    held-out emitters, noiseless readout through the same electronics).
    """
    s = chain_settings(snr_db)
    gains = channel_gains(s, rng) if imbalance else channel_gains(s)
    if kind == "gain":
        return gain_trial(rng, lens=lens, snr_db=snr_db, gains=gains, psd=psd)
    data = simulate_trial(rng, lens, snr_db, gains, psd)
    rays, _, held = heldout_readout(lens, gains, data.l1, s)
    out = _calibrate(data.points_mm, "paper.", rays, held)
    if kind == "noise":
        out.update(_calibrate(data.points_mm, "without.", rays, held, preliminary=False, normalize=False))
        out.update(_calibrate(data.points_mm, "image.", rays, held, cost="image"))
    if kind == "psd":  # our model: the PSD's own radial term about the electrical centre
        out.update(_calibrate(data.points_mm, "l1.", rays, held, psd_radial=1))
    return out


def gain_trial(rng, *, lens: str, snr_db: float | None, gains=None, psd: bool = False, bench_snr_db: float | None = None,
               variants: str = "paper,a,b,c,d") -> dict:
    """One trial of the gain remedies on the same views (issue part 4).

    The same poses and noise stream are read out twice: through equal gains
    (``balanced.``: the no-imbalance reference, paper's model, image cost)
    and through the imbalanced ``gains``, on which:

    * ``paper.``: the paper's model ignoring the imbalance, template cost
      (the Tables 5-6 column), and ``a.`` the same with the image cost;
    * ``b.``: electrical calibration (7 x 7 known spots on the bare PSD
      through the same chain at ``bench_snr_db``, default the same SNR), the
      raw amplitudes corrected by :func:`psdcal.calibration.gains.apply_gains`, then the
      paper's model (image cost); held-out readings corrected the same way;
    * ``c.``: joint calibration ``calibrate(fit_gains=True)`` on the raw
      readout; held-out readings corrected with the fitted gains;
    * ``d.``: general intrinsic matrix (``aspect=True, skew=True``) on the raw
      readout.

    ``variants`` (comma-separated) selects the remedies computed besides
    ``balanced``.

    Returns
    -------
    dict
        ``"<variant>.<parameter>"``; the AoA error ``aoa_rms_deg`` for all.
    """
    want = {v.strip() for v in variants.split(",")}
    s = chain_settings(snr_db)
    if gains is None:
        gains = channel_gains(s, rng)
    gains = np.asarray(gains, dtype=float)
    intr, dist = LENSES[lens]
    l1 = PAPER_L1 if psd else 0.0
    rv, tv = random_poses(default_template(), intr, replace(dist, l1=l1), 9, rng)
    seed_noise = rng.integers(2**63)
    nominal = channel_gains(s)
    bal = simulate_trial(np.random.default_rng(seed_noise), lens, snr_db, nominal, psd, rvecs=rv, tvecs=tv)
    imb = simulate_trial(np.random.default_rng(seed_noise), lens, snr_db, gains, psd, rvecs=rv, tvecs=tv)
    rays, held_amps, held_raw = heldout_readout(lens, gains, l1, s)
    _, _, held_bal = heldout_readout(lens, nominal, l1, s)
    out = {}
    out.update(_calibrate(bal.points_mm, "balanced.", rays, held_bal, cost="image"))
    if "paper" in want:
        out.update(_calibrate(imb.points_mm, "paper.", rays, held_raw))
    if "a" in want:
        out.update(_calibrate(imb.points_mm, "a.", rays, held_raw, cost="image"))
    if "b" in want:
        out.update(_remedy_b(rng, imb, gains, held_amps, rays, chain_settings(snr_db if bench_snr_db is None else bench_snr_db)))
    if "c" in want:
        out.update(_remedy_c(imb, gains, held_raw, rays))
    if "d" in want:  # (d) general intrinsic matrix instead of gains
        out.update(_calibrate(imb.points_mm, "d.", rays, held_raw, cost="image", aspect=True, skew=True,
                              names=_BASE_NAMES + ("fy_mm", "skew")))
    return out


def _gain_errors(prefix: str, fitted, true_gains) -> dict:
    rel = np.asarray(true_gains, dtype=float) / true_gains[0]
    return {f"{prefix}g_{n}_err": float(fitted[i] - rel[i]) for i, n in ((1, "x2"), (2, "y1"), (3, "y2"))}


def _remedy_b(rng, imb: TrialData, gains, held_amps, rays, bench: ChainSettings) -> dict:
    """(b): electrical calibration on the bench, raw amplitudes corrected, then the paper's model."""
    from psdcal.calibration.gains import apply_gains

    s = imb.settings
    try:
        ecal = simulate_electrical_calibration(gains, bench, rng)
        corr = apply_gains(imb.amplitudes, ecal.gains)
        ok = np.all(np.isfinite(corr), axis=-1)
        pts_b = np.full(imb.points_mm.shape, np.nan)
        pts_b[ok] = impact_point(corr[ok], s.lx_mm, s.ly_mm)
        held_b = impact_point(apply_gains(held_amps, ecal.gains), s.lx_mm, s.ly_mm)
    except _CAL_ERRORS:
        return _nan_params("b.", _BASE_NAMES)
    return {**_calibrate(pts_b, "b.", rays, held_b, cost="image"), **_gain_errors("b.", ecal.gains, gains)}


def _remedy_c(imb: TrialData, gains, held_raw, rays) -> dict:
    """(c): joint calibration of gains and geometry; held-out readings corrected with the fitted gains."""
    s = imb.settings
    try:
        res = calibrate(imb.template_mm, imb.points_mm, cost="image", radial=2, tangential=False, fit_gains=True)
    except _CAL_ERRORS:  # ConvergenceError included: a failed joint fit counts as a failure
        return _nan_params("c.", _BASE_NAMES)
    held_c = correct_points(held_raw, res.gains, s.lx_mm, s.ly_mm)
    return {**_params(res, "c.", rays, held_c), **_gain_errors("c.", res.gains, gains)}


def initial_trial(rng, *, lens: str) -> dict:
    """One noiseless set through the linear stage only (Tables 1-2): four variants."""
    data = simulate_trial(rng, lens, float("nan"), channel_gains(chain_settings(float("nan"))), False)
    from psdcal.calibration.core import initial_estimate

    out = {}
    for name, pre, norm in (("noprelim_dlt", False, False), ("noprelim_norm", False, True),
                            ("prelim_dlt", True, False), ("prelim_norm", True, True)):
        try:
            est = initial_estimate(data.template_mm, data.points_mm, preliminary=pre, normalize=norm, radial_terms=2)
            out.update({f"{name}.cx_mm": est.intrinsics.cx_mm, f"{name}.cy_mm": est.intrinsics.cy_mm,
                        f"{name}.f_mm": est.intrinsics.f_mm})
        except _CAL_ERRORS:
            out.update({f"{name}.{p}": float("nan") for p in ("cx_mm", "cy_mm", "f_mm")})
    return out
