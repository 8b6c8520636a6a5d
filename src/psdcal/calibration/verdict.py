"""A statistical verdict on a calibration: *good*, *suspect* (with reasons) or *wrong*.

A converged fit is not a correct one. Each check below tests one thing the
data themselves say about the fit, with a stated false-alarm rate on correct
fits (measured in ``benchmarks/study_verdict.py``, table in the user guide):

``noise``
    The residual sum of squares against the noise the user states
    (``noise_mm``): ``SSR / sigma^2 ~ chi^2(m - n)``. Without a stated noise
    the check says so and does not vote.
``structure``
    Systematic structure: a smooth vector field over the sensor (each
    coordinate a polynomial of degree <= 3 in the sensor position, plus
    radial fields ``d r^4``, ``d r^6`` about C) fitted to the residuals, after
    projecting out what the model's own parameters can absorb (the columns
    of the Jacobian at the solution). Under the model with Gaussian noise the
    explained sum of squares over the rest is an F(p, m - n - p) variable.
    A wrong minimum, a missing distortion term and raw amplitudes through
    unequal gains all leave such a field.
``views``
    Per-view consistency: each view's residual variance (its degrees of
    freedom from the hat matrix, ``sum(1 - h)``) against the other views'
    (F-test, Bonferroni over the views). Names the view.
``leds``
    The same per template LED across all views: an LED far off in every view
    is a wrong template coordinate or a permutation of the LED order.
``scale``, ``focal_length``, ``optical_centre``, ``distortion_monotonic``
    Physical plausibility: the points span a sensible part of the sensor
    (not micrometres: metres given for millimetres), f in a lens' range, C
    within a lens mount's tolerance of the electrical centre, the distortion
    one-to-one over the sensor.

A failed check carries the likely cause and the command that fixes it
(:func:`assess` with ``diagnose=True`` refits the alternatives it suspects:
global re-run, richer model, fitted gains, swapped template LEDs).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from psdcal import _stats
from psdcal.errors import PsdcalError

#: Design false-alarm rate of each statistical check (p-value threshold).
ALPHA = 1e-3
#: A statistical check failed with a p-value below this makes the verdict "wrong".
WRONG_P = 1e-12
#: Polynomial degree of the smooth residual field of the ``structure`` check.
FIELD_DEGREE = 3
#: Focal lengths outside this range (mm) are not a PSD lens.
F_RANGE_MM = (1.0, 500.0)
#: Optical centre farther than this fraction of the sensor's half-size from the electrical centre: suspect.
C_FRACTION = 0.5
#: Points spanning less than these fractions of the sensor: suspect / wrong.
SPAN_SUSPECT, SPAN_WRONG = 0.1, 0.01

VERDICTS = ("good", "suspect", "wrong")


class VerdictError(PsdcalError, ValueError):
    """A calibration refused for its verdict (``psdcal calibrate --strict``)."""


@dataclass(frozen=True)
class Check:
    """One self-check of a calibration.

    Attributes
    ----------
    name : str
    statistic : float or None, the test statistic (F, chi^2/dof, a length, ...)
    threshold : float or None, the value beyond which the check fails
    p_value : float or None, probability of a statistic this extreme on a correct fit
    false_alarm : float, design false-alarm rate on correct fits (0 for plausibility rules)
    passed : bool or None (None: not applicable, e.g. no noise level given)
    message : str, what was found
    advice : str, the likely cause and the command that fixes it ("" when passed)
    severe : bool, a failure that makes the verdict "wrong"
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

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("statistic", "threshold", "p_value"):
            if d[k] is not None:
                d[k] = float(d[k])
        return d


@dataclass(frozen=True)
class Verdict:
    """The verdict on a calibration and the checks it rests on."""

    verdict: str
    checks: tuple

    @property
    def failed(self) -> tuple:
        return tuple(c for c in self.checks if c.passed is False)

    @property
    def reasons(self) -> tuple:
        return tuple(c.message for c in self.failed)

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "checks": [c.to_dict() for c in self.checks]}

    @classmethod
    def from_dict(cls, d: dict) -> "Verdict":
        return cls(str(d["verdict"]), tuple(Check(**c) for c in d.get("checks", [])))

    def lines(self) -> list[str]:
        """Human-readable summary: the verdict, then one line per failed check and its advice."""
        out = [f"verdict: {self.verdict.upper()}"
               + ("" if self.verdict == "good" else f" ({len(self.failed)} check(s) failed)")]
        for c in self.failed:
            out.append(f"  {c.name}: {c.message}")
            if c.advice:
                out.append(f"    advice: {c.advice}")
        for c in self.checks:
            if c.passed is None:
                out.append(f"  {c.name}: {c.message}")
        return out


# -- the linearised model at the solution ----------------------------------------------
@dataclass(frozen=True)
class _Linear:
    e: np.ndarray  # (m,) residuals meas - model, (x, y) per valid point
    perp: object  # B (m, k) -> (I - P) B, P the projector on the Jacobian's columns
    h: np.ndarray  # (m,) leverages
    pts: np.ndarray  # (N, 2) modelled points of the valid observations, mm
    img: np.ndarray  # (N,) image index
    led: np.ndarray  # (N,) template point index
    n: int  # rank of the Jacobian
    extra_names: tuple = ()  # terms the model leaves out
    extra: np.ndarray | None = None  # (m, len(extra_names)) their Jacobian columns at the solution


def _linearise(result, exclude=None) -> _Linear:
    from psdcal.calibration._refine import Evaluator, Problem
    from psdcal.calibration.checks import align_to_problem
    from psdcal.calibration.core import inputs_from_record

    res = align_to_problem(result)
    p = res.problem
    T, X = inputs_from_record(p)
    gains = np.asarray(res.gains, float) if res.model.fit_gains else np.ones(4)
    spec = res.model
    # the richer model: the terms this one leaves out (the next radial term, tangential, PSD l1, skew) at 0; its
    # Jacobian holds this model's columns and theirs (one evaluation for both)
    rich = replace(spec, radial=min(3, spec.radial + 1), tangential=True, psd_radial=max(spec.psd_radial, 1),
                   skew=spec.skew or not spec.aspect)
    extra_names = [n for n in rich.global_names if n not in spec.global_names]
    prob = Problem(T, X, rich, cost="image", sensor_mm=tuple(res.sensor_mm))
    ev = Evaluator(prob, res.intrinsics, res.distortion, gains)
    # the compact block Jacobian: the global columns, then each row's own view's six pose columns
    r, Jc = ev.evaluate_compact(prob.pack(res.intrinsics, res.distortion, gains, res.rvecs, res.tvecs_mm))
    r = np.asarray(r, dtype=float)
    Jc = np.asarray(Jc, dtype=float)
    ng_r = prob.n_global
    G = Jc[:, [prob.names.index(n) for n in spec.global_names]]
    extra = Jc[:, [prob.names.index(n) for n in extra_names]]
    Jpose = Jc[:, ng_r:]
    img, led, d_meas = ev.img_idx, ev.pt_idx, ev.d_meas
    if exclude is not None:  # (n_images, M) bool: observations left out of the test (flagged outliers)
        keep_pt = ~np.asarray(exclude, dtype=bool)[img, led]
        rows = np.repeat(keep_pt, 2)
        r, G, extra, Jpose = r[rows], G[rows], extra[rows], Jpose[rows]
        img, led, d_meas = img[keep_pt], led[keep_pt], d_meas[keep_pt]
    e = -r
    perp, h, rank = _projector(G, Jpose, np.repeat(img, 2), X.shape[0])
    e = perp(e[:, None])[:, 0]  # the solver stops within its tolerance of the stationary point
    # the modelled points (noise-free up to the fitted parameters): fields evaluated at the measured ones would carry
    # the noise's own gradient into the test and correlate with it
    return _Linear(e, perp, h, d_meas + r.reshape(-1, 2), img, led, rank, tuple(extra_names), extra)


def _projector(G, Jpose, row_img, n_img):
    """The projector off the Jacobian's columns, from its block structure.

    The pose columns of a view touch only that view's rows: a batched QR of the
    (rows x 6) blocks projects them out view by view; then a QR of the global
    columns so projected. ``Jpose`` is (m, 6): each row's own view's pose
    columns (the compact form). Returns ``(perp, leverages, rank)`` where
    ``perp(B)`` is ``(I - P) B`` for B (m, k).
    """
    m = row_img.size
    counts = np.bincount(row_img, minlength=n_img)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    pos = np.arange(m) - starts[row_img]
    nr = int(counts.max()) if m else 0
    blocks = np.zeros((n_img, nr, 6))
    blocks[row_img, pos] = Jpose
    blocks /= np.maximum(np.linalg.norm(blocks, axis=1, keepdims=True), 1e-300)
    Qb, Rb = np.linalg.qr(blocks)
    dq = np.abs(np.diagonal(Rb, axis1=1, axis2=2))
    rank = int(np.sum(dq > 1e-10 * max(float(dq.max()), 1e-300)))
    Qrows = Qb[row_img, pos]  # (m, 6): each row's part of its view's basis

    Qbt = np.ascontiguousarray(Qb.transpose(0, 2, 1))

    def perp_pose(B):
        Bb = np.zeros((n_img, nr, B.shape[1]))
        Bb[row_img, pos] = B
        # each view's part of B minus its projection on the view's pose basis (batched matrix products:
        # no (rows, 6, k) temporary)
        return B - np.matmul(Qb, np.matmul(Qbt, Bb))[row_img, pos]

    Gn = G / np.maximum(np.linalg.norm(G, axis=0), 1e-300)
    Gp = perp_pose(Gn)
    if Gp.shape[1]:
        Qg, Rg = np.linalg.qr(Gp)
        dg = np.abs(np.diag(Rg))
        keep = dg > 1e-8 * max(float(dg.max()), 1e-300)
        if not keep.all():
            U, sv, _ = np.linalg.svd(Gp, full_matrices=False)
            Qg = U[:, sv > 1e-8 * sv[0]]
    else:
        Qg = np.zeros((m, 0))
    rank += Qg.shape[1]

    def perp(B):
        Bp = perp_pose(np.asarray(B, dtype=float))
        return Bp - Qg @ (Qg.T @ Bp)

    h = np.sum(Qrows * Qrows, axis=1) + np.sum(Qg * Qg, axis=1)
    return perp, h, rank


def _field_basis(pts, c_mm, half_mm) -> np.ndarray:
    """(2N, p) smooth vector fields over the sensor at ``pts`` (N, 2), rows (x0, y0, x1, y1, ...)."""
    u = pts / half_mm
    cols = []
    for i in range(FIELD_DEGREE + 1):
        for j in range(FIELD_DEGREE + 1 - i):
            m = u[:, 0] ** i * u[:, 1] ** j
            z = np.zeros_like(m)
            cols.append(np.stack([m, z], 1).ravel())
            cols.append(np.stack([z, m], 1).ravel())
    d = (pts - np.asarray(c_mm)) / half_mm
    r2 = np.sum(d * d, axis=1)
    for k in (2, 3):
        cols.append((d * r2[:, None] ** k).ravel())
    return np.stack(cols, axis=1)


def _explained(lin: _Linear, B) -> tuple[float, int]:
    """Sum of squares of the residuals along span(B) minus the Jacobian's span, and its dimension."""
    B = B / np.maximum(np.linalg.norm(B, axis=0), 1e-300)
    Bp = lin.perp(B)
    nb = np.linalg.norm(Bp, axis=0)
    Bp = Bp[:, nb > 1e-4]  # fields the model's parameters absorb (to 1e-4) test nothing
    if Bp.shape[1] == 0:
        return 0.0, 0
    if Bp.shape[1] == 1:  # one field: its direction, no factorisation needed
        u = Bp[:, 0] / np.linalg.norm(Bp[:, 0])
        return float((u @ lin.e) ** 2), 1
    U, s, _ = np.linalg.svd(Bp, full_matrices=False)
    U = U[:, s > 1e-2 * s[0]]
    U = lin.perp(U)  # re-orthogonalise against the Jacobian (round-off of the projection)
    U, _ = np.linalg.qr(U)
    return float(np.sum((U.T @ lin.e) ** 2)), int(U.shape[1])


def _group_f(lin: _Linear, groups, n_groups, ssr, dof):
    """Per-group F statistics of the residual variance against the other groups', and the p-value of the
    largest (``pv`` is NaN for the other groups)."""
    q = lin.e.reshape(-1, 2)
    lev = np.bincount(groups, weights=(1.0 - lin.h).reshape(-1, 2).sum(axis=1), minlength=n_groups)
    sq = np.bincount(groups, weights=np.sum(q * q, axis=1), minlength=n_groups)
    usable = (lev >= 0.5) & (dof - lev >= 0.5)
    d_g = np.where(usable, lev, 1.0)
    d_r = np.where(usable, dof - lev, 1.0)
    F = np.where(usable, (sq / d_g) / (np.maximum(ssr - sq, 1e-300) / d_r), np.nan)
    # the checks test the worst group only (largest F): its p-value is the one computed (the others are NaN)
    worst = int(np.argmax(np.where(np.isfinite(F), F, -np.inf)))
    pv = np.full(n_groups, np.nan)
    pv[worst] = _stats.f_sf(F[worst], d_g[worst], d_r[worst]) if usable[worst] else 1.0
    return F, pv


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
    """
    from psdcal.calibration._refine import _single_threaded_blas

    with _single_threaded_blas():  # small dense linear algebra: one BLAS thread is fastest
        return _assess(result, noise_mm=noise_mm, points_kind=points_kind, diagnose=diagnose)


class _F:
    """F distribution tails (:mod:`psdcal._stats`: no scipy import on the path of every calibration)."""

    sf = staticmethod(lambda x, d1, d2: _stats.f_sf(x, d1, d2))
    isf = staticmethod(lambda a, d1, d2: _stats.f_isf(a, d1, d2))


class _Chi2:
    sf = staticmethod(lambda x, k: _stats.chi2_sf(x, k))
    isf = staticmethod(lambda a, k: _stats.chi2_isf(a, k))


def _assess(result, *, noise_mm, points_kind, diagnose) -> Verdict:
    checks = []
    sensor = np.asarray(result.sensor_mm, dtype=float)
    half = sensor / 2
    lin = _linearise(result)
    m = lin.e.size
    dof = m - lin.n
    ssr = float(lin.e @ lin.e)

    checks.append(_noise_check(ssr, dof, noise_mm))
    sc = _structure_check(result, lin, ssr, dof, half)
    if sc is not None:
        checks.append(sc)

    # terms the model leaves out: a nested-model F-test (the linearised richer model)
    t = terms_test(lin)
    if t is not None:
        F, p, p_dim, best = t
        ok = p >= ALPHA
        checks.append(Check(
            "model_terms", F, None, p, ALPHA, ok,
            f"the terms the model leaves out ({', '.join(lin.extra_names)}) " + (
                f"explain the residuals beyond noise (F = {F:.3g}, p = {p:.2g}; most: {best})" if not ok else
                f"explain no more than noise (F = {F:.3g}, p = {p:.2g})"),
            "" if ok else f"the data need {best}: add {_flag(best, result.model)} (or try --model auto)",
            severe=p < WRONG_P,
        ))

    # views
    n_img = len(result.image_ids)
    if n_img >= 3:
        F, pv = _group_f(lin, lin.img, n_img, ssr, dof)
        worst = int(np.nanargmax(np.where(np.isfinite(F), F, -np.inf)))
        p = float(min(1.0, pv[worst] * n_img))
        ok = p >= ALPHA
        per = result.per_image_rms_mm * 1e3
        others = np.delete(per, worst)
        checks.append(Check(
            "views", float(F[worst]), None, p, ALPHA, ok,
            f"view {result.image_ids[worst]} " + (
                f"disagrees with the others (RMS {per[worst]:.3g} um against a median of {np.median(others):.3g} um, "
                f"F = {F[worst]:.3g}, p = {p:.2g} after {n_img} views)" if not ok else
                f"is the least consistent (F = {F[worst]:.3g}, p = {p:.2g} after {n_img} views): consistent"),
            "" if ok else f"view {result.image_ids[worst]} disagrees with the others: check its labels (two LEDs merged "
                          f"or shifted by the demodulator?) or leave it out",
            severe=p < WRONG_P,
        ))
        bad_view = None if ok else worst
    else:
        bad_view = None

    # leds
    M = len(result.point_ids)
    F, pv = _group_f(lin, lin.led, M, ssr, dof)
    order = np.argsort(-np.where(np.isfinite(F), F, -np.inf))
    worst = int(order[0])
    p = float(min(1.0, pv[worst] * M))
    ok = p >= ALPHA
    checks.append(Check(
        "leds", float(F[worst]), None, p, ALPHA, ok,
        f"template LED {result.point_ids[worst]} " + (
            f"is off in every view (F = {F[worst]:.3g}, p = {p:.2g} after {M} LEDs)" if not ok else
            f"is the least consistent (F = {F[worst]:.3g}, p = {p:.2g} after {M} LEDs): consistent"),
        "" if ok else f"LED {result.point_ids[worst]} disagrees in every view: check its template coordinates and the LED order",
        severe=p < WRONG_P,
    ))

    # plausibility
    checks += _plausibility(result, lin, sensor, half)

    checks = [c for c in checks]
    if diagnose and any(c.passed is False for c in checks):
        checks = _diagnose(result, checks, lin, points_kind, bad_view)
    failed = [c for c in checks if c.passed is False]
    verdict = "good" if not failed else ("wrong" if any(c.severe for c in failed) else "suspect")
    return Verdict(verdict, tuple(checks))


def _noise_check(ssr: float, dof: int, noise_mm) -> Check:
    """chi^2 of the residuals against a stated noise level (not applicable without one)."""
    chi2 = _Chi2
    if noise_mm is not None and noise_mm > 0 and dof > 0:
        stat = ssr / noise_mm ** 2
        p = float(chi2.sf(stat, dof))
        ok = p >= ALPHA
        return Check(
            "noise", stat / dof, float(chi2.isf(ALPHA, dof)) / dof, p, ALPHA, ok,
            f"residual RMS per coordinate {np.sqrt(ssr / dof) * 1e3:.3g} um against the stated noise {noise_mm * 1e3:.3g} um "
            f"(chi2/dof {stat / dof:.3g}, p = {p:.2g})",
            "" if ok else "the model does not explain the points to their noise: see the other checks for the cause; "
                          "if none fails, the stated noise is too low",
            severe=p < WRONG_P,
        )
    return Check("noise", None, None, None, ALPHA, None,
                 "no noise level given (--noise-um): the residual RMS is judged by the other checks only")


def _structure_check(result, lin: _Linear, ssr: float, dof: int, half):
    """F-test of a smooth field over the sensor fitted to the residuals (None when no field is testable)."""
    fdist = _F
    B = _field_basis(lin.pts, result.intrinsics.c, half)
    expl, p_dim = _explained(lin, B)
    if p_dim > 0 and dof - p_dim > 0:
        F = (expl / p_dim) / max((ssr - expl) / (dof - p_dim), 1e-300)
        p = float(fdist.sf(F, p_dim, dof - p_dim))
        ok = p >= ALPHA
        frac = expl / ssr if ssr > 0 else 0.0
        return Check(
            "structure", F, float(fdist.isf(ALPHA, p_dim, dof - p_dim)), p, ALPHA, ok,
            f"a smooth field over the sensor explains {100 * frac:.3g} % of the residuals (F = {F:.3g} on {p_dim} and "
            f"{dof - p_dim} dof, p = {p:.2g})" + ("" if ok else f"; the residual RMS {result.rms_mm * 1e3:.3g} um is systematic, not noise"),
            "", severe=p < WRONG_P,
        )
    return None


def assess_fit(result, jacobian, residuals, points_mm, *, noise_mm: float | None = None) -> Verdict:
    """The verdict on a fit given its dense Jacobian (a single-group fit, e.g. a stage sweep).

    Runs the checks that need no views or template: ``noise`` (with a stated
    noise), ``structure`` (a smooth field over the sensor explains the
    residuals beyond noise: a wrong model, minimum or gains) and the
    plausibility checks. Used by :func:`psdcal.calibration.directions.calibrate_directions`.

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
    lin = _Linear(e, perp, np.sum(Q * Q, axis=1), pts, np.zeros(n_pts, dtype=int), np.arange(n_pts), Q.shape[1])
    sensor = np.asarray(result.sensor_mm, dtype=float)
    half = sensor / 2
    dof = e.size - lin.n
    ssr = float(e @ e)
    checks = [_noise_check(ssr, dof, noise_mm)]
    sc = _structure_check(result, lin, ssr, dof, half) if ok.all() else None
    if sc is not None:
        checks.append(sc)
    checks += _plausibility(result, lin, sensor, half)
    failed = [c for c in checks if c.passed is False]
    verdict = "good" if not failed else ("wrong" if any(c.severe for c in failed) else "suspect")
    return Verdict(verdict, tuple(checks))


def _plausibility(result, lin: _Linear, sensor, half) -> list:
    """The physical-plausibility checks: points' scale, f, C, convergence, a one-to-one distortion."""
    checks = []
    X = lin.pts
    span = float(np.max(np.ptp(X, axis=0))) if len(X) > 1 else 0.0
    frac = span / float(np.max(sensor))
    ok = frac >= SPAN_SUSPECT
    checks.append(Check(
        "scale", span, SPAN_SUSPECT * float(np.max(sensor)), None, 0.0, ok,
        f"the points span {_length(span)} of the {np.max(sensor):g} mm sensor",
        "" if ok else (f"points span {_length(span)}: are they in metres? The points file is in mm"
                       if frac < SPAN_WRONG else "the views cover a small part of the sensor: bring the template closer"),
        severe=frac < SPAN_WRONG,
    ))
    f = result.intrinsics.f_mm
    ok = F_RANGE_MM[0] <= f <= F_RANGE_MM[1]
    checks.append(Check(
        "focal_length", f, None, None, 0.0, ok,
        f"f = {f:.4g} mm" + ("" if ok else f", outside {F_RANGE_MM[0]:g}-{F_RANGE_MM[1]:g} mm"),
        "" if ok else ("not a lens for a PSD: check the units of the points (mm) and the template" if frac < SPAN_SUSPECT
                       else "the fit collapsed to a focal length no lens has: the views or the template do not fit "
                            "a camera (see the other checks: a mislabelled view, a template permutation)"),
        severe=not ok,
    ))
    c = np.asarray(result.intrinsics.c, dtype=float)
    rel = float(np.max(np.abs(c) / half))
    ok = rel <= C_FRACTION
    checks.append(Check(
        "optical_centre", float(np.hypot(*c)), float(C_FRACTION * np.min(half)), None, 0.0, ok,
        f"C = ({c[0]:.3g}, {c[1]:.3g}) mm from the electrical centre",
        "" if ok else "farther from the electrical centre than a lens mount puts it: a wrong minimum or ignored "
                      "channel gains (raw amplitudes: --fit-gains)",
        severe=rel > 1.0,
    ))
    from psdcal.calibration.core import implausible

    why = implausible(result)
    conv = bool(result.converged) and not why
    checks.append(Check(
        "converged", float(result.iterations), None, None, 0.0, conv,
        f"the refinement {'converged' if result.converged else 'did NOT converge'} in {result.iterations} iterations"
        + (f", to a solution that is not a camera ({why})" if why else ""),
        "" if conv else "no minimum was reached: the data do not fit the model (see the other checks: a bad view, "
                        "a template permutation, ignored gains), or allow more iterations (--max-iterations)",
        severe=not conv,
    ))
    mono = _monotonic(result)
    checks.append(Check(
        "distortion_monotonic", None, None, None, 0.0, mono, "the distortion is one-to-one over the sensor" if mono else
        "the distortion folds the sensor (not one-to-one over it)",
        "" if mono else "too many distortion terms for the points' coverage, or a wrong minimum: fewer terms (--radial 1) "
                        "or views reaching the sensor's corners",
        severe=not mono,
    ))

    return checks


def terms_test(lin: _Linear):
    """(F, p, dim, most significant term) of the nested-model test of the left-out terms, None without any."""
    fdist = _F

    if lin.extra is None or lin.extra.shape[1] == 0:
        return None
    dof = lin.e.size - lin.n
    ssr = float(lin.e @ lin.e)
    expl, p_dim = _explained(lin, lin.extra)
    if p_dim == 0 or dof - p_dim <= 0:
        return None
    F = (expl / p_dim) / max((ssr - expl) / (dof - p_dim), 1e-300)
    p = float(fdist.sf(F, p_dim, dof - p_dim))
    # each term alone too (one degree of freedom: more power for a single missing term); Bonferroni over all tests
    single = []
    Bn = lin.extra / np.maximum(np.linalg.norm(lin.extra, axis=0), 1e-300)
    Bp = lin.perp(Bn)  # all columns projected at once
    nb = np.linalg.norm(Bp, axis=0)
    for k, name in enumerate(lin.extra_names):
        if nb[k] > 1e-4:  # as in _explained: a column the model absorbs tests nothing
            ek = float((Bp[:, k] @ lin.e / nb[k]) ** 2)
            Fk = ek / max((ssr - ek) / (dof - 1), 1e-300)
            single.append((float(fdist.sf(Fk, 1, dof - 1)), Fk, name))
    n_tests = 1 + len(single)
    if single and min(single)[0] < p:
        pk, Fk, _ = min(single)
        return float(Fk), float(min(1.0, n_tests * pk)), 1, min(single)[2]
    best = min(single)[2] if single else lin.extra_names[0]
    return float(F), float(min(1.0, n_tests * p)), p_dim, best


def _flag(term: str, model) -> str:
    """The calibrate option that frees ``term``."""
    if term.startswith("k"):
        return f"--radial {term[1]}"
    if term in ("p1", "p2"):
        return "--tangential"
    if term.startswith("l"):
        return f"--psd-radial {term[1]}"
    return "--skew" if term == "skew" else term


def _length(mm: float) -> str:
    return f"{mm * 1e3:.3g} um" if mm < 0.1 else f"{mm:.3g} mm"


def _monotonic(result, n_dir: int = 16, n_r: int = 60) -> bool:
    """Whether the undistorted radius grows along rays from C out to the sensor's farthest corner."""
    from psdcal.model.distortion import undistort

    c = np.asarray(result.intrinsics.c, dtype=float)
    half = np.asarray(result.sensor_mm, dtype=float) / 2
    corners = np.array([[sx * half[0], sy * half[1]] for sx in (-1, 1) for sy in (-1, 1)])
    rmax = float(np.max(np.hypot(*(corners - c).T)))
    ang = np.linspace(0, 2 * np.pi, n_dir, endpoint=False)
    rad = np.linspace(0.02, 1.0, n_r) * rmax
    dirs = np.stack([np.cos(ang), np.sin(ang)], 1)
    d = c + rad[None, :, None] * dirs[:, None, :]
    inside = np.all(np.abs(d) <= half * 1.0001, axis=-1)
    x = undistort(d, result.distortion, c)
    proj = np.sum((x - c) * dirs[:, None, :], axis=-1)
    step = np.diff(proj, axis=1)
    both = inside[:, 1:] & inside[:, :-1]
    return bool(np.all(np.isfinite(proj[inside])) and np.all(step[both] > 0))


# -- diagnosis ---------------------------------------------------------------------------
def _refit(result, **changes):
    """Re-run ``result``'s calibration with changed options (or a changed template); None if it fails."""
    from psdcal.calibration.core import _calibrate_record

    try:
        return _calibrate_record(result, **changes)
    except Exception:  # noqa: BLE001 -- a diagnosis refit that fails is just not the explanation
        return None


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
    # a fit that collapsed (f no lens has) or is not a camera: a bad view or a template permutation first
    broken = (by["converged"].passed is False) or (by["focal_length"].passed is False and by["scale"].passed is not False)
    if broken and len(result.image_ids) >= 4:
        cause = _view_advice(result)
    if broken and cause is None:
        perm = _homography_hint(result) or _permutation_advice(result, lin, base)
        if perm:
            cause = perm
            if leds is not None and leds.passed is False:
                by["leds"] = replace(leds, advice=perm)
    if cause is None and ((st is not None and st.passed is False) or by["optical_centre"].passed is False
                          or (mt is not None and mt.passed is False)):
        again = _refit(result)
        if better(again, 1.01):
            cause = ("the fit stopped in a local minimum: re-run psdcal calibrate (it starts from several optical "
                     "centres) or give the lens' nominal focal length with --f-guess")
        if cause is None and not m.fit_gains and points_kind != "points":
            # the first-order effect of unequal channel gains on the readout (three ratios), off the model's columns
            from psdcal.model.readout import gain_map

            dg = gain_map(lin.pts, np.ones(4), *result.sensor_mm, jacobians=True)[2][..., 1:]  # (N, 2, 3)
            expl_g, _ = _explained(lin, dg.reshape(-1, 3))
            g = None if expl_g > 0.5 * base or m.skew or m.aspect or m.radial < 1 else _refit(result, fit_gains=True)
            if expl_g > 0.5 * base or better(g, 4.0):
                cause = ("residuals show a projective pattern: raw amplitudes through unequal channel gains; "
                         "run with --fit-gains (or calibrate the gains electrically)")
        if cause is None and len(result.image_ids) >= 4:
            cause = _view_advice(result)
        if cause is None:
            extra = []
            for flag, ch in ((f"--radial {m.radial + 1}", {"radial": m.radial + 1}) if m.radial < 3 else (None, None),
                             ("--tangential", {"tangential": True}) if not m.tangential else (None, None),
                             ("--psd-radial 1", {"psd_radial": 1}) if m.psd_radial == 0 else (None, None)):
                if flag is None:
                    continue
                r = _refit(result, **ch)
                if r is not None and _ssr(r) < base / 1.05 and _structure_ok(r) \
                        and F_RANGE_MM[0] <= r.intrinsics.f_mm <= F_RANGE_MM[1]:
                    extra.append((_ssr(r), flag))
            if extra:
                extra.sort()
                cause = f"the model lacks terms the data need: add {extra[0][1]} (or try --model auto)"
    unconverged = by.get("converged") is not None and by["converged"].passed is False
    collapsed = by["focal_length"].passed is False and by["scale"].passed is not False
    views_failed = by.get("views") is not None and by["views"].passed is False
    if cause is None and views_failed and not broken and len(result.image_ids) >= 4:
        verified = _view_advice(result)
        if verified is not None:
            cause = verified
            bad_view = None
    if cause is None and not broken and leds is not None and leds.passed is False:
        perm = _permutation_advice(result, lin, base)
        if perm:
            cause = perm
            if leds is not None and leds.passed is False:
                by["leds"] = replace(leds, advice=perm)
    if cause is None and bad_view is not None:
        cause = f"view {result.image_ids[bad_view]} disagrees with the others: check its labels or leave it out"
    if cause is not None and cause.startswith("view ") and views_failed:
        by["views"] = replace(by["views"], advice=cause)
    if cause is not None and collapsed:
        by["focal_length"] = replace(by["focal_length"], advice=cause)
    if unconverged and cause is not None:
        by["converged"] = replace(by["converged"], advice=cause)
    for name in ("structure", "optical_centre", "model_terms", "views", "leds"):
        c = by.get(name)
        if c is None or c.passed is not False:
            continue
        if name == "model_terms":
            if cause is not None and not cause.startswith("the model lacks"):
                by[name] = replace(c, advice=f"probably a consequence of the cause found: {cause}")
            continue
        if cause is None:
            if name == "structure":
                by[name] = replace(c, advice="a systematic misfit that no richer model, gain fit or re-start removes: "
                                             "check the template coordinates, the point ids and the units")
            continue
        if name in ("structure", "optical_centre"):
            by[name] = replace(c, advice=cause)
        elif name == "views" and not cause.startswith("view "):
            by[name] = replace(c, advice=f"probably a consequence of the cause found: {cause}")
        elif name == "leds" and not cause.startswith("a template permutation"):
            by[name] = replace(c, advice=f"probably a consequence of the cause found: {cause}")
    return [by[c.name] for c in checks]


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


def _view_advice(result) -> str | None:
    """When leaving one view out makes the fit far better (implied noise down 3x, and no other view does), name it."""
    sig = []
    for i in range(len(result.image_ids)):
        r = _refit(result, drop_image=i)
        sig.append(np.inf if r is None else r.sigma_mm)
    sig = np.asarray(sig)
    order = np.argsort(sig)
    if not np.isfinite(sig[order[0]]) or len(sig) < 2:
        return None
    if sig[order[0]] * 3 < result.sigma_mm and sig[order[0]] * 3 < sig[order[1]]:
        i = int(order[0])
        return (f"view {result.image_ids[i]} disagrees with the others (without it the implied noise falls "
                f"{result.sigma_mm / sig[i]:.3g}x): check its labels (two LEDs merged or shifted by the demodulator?) "
                "or leave it out")
    return None


def _structure_ok(result) -> bool:
    """Whether ``result`` passes the structure check (no diagnosis)."""
    v = assess(result, diagnose=False)
    return all(c.passed is not False for c in v.checks if c.name == "structure")


def _permutation_advice(result, lin, base) -> str | None:
    """When swapping template LEDs (among the least consistent) makes the fit far better, say which."""

    M = len(result.point_ids)
    q = lin.e.reshape(-1, 2)
    sq = np.bincount(lin.led, weights=np.sum(q * q, axis=1), minlength=M)
    worst = list(np.argsort(-sq)[: min(5, M)])
    T = np.asarray(result.problem["template"]["xy_mm"], dtype=float)
    best = (base, None)
    for a_i in range(len(worst)):
        for b_i in range(a_i + 1, len(worst)):
            a, b = worst[a_i], worst[b_i]
            T2 = T.copy()
            T2[[a, b]] = T2[[b, a]]
            r = _refit(result, template_mm=T2)
            if r is not None and _ssr(r) < best[0]:
                best = (_ssr(r), (a, b))
    if best[1] is None or best[0] > base / 50:
        return None
    a, b = best[1]
    ids = result.point_ids
    return (f"a template permutation fits: LEDs {ids[a]} and {ids[b]} look swapped (residuals fall "
            f"{base / max(best[0], 1e-300):.3g}x): check the LED order in the template (a row listed in reverse?)")


def structure_test(result, exclude=None) -> tuple[float, float]:
    """(F, p-value) of the structure check on ``result``'s residuals, ``exclude`` (n_images, M) observations left out."""
    fdist = _F

    lin = _linearise(result, exclude)
    dof = lin.e.size - lin.n
    expl, p_dim = _explained(lin, _field_basis(lin.pts, result.intrinsics.c, np.asarray(result.sensor_mm, float) / 2))
    if p_dim == 0 or dof - p_dim <= 0:
        return float("nan"), 1.0
    ssr = float(lin.e @ lin.e)
    F = (expl / p_dim) / max((ssr - expl) / (dof - p_dim), 1e-300)
    return float(F), float(fdist.sf(F, p_dim, dof - p_dim))


def with_check(verdict: dict, check: Check) -> dict:
    """A verdict dict (``Verdict.to_dict()``) with one more check, the verdict recomputed."""
    v = Verdict.from_dict(verdict)
    checks = tuple(c for c in v.checks if c.name != check.name) + (check,)
    failed = [c for c in checks if c.passed is False]
    word = "good" if not failed else ("wrong" if any(c.severe for c in failed) else "suspect")
    return Verdict(word, checks).to_dict()
