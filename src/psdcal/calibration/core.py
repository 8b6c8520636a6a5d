"""The calibration front door: ``psdcal.calibrate`` (the paper's Section 3, docs/model.md#calibration).

Steps, each usable on its own from its private module (the starting values, 1-3 and the choice among
several starts, are gathered in :mod:`.starts`):

1. line-straightness preliminary distortion estimate (:mod:`._straightness`);
2. a homography per image by the DLT, Hartley-normalised (:mod:`._homography`);
3. closed-form intrinsics, then extrinsics (:mod:`._closed_form`);
4. Levenberg-Marquardt refinement on the ``image`` or ``template`` cost
   (:mod:`._refine`), with standard errors from the Jacobian.
"""
from __future__ import annotations

import datetime as _dt
import math
import threading
from dataclasses import replace

import numpy as np

from psdcal.calibration._refine import Problem, SolverOptions, refine
# the result and its record's helpers (result.py); the names users and tests import from core stay reachable here
from psdcal.calibration.result import (
    CalibrationResult,
    _frozen,
    _jsonable,
    _plain,
    _plain_ids,
    inputs_from_record,
    points_from_record,
)
from psdcal.model.distortion import distort
from psdcal.errors import ConvergenceError, DegenerateViewsError, InputError
from psdcal.model.params import DISTORTION_NAMES, Distortion
from psdcal.model.projection import project
from psdcal.model.readout import LX_MM, LY_MM, gain_map
# the fit's starts (starts.py); the names users and tests import from core stay reachable here
from psdcal.calibration.starts import (
    _ALL_INTR,
    _check_inputs,
    COSTS,
    F_GRID_MM,
    focal_from_homographies,
    implausible,
    initial_estimate,
    InitialEstimate,
    linear_starts,
    _compiled_fit,
    _model_spec,
    _n_points,
    MISFIT_FRACTION,
    _psd_multistart,
    _refine_starts,
    _stage_solver,
    staged_start,
    _straightness_lines,
    SUBSAMPLE_POINTS,
    subsample_views,
    template_hint,
)


def calibrate(
    template_mm,
    points_mm,
    *,
    cost: str = "image",
    radial: int = 2,
    tangential: bool = True,
    psd_radial: int = 0,
    skew: bool = False,
    preliminary: bool = True,
    normalize: bool = True,
    aspect: bool = False,
    fit_gains: bool = False,
    gains=None,
    image_ids=None,
    point_ids=None,
    sensor_mm: tuple[float, float] = (LX_MM, LY_MM),
    solver: SolverOptions = SolverOptions(),
    fix: dict | None = None,
    priors=None,
    f_guess_mm: float | None = None,
    verdict: bool = True,
    noise_mm: float | None = None,
) -> CalibrationResult:
    """Calibrate a PSD + lens sensor from views of a planar LED template.

    The adapted Zhang method of the paper (Section 3), with the corrections of
    docs/model.md#calibration: line-straightness preliminary distortion (3.2), Hartley
    normalised DLT (3.3), closed-form intrinsics (Eq 19-25 corrected),
    extrinsics (Eq 26-28) and Levenberg-Marquardt over intrinsics,
    distortion and all poses on the chosen cost.

    Parameters
    ----------
    template_mm : (M, 2) array_like
        Template points (X, Y) in mm, Z = 0.
    points_mm : (n_images, M, 2) array_like
        Measured impact points in mm on the sensor; NaN for a missing point.
    cost : "image" | "template"
        ``image``: maximum-likelihood residual on the sensor (default);
        ``template``: the paper's Eq 29, residual on the template plate.
    radial : int, 0-3
        Number of lens radial terms k1..k3.
    tangential : bool
        Estimate p1, p2.
    psd_radial : int, 0-2
        Number of PSD radial terms l1, l2.
    skew : bool
        Estimate the skew (the paper's gamma).
    preliminary : bool
        Line-straightness preliminary distortion estimate before the DLT.
    normalize : bool
        Hartley normalisation of the DLT.
    aspect : bool
        Separate vertical focal length ``fy_mm`` (general intrinsic matrix).
    fit_gains : bool
        Estimate three relative channel gains with the geometry (``image``
        cost only). ``points_mm`` must then be the raw readout of Eq 1-2.
    gains : (4,) array_like, optional
        Known relative channel gains ``(g_x1, g_x2, g_y1, g_y2)``; with
        ``fit_gains`` they are the start, otherwise they are held fixed and
        the model reads out through them.
    image_ids, point_ids : sequences, optional
        Identifiers carried into the result (default 0..n-1).
    sensor_mm : (Lx, Ly) active lengths of the PSD, mm.
    solver : SolverOptions
    fix : dict name -> value, optional
        Global parameters held at the given value (``{"f_mm": 8.0, "k2": 0.0}``;
        any of :data:`psdcal.calibration.priors.PARAMETER_NAMES`). Their
        standard error is None and they cost no degree of freedom.
    priors : GaussianPrior, dict ``{name: (value, std)}``, prior-file path, or a list of these
        Gaussian priors on free global parameters (:mod:`psdcal.calibration.priors`):
        the maximum a-posteriori fit, with degrees of freedom and standard
        errors that account for them (``s^2`` from the data residuals only).
    f_guess_mm : float, optional
        A nominal focal length, mm (the lens' data sheet): one more start of
        the refinement (optical centre at the electrical centre), and the
        start used when the views alone give none (:func:`linear_starts`).
    verdict : bool
        Attach the statistical verdict (:func:`psdcal.calibration.verdict.assess`)
        as ``result.verdict`` (JSON ``verdict`` and ``checks``); it costs about as much as the fit.
        The diagnosis (refits that name the cause of a failed check) is left
        to ``assess(result)`` and the CLI, so that loops over many fits stay fast.
    noise_mm : float, optional
        Known noise standard deviation per coordinate of the points, mm, for
        the verdict's ``noise`` check.

    Returns
    -------
    CalibrationResult
        ``.to_dict()`` is the calibration JSON.

    Raises
    ------
    InputError, DegenerateViewsError, ConvergenceError

    Examples
    --------
    >>> from psdcal.study.simulate import simulate_set
    >>> s = simulate_set("lens2", n_images=12, noise_mm=0.002, seed=1)
    >>> res = calibrate(s.template_mm, s.points_mm)
    >>> round(res.intrinsics.f_mm, 1)
    8.0
    """
    from psdcal.calibration._refine import _single_threaded_blas

    if fix or priors is not None:
        return _calibrate_constrained(
            template_mm, points_mm, cost=cost, radial=radial, tangential=tangential, psd_radial=psd_radial,
            skew=skew, preliminary=preliminary, normalize=normalize, aspect=aspect, fit_gains=fit_gains,
            gains=gains, image_ids=image_ids, point_ids=point_ids, sensor_mm=sensor_mm, solver=solver,
            fix=fix, priors=priors, f_guess_mm=f_guess_mm, verdict=verdict, noise_mm=noise_mm,
        )
    # small dense linear algebra: one BLAS thread is fastest. Without the verdict, a problem of fewer than
    # BLAS_THREADS_MIN_POINTS points on the compiled path makes no BLAS call that OpenBLAS would thread (its work
    # is in the compiled kernels and 9 x 9 factorisations), and asking threadpoolctl has a cost of its own.
    needed = verdict or _n_points(points_mm) >= BLAS_THREADS_MIN_POINTS or not _compiled_fit(points_mm)
    with _single_threaded_blas(needed):
        try:
            res = _calibrate(
                template_mm, points_mm, cost=cost, radial=radial, tangential=tangential, psd_radial=psd_radial,
                skew=skew, preliminary=preliminary, normalize=normalize, aspect=aspect, fit_gains=fit_gains,
                gains=gains, image_ids=image_ids, point_ids=point_ids, sensor_mm=sensor_mm, solver=solver,
                f_guess_mm=f_guess_mm,
            )
        except ConvergenceError as exc:  # a re-run of the result it carries fails the same way
            if exc.result is not None:
                _remember(exc.result, exc)
            raise
        _remember(res)
        if verdict:
            res = with_verdict(res, noise_mm=noise_mm, diagnose=False)
        return res


def with_verdict(res: CalibrationResult, *, noise_mm: float | None = None, points_kind: str | None = None,
                 diagnose: bool = True) -> CalibrationResult:
    """``res`` with its statistical verdict attached (:func:`psdcal.calibration.verdict.assess`).

    A systematic effect the verdict finds too small to move the result beyond
    its uncertainty still enters the covariance: the covariance (and the
    standard errors of the parameters and poses) are multiplied by the
    verdict's inflation (``1 + effect_sigma^2`` of its largest effect; 1 on
    most correct fits), recorded as ``stages["covariance_inflation"]``. A
    verdict attached again starts from the uninflated covariance.
    """
    from psdcal.calibration.verdict import assess

    v = assess(res, noise_mm=noise_mm, points_kind=points_kind, diagnose=diagnose)
    stages = dict(res.stages or {})
    old = float(stages.get("covariance_inflation", {}).get("factor", 1.0))
    new = v.inflation
    if old == new:
        return replace(res, verdict=v.to_dict())
    k = new / old
    sk = math.sqrt(k)
    std = {n: (None if s is None else float(s) * sk) for n, s in res.std.items()}
    if new == 1.0:
        stages.pop("covariance_inflation", None)
    else:
        why = [c.name for c in v.checks if (c.inflation or 1.0) == new]
        stages["covariance_inflation"] = {
            "factor": float(new), "checks": why,
            "rule": "covariance x (1 + effect_sigma^2) of the verdict's largest effect (psdcal.calibration.verdict)"}
    return replace(res, covariance=np.asarray(res.covariance, dtype=float) * k, std=std,
                   pose_std=np.asarray(res.pose_std, dtype=float) * sk, stages=stages, verdict=v.to_dict())


def _calibrate_constrained(template_mm, points_mm, *, fix, priors, gains, fit_gains, solver, verdict=True, noise_mm=None,
                           **kw) -> CalibrationResult:
    """``calibrate`` with fixed parameters and Gaussian priors (:mod:`psdcal.calibration.priors`).

    The free calibration (all start strategies) gives the start; the fixed /
    prior-weighted problem is then refined from it. Known gains given by
    ``fix`` (without ``fit_gains``) are applied like ``gains=``.
    """
    from psdcal.calibration._refine import _single_threaded_blas
    from psdcal.calibration.priors import GAIN_NAMES, PARAMETER_NAMES, as_priors, constrain, split_priors

    fix = {str(n): float(v) for n, v in (fix or {}).items()}
    for n, v in fix.items():
        if n not in PARAMETER_NAMES:
            raise InputError(f"fix: unknown parameter {n!r} (one of {', '.join(PARAMETER_NAMES)})", field="fix")
        if not np.isfinite(v):
            raise InputError(f"fix: {n} must be finite", field="fix")
    pri, fix = split_priors(as_priors(priors), fix)
    merged = {}
    if not fit_gains and any(n in GAIN_NAMES for n in fix):
        g = np.ones(4) if gains is None else np.asarray(gains, dtype=float) / float(np.asarray(gains)[0])
        for i, n in enumerate(GAIN_NAMES, start=1):
            if n in fix:
                merged[n] = fix.pop(n)
                g[i] = merged[n]
        gains = g
    with _single_threaded_blas():
        try:
            free = _calibrate(template_mm, points_mm, gains=gains, fit_gains=fit_gains, solver=solver, **kw)
        except ConvergenceError as exc:  # the constraints may be what makes the problem well posed
            if exc.result is None:
                raise
            free = exc.result
        # without any fix or informative prior this is the free fit, polished by Gauss-Newton steps
        result = constrain(free, fix, pri, solver, merged_gain_fix=merged)
    what = "constrained " + result.cost
    if not result.converged:
        exc = ConvergenceError(f"the {what}-cost refinement did not converge in {result.iterations} iterations "
                               f"({result.message}); check the fixed values and priors", result=result)
        _remember(result, exc)
        raise exc
    why = implausible(result)
    if why:
        exc = ConvergenceError(f"the {what}-cost refinement stopped at a solution that is not a camera ({why}); "
                               "check the fixed values and priors", result=result)
        _remember(result, exc)
        raise exc
    _remember(result)
    if verdict:
        result = with_verdict(result, noise_mm=noise_mm, diagnose=False)
    return result


def _calibrate(template_mm, points_mm, *, cost, radial, tangential, psd_radial, skew, preliminary, normalize,
               aspect, fit_gains, gains, image_ids, point_ids, sensor_mm, solver, f_guess_mm=None) -> CalibrationResult:
    if cost not in COSTS:
        raise InputError(f"cost must be one of {COSTS}, got {cost!r}", field="cost")
    spec = _model_spec(radial, tangential, psd_radial, skew, aspect, fit_gains)
    if fit_gains and cost != "image":
        raise InputError("fit_gains needs the image cost", field="cost")
    if fit_gains and (skew or aspect or (radial == 0 and psd_radial == 0)):
        # psdcal.calibration.gains.identifiability: unequal gains make the readout a homography of
        # the sensor plane; a general intrinsic matrix absorbs all three gain ratios
        # (and a pure single-f pinhole one combination of them) in a rotation of the poses.
        raise InputError(
            "the channel gains are not identifiable with skew/aspect or without any distortion term; "
            "fit them with a single f, zero skew and radial >= 1 (or calibrate them electrically)",
            field="fit_gains",
        )
    T, X, ids = _check_inputs(template_mm, points_mm, image_ids, 3 if (skew or aspect or fit_gains) else 2)
    pids = tuple(range(T.shape[0])) if point_ids is None else tuple(point_ids)
    g0 = np.ones(4) if gains is None else np.asarray(gains, dtype=float) / float(np.asarray(gains)[0])
    known_gains = None
    if not fit_gains and gains is not None and not np.allclose(g0, 1.0):  # (no gains: g0 is exactly 1)
        # Known gains held fixed: the raw readout is a homography of the equal-gain one
        # (psdcal.calibration.gains); map it back once, so that every stage sees corrected points.
        from psdcal.calibration.gains import correct_points

        known_gains, X, g0 = g0, correct_points(X, g0, *sensor_mm), np.ones(4)
    # Many points per view (a chessboard): the homographies of the closed form, and the starts, are fitted and
    # compared on a spread subset of each view's points (the basins of the cost are those of the whole set), and
    # the final refinement takes every point.
    Xs = subsample_views(T, X)
    sub = Xs is not None
    primary, cands = linear_starts(
        T, X, preliminary=preliminary, normalize=normalize, radial=radial, skew=skew, aspect=aspect,
        general=fit_gains, f_guess_mm=f_guess_mm, image_ids=ids, point_ids=pids, dlt_points=Xs,
    )
    start = primary
    g0_start = g0
    prob = Problem(T, X, spec, cost=cost, sensor_mm=tuple(sensor_mm))
    staged = staged_start(spec)
    # Every start is refined on the image cost with the core model (or the model itself
    # when it has nothing beyond the core); the lowest cost wins (global minimum).
    first = staged if staged is not None else spec
    if Xs is None and first is spec and cost == "image":
        pfirst = prob  # the same problem (and its per-problem caches)
    else:
        pfirst = Problem(T, X if Xs is None else Xs, first, cost="image", sensor_mm=tuple(sensor_mm))
    # a start stage only seeds the final refinement: looser tolerances (_stage_solver) unless it is the final one
    final_start = staged is None and cost == "image" and not sub
    tried = _refine_starts(pfirst, first, cands, g0_start, solver if final_start else _stage_solver(solver))
    good = [t for t in tried if t[2]]
    if not good:
        good = [t for t in tried if np.isfinite(t[1].cost_rms)]
    if not good:
        hint = template_hint(T, X, start.homographies, pids)
        raise DegenerateViewsError(f"no start of the refinement converged: {hint}" if hint else
                                   "no start of the refinement converged: the views do not determine the intrinsics; "
                                   "tilt the template differently between views, or give --f-guess")
    label, best0, _ = min(good, key=lambda t: t[1].cost_rms)
    start_record = {"starts": [{"start": lb, "cost_rms": float(r.cost_rms), "converged": bool(r.converged), "f_mm": float(r.intrinsics.f_mm),
                                "cx_mm": float(r.intrinsics.cx_mm), "cy_mm": float(r.intrinsics.cy_mm)} for lb, r, _ in tried],
                    "chosen": label}
    if sub:
        start_record["points_per_view"] = SUBSAMPLE_POINTS
    intr0 = best0.intrinsics
    if aspect and intr0.fy_mm is None:
        intr0 = replace(intr0, fy_mm=intr0.f_mm)
    dist0 = Distortion.from_array(best0.coeffs)
    rv0, tv0 = best0.rvecs, best0.tvecs
    final_done = best0 if final_start else None
    if spec.psd_radial > 0:
        best = _psd_multistart(T, X, spec, sensor_mm, start, intr0, dist0, g0, rv0, tv0, solver)
        if best is not None:
            intr0, dist0, rv0, tv0 = best.intrinsics, Distortion.from_array(best.coeffs), best.rvecs, best.tvecs
    if cost == "template":
        # The plate-plane cost (Eq 29) is poorly conditioned far from the solution
        # (its residuals scale with each view's distance); start it from the
        # sensor-plane solution, which it then moves by O(noise).
        pimg = Problem(T, X, spec, cost="image", sensor_mm=tuple(sensor_mm))
        ri = refine(pimg, intr0, dist0, g0, rv0, tv0, solver)
        if ri.converged and np.isfinite(ri.cost_rms):
            intr0 = ri.intrinsics
            dist0 = Distortion.from_array(ri.coeffs)
            rv0, tv0 = ri.rvecs, ri.tvecs
    ref = final_done if final_done is not None and spec.psd_radial == 0 else refine(prob, intr0, dist0, g0, rv0, tv0, solver)
    result = _make_result(prob, ref, start, ids, pids, spec, cost, g0, preliminary, normalize, solver,
                          extra_stages={"multistart": start_record})
    if f_guess_mm is not None:
        result = replace(result, problem={**result.problem, "options": {**result.problem["options"], "f_guess_mm": float(f_guess_mm)}})
    if known_gains is not None:
        result = replace(result, gains=known_gains)
    if not ref.converged:
        raise ConvergenceError(
            f"the {cost}-cost refinement did not converge in {ref.iterations} iterations ({ref.message}); "
            "check the data, or try --cost image, fewer distortion terms or more images",
            result=result,
        )
    why = implausible(result)
    if why:
        raise ConvergenceError(
            f"the {cost}-cost refinement stopped at a solution that is not a camera ({why}); "
            "check the data (template, point ids, gains), or try fewer distortion terms or more images",
            result=result,
        )
    return result


#: Below this many observations (without the verdict, on the compiled path) :func:`calibrate` does not ask
#: threadpoolctl for one BLAS thread: no BLAS call of such a problem is large enough for OpenBLAS to thread,
#: and asking threadpoolctl has a cost of its own on every call.
BLAS_THREADS_MIN_POINTS = 5000


def _make_result(prob, ref, start, ids, pids, spec, cost, g0, preliminary, normalize, solver, extra_stages=None):
    X = prob.points_mm
    intr = ref.intrinsics
    dist = Distortion.from_array(ref.coeffs)
    valid = prob.valid
    every = bool(valid.all())  # every point seen: the valid points are all of them, in order (no boolean indexing)
    # modelled measured points on the sensor, whichever cost was minimised
    if ref.model_mm is not None and every:  # the image cost already has them
        model = ref.model_mm.reshape(X.shape)
    elif ref.model_mm is not None:
        model = np.full(X.shape, np.nan)
        model[valid] = ref.model_mm
    else:
        x = np.stack([project(prob.template_mm, intr, r, t) for r, t in zip(ref.rvecs, ref.tvecs)])
        model = distort(x, dist, intr.c, d0_mm=X).d_mm
        if spec.fit_gains or not np.allclose(ref.gains, 1.0):
            model = gain_map(model, ref.gains, *prob.sensor_mm)
    res = X - model
    # squared residual of each valid point (0 elsewhere; a non-finite residual counts as 0, as nan_to_num makes it)
    rv = res.reshape(-1, 2) if every else res[valid]
    if not np.isfinite(rv).all():
        rv = np.nan_to_num(rv)
    if every:
        sq = (rv[:, 0] ** 2 + rv[:, 1] ** 2).reshape(valid.shape)
        n_valid = valid.size
    else:
        sq = np.zeros(valid.shape)
        sq[valid] = rv[:, 0] ** 2 + rv[:, 1] ** 2
        n_valid = int(valid.sum())
    sq_total = float(sq.sum())
    rms = math.sqrt(sq_total / max(n_valid, 1))
    # (every point seen: each view's count is M, the same division as by the counts' array)
    per_image = np.sqrt(sq.sum(axis=1) / (max(valid.shape[1], 1) if every else np.maximum(valid.sum(axis=1), 1)))
    cov = ref.covariance_global  # the reduced (Schur) system's inverse: no matrix of all poses
    std = {n: None for n in ("f_mm", "cx_mm", "cy_mm", "skew", *DISTORTION_NAMES)}
    if spec.aspect:
        std["fy_mm"] = None
    for n, c in zip(prob.names, np.diagonal(cov).tolist()):  # (plain floats: math.sqrt rounds as np.sqrt does)
        std[n] = math.sqrt(max(c, 0.0))
    pose_std = np.sqrt(np.maximum(np.diagonal(ref.pose_covariance, axis1=1, axis2=2), 0.0))  # (n, 6)
    m = 2 * n_valid
    dof = max(m - ref.z.size, 1)
    sigma_mm = math.sqrt(sq_total / dof) if cost == "image" else float(rms / np.sqrt(2.0) * np.sqrt(m / dof))
    plain_ids = [_plain(i) for i in ids]
    stages = {
        "preliminary": {"k1": float(start.preliminary_k[0]), "k2": float(start.preliminary_k[1]), "line_groups": start.n_lines, "applied": bool(preliminary and start.n_lines > 0)},
        "closed_form": {**start.intrinsics.to_dict(), "normalized": bool(normalize),
                        **({"points_per_view": int(ppv)} if (ppv := getattr(start, "points_per_view", None)) else {})},
        "initial_extrinsics": [{"image_id": i, "rvec": r, "tvec_mm": t} for i, r, t in zip(plain_ids, start.rvecs.tolist(), start.tvecs_mm.tolist())],
        **(extra_stages or {}),
    }
    pids = _plain_ids(pids)
    # the inputs are kept as (read-only) arrays; to_dict() writes them as lists, NaN as null
    problem = {
        "template": {"point_ids": list(pids), "xy_mm": _frozen(prob.template_mm)},
        "points": {"image_ids": list(plain_ids), "xy_mm": _frozen(X)},
        "options": {
            "cost": cost,
            "radial": spec.radial,
            "tangential": spec.tangential,
            "psd_radial": spec.psd_radial,
            "skew": spec.skew,
            "aspect": spec.aspect,
            "fit_gains": spec.fit_gains,
            "preliminary": preliminary,
            "normalize": normalize,
            "gains": np.asarray(g0, dtype=float).tolist(),
            "sensor_mm": list(prob.sensor_mm),
            "solver": {"ftol": solver.ftol, "xtol": solver.xtol, "gtol": solver.gtol, "max_iterations": solver.max_iterations},
        },
    }
    return CalibrationResult(
        intrinsics=intr,
        distortion=dist,
        gains=ref.gains,
        model=spec,
        cost=cost,
        param_names=tuple(prob.names),
        covariance=cov,
        std=std,
        image_ids=tuple(plain_ids),
        point_ids=pids,
        rvecs=ref.rvecs,
        tvecs_mm=ref.tvecs,
        pose_std=pose_std,
        residuals_mm=res,
        rms_mm=rms,
        per_image_rms_mm=per_image,
        cost_rms=ref.cost_rms,
        sigma_mm=sigma_mm,
        iterations=ref.iterations,
        converged=ref.converged,
        message=ref.message,
        stages=stages,
        problem=problem,
        sensor_mm=tuple(prob.sensor_mm),
        created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    )


def recalibrate(calib: dict | CalibrationResult, *, verdict: bool = True) -> CalibrationResult:
    """Re-run a calibration exactly from the problem record saved inside it."""
    return _calibrate_record(calib, verdict=verdict)


#: The last few results :func:`calibrate` returned, by the identity of their problem record (which
#: :func:`dataclasses.replace`, the verdict included, passes on unchanged): ``id(problem) -> (problem, result)``.
_RECENT: dict = {}
_RECENT_SIZE = 4
_RECENT_LOCK = threading.Lock()  # calibrations run in threads (the studies' local clusters)


def _remember(res: CalibrationResult, error: Exception | None = None) -> None:
    """Keep ``res`` as the answer to a re-run of its own problem record (:func:`_calibrate_record` without changes),
    or ``error`` when the calibration that made it raised that error (the result it carried).

    The calibration is deterministic, so re-running the record of a result this
    process has just computed gives that result (or that error) again; the
    verdict's diagnosis (a re-run that reaches a lower cost means a local
    minimum) then costs nothing for a fit of this process, and still re-runs a
    result read from a file.
    """
    p = res.problem
    if not isinstance(p, dict):
        return
    with _RECENT_LOCK:
        _RECENT.pop(id(p), None)
        _RECENT[id(p)] = (p, res if error is None else error)
        while len(_RECENT) > _RECENT_SIZE:
            _RECENT.pop(next(iter(_RECENT)))


def _calibrate_record(calib, *, verdict: bool = False, template_mm=None, drop_image=None, reuse: bool = False,
                      **changes) -> CalibrationResult:
    """Re-run the calibration recorded in ``calib`` with ``changes`` to its options (another template, an image left out).

    ``reuse``: a re-run without changes of a result :func:`calibrate` returned in this process is that result
    (:func:`_remember`).
    """
    if reuse and not verdict and template_mm is None and drop_image is None and not changes \
            and isinstance(calib, CalibrationResult):
        with _RECENT_LOCK:
            hit = _RECENT.get(id(calib.problem))
        if hit is not None and hit[0] is calib.problem:
            if isinstance(hit[1], Exception):
                raise hit[1]
            return hit[1]
    d = calib.to_dict() if isinstance(calib, CalibrationResult) else calib
    p = d["problem"]
    if p.get("kind") == "directions":  # a rotation-stage calibration (psdcal.calibration.directions)
        from psdcal.calibration.directions import recalibrate_directions

        return recalibrate_directions(d)
    o = {**p["options"], **changes}
    X = points_from_record(p["points"]["xy_mm"])
    image_ids = list(p["points"]["image_ids"])
    if drop_image is not None:
        X = np.delete(X, drop_image, axis=0)
        del image_ids[drop_image]
    return calibrate(
        np.array(p["template"]["xy_mm"], dtype=float) if template_mm is None else np.asarray(template_mm, dtype=float),
        X,
        cost=o["cost"],
        radial=o["radial"],
        tangential=o["tangential"],
        psd_radial=o["psd_radial"],
        skew=o["skew"],
        preliminary=o["preliminary"],
        normalize=o["normalize"],
        aspect=o.get("aspect", False),
        fit_gains=o.get("fit_gains", False),
        gains=o.get("gains"),
        image_ids=image_ids,
        point_ids=p["template"]["point_ids"],
        sensor_mm=tuple(o.get("sensor_mm", (LX_MM, LY_MM))),
        solver=SolverOptions(**o.get("solver", {})),
        fix=o.get("fix") or None,
        priors=[_prior_from_record(q) for q in o.get("priors") or []] or None,
        f_guess_mm=o.get("f_guess_mm"),
        verdict=verdict,
    )


def _prior_from_record(q: dict):
    from psdcal.calibration.priors import GaussianPrior

    return GaussianPrior.from_dict(q)
