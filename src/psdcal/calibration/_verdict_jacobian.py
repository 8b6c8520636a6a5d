"""The verdict's one evaluation of the richer model: residuals and the compact Jacobian at the fit's solution.

:func:`psdcal.calibration._verdict_linear.linearise` linearises the fit in a
richer model (the terms the fit's model leaves out, at 0): its Jacobian holds
the fit's columns and the left-out terms' (one evaluation for both).
:func:`rich_jacobian` evaluates it once, with the columns in the order the
verdict uses them (the free global parameters, the left-out terms, the fixed
parameters, then each row's own view's six pose columns): with the compiled
image cost the kernel writes them in that order (its ``gmap``), with no
:class:`~psdcal.calibration._refine.Evaluator` (whose caches serve a solver's
many evaluations) and no gather of the columns afterwards; otherwise the
Evaluator's numpy reference, its columns gathered into that order. Both start
the Newton inverse of the distortion the same way (the fixed-point start, then
the measured point): the same roots, the same numbers.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from psdcal import _jit

#: The pose columns of each view (rotation vector, translation).
POSE = 6
#: The Newton inverse's tolerance (mm, relative to the ideal point's distance from the origin beyond 1 mm) and
#: iteration limit: :class:`~psdcal.calibration._refine.Evaluator`'s.
NEWTON_TOL_MM, NEWTON_MAX_ITER = 1e-13, 50


@dataclass(frozen=True)
class RichJacobian:
    """The richer model at the fit's solution: ``r`` (2N,) residuals model - measured (mm, rows x0, y0, x1, ...;
    1e3 where not finite), ``X`` (2N, g + ne + nf + 6) C-contiguous: the columns of ``free`` (natural units; f
    moves fy too when the fit's model has one focal length), ``extra``, ``fixed``, then the row's view's six pose
    columns (zero rows where ``r`` is not finite); ``img``, ``led`` (N,) the view and template point of each valid
    observation, ``d_meas`` (N, 2) its measured point (mm), ``n_img`` the number of views, ``dense`` whether every
    view has every point (the rows in view order, as many each)."""

    r: np.ndarray
    X: np.ndarray
    free: tuple
    extra: tuple
    fixed: tuple
    img: np.ndarray
    led: np.ndarray
    d_meas: np.ndarray
    n_img: int
    dense: bool


def rich_spec(spec):
    """The richer model: the next radial term, tangential, PSD l1, skew (without fy) and fy added to ``spec``."""
    return replace(spec, radial=min(3, spec.radial + 1), tangential=True, psd_radial=max(spec.psd_radial, 1),
                   skew=spec.skew or not spec.aspect, aspect=True)


def rich_jacobian(res, fixed: tuple) -> RichJacobian:
    """:class:`RichJacobian` of the result ``res`` (aligned to its problem record) with the parameters ``fixed``
    held (their columns last but the poses')."""
    from psdcal.calibration._refine import Problem
    from psdcal.calibration.core import inputs_from_record

    T, obs = inputs_from_record(res.problem)
    gains = np.asarray(res.gains, float) if res.model.fit_gains else np.ones(4)
    spec = res.model
    rich = rich_spec(spec)
    extra = tuple(n for n in rich.global_names if n not in spec.global_names)
    free = tuple(n for n in spec.global_names if n not in fixed)
    prob = Problem(T, obs, rich, cost="image", sensor_mm=tuple(res.sensor_mm))
    order = (*free, *extra, *fixed)
    img, led, d_meas, P = prob.observations
    if _jit.use_compiled(len(img)):
        X, y = _compiled(prob, res, gains, order, P, img, d_meas)
        r = (y - d_meas).ravel()
        bad = ~np.isfinite(r)
        if np.any(bad):  # as Evaluator.evaluate_compact
            r = np.where(bad, 1e3, r)
            X = np.nan_to_num(np.where(bad[:, None], 0.0, X))
    else:
        from psdcal.calibration._refine import Evaluator

        ev = Evaluator(prob, res.intrinsics, res.distortion, gains)
        r, Jc = ev.evaluate_compact(prob.pack(res.intrinsics, res.distortion, gains, res.rvecs, res.tvecs_mm))
        r = np.asarray(r, dtype=float)
        Jc = np.asarray(Jc, dtype=float)
        ng = prob.n_global
        cols = np.array([prob.names.index(n) for n in order] + list(range(ng, ng + POSE)), dtype=np.intp)
        X = Jc.take(cols, axis=1)  # (ndarray.take with an index array: row-major)
    if not spec.aspect and "f_mm" in order:  # the rich model's f moves x only and fy y: this model's f moves both
        X[:, order.index("f_mm")] += X[:, order.index("fy_mm")]
    return RichJacobian(r, X, free, extra, fixed, img, led, d_meas, obs.shape[0], bool(prob.valid.all()))


def _compiled(prob, res, gains, order, P, img, d_meas):
    """(Jacobian (2N, len(order) + 6), modelled measured points (N, 2)) by the compiled image cost
    (:func:`psdcal.calibration._image_kernel.image_model`), its global columns those of ``order``: the arguments
    :class:`~psdcal.calibration._refine.Evaluator` gives it from a cold start (the same numbers)."""
    from psdcal.calibration._image_kernel import global_map, image_model

    from psdcal.calibration._refine import kernel_theta

    z = prob.pack(res.intrinsics, res.distortion, gains, res.rvecs, res.tvecs_mm)
    ng = prob.n_global
    theta = kernel_theta(res.intrinsics, res.distortion, gains, prob.spec.skew)
    theta[global_map(prob.names)] = z[:ng]
    gain_basis = prob.kernel_constants[2] if prob.spec.fit_gains else _NO_GAINS
    # the Newton inverse from the fixed-point start, as the Evaluator's first evaluation: a start from the measured
    # points (fewer iterations) finds another root of a badly wrong fit (a swapped template's: its checks change)
    _, _, y, J = image_model(P, img, theta, prob.spec.aspect, z[ng:].reshape(-1, POSE), np.full(d_meas.shape, np.nan),
                             d_meas, global_map(order), True, NEWTON_TOL_MM, NEWTON_MAX_ITER, gain_basis)
    return J, y


_NO_GAINS = np.zeros((0, 3, 3))
