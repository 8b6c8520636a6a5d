"""Tail probabilities of the chi-squared and F distributions, without scipy.

The verdict of every calibration (:mod:`psdcal.calibration.verdict`) needs a
handful of p-values and critical values; importing ``scipy.special`` for them
would cost a fresh ``psdcal calibrate`` process more than the calibration
itself. These functions use only :mod:`math` (numpy only in
:func:`std_standard_error`, the Monte Carlo standard error of a std; the
incomplete beta's and gamma's loops compiled where numba is already loaded,
after the process's first hundred tails):

- the chi-squared survival function is the regularised upper incomplete gamma
  function, ``Q(k/2, x/2)``, by its power series below ``a + 1`` and its
  continued fraction above (both converge fast there);
- the F survival function is the regularised incomplete beta function,
  ``I_{d2 / (d2 + d1 x)}(d2/2, d1/2)``, by its continued fraction (evaluated
  with the modified Lentz method, using the symmetry
  ``I_x(a, b) = 1 - I_{1-x}(b, a)`` on the side where it converges);
- the inverse survival functions by safeguarded Newton steps on
  ``log sf`` inside a bracket (bisection when a step leaves it).

``tests/test_stats.py`` checks them against ``scipy.special`` to 1e-10
relative over the ranges the verdict uses.
"""
from __future__ import annotations

import math

import psdcal._jit as _jit

#: The tails computed in a process by the Python loops before the compiled ones are used (where numba is loaded):
#: loading a compiled loop from numba's cache costs a process some 3 ms, what the Python loops take for about a
#: hundred tails (10-40 us each at the verdict's degrees of freedom, 1-3 us compiled). A one-shot command's verdict
#: (a dozen tails) never loads them; a Monte Carlo run or a benchmark does after its first verdicts.
COMPILED_AFTER = 100
_n_tails = 0


def _compiled_pays() -> bool:
    """Whether this tail takes the compiled loops: numba loaded and :data:`COMPILED_AFTER` tails done already."""
    global _n_tails
    if _n_tails < COMPILED_AFTER:
        _n_tails += 1
        return False
    return _jit.loaded()


_EPS = 1e-15
_TINY = 1e-300
_MAX_TERMS = 10_000


def _gamma_p_sum(a: float, x: float) -> float:
    """The power series of P(a, x) without its front factor: ``sum_n x^n / (a (a + 1) ... (a + n))``."""
    term = 1.0 / a
    total = term
    ap = a
    for _ in range(_MAX_TERMS):
        ap += 1.0
        term *= x / ap
        total += term
        if abs(term) < abs(total) * _EPS:
            break
    return total


def _gamma_p_series(a: float, x: float) -> float:
    """Regularised lower incomplete gamma P(a, x) by its power series (x < a + 1)."""
    total = (_gamma_p_sum_compiled if _compiled_pays() else _gamma_p_sum)(float(a), float(x))
    return total * math.exp(-x + a * math.log(x) - math.lgamma(a))


def _gamma_fraction(a: float, x: float) -> float:
    """The continued fraction of Q(a, x) without its front factor (converges for x >= a + 1), Lentz's method."""
    b = x + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    # each term b + an / ... by the modified Lentz method, written out (no call per term)
    tiny = _TINY
    for i in range(1, _MAX_TERMS):
        b += 2.0
        an = -i * (i - a)
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < _EPS:
            break
    return h


def _gamma_q_fraction(a: float, x: float) -> float:
    """Regularised upper incomplete gamma Q(a, x) by its continued fraction (x >= a + 1), Lentz's method."""
    h = (_gamma_fraction_compiled if _compiled_pays() else _gamma_fraction)(float(a), float(x))
    return math.exp(-x + a * math.log(x) - math.lgamma(a)) * h


def gamma_q(a: float, x: float) -> float:
    """Regularised upper incomplete gamma function Q(a, x) = Gamma(a, x) / Gamma(a), a > 0, x >= 0."""
    if x <= 0.0:
        return 1.0
    if x < a + 1.0:
        return 1.0 - _gamma_p_series(a, x)
    return _gamma_q_fraction(a, x)


def _beta_fraction(a: float, b: float, x: float) -> float:
    """The continued fraction of the incomplete beta function (converges for x < (a + 1) / (a + b + 2))."""
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c = 1.0
    d = 1.0 - qab * x / qap
    d = _TINY if abs(d) < _TINY else d
    d = 1.0 / d
    h = d
    # the two Lentz steps of each m written out (b_n = 1; as in :func:`_gamma_fraction`, the same operations in the same
    # order): the p-values of a verdict spend most of their time in this loop's calls otherwise
    tiny = _TINY
    for m in range(1, _MAX_TERMS):
        m2 = 2 * m
        an = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = an * d + 1.0
        d = tiny if abs(d) < tiny else d
        c = 1.0 + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        h *= d * c
        an = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = an * d + 1.0
        d = tiny if abs(d) < tiny else d
        c = 1.0 + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < _EPS:
            break
    return h


#: :func:`_beta_fraction`, :func:`_gamma_fraction` and :func:`_gamma_p_sum` compiled (the same operations in the
#: same order: the same numbers), used once numba is loaded in the process by another kernel (a light command never
#: imports it for a p-value) and the process has computed :data:`COMPILED_AFTER` tails (:func:`_compiled_pays`)
_beta_fraction_compiled = _jit.lazy_njit(_beta_fraction)
_gamma_fraction_compiled = _jit.lazy_njit(_gamma_fraction)
_gamma_p_sum_compiled = _jit.lazy_njit(_gamma_p_sum)


def beta_i(a: float, b: float, x: float, y: float | None = None) -> float:
    """Regularised incomplete beta function I_x(a, b), a, b > 0, 0 <= x <= 1.

    ``y`` is ``1 - x`` when the caller has it more accurately than ``1 - x``
    rounds to (x near 1).
    """
    y = 1.0 - x if y is None else y
    if x <= 0.0:
        return 0.0
    if y <= 0.0:
        return 1.0
    log_front = (math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log(y))
    fraction = _beta_fraction_compiled if _compiled_pays() else _beta_fraction
    if x < (a + 1.0) / (a + b + 2.0):
        return math.exp(log_front) * fraction(float(a), float(b), float(x)) / a
    return 1.0 - math.exp(log_front) * fraction(float(b), float(a), float(y)) / b


def chi2_sf(x: float, k: float) -> float:
    """P(X > x) for X chi-squared with k degrees of freedom."""
    if not k > 0:
        raise ValueError(f"chi2 degrees of freedom must be positive, got {k}")
    return gamma_q(0.5 * k, 0.5 * max(float(x), 0.0))


def f_sf(x: float, d1: float, d2: float) -> float:
    """P(X > x) for X F-distributed with (d1, d2) degrees of freedom."""
    if not (d1 > 0 and d2 > 0):
        raise ValueError(f"F degrees of freedom must be positive, got ({d1}, {d2})")
    x = float(x)
    if x <= 0.0:
        return 1.0
    if math.isinf(x):
        return 0.0
    den = d2 + d1 * x
    return beta_i(0.5 * d2, 0.5 * d1, d2 / den, d1 * x / den)


def _chi2_logpdf(x: float, k: float) -> float:
    h = 0.5 * k
    return (h - 1.0) * math.log(x) - 0.5 * x - h * math.log(2.0) - math.lgamma(h)


def _f_logpdf(x: float, d1: float, d2: float) -> float:
    a, b = 0.5 * d1, 0.5 * d2
    return (a * math.log(d1 / d2) + (a - 1.0) * math.log(x) - (a + b) * math.log1p(d1 * x / d2)
            - (math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)))


def _isf(sf, logpdf, alpha: float, guess: float) -> float:
    """x with sf(x) = alpha: Newton on log sf inside an expanding bracket, bisection as safeguard."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    lo, hi = 0.0, max(guess, 1e-8)
    while sf(hi) > alpha:
        lo, hi = hi, 2.0 * hi
        if hi > 1e300:
            return math.inf
    x = 0.5 * (lo + hi) if not lo < guess < hi else guess
    target = math.log(alpha)
    for _ in range(200):
        s = sf(x)
        if s > alpha:
            lo = x
        else:
            hi = x
        g = math.log(max(s, _TINY)) - target
        # d log sf / dx = -pdf / sf
        pdf = math.exp(logpdf(x)) if x > 0 else 0.0  # underflows far in the tail of a large dof
        step = g / (pdf / max(s, _TINY)) if pdf > 0.0 else math.inf  # inf: a bisection step
        nx = x + step
        if not lo < nx < hi:
            nx = 0.5 * (lo + hi)
        if abs(nx - x) <= 1e-14 * max(abs(x), 1e-300) or hi - lo <= 1e-15 * hi:
            return nx
        x = nx
    return x


def chi2_isf(alpha: float, k: float) -> float:
    """The x with chi2_sf(x, k) = alpha (the upper-alpha critical value)."""
    return _isf(lambda x: chi2_sf(x, k), lambda x: _chi2_logpdf(x, k), alpha, max(float(k), 1.0))


def f_isf(alpha: float, d1: float, d2: float) -> float:
    """The x with f_sf(x, d1, d2) = alpha (the upper-alpha critical value)."""
    return _isf(lambda x: f_sf(x, d1, d2), lambda x: _f_logpdf(x, d1, d2), alpha, 1.0)


def std_standard_error(values) -> float:
    """Standard error of the sample standard deviation, without assuming normality.

    ``var(s^2) ~ (m4 - s^4 (n - 3) / (n - 1)) / n`` (``m4`` the fourth
    central sample moment) and ``se(s) = sqrt(var(s^2)) / (2 s)`` (delta
    method).  For normal data this is ``s / sqrt(2 (n - 1))``.  NaNs are
    ignored; NaN for fewer than 2 values or ``s = 0``.

    Parameters
    ----------
    values : (n,) array_like

    Returns
    -------
    float
    """
    import numpy as np

    v = np.asarray(values, dtype=float).ravel()
    v = v[np.isfinite(v)]
    n = v.size
    if n < 2:
        return float("nan")
    s2 = v.var(ddof=1)
    if s2 == 0:
        return float("nan")
    m4 = np.mean((v - v.mean()) ** 4)
    var_s2 = (m4 - s2 * s2 * (n - 3) / (n - 1)) / n
    return float(np.sqrt(max(var_s2, 0.0)) / (2.0 * np.sqrt(s2)))



__all__ = ["beta_i", "chi2_isf", "chi2_sf", "f_isf", "f_sf", "gamma_q", "std_standard_error"]
