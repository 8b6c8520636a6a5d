"""One vocabulary of self-checks for every least-squares answer psdcal gives.

Calibration, rotation-stage directions, gains, pose, bundle adjustment,
triangulation, locate and tracking all end the same way: a weighted residual
sum of squares ``chi2`` with ``dof`` degrees of freedom, where the weights are
the noise the user (or the demodulator) stated. If that noise is right and the
model holds, ``chi2 ~ chi^2(dof)``. This module turns that one fact into a
:class:`Check` with the same fields, JSON and wording everywhere:

- the statistic, its degrees of freedom, its p-value and the design
  false-alarm rate ``alpha`` of the test;
- whether it passed, and how much the failure moves the result *in its own
  sigmas* (``effect_sigma``);
- what happens to the covariance: when the data disagree with the stated
  noise beyond ``alpha``, the covariance is multiplied by ``inflation``
  (the documented rule below) so that the stated uncertainty covers the error
  the data show; a warning line gives its size.

Inflation rules
---------------
``"ratio"`` (default, Birge ratio)
    ``inflation = chi2 / dof``: every weight was too large by the same factor.
    Sigmas grow by ``sqrt(chi2 / dof)``.
``"extra"`` (:func:`extra_variance`)
    An extra, independent noise of variance ``s2`` added to every residual's
    stated variance, with ``s2`` such that ``sum r_i^2 / (v_i + s2) = dof``.
    Better when the stated noises differ a lot between residuals (a fixed
    unmodelled error dominates the quiet ones).

Neither rule is applied when the test passes: on correct data the covariance
is left as it is in a fraction ``1 - alpha`` of cases (the false-alarm rate
of the inflation is ``alpha``).

``effect_sigma`` of an inflated covariance is ``sqrt(inflation) - 1``: by how
many of its own (stated) sigmas an error of one real sigma could lie outside
the stated one-sigma band. Checks that refit (leave one view out, a richer
model) give their own effect: the shift of the result over its standard error.

This module imports only :mod:`math`, :mod:`numpy` and :mod:`psdcal._stats`,
so every layer can use it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from psdcal._stats import chi2_isf, chi2_sf

#: Design false-alarm rate of a chi-squared consistency check (p-value threshold).
ALPHA = 1e-3
#: Verdict words, shared with the calibration verdict.
VERDICTS = ("good", "suspect", "wrong")


@dataclass(frozen=True)
class Check:
    """One self-check of a result.

    Attributes
    ----------
    name : str
        What was checked (``"noise"``, ``"structure"``, ``"pose_chi2"``, ...).
    statistic : float or None
        The test statistic (chi^2, F, a length, ...).
    threshold : float or None
        The value of the statistic beyond which the check fails.
    p_value : float or None
        Probability of a statistic this extreme when the model and the stated noise hold.
    false_alarm : float
        Design false-alarm rate on correct data (0 for plausibility rules).
    passed : bool or None
        None: not applicable (no redundancy, no noise given).
    message : str
        What was found, in one line.
    advice : str
        The likely cause and what to do ("" when passed).
    severe : bool
        A failure that makes the result wrong (not only its sigmas).
    dof : float or None
        Degrees of freedom of the statistic.
    effect_sigma : float or None
        How much the problem moves the result, in the result's own standard errors.
    inflation : float or None
        The factor applied to the covariance because of this check (1: none).
    """

    name: str
    statistic: float | None
    threshold: float | None
    p_value: float | None
    false_alarm: float
    passed: bool | None
    message: str
    advice: str = ""
    severe: bool = False
    dof: float | None = None
    effect_sigma: float | None = None
    inflation: float | None = None

    def to_dict(self) -> dict:
        # the fields are scalars and strings: a shallow dict is ``asdict`` without its deep copies (a tenth of the cost)
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        for k in ("statistic", "threshold", "p_value", "dof", "effect_sigma", "inflation"):
            if d[k] is not None:
                d[k] = float(d[k])
        for k in ("passed", "severe"):  # numpy's bool_ is not JSON
            if d[k] is not None:
                d[k] = bool(d[k])
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Check":
        names = cls.__dataclass_fields__
        return cls(**{k: v for k, v in d.items() if k in names})

    def line(self) -> str:
        """The check as one line (``name: message``), for warnings and summaries."""
        return f"{self.name}: {self.message}"


def verdict_of(checks) -> str:
    """``wrong`` if a severe check failed, ``suspect`` if another failed, else ``good``."""
    failed = [c for c in checks if c.passed is False]
    if any(c.severe for c in failed):
        return "wrong"
    return "suspect" if failed else "good"


def chi2_check(chi2: float, dof: float, *, name: str = "chi2", what: str = "the residuals",
               alpha: float = ALPHA, inflate: bool = True, advice: str = "") -> Check:
    """The chi-squared consistency test of a weighted least-squares fit.

    Parameters
    ----------
    chi2 : float
        Weighted residual sum of squares at the solution (dimensionless).
    dof : float
        Its degrees of freedom (residuals minus estimated parameters).
    name : str
        The check's name in the JSON (``"pose_chi2"``, ``"triangulation_chi2"``, ...).
    what : str
        The data in words, for the message ("the angles of 12 emitters").
    alpha : float
        The false-alarm rate: the check fails when ``P(chi^2(dof) > chi2) < alpha``.
    inflate : bool
        Whether a failure inflates the covariance by the ratio rule.
    advice : str
        The likely causes, for the failed case.

    Returns
    -------
    Check
        ``passed`` is None when ``dof <= 0`` (nothing to check); ``inflation``
        is ``chi2 / dof`` when the check failed and ``inflate``, else 1.
    """
    chi2 = float(chi2)
    if not dof > 0:
        return Check(name, chi2, None, None, alpha, None,
                     f"{what}: no redundancy (dof {dof:g}), the fit cannot be checked", dof=float(dof),
                     inflation=1.0)
    if not math.isfinite(chi2):
        return Check(name, chi2, None, 0.0, alpha, False, f"{what}: chi2 is not finite", advice=advice,
                     severe=True, dof=float(dof), inflation=1.0)
    p = chi2_sf(chi2, dof)
    thr = chi2_isf(alpha, dof)
    ratio = chi2 / dof
    if p >= alpha:
        return Check(name, chi2, thr, p, alpha, True,
                     f"{what} agree with the stated noise (chi2 {chi2:.4g} for {dof:g} dof, p = {p:.2g})",
                     dof=float(dof), effect_sigma=0.0, inflation=1.0)
    infl = ratio if inflate else 1.0
    msg = (f"{what} disagree with the stated noise: chi2 {chi2:.4g} for {dof:g} dof (p = {p:.2g}), "
           f"the noise is {math.sqrt(ratio):.3g}x the stated one")
    if inflate:
        msg += f"; covariance inflated x{infl:.4g} (sigmas x{math.sqrt(infl):.3g})"
    return Check(name, chi2, thr, p, alpha, False, msg, advice=advice, dof=float(dof),
                 effect_sigma=math.sqrt(ratio) - 1.0, inflation=infl)


def extra_variance(r, var, dof: float, *, tol: float = 1e-10) -> float:
    """The extra noise variance ``s2 >= 0`` with ``sum r_i^2 / (var_i + s2) = dof``.

    Parameters
    ----------
    r : (m,) array_like
        Residuals (any unit).
    var : (m,) array_like
        Their stated variances (the same unit squared), > 0.
    dof : float
        Degrees of freedom of the fit.

    Returns
    -------
    float
        ``s2`` in the residuals' unit squared; 0 when ``sum r^2 / var <= dof``.
    """
    r2 = np.asarray(r, dtype=float) ** 2
    v = np.asarray(var, dtype=float)
    if not dof > 0 or r2.size == 0:
        return 0.0
    if float(np.sum(r2 / v)) <= dof:
        return 0.0
    lo, hi = 0.0, max(float(np.sum(r2)) / dof, 1e-300)
    while float(np.sum(r2 / (v + hi))) > dof:  # pragma: no cover - sum r2 / dof already brackets it
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if float(np.sum(r2 / (v + mid))) > dof:
            lo = mid
        else:
            hi = mid
        if hi - lo <= tol * hi:
            break
    return 0.5 * (lo + hi)


def inflate(cov, check: Check):
    """The covariance multiplied by the check's ``inflation`` (unchanged when it is 1 or None)."""
    f = 1.0 if check.inflation is None else float(check.inflation)
    if f == 1.0:
        return cov
    return np.asarray(cov, dtype=float) * f


def with_advice(check: Check, advice: str) -> Check:
    """The check with its advice replaced (for a stage that knows its likely causes)."""
    return replace(check, advice=advice)


__all__ = ["ALPHA", "Check", "VERDICTS", "chi2_check", "extra_variance", "extra_variance_on_grid", "inflate", "verdict_of",
           "with_advice"]


def extra_variance_on_grid(grid, sums, dof: float) -> float:
    """:func:`extra_variance` from sums pooled over many calls (bounded memory).

    Parameters
    ----------
    grid : (g,) array_like
        Increasing trial values of the extra variance ``s2`` (> 0, log-spaced).
    sums : (g,) array_like
        ``sum_i r_i^2 / (var_i + s2)`` over all residuals for each ``s2`` of ``grid``.
    dof : float
        Degrees of freedom of the pooled residuals.

    Returns
    -------
    float
        The ``s2`` where the sums cross ``dof`` (log-log interpolation between
        grid points); 0 when even the smallest ``s2`` gives ``sums <= dof``,
        the largest grid value when they never come down to ``dof``.
    """
    g = np.asarray(grid, dtype=float)
    f = np.asarray(sums, dtype=float)
    if not dof > 0 or f.size == 0 or f[0] <= dof:
        return 0.0
    below = np.flatnonzero(f <= dof)
    if below.size == 0:
        return float(g[-1])
    j = int(below[0])
    x0, x1 = math.log(g[j - 1]), math.log(g[j])
    y0, y1 = math.log(f[j - 1]), math.log(max(f[j], 1e-300))
    x = x0 + (math.log(dof) - y0) * (x1 - x0) / (y1 - y0) if y1 != y0 else x1
    return float(math.exp(x))
