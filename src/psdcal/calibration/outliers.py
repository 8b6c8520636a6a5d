"""Outlier points and images of a calibration: flag them, remove them, refit.

A calibration point is an outlier when its residual on the sensor is far
larger than the noise: a LED that failed or was hidden, a reflection, a
point matched to the wrong template LED.  The noise level is estimated
robustly from the residuals themselves, so that the outliers do not inflate
it: with Gaussian noise of standard deviation ``sigma`` on each coordinate,
the residual length ``|r|`` follows a Rayleigh distribution whose median is
``sigma sqrt(2 ln 2)``, hence::

    sigma_robust = median(|r|) / sqrt(2 ln 2)

A point is flagged when ``|r| > k sigma_robust``.  For Gaussian noise the
chance of a clean point exceeding ``k sigma`` is ``exp(-k^2 / 2)``: 3.7e-6 at
``k = 5``.  An image is flagged when its sum of squared residuals is
improbable under that noise (a chi-square test, see :func:`flag_images`).

:func:`reject_outliers` removes flagged points (sets them missing) and refits
with :func:`psdcal.calibration.core.recalibrate` until none is left, largest first,
so that a gross error's pull on its neighbours does not get them removed too.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from psdcal.calibration.checks import align_to_problem, model_points_mm
from psdcal.errors import InputError, PsdcalError

#: Median of a unit Rayleigh distribution: median(|r|) = sigma * RAYLEIGH_MEDIAN.
RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))

#: Default threshold (in robust standard deviations) above which a point is an outlier.
DEFAULT_K = 5.0


def residual_norms_mm(residuals_mm) -> np.ndarray:
    """Lengths ``|r|`` (...,) of residual vectors (..., 2) in mm (NaN where missing)."""
    r = np.asarray(residuals_mm, dtype=float)
    return np.sqrt(np.sum(r * r, axis=-1))


def robust_sigma_mm(residuals_mm) -> float:
    """Robust noise standard deviation per coordinate, mm, from residual vectors.

    Parameters
    ----------
    residuals_mm : (..., 2) array_like
        Residual vectors on the sensor, mm; NaN where missing.

    Returns
    -------
    float
        ``median(|r|) / sqrt(2 ln 2)`` over the valid residuals (the sigma of
        the Rayleigh distribution with that median); NaN when there is none.
    """
    n = residual_norms_mm(residuals_mm)
    n = n[np.isfinite(n)]
    if n.size == 0:
        return float("nan")
    return float(np.median(n) / RAYLEIGH_MEDIAN)


def dof_factor(result) -> float:
    """``sqrt(m / (m - p))``: corrects a noise estimate from fitted residuals for the fitted parameters.

    ``m`` is the number of residual components (2 per valid point), ``p``
    the number of free parameters (global ones and 6 per pose). Fitted
    residuals are smaller than the noise by about ``sqrt((m - p) / m)``.
    """
    m = 2 * int(np.all(np.isfinite(np.asarray(result.residuals_mm, dtype=float)), axis=-1).sum())
    p = len(result.param_names) + 6 * len(result.image_ids)
    return float(np.sqrt(m / (m - p))) if m > p else 1.0


@dataclass(frozen=True)
class OutlierFlags:
    """Which points and images of a calibration look like outliers.

    Attributes
    ----------
    k : float
        Threshold in robust standard deviations.
    sigma_mm : float
        Robust noise standard deviation per coordinate, mm.
    ratio : (n_images, M) ndarray
        ``|r| / sigma_mm`` of every point (NaN where missing).
    points : (n_images, M) bool ndarray
        Points with ``|r| > k sigma_mm``.
    images : (n_images,) bool ndarray
        Images whose residuals are improbable under the noise (chi-square test).
    image_p_values : (n_images,) ndarray
        Upper-tail probability of each image's sum of squared residuals.
    """

    k: float
    sigma_mm: float
    ratio: np.ndarray
    points: np.ndarray
    images: np.ndarray
    image_p_values: np.ndarray

    @property
    def n_points(self) -> int:
        """Number of flagged points."""
        return int(self.points.sum())


def flag_images(residuals_mm, sigma_mm: float, *, alpha: float = 1e-3):
    """Images whose residuals are too large for the noise level.

    Under Gaussian noise of standard deviation ``sigma_mm`` per coordinate,
    an image with ``n`` points has ``sum |r|^2 / sigma^2`` close to a
    chi-square variable with ``2 n`` degrees of freedom (a little less: the
    fit absorbs some of the noise, which makes the test conservative).  An
    image is flagged when its upper-tail probability is below
    ``alpha / n_images`` (Bonferroni over the images).

    Parameters
    ----------
    residuals_mm : (n_images, M, 2) array_like, NaN where missing.
    sigma_mm : float
    alpha : float
        Family-wise false-alarm probability for the whole set.

    Returns
    -------
    flagged : (n_images,) bool ndarray
    p_values : (n_images,) ndarray
    """
    from scipy.special import chdtrc  # chi-square survival function (lighter than scipy.stats)

    r = np.asarray(residuals_mm, dtype=float)
    ok = np.all(np.isfinite(r), axis=-1)
    ss = np.sum(np.where(ok[..., None], r, 0.0) ** 2, axis=(-1, -2))
    dof = 2 * ok.sum(axis=-1)
    if not np.isfinite(sigma_mm) or sigma_mm <= 0:
        p = np.ones(r.shape[0])
    else:
        p = np.where(dof > 0, chdtrc(np.maximum(dof, 1), ss / sigma_mm**2), 1.0)
    return p < alpha / max(r.shape[0], 1), p


def flag_outliers(result, k: float = DEFAULT_K, *, alpha: float = 1e-3, refit: bool = False) -> OutlierFlags:
    """Flag the outlier points and images of a calibration.

    Parameters
    ----------
    result : CalibrationResult
        Uses ``result.residuals_mm`` (n_images, M, 2), mm.
    k : float
        A point is flagged when ``|r| > k sigma_robust``.
    alpha : float
        False-alarm probability of the image test (:func:`flag_images`).
    refit : bool
        Flag only the points :func:`reject_outliers` would remove (a trial
        rejection with refits).  A gross error pulls its image's pose, which
        can lift clean neighbours over the threshold; the trial refit tells
        them apart.  Needs the calibration's problem record; without one the
        plain threshold is used.  The image test then leaves the flagged
        points out.

    Returns
    -------
    OutlierFlags
    """

    _check_k(k)
    result = align_to_problem(result)
    r = np.asarray(result.residuals_mm, dtype=float)
    sigma = robust_sigma_mm(r) * dof_factor(result)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = residual_norms_mm(r) / sigma
    points = np.nan_to_num(ratio, nan=0.0) > k
    if refit and points.any() and all(key in (result.problem or {}) for key in ("points", "template", "options")):
        try:
            trial = reject_outliers(result, k)
        except PsdcalError:  # a refit failed: keep the plain threshold
            trial = None
        if trial is not None:
            index_i = {iid: i for i, iid in enumerate(result.image_ids)}
            index_j = {pid: j for j, pid in enumerate(result.point_ids)}
            points = np.zeros_like(points)
            for p in trial.removed:
                points[index_i[p.image_id], index_j[p.point_id]] = True
    images, p = flag_images(np.where(points[..., None], np.nan, r), sigma, alpha=alpha)
    return OutlierFlags(float(k), sigma, ratio, points, images, p)


@dataclass(frozen=True)
class RemovedPoint:
    """A point removed as an outlier.

    Attributes
    ----------
    image_id, point_id : identifiers of the point.
    x_mm, y_mm : float
        The measured impact point, mm.
    dx_mm, dy_mm : float
        Its residual (measured minus modelled) against the **final** fit, mm.
    ratio : float
        ``|r| / sigma_mm`` against the final fit and the final robust sigma.
    round : int
        The refit round in which it was removed (1-based).
    line : int or None
        Its line in the points file, when known.
    """

    image_id: object
    point_id: object
    x_mm: float
    y_mm: float
    dx_mm: float
    dy_mm: float
    ratio: float
    round: int
    line: int | None = None

    @property
    def residual_mm(self) -> float:
        """Length of the residual, mm."""
        return float(np.hypot(self.dx_mm, self.dy_mm))

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["residual_mm"] = self.residual_mm
        return d


@dataclass(frozen=True)
class RejectionResult:
    """What :func:`reject_outliers` did.

    Attributes
    ----------
    result : CalibrationResult
        The final fit, with the rejection recorded in
        ``result.problem["outlier_rejection"]`` (see :func:`rejection_record`).
    removed : tuple of RemovedPoint
    k : float
    sigma_mm : float
        Robust noise estimate of the final fit, mm.
    rounds : int
        Number of refits done.
    kept_flagged : tuple of (image_id, point_id)
        Points still above the threshold that were kept, because removing
        them would have left an image with too few points or exceeded
        ``max_fraction``.
    """

    result: object
    removed: tuple
    k: float
    sigma_mm: float
    rounds: int
    kept_flagged: tuple = ()


def _check_k(k):
    if not (isinstance(k, (int, float, np.floating)) and np.isfinite(k) and k > 0):
        raise InputError(f"the outlier threshold K must be a positive number, got {k!r}", field="k")


def _refit(result, points_mm):
    from psdcal.calibration.core import _jsonable, recalibrate

    d = result.to_dict()
    d["problem"] = {**d["problem"], "points": {**d["problem"]["points"], "xy_mm": _jsonable(points_mm)}}
    return recalibrate(d, verdict=False)


class SystematicMisfitError(PsdcalError, ValueError):
    """``--reject`` refused: the misfit is systematic (a wrong model, gains or template), not a few bad points."""


#: --reject is refused when a smooth field explains more than this fraction of the residuals left.
SYSTEMATIC_FRACTION = 0.5


def _rest_dof(result, exclude, ch) -> float:
    """The F statistic's denominator degrees of freedom times 1 (so that F dof1 / (F dof1 + dof2) is the explained
    fraction)."""
    from psdcal.calibration._verdict_linear import linearise

    return float(linearise(result, exclude).dof - ch.dof)


def refuse_if_systematic(result, k: float = DEFAULT_K, *, points_kind=None, alpha: float | None = None) -> None:
    """Raise :class:`SystematicMisfitError` when the residuals, without the points above ``k`` sigma, still show a
    structure that moves the result.

    Removing points cannot repair a misfit that a smooth field over the sensor
    explains: deleting the worst points of such a fit deletes good points and
    leaves a wrong calibration. The test is the verdict's ``structure`` check
    on the points that would remain (:func:`psdcal.calibration.verdict.structure_judged`):
    refused when the field fails it (significant at the verdict's false-alarm
    rate and moving f, C or the angles by a standard error or more) *and*
    either explains more than :data:`SYSTEMATIC_FRACTION` of the remaining
    residual sum of squares (the misfit is mostly systematic) or moves the
    result by :data:`~psdcal.calibration.verdict.EFFECT_WRONG` standard errors
    or more. A systematic pattern that is a small part of the residuals (real
    lenses, thousands of points) does not block the rejection of a few bad
    points; the verdict of the refit reports it. The message carries the
    verdict's diagnosis (the command that fixes the cause).
    """
    from psdcal.calibration.verdict import ALPHA, EFFECT_WRONG, assess, structure_judged

    alpha = ALPHA if alpha is None else alpha
    flags = flag_outliers(align_to_problem(result), k)
    ch = structure_judged(result, exclude=flags.points, alpha=alpha)
    if ch is None or ch.passed is not False:
        return
    frac = ch.dof and ch.statistic * ch.dof / (ch.statistic * ch.dof + _rest_dof(result, flags.points, ch))
    if frac <= SYSTEMATIC_FRACTION and (ch.effect_sigma or 0.0) < EFFECT_WRONG:
        return  # a few bad points on top of a small systematic pattern: reject them; the verdict reports the rest
    v = assess(result, points_kind=points_kind)
    advice = next((c.advice for c in v.failed if c.name == "structure" and c.advice), "") or \
        next((c.advice for c in v.failed if c.advice), "")
    raise SystematicMisfitError(
        f"--reject refused: the misfit is systematic, not a few bad points (with the {int(flags.points.sum())} point(s) "
        f"above {k:g} sigma left out, a smooth field over the sensor still explains the residuals: F = {ch.statistic:.3g}, "
        f"p = {ch.p_value:.2g}, and removing it moves the result by {ch.effect_sigma:.2g} sigma); removing points "
        "would delete good ones" + (f". {advice}" if advice else "")
    )


def reject_outliers(
    result,
    k: float = DEFAULT_K,
    *,
    line_numbers=None,
    max_rounds: int = 20,
    max_fraction: float = 0.2,
    min_points_per_image: int = 6,
) -> RejectionResult:
    """Remove points whose residual exceeds ``k`` robust sigmas, refit, repeat.

    Each round removes the flagged points whose residual is at least half
    the largest residual (the gross errors first: their pull on the fit
    can push a clean neighbour over the threshold, which the refit undoes),
    then refits with the same options (:func:`psdcal.calibration.core.recalibrate`).
    It stops when no point is above ``k sigma_robust`` or after
    ``max_rounds`` refits.

    Parameters
    ----------
    result : CalibrationResult
        A calibration whose ``problem`` record holds the template, the points
        and the options (every result of :func:`psdcal.calibrate` does).
    k : float
        Threshold in robust standard deviations (:func:`robust_sigma_mm`).
    line_numbers : (n_images, M) array_like of int, optional
        Line of each point in its file (``PointsFile.line_numbers``), to name
        the removed points' lines.
    max_rounds : int
        Most refits.
    max_fraction : float
        Never remove more than this fraction of the valid points.
    min_points_per_image : int
        Never leave an image with fewer valid points than this.

    Returns
    -------
    RejectionResult
        ``.result`` is the final fit (the input itself when nothing was
        removed), with the record of the rejection in its ``problem``.

    Raises
    ------
    InputError
        ``k`` not positive, or a result without its problem record.
    ConvergenceError, DegenerateViewsError
        From a refit.
    """

    _check_k(k)
    if "points" not in (result.problem or {}) or "template" not in (result.problem or {}):
        raise InputError("the calibration holds no problem record (points, template); cannot refit", field="problem")
    from psdcal.calibration.core import points_from_record

    result = align_to_problem(result)
    X0 = points_from_record(result.problem["points"]["xy_mm"])
    X = X0.copy()
    n_valid0 = int(np.all(np.isfinite(X0), axis=-1).sum())
    budget = int(np.floor(max_fraction * n_valid0))
    removed_at: dict = {}
    kept: set = set()
    cur = result
    rounds = 0
    while rounds < max_rounds:
        flags = flag_outliers(cur, k)
        ratio = np.nan_to_num(flags.ratio, nan=0.0)
        cand = flags.points.copy()
        for ij in kept:
            cand[ij] = False
        if not cand.any():
            break
        cand &= ratio >= 0.5 * ratio[cand].max()
        valid = np.all(np.isfinite(X), axis=-1)
        take = []
        left = valid.sum(axis=1)
        for i, j in sorted(zip(*np.nonzero(cand)), key=lambda ij: -ratio[ij]):
            if len(removed_at) + len(take) >= budget or left[i] - 1 < min_points_per_image:
                kept.add((int(i), int(j)))
                continue
            take.append((int(i), int(j)))
            left[i] -= 1
        if not take:
            continue  # all candidates are kept; look again for others
        rounds += 1
        for i, j in take:
            X[i, j] = np.nan
            removed_at[(i, j)] = rounds
        cur = _refit(cur, X)
    sigma = robust_sigma_mm(cur.residuals_mm) * dof_factor(cur)
    model = model_points_mm(cur) if removed_at else None
    lines = None if line_numbers is None else np.asarray(line_numbers)
    removed = []
    for (i, j), rnd in sorted(removed_at.items(), key=lambda kv: (kv[1], kv[0])):
        r = X0[i, j] - model[i, j]
        line = None if lines is None or not lines[i, j] else int(lines[i, j])
        removed.append(
            RemovedPoint(
                image_id=cur.image_ids[i], point_id=cur.point_ids[j],
                x_mm=float(X0[i, j, 0]), y_mm=float(X0[i, j, 1]),
                dx_mm=float(r[0]), dy_mm=float(r[1]),
                ratio=float(np.hypot(*r) / sigma), round=rnd, line=line,
            )
        )
    kept_ids = tuple((cur.image_ids[i], cur.point_ids[j]) for i, j in sorted(kept))
    rej = RejectionResult(cur, tuple(removed), float(k), sigma, rounds, kept_ids)
    final = dataclasses.replace(cur, problem={**cur.problem, "outlier_rejection": rejection_record(rej)})
    return dataclasses.replace(rej, result=final)


def rejection_record(rej: RejectionResult) -> dict:
    """The JSON record of a rejection, kept in ``problem["outlier_rejection"]``.

    Keys: ``k``, ``sigma_mm``, ``rounds``, ``removed`` (list of
    :meth:`RemovedPoint.to_dict`), ``kept_flagged`` (list of [image_id, point_id]).
    """
    return {
        "k": rej.k,
        "sigma_mm": rej.sigma_mm,
        "rounds": rej.rounds,
        "removed": [p.to_dict() for p in rej.removed],
        "kept_flagged": [list(p) for p in rej.kept_flagged],
    }


def removed_points(result) -> tuple:
    """The points a calibration's outlier rejection removed (empty when none).

    Reads ``result.problem["outlier_rejection"]["removed"]`` (also from a
    calibration loaded from JSON).

    Returns
    -------
    tuple of RemovedPoint
    """
    rec = (result.problem or {}).get("outlier_rejection") or {}
    names = {f.name for f in dataclasses.fields(RemovedPoint)}
    out = []
    for d in rec.get("removed", []) or []:
        out.append(RemovedPoint(**{k: v for k, v in d.items() if k in names}))
    return tuple(out)


__all__ = [
    "DEFAULT_K",
    "OutlierFlags",
    "RemovedPoint",
    "dof_factor",
    "RejectionResult",
    "flag_images",
    "flag_outliers",
    "model_points_mm",
    "reject_outliers",
    "rejection_record",
    "removed_points",
    "residual_norms_mm",
    "robust_sigma_mm",
]
