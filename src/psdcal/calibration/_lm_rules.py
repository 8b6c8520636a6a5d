"""The acceptance and damping rules of Levenberg-Marquardt, for the compiled loops.

:func:`psdcal.calibration._lm.levenberg_marquardt` (the Python loop, the
reference) states them; the compiled loops of the image cost
(:mod:`psdcal.calibration._lm_kernel`) and of the line-straightness step
(:mod:`psdcal.calibration._straightness_kernel`) take them from here, so that
the three follow one rule. Each loop stops before a trial point when
:func:`negligible_decrement` holds at the current point.
"""
from __future__ import annotations

import math

from psdcal._jit import njit_inline


@njit_inline
def trial_verdict(F, F_new, pred, nu, ftol):
    """Whether a trial step is taken: ``(accept, small, rho)``.

    ``F``, ``F_new``: half the squared residual norm before and at the trial;
    ``pred``: the reduction the linear model predicts; ``nu``: the damping's
    growth factor (2 right after an accepted step). The gain ratio ``rho``
    accepts a step that reduces the cost; at the optimum to round-off, the
    first step after an accepted one that predicts and makes a relative change
    below ``ftol`` is taken as the last one (MINPACK's ftol test); ``small``:
    the relative reduction is below ``ftol`` (stop after taking it).
    """
    rho = (F - F_new) / pred if pred > 0 else -1.0
    final = nu == 2.0 and 0 < pred <= ftol * F and abs(F - F_new) <= ftol * F
    accept = (rho > 0 or final) and math.isfinite(F_new)
    small = final or ((F - F_new) <= ftol * F and pred <= ftol * F)
    return accept, small, rho


@njit_inline
def negligible_decrement(dec, F, ftol):
    """Whether the Gauss-Newton model of the cost at the current point promises no reduction above ``ftol``
    of it: the loop then stops there (status 3) without evaluating another trial point.

    ``dec = g^T A^-1 g / 2`` (``A = J^T J``, ``g = J^T r``, no damping) is the
    reduction of the undamped Gauss-Newton step as the linear model predicts
    it: the largest any step can make under that model, whatever the damping
    (Newton's decrement, with ``J^T J`` for the Hessian). At or below
    ``ftol * F`` the current point is within ``ftol`` of the model's minimum,
    what the ``small`` test of :func:`trial_verdict` establishes only after
    evaluating one more point. A NaN ``dec`` (a singular ``A``) never stops.
    """
    return dec <= ftol * F


@njit_inline
def next_damping(mu, nu, rho, accepted):
    """Nielsen's update of the damping ``mu`` and its growth factor ``nu`` (Madsen, Nielsen & Tingleff,
    2004, Algorithm 3.16): ``(mu, nu)`` after an accepted or a rejected step."""
    if accepted:
        return mu * max(1.0 / 3.0, 1.0 - math.pow(2.0 * rho - 1.0, 3.0)), 2.0
    return mu * nu, nu * 2.0
