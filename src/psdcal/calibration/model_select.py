"""Model choice by evidence (``psdcal calibrate --model auto``) and cross-validation (``--cross-validate K``).

Model choice: forward selection over nested models. Start from the smallest
useful model (f, C, k1); at each step fit, then test each group of terms the
model leaves out -- the next lens radial term, the tangential pair (p1, p2),
the next PSD radial term, the skew -- by the F-test of the linearised richer
model (the ``model_terms`` check of :mod:`psdcal.calibration.verdict`): the
residual sum of squares the group's Jacobian columns explain beyond the
model's own, against the residual variance. The most significant group is
added when its p-value, Bonferroni-corrected over the groups tested, is
below ``alpha``; the selection stops when none is. Each step's false-alarm
rate (adding a term the data do not need) is at most ``alpha``.

Cross-validation: the views are split into K folds; each fold is left out,
the calibration refitted on the others, each left-out view's pose fitted
with the refitted intrinsics and distortion held, and its points predicted.
Under the model, the left-out residuals have the noise variance of the
fit (inflated slightly by the intrinsics' own uncertainty, which is
included to first order): the sum of their squares over the predicted
variance is a chi-square variable, and its p-value says whether the
calibration predicts new views as well as it claims.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from psdcal.calibration.verdict import ALPHA, _explained, _linearise

#: Groups of terms ``--model auto`` can add, in the order they are reported.
TERM_GROUPS = ("radial", "tangential", "psd_radial", "skew")


def _groups(spec):
    """(group, names, changed spec) of the term groups ``spec`` leaves out."""
    out = []
    if spec.radial < 3:
        out.append(("radial", (f"k{spec.radial + 1}",), replace(spec, radial=spec.radial + 1)))
    if not spec.tangential:
        out.append(("tangential", ("p1", "p2"), replace(spec, tangential=True)))
    if spec.psd_radial < 1:
        out.append(("psd_radial", ("l1",), replace(spec, psd_radial=spec.psd_radial + 1)))
    if not spec.skew and not spec.aspect:
        out.append(("skew", ("skew",), replace(spec, skew=True)))
    return out


def group_tests(result) -> list[dict]:
    """F-test of each left-out term group of ``result``'s model: ``[{group, terms, F, p, dof}]``."""
    from scipy.stats import f as fdist

    lin = _linearise(result)
    dof = lin.e.size - lin.n
    ssr = float(lin.e @ lin.e)
    out = []
    for group, names, _ in _groups(result.model):
        idx = [lin.extra_names.index(n) for n in names if n in lin.extra_names]
        if not idx:
            continue
        expl, p_dim = _explained(lin, lin.extra[:, idx])
        if p_dim == 0 or dof - p_dim <= 0:
            out.append({"group": group, "terms": list(names), "F": 0.0, "p": 1.0, "dof": 0})
            continue
        F = (expl / p_dim) / max((ssr - expl) / (dof - p_dim), 1e-300)
        out.append({"group": group, "terms": list(names), "F": float(F), "p": float(fdist.sf(F, p_dim, dof - p_dim)), "dof": p_dim})
    return out


def select_model(template_mm, points_mm, *, alpha: float = ALPHA, start: dict | None = None, **kwargs):
    """Fit with the model the data support (forward selection by nested F-tests).

    Parameters
    ----------
    template_mm, points_mm : as :func:`psdcal.calibrate`.
    alpha : float
        Bonferroni-corrected p-value below which a term group is added.
    start : dict, optional
        The first model's switches (default radial 1, no tangential, no PSD terms, no skew).
    **kwargs
        Other :func:`psdcal.calibrate` arguments (cost, aspect, sensor_mm, ...);
        the model switches in them are ignored.

    Returns
    -------
    result : CalibrationResult of the chosen model (with its verdict; the
        selection path in ``result.problem["model_selection"]``).
    steps : list of dict, one per step: the model, the group tests, what was added.
    """
    from psdcal.calibration.core import calibrate, with_verdict

    for k in ("radial", "tangential", "psd_radial", "skew", "verdict"):
        kwargs.pop(k, None)
    spec = {"radial": 1, "tangential": False, "psd_radial": 0, "skew": False, **(start or {})}
    steps = []
    res = None
    for _ in range(8):
        res = calibrate(template_mm, points_mm, **spec, verdict=False, **kwargs)
        tests = group_tests(res)
        n = max(len(tests), 1)
        best = min(tests, key=lambda t: t["p"]) if tests else None
        add = best is not None and best["p"] * n < alpha
        steps.append({"model": dict(spec), "tests": tests, "added": best["group"] if add else None,
                      "p_corrected": None if best is None else float(min(1.0, best["p"] * n))})
        if not add:
            break
        g = best["group"]
        if g == "radial":
            spec["radial"] += 1
        elif g == "tangential":
            spec["tangential"] = True
        elif g == "psd_radial":
            spec["psd_radial"] += 1
        else:
            spec["skew"] = True
    res = replace(res, problem={**res.problem, "model_selection": {"alpha": alpha, "steps": steps}})
    return with_verdict(res, diagnose=False), steps


def describe_selection(steps) -> list[str]:
    """Lines that tell the selection path."""
    out = []
    for s in steps:
        m = s["model"]
        name = f"radial {m['radial']}, tangential {'on' if m['tangential'] else 'off'}, psd-radial {m['psd_radial']}, skew {'on' if m['skew'] else 'off'}"
        tests = ", ".join(f"{t['group']} p={t['p']:.2g}" for t in s["tests"])
        verb = f"add {s['added']}" if s["added"] else "stop"
        out.append(f"  [{name}] tests: {tests or 'none'} -> {verb}")
    return out


@dataclass(frozen=True)
class CrossValidation:
    """Leave-views-out prediction against the predicted uncertainty.

    Attributes
    ----------
    k : int, number of folds
    rms_mm : RMS per coordinate of the left-out points' prediction errors, mm
    predicted_rms_mm : RMS per coordinate the calibration predicts for them, mm
    ratio : rms_mm / predicted_rms_mm (about 1 when the calibration predicts as well as it claims)
    chi2 : sum of squared errors over the predicted variances; dof its degrees of freedom
    p_value : chi-square upper tail (small: worse than claimed)
    per_view : list of (image_id, rms_mm)
    passed : p_value >= alpha (and every fold refitted)
    failed_folds : folds whose refit failed (the views left in did not calibrate)
    """

    k: int
    rms_mm: float
    predicted_rms_mm: float
    ratio: float
    chi2: float
    dof: int
    p_value: float
    per_view: tuple
    passed: bool
    failed_folds: int = 0

    def to_dict(self) -> dict:
        return {"k": self.k, "rms_mm": self.rms_mm, "predicted_rms_mm": self.predicted_rms_mm, "ratio": self.ratio,
                "chi2": self.chi2, "dof": self.dof, "p_value": self.p_value, "passed": self.passed,
                "failed_folds": self.failed_folds,
                "per_view": [[_plain(i), float(r)] for i, r in self.per_view]}

    def check(self):
        """This cross-validation as a verdict check (``cross_validation``)."""
        from psdcal.calibration.verdict import Check

        return Check(
            "cross_validation", self.chi2 / max(self.dof, 1), None, self.p_value, ALPHA, self.passed, self.line(),
            "" if self.passed else "the calibration predicts new views worse than its uncertainty claims: a model "
                                   "that misses terms (--model auto), ignored gains (--fit-gains) or a bad view",
            severe=False,
        )

    def line(self) -> str:
        state = "consistent with" if self.passed else "WORSE than"
        if self.failed_folds:
            state += f" (and {self.failed_folds} fold(s) could not be refitted without their views)"
        return (f"cross-validation ({self.k} folds): left-out views predicted to {self.rms_mm * 1e3:.3g} um RMS per coordinate "
                f"against {self.predicted_rms_mm * 1e3:.3g} um predicted (ratio {self.ratio:.3g}, chi2/dof "
                f"{self.chi2 / max(self.dof, 1):.3g}, p = {self.p_value:.2g}): {state} the claimed uncertainty")


def _plain(v):
    return v.item() if isinstance(v, np.generic) else v


def _fit_pose(T, x_meas, intr, dist, rv0, tv0):
    """Pose (rvec, tvec) of one view with the intrinsics and distortion held, and its Jacobian (2M', 6)."""
    from scipy.optimize import least_squares

    from psdcal.model.distortion import distort
    from psdcal.model.projection import project

    ok = np.all(np.isfinite(x_meas), axis=1)

    def fun(q):
        x = project(T[ok], intr, q[:3], q[3:])
        return (distort(x, dist, intr.c).d_mm - x_meas[ok]).ravel()

    sol = least_squares(fun, np.concatenate([rv0, tv0]), method="lm", xtol=1e-12, ftol=1e-12)
    return sol.x[:3], sol.x[3:], sol.fun, sol.jac


def cross_validate(result, k: int = 5, *, alpha: float = ALPHA) -> CrossValidation:
    """Leave-views-out cross-validation of ``result`` (refits its recorded problem K times).

    Each left-out view's pose is fitted with the fold's intrinsics and
    distortion held (6 parameters per view), so its residuals have ``2 M' - 6``
    degrees of freedom; the predicted variance of each is the fold's noise
    variance plus the intrinsics' contribution ``J_g C_g J_g^T`` projected
    off the pose directions (to first order).
    """
    from scipy.stats import chi2 as chi2dist

    from psdcal.calibration._closed_form import poses_from_homographies
    from psdcal.calibration._homography import homographies
    from psdcal.calibration.checks import align_to_problem
    from psdcal.calibration.core import _calibrate_record
    from psdcal.calibration.core import inputs_from_record
    from psdcal.errors import InputError, PsdcalError

    res = align_to_problem(result)
    p = res.problem
    T, X = inputs_from_record(p)
    n = X.shape[0]
    if not 2 <= k <= n:
        raise InputError(f"--cross-validate K needs 2 <= K <= the number of views ({n}), got {k}", field="cross_validate")
    folds = [list(range(i, n, k)) for i in range(k)]
    sq = 0.0
    pred = 0.0
    dof = 0
    chi2 = 0.0
    per_view = []
    failed_folds = 0
    for fold in folds:
        keep = [i for i in range(n) if i not in fold]
        if len(keep) < 3:
            continue
        d = res.to_dict()
        xy = [[[None if not np.isfinite(v) else v for v in pt] for pt in img] for img in X[keep].tolist()]
        d["problem"] = {**p, "points": {**p["points"], "xy_mm": xy, "image_ids": [p["points"]["image_ids"][i] for i in keep]}}
        try:
            fit = _calibrate_record(d)
        except PsdcalError:
            failed_folds += 1  # the views left in do not calibrate on their own: the set is not self-consistent
            continue
        s2 = fit.sigma_mm ** 2
        for i in fold:
            xm = X[i]
            ok = np.all(np.isfinite(xm), axis=1)
            if ok.sum() < 4:
                continue
            H = homographies(T[ok], xm[ok][None])[0]
            rv0, tv0 = poses_from_homographies(H[None], fit.intrinsics)
            rv, tv, r, Jp = _fit_pose(T, xm, fit.intrinsics, fit.distortion, rv0[0], tv0[0])
            m = r.size
            # the intrinsics' part of the prediction variance, off the pose directions (first order)
            var = np.full(m, s2)
            var_g = _global_variance(T, xm, fit, r, Jp, rv, tv)
            if var_g is not None:
                var = var + var_g
            Qp, _ = np.linalg.qr(Jp)
            lev = np.sum(Qp * Qp, axis=1)
            chi2 += float(np.sum(r * r / var))
            dof += m - 6
            sq += float(r @ r)
            pred += float(np.sum(var * (1 - lev)))
            per_view.append((res.image_ids[i], float(np.sqrt(r @ r / m))))
    nn = max(dof, 1)
    rms = float(np.sqrt(sq / nn))
    prms = float(np.sqrt(pred / nn))
    pval = float(chi2dist.sf(chi2, nn)) if not failed_folds else 0.0
    return CrossValidation(k, rms, prms, rms / prms if prms > 0 else float("inf"), chi2, dof, pval, tuple(per_view),
                           pval >= alpha, failed_folds)


def _global_variance(T, xm, fit, r, Jp, rv, tv):
    """Diagonal of ``(I - P) J_g C_g J_g^T (I - P)`` for one view (P: projector on its pose columns), or None."""
    from psdcal.calibration._refine import Evaluator, Problem

    names = list(fit.param_names)
    C = np.asarray(fit.covariance, dtype=float)
    if C.shape != (len(names), len(names)) or not names:
        return None
    gains = np.asarray(fit.gains, float) if fit.model.fit_gains else np.ones(4)
    prob = Problem(T, np.asarray(xm, dtype=float)[None], fit.model, cost="image", sensor_mm=tuple(fit.sensor_mm))
    ev = Evaluator(prob, fit.intrinsics, fit.distortion, gains)
    z = prob.pack(fit.intrinsics, fit.distortion, gains, rv[None], tv[None])
    J = np.asarray(ev.evaluate(z)[1], dtype=float)
    if J.shape[0] != r.size:
        return None
    Jg = J[:, : len(names)]
    Qp, _ = np.linalg.qr(Jp)
    A = Jg - Qp @ (Qp.T @ Jg)
    return np.einsum("ij,jk,ik->i", A, C, A)
