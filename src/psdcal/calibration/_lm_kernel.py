"""The refinement's Levenberg-Marquardt loop in one compiled call (image and template costs).

:func:`psdcal.calibration._lm.levenberg_marquardt`, driven by the compiled
costs (``Evaluator``), spends a small set's time in Python between kernel
calls: on 5 views of 14 points an iteration's kernels (residuals and
Jacobian, block normal equations, Schur step) take about 15 us and the Python
around them as much again. :func:`lm_image` runs the same iterations inside
numba: the same kernels
(:func:`~psdcal.calibration._image_kernel.image_model`, into arrays reused from one evaluation to the next, or
:func:`~psdcal.calibration._image_kernel.template_model`,
:func:`~psdcal.calibration._gram_kernel.gram_block_normal`,
:func:`~psdcal.calibration._schur_kernel.schur_solve`), the same damping and
stopping rules in the same order, the Newton inverse of each trial point
warm-started from the last accepted point, as the Python loop does.

The Python loop stays the reference (and the path of priors and of the numpy
model); the tests compare the two.
"""
from __future__ import annotations

import numpy as np

from psdcal._jit import njit
from psdcal.calibration._gram_kernel import gram_block_normal
from psdcal.calibration._image_kernel import image_model_into, template_model
from psdcal.calibration._lm_rules import negligible_decrement, next_damping, trial_verdict
from psdcal.calibration._schur_kernel import schur_covariance, schur_solve

#: status codes of :func:`lm_image` (those of ``levenberg_marquardt``, and 5: its damping overflow, a 2 there)
MESSAGES = {
    0: "iteration limit reached",
    1: "gradient below gtol",
    2: "step below xtol",
    3: "relative cost reduction below ftol",
    4: "zero residual",
    5: "no further progress possible (damping overflow)",
}

_BIG = np.finfo(np.float64).max


@njit
def _state(theta0, gmap, z, n_views):
    """The kernels' 16 global parameters (``theta0`` with the state's free ones) and poses (n_views, 6) of ``z``."""
    ng = gmap.shape[0]
    theta = theta0.copy()
    for k in range(ng):
        theta[gmap[k]] = z[k]
    poses = np.empty((n_views, 6))
    for v in range(n_views):
        for a in range(6):
            poses[v, a] = z[ng + 6 * v + a]
    return theta, poses


@njit
def _evaluate(P, img, theta0, separate_fy, gmap, gain_basis, meas, z, n_views, warm, tol_mm, max_newton, r, J, d, ok,
              y):
    """Residuals ``r`` (2N,), compact Jacobian ``J`` (2N, ng + 6), model points ``d`` and ``y`` (N, 2) at the
    state ``z``, written into the given arrays (``y`` is ``d`` without gains; ``ok`` (N,): the Newton inverse
    converged).

    As ``Evaluator.evaluate_compact`` with the compiled kernel: non-finite
    residuals become 1e3 with zero Jacobian rows, and then the Jacobian's
    non-finite entries are replaced as ``np.nan_to_num`` does.
    """
    theta, poses = _state(theta0, gmap, z, n_views)
    image_model_into(P, img, theta, separate_fy, poses, warm, meas, gmap, True, tol_mm, max_newton, gain_basis,
                     d, ok, y, J)
    N = meas.shape[0]
    for i in range(N):
        r[2 * i] = y[i, 0] - meas[i, 0]
        r[2 * i + 1] = y[i, 1] - meas[i, 1]
    _clean(r, J)


@njit
def _clean(r, J):
    """In place, as ``Evaluator`` does: a non-finite residual becomes 1e3 with a zero Jacobian row (J may be
    (0, 0): residuals only), and when there was one, the Jacobian's non-finite entries become what
    ``np.nan_to_num`` makes of them."""
    any_bad = False
    has_jac = J.shape[0] == r.shape[0]
    for j in range(r.shape[0]):
        if not np.isfinite(r[j]):
            any_bad = True
            r[j] = 1e3
            if has_jac:
                for c in range(J.shape[1]):
                    J[j, c] = 0.0
    if any_bad and has_jac:
        for j in range(r.shape[0]):
            for c in range(J.shape[1]):
                e = J[j, c]
                if np.isnan(e):
                    J[j, c] = 0.0
                elif np.isinf(e):
                    J[j, c] = _BIG if e > 0 else -_BIG


@njit
def _evaluate_template(P, img, theta0, separate_fy, gmap, meas, z, n_views, want_jac):
    """Residuals (2N,) of the template cost (Eq 29) and, with ``want_jac``, the compact Jacobian at ``z``
    (cleaned as :func:`_clean`)."""
    theta, poses = _state(theta0, gmap, z, n_views)
    r, J = template_model(P, img, theta, separate_fy, poses, meas, gmap, want_jac)
    _clean(r, J)
    return r, J


@njit
def _system_vectors(U, V, gg, gp):
    """``g`` and ``diag(A)`` of block normal equations, in the state's order (globals, then 6 per view)."""
    ng = U.shape[0]
    n = V.shape[0]
    g = np.empty(ng + 6 * n)
    dg = np.empty(ng + 6 * n)
    for a in range(ng):
        g[a] = gg[a]
        dg[a] = U[a, a]
    for v in range(n):
        for a in range(6):
            g[ng + 6 * v + a] = gp[v, a]
            dg[ng + 6 * v + a] = V[v, a, a]
    return g, dg


@njit
def lm_image(P, img, theta0, separate_fy, gmap, gain_basis, meas, z0, n_views, ftol, xtol, gtol, max_iterations,
             tol_mm, max_newton, template):
    """Levenberg-Marquardt on the image or the template cost, all iterations in one call.

    The algorithm of ``levenberg_marquardt`` (Marquardt scaling by the running
    maximum of ``diag(J^T J)``, Nielsen's damping rule, MINPACK's gtol / xtol
    / ftol tests and the last round-off step) with the poses eliminated by
    the Schur complement at every step, and its test of the Gauss-Newton
    decrement before each trial (:func:`~psdcal.calibration._lm_rules.negligible_decrement`).

    Parameters
    ----------
    P, img, theta0, separate_fy, gmap, gain_basis, meas :
        as :func:`~psdcal.calibration._image_kernel.image_model` (``theta0``:
        the 16 global parameters, of which those in ``gmap`` are the state's).
    z0 : (ng + 6 n_views,) start: the free globals, then (r, t) of each view
    n_views : int
    ftol, xtol, gtol, max_iterations : ``SolverOptions``
    tol_mm, max_newton : the Newton inverse of the distortion
    template : bool
        The template-plane cost (Eq 29, :func:`~psdcal.calibration._image_kernel.template_model`)
        instead of the image cost; d and y are then empty (0, 2).

    Every trial point's Jacobian comes with its residuals (one pass; most steps are
    accepted), for both costs. The Python loop evaluates the template cost's trial points
    without it and the accepted point again with it: the same residuals and Jacobians.

    Returns
    -------
    x, F (0.5 |r|^2), status (:data:`MESSAGES`), njev, nfev, and at ``x``:
    r (2N,), Jc (2N, ng + 6), d and y (N, 2), and the blocks of the inverse of
    the normal equations (``schur_covariance``): cov_ok, Cg, Cp, Cx.
    """
    ng = gmap.shape[0]
    x = z0.copy()
    # the image cost's evaluations go into two sets of arrays, the accepted point's and the trial's, swapped at
    # each accepted step (no allocation, and no first touch of fresh pages, per evaluation)
    N = meas.shape[0] if not template else 0
    gains_on = gain_basis.shape[0] == 4
    conv = np.empty(N, dtype=np.bool_)
    r_s = np.empty(2 * N)
    J_s = np.empty((2 * N, ng + 6))
    d_s = np.empty((N, 2))
    y_s = np.empty((N, 2)) if gains_on else d_s
    if template:
        r, J = _evaluate_template(P, img, theta0, separate_fy, gmap, meas, x, n_views, True)
        d = np.empty((0, 2))
        y = d
    else:
        r = np.empty(2 * N)
        J = np.empty((2 * N, ng + 6))
        d = np.empty((N, 2))
        y = np.empty((N, 2)) if gains_on else d
        _evaluate(P, img, theta0, separate_fy, gmap, gain_basis, meas, x, n_views, np.full(meas.shape, np.nan),
                  tol_mm, max_newton, r, J, d, conv, y)
    nfev = 1
    njev = 1
    F = 0.5 * np.dot(r, r)
    U, W, V, gg, gp = gram_block_normal(J, r, img, n_views)
    g, diagA = _system_vectors(U, V, gg, gp)
    D = np.maximum(diagA, 1e-300)
    mu = 1e-8
    nu = 2.0
    status = 0
    max_nfev = 4 * max_iterations + 10
    fresh = True
    sD = np.sqrt(D)
    x_scale = 0.0
    damp_p = np.empty((n_views, 6))
    zero_g = np.zeros(ng)
    zero_p = np.zeros((n_views, 6))
    while njev <= max_iterations and nfev < max_nfev:
        if F == 0.0:
            status = 4
            break
        if fresh:
            colnorm = np.sqrt(np.maximum(diagA, 1e-300))
            if np.max(np.abs(g) / colnorm) <= gtol * np.sqrt(2 * F):
                status = 1
                break
            sD = np.sqrt(D)
            sx = sD * x
            x_scale = np.sqrt(np.dot(sx, sx))
            fresh = False
            # the undamped Gauss-Newton step's predicted reduction: at most ftol of the cost, stop here
            ok0, hg0, hp0 = schur_solve(U, W, V, gg, gp, zero_g, zero_p)
            if ok0 and negligible_decrement(0.5 * (np.dot(gg, hg0) + np.sum(gp * hp0)), F, ftol):
                status = 3
                break
        damp = mu * D
        for v in range(n_views):
            for a in range(6):
                damp_p[v, a] = damp[ng + 6 * v + a]
        ok, hg, hp = schur_solve(U, W, V, gg, gp, damp[:ng].copy(), damp_p)
        if not ok:  # not positive definite at this damping
            mu *= nu
            nu *= 2.0
            if not np.isfinite(mu) or mu > 1e200:  # (a system with NaN in it fails at every damping)
                status = 5
                break
            continue
        h = np.empty(x.size)
        for a in range(ng):
            h[a] = -hg[a]
        for v in range(n_views):
            for a in range(6):
                h[ng + 6 * v + a] = -hp[v, a]
        sh = sD * h
        if np.sqrt(np.dot(sh, sh)) <= xtol * (x_scale + xtol):
            status = 2
            break
        x_new = x + h
        if template:
            r_new, J_new = _evaluate_template(P, img, theta0, separate_fy, gmap, meas, x_new, n_views, True)
            d_new = d
            y_new = y
        else:  # into the spare set; the Newton inverses start from the accepted point's d
            _evaluate(P, img, theta0, separate_fy, gmap, gain_basis, meas, x_new, n_views, d, tol_mm, max_newton,
                      r_s, J_s, d_s, conv, y_s)
            r_new, J_new, d_new, y_new = r_s, J_s, d_s, y_s
        nfev += 1
        F_new = 0.5 * np.dot(r_new, r_new)
        pred = 0.5 * np.dot(h, mu * D * h - g)
        accept, small, rho = trial_verdict(F, F_new, pred, nu, ftol)
        mu, nu = next_damping(mu, nu, rho, accept)
        if accept:
            if not template:  # the old accepted point's arrays become the spare set
                r_s, J_s, d_s, y_s = r, J, d, y
            x, r, F, J, d, y = x_new, r_new, F_new, J_new, d_new, y_new
            njev += 1
            U, W, V, gg, gp = gram_block_normal(J, r, img, n_views)
            g, diagA = _system_vectors(U, V, gg, gp)
            D = np.maximum(D, diagA)
            fresh = True
            if small:
                status = 3
                break
        elif not np.isfinite(mu) or mu > 1e200:
            status = 5
            break
    cov_ok, Cg, Cp, Cx = schur_covariance(U, W, V)
    return x, F, status, njev, nfev, r, J, d, y, cov_ok, Cg, Cp, Cx
