"""Levenberg-Marquardt in numpy: the solver of the refinement's Python path and the reference of the compiled
loops (:mod:`psdcal.calibration._lm_kernel`, :mod:`psdcal.calibration._straightness_kernel`), and its settings.

:mod:`psdcal.calibration._refine` re-exports :class:`SolverOptions`, :class:`LMResult` and
:func:`levenberg_marquardt`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psdcal.calibration._normal import _as_system


@dataclass(frozen=True)
class SolverOptions:
    """Settings of the LM solver.

    Attributes
    ----------
    ftol, xtol, gtol : float
        Tolerances of :func:`levenberg_marquardt`: relative reduction of the
        cost, relative scaled step, scaled gradient. A relative cost change of
        1e-12 puts the parameters within ~1e-5 standard errors of the optimum
        on noisy data; noiseless data converge quadratically to round-off.
    max_iterations : int
        Maximum number of Jacobian evaluations (LM iterations).
    """

    ftol: float = 1e-12
    xtol: float = 1e-12
    gtol: float = 1e-12
    max_iterations: int = 200


@dataclass(frozen=True)
class LMResult:
    """Outcome of :func:`levenberg_marquardt`."""

    x: np.ndarray
    cost: float
    status: int  # > 0 converged (1 gradient, 2 step, 3 cost reduction, 4 zero residual), 0 limit reached
    message: str
    njev: int
    nfev: int
    system: object = field(default=None, repr=False)  # the normal equations at x (DenseNormal / BlockNormal)


def levenberg_marquardt(fun, jac, x0, options: SolverOptions = SolverOptions(), normal=None) -> LMResult:
    """Levenberg-Marquardt on the normal equations with Marquardt's scaling.

    Minimises ``0.5 |fun(x)|^2``. Each iteration solves
    ``(J^T J + mu D) h = -J^T r`` by Cholesky, where ``D`` is the running
    maximum of ``diag(J^T J)`` (scale invariance, as in MINPACK); the damping
    ``mu`` follows Nielsen's rule (Madsen, Nielsen & Tingleff, *Methods for
    non-linear least squares problems*, 2004, Algorithm 3.16). The Jacobian
    is evaluated only at accepted points; trial points need residuals only.
    For the small calibration problems (tens to hundreds of unknowns) this is
    several times faster than MINPACK's QR of the full Jacobian.

    Stops with status 1 when ``max_j |(J^T r)_j| / (|J_j| |r|) <= gtol``
    (MINPACK's gradient test), 2 when the scaled step is below ``xtol``
    times the scaled state, 3 when the actual and predicted relative
    reductions of the cost are both below ``ftol`` or, before a trial point
    is evaluated, when the undamped Gauss-Newton step predicts a relative
    reduction below ``ftol`` at the current point (``g^T (J^T J)^-1 g / 2 <=
    ftol F``: the point is within ftol of the linear model's minimum, and
    the trial would only confirm it), 4 on a zero residual, and
    0 (not converged) when ``max_iterations`` Jacobians have been evaluated.

    ``normal(J, r)``, when given, returns ``(J^T J, J^T r)`` (e.g. exploiting
    the sparsity of J) or a normal-equations object with ``g``, ``diagonal()``
    and ``solve(damp)`` (:class:`BlockNormal`: the poses are eliminated by the
    Schur complement, so each iteration costs O(views)); by default they are
    dense products (:class:`DenseNormal`).
    """
    if normal is None:
        def normal(J, r):
            return J.T @ J, J.T @ r

    x = np.asarray(x0, dtype=float).copy()
    r = fun(x)
    J = jac(x)
    nfev, njev = 1, 1
    F = 0.5 * float(r @ r)
    sysm = _as_system(normal(J, r))
    g = sysm.g
    diagA = sysm.diagonal()
    D = np.maximum(diagA, 1e-300)
    mu = 1e-8  # start near Gauss-Newton, like MINPACK's large initial trust region: a damped
    # first step from a poor closed-form start (C off by mm, Lens 1) can walk into a local minimum
    nu = 2.0
    status, message = 0, "iteration limit reached"
    max_nfev = 4 * options.max_iterations + 10
    fresh = True  # g, diagA and D changed (the tests that depend on them only alone are redone)
    while njev <= options.max_iterations and nfev < max_nfev:
        if F == 0.0:
            status, message = 4, "zero residual"
            break
        if fresh:
            colnorm = np.sqrt(np.maximum(diagA, 1e-300))
            if np.max(np.abs(g) / colnorm) <= options.gtol * np.sqrt(2 * F):
                status, message = 1, "gradient below gtol"
                break
            sD = np.sqrt(D)
            x_scale = np.sqrt((sD * x) @ (sD * x))
            fresh = False
            # the undamped Gauss-Newton step's predicted reduction (Newton's decrement with J^T J): at most
            # ftol of the cost, x is converged and no trial point is evaluated (_lm_rules.negligible_decrement)
            h0 = sysm.solve(np.zeros_like(D))
            if h0 is not None and 0.5 * float(g @ h0) <= options.ftol * F:
                status, message = 3, "relative cost reduction below ftol"
                break
        h = sysm.solve(mu * D)
        if h is None:  # not positive definite at this damping
            mu *= nu
            nu *= 2.0
            if not np.isfinite(mu) or mu > 1e200:  # (a system with NaN in it fails at every damping)
                status, message = 2, "no further progress possible (damping overflow)"
                break
            continue
        h = -h
        if np.sqrt((sD * h) @ (sD * h)) <= options.xtol * (x_scale + options.xtol):
            status, message = 2, "step below xtol"
            break
        x_new = x + h
        r_new = fun(x_new)
        nfev += 1
        F_new = 0.5 * float(r_new @ r_new)
        pred = 0.5 * float(h @ (mu * D * h - g))
        rho = (F - F_new) / pred if pred > 0 else -1.0
        # At the optimum to round-off, the first step after an accepted one (damping not raised since) can
        # predict a reduction below ftol and change the cost by round-off only, either way: it is then
        # taken, as the last one (MINPACK's ftol test, which it applies to every trial). Rejecting it
        # would only raise the damping trial after trial until the step falls below xtol.
        final = nu == 2.0 and 0 < pred <= options.ftol * F and abs(F - F_new) <= options.ftol * F
        if (rho > 0 or final) and np.isfinite(F_new):
            small = final or ((F - F_new) <= options.ftol * F and pred <= options.ftol * F)
            x, r, F = x_new, r_new, F_new
            J = jac(x)
            njev += 1
            sysm = _as_system(normal(J, r))
            g = sysm.g
            diagA = sysm.diagonal()
            D = np.maximum(D, diagA)
            fresh = True
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if small:
                status, message = 3, "relative cost reduction below ftol"
                break
        else:
            mu *= nu
            nu *= 2.0
            if not np.isfinite(mu) or mu > 1e200:
                status, message = 2, "no further progress possible (damping overflow)"
                break
    return LMResult(x=x, cost=F, status=status, message=message, njev=njev, nfev=nfev, system=sysm)
