"""A verdict on a calibration judged by its consequences: *good*, *suspect* (with reasons) or *wrong*.

A converged fit is not a correct one, and a fit that the data show to be
imperfect is not necessarily a wrong one: with thousands of points every tiny
systematic effect is statistically "significant". Each check below therefore
asks two questions:

1. does the check's alternative explain the residuals beyond noise (a test
   with a stated false-alarm rate ``ALPHA`` on correct fits, measured in
   ``benchmarks/study_verdict.py``)?
2. if so, how much would it move what the user uses: the focal length, the
   optical centre and the angles of arrival over the field of view, in units
   of their own standard errors (``effect_sigma``; a linearised refit with
   the alternative: :mod:`psdcal.calibration._verdict_linear`)?

An effect below :data:`EFFECT_SUSPECT` (one standard error) is a *note*: the
check passes, its message gives the size ("a smooth field of 0.6 um RMS ...
moves the angles by at most 0.3 sigma") and the effect enters the covariance:
it is multiplied by ``1 + effect_sigma^2`` (the check's ``inflation``; the
result's covariance takes the largest inflation of its checks) so that the
stated sigmas cover the bias. An effect of one to :data:`EFFECT_WRONG`
standard errors makes the verdict *suspect*, beyond it *wrong*.

``noise``
    The residual sum of squares against the noise the user states
    (``noise_mm``): ``SSR / sigma^2 ~ chi^2(m - n)``. Without a stated noise
    the check says so and does not vote. The covariance already uses the
    noise the residuals imply, so a failure is *suspect* (the stated noise or
    the model is wrong), never a reason to inflate.
``structure``
    Systematic structure: a smooth vector field over the sensor (each
    coordinate a polynomial of degree <= 3 in the sensor position, plus
    radial fields ``d r^4``, ``d r^6`` about C) fitted to the residuals, after
    projecting out what the model's own parameters can absorb. Under the
    model with Gaussian noise the explained sum of squares over the rest is
    an F(p, m - n - p) variable. Effect: the refit with the field removed
    from the points.
``model_terms``
    The terms the model leaves out (the next radial term, tangential, PSD l1,
    skew): a nested F-test. Effect: the refit with them.
``views`` / ``leds``
    Each view's (each template LED's) residual variance against the others'
    (F-test, Bonferroni). Effect: the refit without that view (LED).
``held_values``
    A fixed value or a prior that the data contradict, named in sigmas.
``determination``
    f known worse than 10 % (suspect) or 30 % (wrong: undetermined), C worse
    than a quarter of the sensor's half-size (suspect).
``scale``, ``focal_length``, ``optical_centre``, ``converged``, ``distortion_monotonic``
    Physical plausibility (:mod:`psdcal.calibration._verdict_rules`).

A failed check carries the likely cause and the command that fixes it
(:func:`assess` with ``diagnose=True`` refits the alternatives it suspects:
global re-run, richer model, fitted gains, swapped template LEDs, one view
left out: :mod:`psdcal.calibration._verdict_diagnosis`).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from psdcal import _stats
from psdcal._consistency import Check
from psdcal.calibration._verdict_fields import (
    explained,
    f_test,
    field_shift,
    structure_fields,
    structure_test,
    terms_test,
)
from psdcal.calibration._verdict_linear import (
    FIELD_DEGREE,
    Linear,
    consequences,
    effect,
    field_basis,
    field_parts,
    group_f,
    group_shift,
    linearise,
    view_shift,
)
from psdcal.calibration._verdict_rules import (
    C_FRACTION,
    F_RANGE_MM,
    SPAN_SUSPECT,
    SPAN_WRONG,
    determination,
    held_values,
    plausibility,
    template_side,
)
from psdcal.errors import PsdcalError

#: Design false-alarm rate of each statistical check (p-value threshold).
ALPHA = 1e-3
#: A significant effect that moves the result by at least this many of its standard errors fails its check (suspect).
EFFECT_SUSPECT = 1.0
#: ... and by at least this many makes the verdict wrong.
EFFECT_WRONG = 10.0
#: The structure check's effect counts the field combinations at least this fraction visible off the parameters.
FIELD_VISIBLE = 0.3

VERDICTS = ("good", "suspect", "wrong")

# the checks' thresholds depend only on (alpha, degrees of freedom): computed once per size (Monte Carlo trials repeat
# them), each an iterative inversion of a distribution function
_f_isf = functools.lru_cache(maxsize=1024)(_stats.f_isf)
_chi2_isf = functools.lru_cache(maxsize=1024)(_stats.chi2_isf)

# the names the verdict's users import (kept from the single-module layout)
_Linear = Linear
_linearise = linearise
_explained = explained
_field_basis = field_basis
_group_f = group_f

__all__ = [
    "ALPHA",
    "C_FRACTION",
    "EFFECT_SUSPECT",
    "EFFECT_WRONG",
    "FIELD_DEGREE",
    "F_RANGE_MM",
    "SPAN_SUSPECT",
    "SPAN_WRONG",
    "VERDICTS",
    "Check",
    "Verdict",
    "VerdictError",
    "assess",
    "assess_fit",
    "covariance_inflation",
    "structure_judged",
    "structure_test",
    "terms_test",
    "with_check",
]


class VerdictError(PsdcalError, ValueError):
    """A calibration refused for its verdict (``psdcal calibrate --strict``)."""


@dataclass(frozen=True)
class Verdict:
    """The verdict on a calibration and the checks it rests on."""

    verdict: str
    checks: tuple

    @property
    def failed(self) -> tuple:
        return tuple(c for c in self.checks if c.passed is False)

    @property
    def notes(self) -> tuple:
        """Checks that found an effect too small to move the result (passed, with a covariance inflation)."""
        return tuple(c for c in self.checks if c.passed is True and (c.inflation or 1.0) > 1.0)

    @property
    def reasons(self) -> tuple:
        return tuple(c.message for c in self.failed)

    @property
    def inflation(self) -> float:
        """The factor the covariance takes from the checks (the largest of theirs, 1 when none)."""
        return covariance_inflation(self.checks)

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "checks": [c.to_dict() for c in self.checks]}

    @classmethod
    def from_dict(cls, d: dict) -> Verdict:
        return cls(str(d["verdict"]), tuple(Check.from_dict(c) for c in d.get("checks", [])))

    def lines(self) -> list[str]:
        """Human-readable summary: the verdict, one line per failed check and its advice, then the notes."""
        out = [f"verdict: {self.verdict.upper()}"
               + ("" if self.verdict == "good" else f" ({len(self.failed)} check(s) failed)")]
        for c in self.failed:
            out.append(f"  {c.name}: {c.message}")
            if c.advice:
                out.append(f"    advice: {c.advice}")
        for c in self.notes:
            out.append(f"  note: {c.name}: {c.message}")
        for c in self.checks:
            if c.passed is None:
                out.append(f"  {c.name}: {c.message}")
        f = self.inflation
        if f > 1.0:
            why = ", ".join(c.name for c in self.checks if (c.inflation or 1.0) == f)
            out.append(f"  covariance inflated x{f:.3g} (standard errors x{math.sqrt(f):.3g}) to cover the effect "
                       f"found by {why}")
        return out


def covariance_inflation(checks) -> float:
    """The largest ``inflation`` of the checks (dicts or :class:`Check`), 1 when none."""
    f = 1.0
    for c in checks:
        v = c.get("inflation") if isinstance(c, dict) else c.inflation
        if v is not None and math.isfinite(float(v)):
            f = max(f, float(v))
    return f


# -- the checks --------------------------------------------------------------------------
def assess(result, *, noise_mm: float | None = None, points_kind: str | None = None, diagnose: bool = True) -> Verdict:
    """The verdict on ``result`` (a :class:`~psdcal.calibration.core.CalibrationResult`).

    Parameters
    ----------
    result : CalibrationResult with its problem record (every result of ``calibrate`` has one).
    noise_mm : float, optional
        Standard deviation of the noise on each coordinate of the impact
        points, mm, when known (the lock-in's amplitude noise carried to the
        sensor plane); without it the ``noise`` check does not vote.
    points_kind : "points" | "amplitudes", optional
        What the points file held; raw amplitudes make ignored channel gains
        a candidate cause of structured residuals.
    diagnose : bool
        Refit the alternatives a failed check suggests (global re-run, richer
        model, fitted gains, swapped LEDs) to name the cause. Costs a few
        refits, only when a check fails.

    Returns
    -------
    Verdict
        Each check with its ``effect_sigma`` (how far its alternative moves f,
        C or the angles, in their standard errors) and ``inflation`` (the
        factor it asks of the covariance; :func:`covariance_inflation`).
    """
    from psdcal.calibration._refine import _single_threaded_blas

    with _single_threaded_blas():  # small dense linear algebra: one BLAS thread is fastest
        return _assess(result, noise_mm=noise_mm, points_kind=points_kind, diagnose=diagnose)


def _uninflated_cov(result, lin: Linear):
    """The covariance of ``lin.names`` before any verdict inflation (the result's when it matches them)."""
    names = list(getattr(result, "param_names", ()) or ())
    C = np.asarray(getattr(result, "covariance", np.zeros((0, 0))), dtype=float)
    infl = float((result.stages or {}).get("covariance_inflation", {}).get("factor", 1.0)) if isinstance(
        result.stages, dict) else 1.0
    if C.shape == (len(names), len(names)) and all(n in names for n in lin.names) and np.isfinite(C).all():
        if len(lin.names) == len(names) and tuple(lin.names) == tuple(names):  # the same order: all of C
            return C / infl
        idx = [names.index(n) for n in lin.names]
        return C[np.ix_(idx, idx)] / infl
    return lin.s2 * lin.ninv


def _judge(name, stat, thr, p, dof, eff, found, size, advice, *, ok_words, lead="", alpha: float = ALPHA):
    """A statistical check judged by its consequence ``eff`` (:class:`~psdcal.calibration._verdict_linear.Effect`)."""
    if p >= alpha:
        return Check(name, stat, thr, p, alpha, True, ok_words, dof=dof, effect_sigma=None, inflation=1.0)
    E = float(eff.sigma) if eff is not None and math.isfinite(eff.sigma) else math.inf
    moves = lead + eff.words() if eff is not None else "its effect on the result could not be computed"
    found = f"{found}; {size}" if size else found
    if E < EFFECT_SUSPECT:
        infl = 1.0 + E * E
        return Check(name, stat, thr, p, alpha, True,
                     f"{found}; {moves}: within the uncertainty, covariance inflated x{infl:.3g}",
                     dof=dof, effect_sigma=E, inflation=infl)
    infl = 1.0 + E * E if math.isfinite(E) else 1.0
    return Check(name, stat, thr, p, alpha, False,
                 f"{found}; {moves}: beyond the uncertainty", advice,
                 severe=E >= EFFECT_WRONG, dof=dof, effect_sigma=E, inflation=infl)


def _assess(result, *, noise_mm, points_kind, diagnose) -> Verdict:
    checks = []
    sensor = np.asarray(result.sensor_mm, dtype=float)
    half = sensor / 2
    lin = linearise(result)
    m = lin.e.size
    dof = m - lin.n
    ssr = float(lin.e @ lin.e)
    cov = _uninflated_cov(result, lin)
    cons = _LazyConsequences(lin, result, cov)  # computed by the first check that finds something
    n_pts = m // 2

    checks.append(_noise_check(ssr, dof, noise_mm))
    sc = _structure_check(result, lin, ssr, dof, cons, n_pts)
    if sc is not None:
        checks.append(sc)

    # terms the model leaves out: a nested-model F-test (the linearised richer model)
    t = terms_test(lin)
    if t is not None:
        F, p, p_dim, best = t
        eff = size = None
        if p < ALPHA and cons:
            c, dth = field_shift(lin, lin.extra)
            eff = effect(cons, dth, dextra=c)
            vis = lin.perp(lin.extra @ c[:, None])[:, 0]
            size = f"they explain {_um(math.sqrt(float(vis @ vis) / max(n_pts, 1)))} RMS; most: {best}"
        checks.append(_judge(
            "model_terms", F, None, p, float(p_dim),
            eff, f"the terms the model leaves out ({', '.join(lin.extra_names)}) explain the residuals beyond noise "
                 f"(F = {F:.3g}, p = {p:.2g})", size,
            f"the data need {best}: add {_flag(best)}" + ("" if best == "fy_mm" else " (or try --model auto)"),
            lead="adding them ",
            ok_words=f"the terms the model leaves out ({', '.join(lin.extra_names)}) explain no more than noise "
                     f"(F = {F:.3g}, p = {p:.2g})"))

    # views
    n_img = len(result.image_ids)
    bad_view = None
    if n_img >= 3:
        F, pv = group_f(lin, lin.img, n_img, ssr, dof)
        worst = _argmax_finite(F.tolist())
        p = float(min(1.0, pv[worst] * n_img))
        per = result.per_image_rms_mm * 1e3
        others = per.tolist()
        del others[worst]
        vid = result.image_ids[worst]
        eff = None
        if p < ALPHA and cons:
            eff = effect(cons, view_shift(lin, worst))
        ch = _judge(
            "views", float(F[worst]), None, p, None, eff,
            f"view {vid} disagrees with the others (F = {F[worst]:.3g}, p = {p:.2g} after {n_img} views)",
            f"RMS {per[worst]:.3g} um against a median of {_median_floats(others):.3g} um",
            f"view {vid} disagrees with the others: check its labels (two LEDs merged or shifted by the "
            "demodulator?) or leave it out", lead="leaving it out ",
            ok_words=f"view {vid} is the least consistent (F = {F[worst]:.3g}, p = {p:.2g} after {n_img} views): "
                     "consistent")
        checks.append(ch)
        bad_view = None if ch.passed is not False else worst

    # leds
    M = len(result.point_ids)
    F, pv = group_f(lin, lin.led, M, ssr, dof)
    worst = int(np.argmax(np.where(np.isfinite(F), F, -np.inf)))
    p = float(min(1.0, pv[worst] * M))
    pid = result.point_ids[worst]
    eff = None
    if p < ALPHA and cons:
        eff = effect(cons, group_shift(lin, np.repeat(lin.led == worst, 2)))
    off = _rms_points(lin.e.reshape(-1, 2)[lin.led == worst])
    checks.append(_judge(
        "leds", float(F[worst]), None, p, None, eff,
        f"template LED {pid} is off in every view (F = {F[worst]:.3g}, p = {p:.2g} after {M} LEDs)",
        f"RMS {_um(off)} against {_um(math.sqrt(ssr / max(n_pts, 1)))} over all",
        f"LED {pid} disagrees in every view: check its template coordinates and the LED order", lead="leaving it out ",
        ok_words=f"template LED {pid} is the least consistent (F = {F[worst]:.3g}, p = {p:.2g} after {M} LEDs): "
                 "consistent"))

    hv = held_values(result, lin, ALPHA)
    if hv is not None:
        checks.append(hv)
    checks.append(determination(result, cov, lin.names, half))
    checks += plausibility(result, lin, sensor, half)
    side = template_side(result)
    if side is not None:
        checks.append(side)

    if diagnose and any(c.passed is False for c in checks):
        from psdcal.calibration._verdict_diagnosis import _diagnose

        checks = _diagnose(result, checks, lin, points_kind, bad_view)
    return Verdict(_word(checks), tuple(checks))


class _LazyConsequences:
    """:func:`~psdcal.calibration._verdict_linear.consequences`, computed on first use (most correct fits never
    need it); false when there are no free global parameters."""

    def __init__(self, lin, result, cov):
        self._args = (lin, result, cov)
        self._c = None

    def __bool__(self) -> bool:
        return bool(self._args[0].names)

    def __getattr__(self, name):
        if name.startswith("_"):
            raise AttributeError(name)
        if self._c is None:
            self._c = consequences(*self._args)
        return getattr(self._c, name)


def _word(checks) -> str:
    failed = [c for c in checks if c.passed is False]
    return "good" if not failed else ("wrong" if any(c.severe for c in failed) else "suspect")


def _median(x) -> float:
    """``np.median`` of a 1-d array, without the import of ``numpy.ma`` that np.median makes (some 20 ms of a
    fresh command-line process)."""
    x = np.sort(np.asarray(x, dtype=float).ravel())
    if x.size == 0 or np.isnan(x[-1]):  # NaN sorts last
        return float("nan")
    k = x.size // 2
    return float(x[k]) if x.size % 2 else float(0.5 * (x[k - 1] + x[k]))


def _rms_points(q) -> float:
    """RMS length of the points ``q`` (k, 2), 0 for none: ``np.sqrt(np.mean(q[:, 0] ** 2 + q[:, 1] ** 2))`` on
    its one sum (the same number)."""
    sq = q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1]
    return math.sqrt(float(sq.sum()) / sq.size) if sq.size else 0.0


def _median_floats(x: list) -> float:
    """:func:`_median` of a list of floats (the same number: NaN when one is NaN or the list is empty)."""
    if not x or any(v != v for v in x):
        return float("nan")
    x = sorted(x)
    k = len(x) // 2
    return float(x[k]) if len(x) % 2 else 0.5 * (x[k - 1] + x[k])


def _argmax_finite(x: list) -> int:
    """``np.argmax(np.where(np.isfinite(x), x, -np.inf))`` of a list of floats (the first largest finite; 0 when
    none is finite)."""
    best, k = -math.inf, 0
    for i, v in enumerate(x):
        if v > best and v != math.inf:
            best, k = v, i
    return k


def _um(mm: float) -> str:
    return f"{mm * 1e3:.2g} um"


def _noise_check(ssr: float, dof: int, noise_mm) -> Check:
    """chi^2 of the residuals against a stated noise level (not applicable without one)."""
    if noise_mm is not None and noise_mm > 0 and dof > 0:
        stat = ssr / noise_mm ** 2
        p = float(_stats.chi2_sf(stat, dof))
        ok = p >= ALPHA
        return Check(
            "noise", stat / dof, float(_chi2_isf(ALPHA, dof)) / dof, p, ALPHA, ok,
            f"residual RMS per coordinate {np.sqrt(ssr / dof) * 1e3:.3g} um against the stated noise {noise_mm * 1e3:.3g} um "
            f"(chi2/dof {stat / dof:.3g}, p = {p:.2g})" + ("" if ok else "; the standard errors use the implied noise"),
            "" if ok else "the model does not explain the points to their noise: see the other checks for the cause; "
                          "if none fails, the stated noise is too low",
            dof=float(dof), effect_sigma=0.0, inflation=1.0,
        )
    return Check("noise", None, None, None, ALPHA, None,
                 "no noise level given (--noise-um): the residual RMS is judged by the other checks only")


def _structure_check(result, lin: Linear, ssr: float, dof: int, cons, n_pts, alpha: float = ALPHA):
    """F-test of a smooth field over the sensor fitted to the residuals, judged by what removing the field moves
    (None when no field is testable)."""
    B = structure_fields(lin, result, parts=True)
    F, p, p_dim, expl = f_test(lin, B)
    if p_dim == 0:
        return None
    frac = expl / ssr if ssr > 0 else 0.0
    thr = float(_f_isf(alpha, p_dim, dof - p_dim))
    found = (f"a smooth field over the sensor explains {100 * frac:.3g} % of the residuals (F = {F:.3g} on {p_dim} "
             f"and {dof - p_dim} dof, p = {p:.2g})")
    eff = size = None
    if p < alpha and cons:
        c, dth = field_shift(lin, B, min_visible=FIELD_VISIBLE)
        at_grid = field_parts(cons.grid, result.intrinsics.c, np.asarray(result.sensor_mm, float) / 2).field(c)
        eff = effect(cons, dth, field_at_grid=at_grid)
        size = f"unmodelled {_um(math.sqrt(expl / max(n_pts, 1)))} RMS of {_um(math.sqrt(ssr / max(n_pts, 1)))}"
    ch = _judge("structure", F, thr, p, float(p_dim), eff, found, size,
                "a systematic misfit over the sensor: see the advice of the other checks", lead="removing it ",
                ok_words=found, alpha=alpha)
    return ch


def structure_judged(result, *, exclude=None, alpha: float = ALPHA) -> Check | None:
    """The ``structure`` check of :func:`assess` (test and effect) on ``result`` with the observations ``exclude``
    (n_images, M) bool left out (None when no field is testable)."""
    lin = linearise(result, exclude)
    if not lin.names:
        return None
    cov = _uninflated_cov(result, lin)
    cons = consequences(lin, result, cov)
    ch = _structure_check(result, lin, float(lin.e @ lin.e), lin.dof, cons, lin.e.size // 2, alpha=alpha)
    return ch


def assess_fit(result, jacobian, residuals, points_mm, *, noise_mm: float | None = None) -> Verdict:
    """The verdict on a fit given its dense Jacobian (a single-group fit, e.g. a stage sweep).

    Runs the checks that need no views or template: ``noise`` (with a stated
    noise), ``structure`` (a smooth field over the sensor explains the
    residuals beyond noise: a wrong model, minimum or gains) and the
    plausibility checks. Used by :func:`psdcal.calibration.directions.calibrate_directions`.
    Without the views' block structure the structure check's effect is not
    computed: a significant field fails it (suspect).

    Parameters
    ----------
    result : CalibrationResult
    jacobian : (2N, n) array, d(model)/d(free parameters) at the solution, rows (x0, y0, x1, ...)
    residuals : (2N,) array, model minus measured, same row order (mm)
    points_mm : (N, 2) array, the modelled points, mm
    noise_mm : float, optional, known noise per coordinate (mm)
    """
    J = np.asarray(jacobian, dtype=float)
    r = np.asarray(residuals, dtype=float)
    ok = np.all(np.isfinite(J), axis=1) & np.isfinite(r)
    J, r = J[ok], r[ok]
    U, s, _ = np.linalg.svd(J / np.maximum(np.linalg.norm(J, axis=0), 1e-300), full_matrices=False)
    Q = U[:, s > 1e-8 * max(float(s[0]) if s.size else 0.0, 1e-300)]

    def perp(B):  # B: (m, k) over the finite rows
        B = np.asarray(B, dtype=float)
        return B - Q @ (Q.T @ B)

    e = perp(-r[:, None])[:, 0]
    pts = np.asarray(points_mm, dtype=float).reshape(-1, 2)
    n_pts = pts.shape[0]
    lin = Linear(e, perp, np.sum(Q * Q, axis=1), pts, np.zeros(n_pts, dtype=int), np.arange(n_pts), Q.shape[1])
    sensor = np.asarray(result.sensor_mm, dtype=float)
    half = sensor / 2
    dof = e.size - lin.n
    ssr = float(e @ e)
    checks = [_noise_check(ssr, dof, noise_mm)]
    if ok.all():
        F, p, p_dim, expl = f_test(lin, structure_fields(lin, result))
        if p_dim:
            good = p >= ALPHA
            checks.append(Check(
                "structure", F, float(_f_isf(ALPHA, p_dim, dof - p_dim)), p, ALPHA, good,
                f"a smooth field over the sensor explains {100 * expl / max(ssr, 1e-300):.3g} % of the residuals "
                f"(F = {F:.3g} on {p_dim} and {dof - p_dim} dof, p = {p:.2g})",
                "" if good else "a systematic misfit over the sensor: a missing model term, ignored gains or a "
                                "wrong minimum", dof=float(p_dim)))
    checks += plausibility(result, lin, sensor, half)
    return Verdict(_word(checks), tuple(checks))


def _flag(term: str) -> str:
    """The calibrate option that frees ``term``."""
    if term.startswith("k"):
        return f"--radial {term[1]}"
    if term in ("p1", "p2"):
        return "--tangential"
    if term.startswith("l"):
        return f"--psd-radial {term[1]}"
    if term == "fy_mm":
        return "--aspect"
    return "--skew" if term == "skew" else term


def with_check(verdict: dict, check: Check) -> dict:
    """A verdict dict (``Verdict.to_dict()``) with one more check, the verdict recomputed."""
    v = Verdict.from_dict(verdict)
    checks = tuple(c for c in v.checks if c.name != check.name) + (check,)
    return Verdict(_word(checks), checks).to_dict()
