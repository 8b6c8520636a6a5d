"""The calibration verdict's diagnosis: refit the alternatives a failed check suggests and name the cause.

Only run when a check fails (:func:`psdcal.calibration.verdict.assess` with
``diagnose=True``): a global re-run (a local minimum), fitted channel gains
(raw amplitudes through unequal gains), the richer models, one view left out,
two template LEDs swapped.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass, replace

import numpy as np

from psdcal.calibration._verdict_fields import explained as _explained
from psdcal.calibration._verdict_rules import F_RANGE_MM


# -- diagnosis ---------------------------------------------------------------------------
def _refit(result, **changes):
    """Re-run ``result``'s calibration with changed options (or a changed template); None if it fails.

    Without changes, the re-run of a result this process has just computed is that result (the calibration is
    deterministic: :func:`psdcal.calibration.core._remember`).
    """
    from psdcal.calibration.core import _calibrate_record

    try:
        return _calibrate_record(result, reuse=True, **changes)
    except Exception:  # noqa: BLE001 -- a diagnosis refit that fails is just not the explanation
        return None


@dataclass(frozen=True)
class _Warm:
    """A warm-started refit (:func:`_warm_refit`): what the diagnosis reads of a refit."""

    intrinsics: object
    residuals_mm: np.ndarray  # (N, 2) of the valid observations, mm
    sigma_mm: float


#: Model changes :func:`_warm_refit` refines from the fit's own solution (the new terms at 0).
WARM_CHANGES = frozenset({"radial", "tangential", "psd_radial", "aspect", "fit_gains"})


def _warm_refit(result, *, drop_image=None, **changes):
    """The refinement of ``result``'s problem with ``changes`` to its model (terms added at 0) or a view left out,
    started from the fit's own solution; None when it fails or stops where no camera is.

    A diagnosis asks whether an alternative explains the residuals; the fit's
    solution is in the alternative's valley (the terms added are small, a view
    left out changes little of the rest), so the refinement from it costs a
    few iterations where a full calibration runs every start. (Not for a
    template permutation: from the fit of the wrong template, the right one's
    refinement crawls along a valley.) Results of
    another cost, with fixed values or priors, fall back to the full refit
    (:func:`_refit`).
    """
    from psdcal.calibration._refine import Problem, SolverOptions, refine
    from psdcal.calibration.checks import align_to_problem
    from psdcal.calibration.core import inputs_from_record

    p = result.problem if isinstance(result.problem, dict) else {}
    o = p.get("options", {})
    if o.get("cost", "image") != "image" or o.get("fix") or o.get("priors") or not set(changes) <= WARM_CHANGES:
        kw = dict(changes)
        if drop_image is not None:
            kw["drop_image"] = drop_image
        return _refit(result, **kw)
    try:
        res = align_to_problem(result)
        T, X = inputs_from_record(res.problem)
        rv, tv = np.asarray(res.rvecs, float), np.asarray(res.tvecs_mm, float)
        if drop_image is not None:
            X, rv, tv = np.delete(X, drop_image, axis=0), np.delete(rv, drop_image, axis=0), \
                np.delete(tv, drop_image, axis=0)
        spec = replace(res.model, **changes)
        intr = res.intrinsics
        if spec.aspect and intr.fy_mm is None:
            intr = replace(intr, fy_mm=intr.f_mm)
        gains = np.asarray(res.gains, float) if res.model.fit_gains else np.ones(4)
        solver = SolverOptions(**o.get("solver", {}))
        prob = Problem(T, X, spec, cost="image", sensor_mm=tuple(res.sensor_mm))
        with np.errstate(all="ignore"):
            r = refine(prob, intr, res.distortion, gains, rv, tv, solver)
    except Exception:  # noqa: BLE001 -- a diagnosis refit that fails is just not the explanation
        return None
    q = np.asarray(r.residuals, dtype=float).reshape(-1, 2)
    if not (r.converged and np.all(np.isfinite(q)) and r.intrinsics.f_mm > 0 and np.all(r.tvecs[:, 2] > 0)):
        return None
    dof = max(q.size - r.z.size, 1)
    return _Warm(r.intrinsics, q, float(np.sqrt(np.sum(q * q) / dof)))


#: A diagnosis refit runs only when the linearised refit (the Gauss-Newton step from the fit, computed from its
#: Jacobian) explains at least 1 / SCREEN of the fall of the cost the refit must show to name its cause.
SCREEN = 4.0
#: ... and a model change only when its linearised fall is at least 1 / SCREEN_BEST of the fall the best change
#: refitted so far reached (the changes are refitted in the order of their linearised falls).
SCREEN_BEST = 2.0

#: The left-out terms (names of the verdict's richer model, :func:`psdcal.calibration._verdict_linear.linearise`)
#: each model change of the diagnosis adds, given the fit's model.
_TERMS_OF = {
    "radial": lambda m: (f"k{m.radial + 1}",),
    "tangential": lambda m: ("p1", "p2"),
    "psd_radial": lambda m: ("l1",),
    "aspect": lambda m: ("fy_mm",),
}


def _predicted_fall(lin, terms) -> float | None:
    """The fall of the residual sum of squares (mm^2) the linearised fit predicts when ``terms`` are added (None when
    they are not among ``lin``'s left-out terms: then the refit decides alone)."""
    names = list(lin.extra_names or ())
    if lin.extra is None or not terms or any(t not in names for t in terms):
        return None
    expl, _ = _explained(lin, lin.extra[:, [names.index(t) for t in terms]])
    return float(expl)


def _load_kernels() -> None:
    """Before several full calibrations: load the compiled kernels when they are available and already compiled
    on this machine, so that the refits run on them (the command line keeps small problems on the numpy path,
    :func:`psdcal._jit.use_compiled`, until the kernels are loaded; loading them costs well under a second,
    the numpy path's calibrations of a fit that collapsed seconds each)."""
    from psdcal import _jit

    if not _jit.enabled() or "psdcal.calibration._image_kernel" in sys.modules or not _jit.cache_is_warm():
        return
    try:
        import psdcal.calibration._image_kernel  # noqa: F401
    except Exception:  # noqa: BLE001 -- without the kernels the refits run on the numpy path
        return


def _ssr(r) -> float:
    q = r.residuals_mm
    return float(np.nansum(q * q))


def _diagnose(result, checks, lin, points_kind, bad_view):
    """Name the likely cause of the failed checks by refitting the alternatives."""
    by = {c.name: c for c in checks}
    base = _ssr(result)

    def better(r, factor):
        return r is not None and _ssr(r) < base / factor

    st = by.get("structure")
    leds = by.get("leds")
    m = result.model
    mt = by.get("model_terms")
    cause = None
    extra_checks = []
    det = by.get("held_values")
    if by.get("scale") is not None and by["scale"].passed is False and by["scale"].severe:
        det = by["scale"]  # points in metres: every other symptom follows from the units
    statistical = ("structure", "model_terms", "views", "leds")
    undetermined = None
    collapsed_fit = (by["converged"].passed is False) or (by["focal_length"].passed is False
                                                          and by["scale"].passed is not False)
    if det is None or det.passed is not False:
        det = by.get("determination")
        if any(by[n].p_value is not None and by[n].p_value < by[n].false_alarm for n in statistical if n in by):
            det = None  # a bad view or LED also leaves f undetermined: look for it first
        elif det is not None and det.passed is False and collapsed_fit:
            undetermined, det = det, None  # a collapsed fit: a bad view or a permutation first, then the views

    def blame(det):
        # the views do not determine the camera, or a held value is wrong: every other symptom follows from that
        for name, c in by.items():
            if c.passed is False and name != det.name:
                by[name] = replace(c, advice=f"probably a consequence of the cause found: {det.advice}")
        return [by[c.name] for c in checks]

    if det is not None and det.passed is False:
        return blame(det)
    # a fit that collapsed (f no lens has) or is not a camera: a bad view or a template permutation first
    broken = collapsed_fit \
        or (by.get("determination") is not None and by["determination"].passed is False and by["determination"].severe)
    if broken and len(result.image_ids) >= 4:
        cause = _view_advice(result)  # the linearisation of a collapsed fit says little: refit each view out
    if broken and cause is None:
        perm = _homography_hint(result) or _permutation_advice(result, lin, base, full=True)
        if perm:
            cause = perm
            if leds is not None:  # verified by the refit: the result is wrong
                by["leds"] = replace(leds, passed=False, severe=True, advice=perm)
    if cause is None and undetermined is not None:
        return blame(undetermined)
    if cause is None and ((st is not None and st.passed is False) or by["optical_centre"].passed is False
                          or (mt is not None and mt.passed is False)):
        again = _refit(result)
        if better(again, 1.01):
            cause = ("the fit stopped in a local minimum: re-run psdcal calibrate (it starts from several optical "
                     "centres) or give the lens' nominal focal length with --f-guess")
            extra_checks.append(_minimum_check(result, again, base, cause))
        if cause is None and not m.fit_gains and points_kind != "points":
            # the first-order effect of unequal channel gains on the readout (three ratios), off the model's columns
            from psdcal.model.readout import gain_map

            dg = gain_map(lin.pts, np.ones(4), *result.sensor_mm, jacobians=True)[2][..., 1:]  # (N, 2, 3)
            expl_g, _ = _explained(lin, dg.reshape(-1, 3))
            g = None if expl_g > 0.5 * base or m.skew or m.aspect or m.radial < 1 or expl_g < base * 0.75 / SCREEN \
                else _warm_refit(result, fit_gains=True)
            if expl_g > 0.5 * base or better(g, 4.0):
                cause = ("residuals show a projective pattern: raw amplitudes through unequal channel gains; "
                         "run with --fit-gains (or calibrate the gains electrically)")
        if cause is None and len(result.image_ids) >= 4:
            cause = _view_advice(result, lin)
        if cause is None:
            extra = []
            cands = [(flag, ch) for flag, ch in (
                (f"--radial {m.radial + 1}", {"radial": m.radial + 1}) if m.radial < 3 else (None, None),
                ("--tangential", {"tangential": True}) if not m.tangential else (None, None),
                ("--psd-radial 1", {"psd_radial": 1}) if m.psd_radial == 0 else (None, None),
                ("--aspect", {"aspect": True}) if not (m.aspect or m.skew) else (None, None)) if flag is not None]
            # the linearised fall of the cost each change brings; refitted in that order (largest first), a change
            # whose linearised fall is below 1 / SCREEN of the fall it needs, or below 1 / SCREEN_BEST of the fall
            # of the best one refitted, is not
            needed = base * (1 - 1 / 1.05)
            pred = [_predicted_fall(lin, _TERMS_OF[next(iter(ch))](m)) for _, ch in cands]
            order = sorted(range(len(cands)), key=lambda k: -(np.inf if pred[k] is None else pred[k]))
            best_fall = 0.0
            for k in order:
                flag, ch = cands[k]
                if pred[k] is not None and (pred[k] < needed / SCREEN or pred[k] < best_fall / SCREEN_BEST):
                    continue
                r = _warm_refit(result, **ch)
                if r is not None and _ssr(r) < base / 1.05 and F_RANGE_MM[0] <= r.intrinsics.f_mm <= F_RANGE_MM[1]:
                    extra.append((_ssr(r), flag))
                    best_fall = max(best_fall, base - _ssr(r))
            if extra:
                extra.sort()
                cause = f"the model lacks terms the data need: add {extra[0][1]}" + (
                    "" if extra[0][1] == "--aspect" else " (or try --model auto)")
    unconverged = by.get("converged") is not None and by["converged"].passed is False
    collapsed = by["focal_length"].passed is False and by["scale"].passed is not False
    views_failed = by.get("views") is not None and by["views"].passed is False
    if cause is None and views_failed and not broken and len(result.image_ids) >= 4:
        verified = _view_advice(result, lin)
        if verified is not None:
            cause = verified
            bad_view = None
    if cause is None and not broken and leds is not None and leds.passed is False and leds.severe:
        perm = _permutation_advice(result, lin, base)
        if perm:
            cause = perm
            if leds is not None:  # verified by the refit: the result is wrong
                by["leds"] = replace(leds, passed=False, severe=True, advice=perm)
    verified = cause is not None
    if cause is None and bad_view is not None and by["views"].severe:
        cause = f"view {result.image_ids[bad_view]} disagrees with the others: check its labels or leave it out"
    if cause is not None and cause.startswith("view ") and by.get("views") is not None:
        # a refit without the view verified it (implied noise down 3x): the result with it is wrong
        by["views"] = replace(by["views"], advice=cause, passed=False, severe=verified or by["views"].severe)
    if cause is not None and collapsed:
        by["focal_length"] = replace(by["focal_length"], advice=cause)
    if unconverged and cause is not None:
        by["converged"] = replace(by["converged"], advice=cause)
    for name in ("structure", "optical_centre", "model_terms", "views", "leds"):
        c = by.get(name)
        if c is None or c.passed is not False:
            continue
        if name == "model_terms":
            if verified and not cause.startswith("the model lacks"):
                by[name] = replace(c, advice=f"probably a consequence of the cause found: {cause}")
            continue
        if cause is None:
            if name == "structure":
                vw = by.get("views")
                if mt is not None and mt.passed is False:
                    by[name] = replace(c, advice=f"probably the terms the model leaves out: {mt.advice}")
                elif vw is not None and vw.passed is False:
                    by[name] = replace(c, advice=f"perhaps the view that disagrees: {vw.advice}")
                else:
                    by[name] = replace(c, advice="a systematic misfit that no richer model, gain fit or re-start "
                                                 "removes: check the template coordinates, the point ids and the units")
            continue
        if name in ("structure", "optical_centre"):
            by[name] = replace(c, advice=cause)
        elif name == "views" and not cause.startswith("view "):
            by[name] = replace(c, advice=f"probably a consequence of the cause found: {cause}")
        elif name == "leds" and not cause.startswith("a template permutation"):
            by[name] = replace(c, advice=f"probably a consequence of the cause found: {cause}")
    if cause is not None and by.get("determination") is not None and by["determination"].passed is False:
        by["determination"] = replace(by["determination"], advice=f"probably a consequence of the cause found: {cause}")
    return [by[c.name] for c in checks] + extra_checks


def _minimum_check(result, again, base, cause):
    """The ``global_minimum`` check: a re-run reached a lower cost; how far it moves f and C in their sigmas."""
    from psdcal._consistency import Check

    moves = []
    for n in ("f_mm", "cx_mm", "cy_mm"):
        sd = result.std.get(n)
        if sd:
            moves.append((abs(again.parameter(n) - result.parameter(n)) / sd, n))
    E, name = max(moves) if moves else (float("inf"), "f_mm")
    return Check("global_minimum", base / max(_ssr(again), 1e-300), 1.01, None, 0.0, False,
                 f"a re-run reaches a cost {base / max(_ssr(again), 1e-300):.3g}x lower (f = {again.intrinsics.f_mm:.4g} mm "
                 f"instead of {result.intrinsics.f_mm:.4g}): this is not the least-squares solution; it moves {name} by "
                 f"{E:.3g} sigma", cause, severe=True, effect_sigma=float(E))


def _homography_hint(result) -> str | None:
    """The linear stage's template diagnosis (:func:`psdcal.calibration.core.template_hint`), None when it says nothing."""
    from psdcal.calibration._homography import homographies
    from psdcal.calibration.core import inputs_from_record, template_hint

    try:
        T, X = inputs_from_record(result.problem)
        hint = template_hint(T, X, homographies(T, X), list(result.point_ids))
    except Exception:  # noqa: BLE001 -- a diagnosis that cannot run says nothing
        return None
    return hint or None


def _view_advice(result, lin=None) -> str | None:
    """When leaving one view out makes the fit far better (implied noise down 3x, and no other view does), name it.

    With the linearised fit ``lin`` the implied noise without each view is
    computed from the Jacobian (no refit); only the best candidate is refitted
    to confirm it.
    """
    n = len(result.image_ids)
    if n < 2:
        return None
    if lin is not None and lin.gt is not None:
        ssr, dof = float(lin.e @ lin.e), lin.dof
        N = lin.gt.T @ lin.gt
        sig = np.full(n, np.inf)
        for i in range(n):
            rows = np.repeat(lin.img == i, 2)
            ei, gi = lin.e[rows], lin.gt[rows]
            b = gi.T @ ei
            from psdcal.calibration._verdict_linear import _pinv_sym

            s_i = ssr - float(ei @ ei) - float(b @ _pinv_sym(N - gi.T @ gi) @ b)
            d_i = dof - int(rows.sum()) + 6
            if d_i > 0:
                sig[i] = np.sqrt(max(s_i, 0.0) / d_i)
        base = np.sqrt(ssr / max(dof, 1))
        order = np.argsort(sig)
        if not (np.isfinite(sig[order[0]]) and sig[order[0]] * 3 < base and sig[order[0]] * 3 < sig[order[1]]):
            return None
        i = int(order[0])
        r = _warm_refit(result, drop_image=i)
        if r is None or not r.sigma_mm * 3 < result.sigma_mm:
            return None
        return (f"view {result.image_ids[i]} disagrees with the others (without it the implied noise falls "
                f"{result.sigma_mm / r.sigma_mm:.3g}x): check its labels (two LEDs merged or shifted by the demodulator?) "
                "or leave it out")
    sig = []
    _load_kernels()  # a full calibration per view follows
    for i in range(n):
        r = _refit(result, drop_image=i)
        sig.append(np.inf if r is None else r.sigma_mm)
    sig = np.asarray(sig)
    order = np.argsort(sig)
    if not np.isfinite(sig[order[0]]):
        return None
    if sig[order[0]] * 3 < result.sigma_mm and sig[order[0]] * 3 < sig[order[1]]:
        i = int(order[0])
        return (f"view {result.image_ids[i]} disagrees with the others (without it the implied noise falls "
                f"{result.sigma_mm / sig[i]:.3g}x): check its labels (two LEDs merged or shifted by the demodulator?) "
                "or leave it out")
    return None


def _permutation_advice(result, lin, base, *, full: bool = False) -> str | None:
    """When swapping template LEDs (among the least consistent) makes the fit far better, say which.

    The swaps are ranked by how well each view's homography fits the swapped
    template (a linear fit per view, no refinement: a wrong pair leaves two
    points off by the LEDs' spacing, the right one leaves the lens'
    distortion); the best-ranked swap is calibrated (all starts, 40
    iterations), and named when its cost falls 50x. ``full``: when it does not
    (a collapsed fit), every swap is calibrated, as the ranking then says
    little.
    """
    from psdcal.calibration._homography import apply_homography, homographies
    from psdcal.calibration.core import points_from_record

    M = len(result.point_ids)
    q = lin.e.reshape(-1, 2)
    sq = np.bincount(lin.led, weights=np.sum(q * q, axis=1), minlength=M)
    worst = list(np.argsort(-sq)[: min(5, M)])
    T = np.asarray(result.problem["template"]["xy_mm"], dtype=float)
    X = points_from_record(result.problem["points"]["xy_mm"])
    pairs = [(worst[a_i], worst[b_i]) for a_i in range(len(worst)) for b_i in range(a_i + 1, len(worst))]
    solver = {**result.problem["options"].get("solver", {}), "max_iterations": 40}

    def swapped(a, b):
        T2 = T.copy()
        T2[[a, b]] = T2[[b, a]]
        return T2

    def misfit(T2) -> float:
        try:
            Hs = homographies(T2, X, normalize=True)
        except Exception:  # noqa: BLE001 -- a swap the DLT cannot fit ranks last
            return np.inf
        d = np.stack([apply_homography(H, T2) for H in Hs]) - X
        return float(np.nansum(d * d))

    def search(cands):
        best = (base, None)
        for a, b in cands:
            r = _refit(result, template_mm=swapped(a, b), solver=solver)
            if r is not None and _ssr(r) < best[0]:
                best = (_ssr(r), (a, b))
        return best

    ranked = sorted(pairs, key=lambda ab: misfit(swapped(*ab)))
    best = search(ranked[:1])
    if full and (best[1] is None or best[0] > base / 50):
        _load_kernels()  # a full calibration per swap follows
        best = search(ranked[1:]) if best[1] is None else min(best, search(ranked[1:]), key=lambda t: t[0])
    if best[1] is None or best[0] > base / 50:
        return None
    a, b = best[1]
    ids = result.point_ids
    return (f"a template permutation fits: LEDs {ids[a]} and {ids[b]} look swapped (residuals fall "
            f"{base / max(best[0], 1e-300):.3g}x): check the LED order in the template (a row listed in reverse?)")

