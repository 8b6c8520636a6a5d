"""Fixed parameters and Gaussian priors for the calibration (``calibrate(fix=..., priors=...)``).

A *fixed* parameter leaves the state vector: it is held at its given value,
its standard error is ``None`` and it costs no degree of freedom.

A *Gaussian prior* ``theta_S ~ N(mu, C)`` on a set S of free global
parameters (intrinsics, distortion, gains) adds the whitened residual rows
``s L^-1 (theta_S - mu)`` (``C = L L^T``) to the least-squares problem, where
``s^2`` is the noise variance of the data residuals (in the unit of the
minimised cost). The minimised sum is then
``|r_data|^2 + s^2 (theta_S - mu)^T C^-1 (theta_S - mu)``, i.e. ``s^2`` times
the negative log-posterior: the maximum a-posteriori estimate. ``s^2`` is not
known in advance; it is estimated from the data residuals only,

    s^2 = |r_data|^2 / (m - n + t),   t = tr(s^2 P (J^T J + s^2 P)^-1),

(``m`` data residuals, ``n`` free parameters, ``P`` the prior information
embedded in the state), and the fit is repeated with the new weight until
``s`` is stable. ``t`` is the number of parameters the prior (rather than
the data) determines: 0 for an infinitely wide prior (the free fit's
``m - n``) and the number of prior rows for an infinitely tight one (the fixed
fit's ``m - n + k``). The covariance is ``s^2 (J^T J + s^2 P)^-1``: for a
linear model exactly the information sum of the two Gaussian estimates
``Cov^-1 = Cov_data^-1 + C^-1``.

A prior with zero variance on a single parameter is the same as fixing it;
an infinite variance is no prior at all.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from psdcal.errors import InputError
from psdcal.model.params import DISTORTION_NAMES

#: Every global parameter a calibration can fix or give a prior.
PARAMETER_NAMES = ("f_mm", "cx_mm", "cy_mm", "skew", "fy_mm", *DISTORTION_NAMES, "g_x2", "g_y1", "g_y2")
GAIN_NAMES = ("g_x2", "g_y1", "g_y2")
#: Parameters of a direction (rotation-stage) calibration that may also get a prior
#: (:mod:`psdcal.calibration.directions`): the stage rotation (rad) and the offsets (mm).
STAGE_PARAMETER_NAMES = ("stage_rx", "stage_ry", "stage_rz", "offset_x_mm", "offset_y_mm", "offset_z_mm")
_PRIOR_NAMES = PARAMETER_NAMES + STAGE_PARAMETER_NAMES
_GAIN_INDEX = {"g_x2": 1, "g_y1": 2, "g_y2": 3}
#: The LM step test compares the step with the state in Marquardt's scaled norm; a tight prior
#: makes its parameter's scale dominate that norm, and the test would stop the other
#: parameters early. The prior-weighted fit therefore stops on the cost and gradient tests only.
XTOL_FACTOR = 0.0


@dataclass(frozen=True)
class GaussianPrior:
    """A Gaussian prior ``N(mean, covariance)`` on named global parameters.

    Attributes
    ----------
    names : tuple of str, names from :data:`PARAMETER_NAMES` (distinct)
    mean : (k,) prior means, in each parameter's unit
    covariance : (k, k) symmetric positive semi-definite; ``inf`` on the
        diagonal (with zero correlations) means no information on that
        parameter, a zero-variance 1-parameter prior means "fixed"
    source : where it came from (a file name or ``"--prior"``), for records
    """

    names: tuple
    mean: np.ndarray
    covariance: np.ndarray
    source: str = ""

    def __post_init__(self):
        names = tuple(str(n) for n in self.names)
        mean = np.atleast_1d(np.asarray(self.mean, dtype=float))
        cov = np.atleast_2d(np.asarray(self.covariance, dtype=float))
        k = len(names)
        where = self.source or None
        if mean.shape != (k,) or cov.shape != (k, k):
            raise InputError(f"a prior on {k} parameters needs {k} means and a {k}x{k} covariance, "
                             f"got {mean.shape} and {cov.shape}", path=where)
        for n in names:
            if n not in _PRIOR_NAMES:
                raise InputError(f"unknown parameter {n!r} (one of {', '.join(_PRIOR_NAMES)})", path=where, field="names")
        if len(set(names)) != k:
            raise InputError("a parameter appears twice in one prior", path=where, field="names")
        if not np.all(np.isfinite(mean)):
            raise InputError("prior means must be finite", path=where, field="mean")
        if np.any(np.isnan(cov)) or np.any(np.diag(cov) < 0):
            raise InputError("prior variances must be >= 0 (inf: no information)", path=where, field="covariance")
        fin = np.isfinite(np.diag(cov))
        off = cov[np.ix_(fin, fin)]
        if not np.allclose(off, off.T, rtol=1e-9, atol=0.0):
            raise InputError("the prior covariance is not symmetric", path=where, field="covariance")
        inf_rows = ~fin
        if np.any(inf_rows) and np.any(np.isfinite(cov[inf_rows][:, fin]) & (cov[inf_rows][:, fin] != 0)):
            raise InputError("a parameter with infinite prior variance must be uncorrelated", path=where, field="covariance")
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "covariance", cov)

    @classmethod
    def from_std(cls, name: str, value: float, std: float, source: str = "") -> "GaussianPrior":
        """A prior ``value +- std`` on one parameter."""
        return cls((name,), [value], [[float(std) ** 2]], source)

    def informative(self) -> "GaussianPrior | None":
        """This prior without its infinite-variance parameters (None when nothing is left)."""
        fin = np.isfinite(np.diag(self.covariance))
        if not np.any(fin):
            return None
        if np.all(fin):
            return self
        idx = np.nonzero(fin)[0]
        return GaussianPrior(tuple(self.names[i] for i in idx), self.mean[idx], self.covariance[np.ix_(idx, idx)], self.source)

    def to_dict(self) -> dict:
        cov = [[None if not math.isfinite(v) else float(v) for v in row] for row in self.covariance]
        return {"names": list(self.names), "mean": [float(v) for v in self.mean], "covariance": cov, "source": self.source}

    @classmethod
    def from_dict(cls, d: dict, source: str = "") -> "GaussianPrior":
        cov = np.array([[np.inf if v is None else v for v in row] for row in d["covariance"]], dtype=float)
        # None off the diagonal came from an infinite variance's zero correlation
        k = cov.shape[0]
        cov[~np.eye(k, dtype=bool) & np.isinf(cov)] = 0.0
        return cls(tuple(d["names"]), d["mean"], cov, d.get("source", source))


# -- parsing --------------------------------------------------------------------------------
def _number(text: str, what: str, where=None) -> float:
    try:
        v = float(text)
    except ValueError:
        raise InputError(f"{what}: {text!r} is not a number", path=where) from None
    if math.isnan(v):
        raise InputError(f"{what}: NaN is not allowed", path=where)
    return v


def parse_fix(items) -> dict:
    """``["f_mm=8.0", "k2=0"]`` -> ``{"f_mm": 8.0, "k2": 0.0}`` (the ``--fix`` option)."""
    out = {}
    for it in items or ():
        name, sep, value = str(it).partition("=")
        name = name.strip()
        if not sep or name not in PARAMETER_NAMES:
            raise InputError(f"--fix {it!r}: expected NAME=VALUE with NAME one of {', '.join(PARAMETER_NAMES)}")
        v = _number(value.strip(), f"--fix {name}")
        if not math.isfinite(v):
            raise InputError(f"--fix {name}: the value must be finite")
        out[name] = v
    return out


def parse_prior(text: str) -> GaussianPrior:
    """``"f_mm=8.0,0.05"`` -> a prior ``8.0 +- 0.05`` on ``f_mm`` (the ``--prior`` option)."""
    name, sep, rest = str(text).partition("=")
    name = name.strip()
    parts = rest.split(",")
    if not sep or name not in _PRIOR_NAMES or len(parts) != 2:
        raise InputError(f"--prior {text!r}: expected NAME=VALUE,STD with NAME one of {', '.join(PARAMETER_NAMES)} "
                         "(and for calibrate-directions stage_rx/ry/rz, offset_x_mm/y_mm/z_mm)")
    value = _number(parts[0].strip(), f"--prior {name} value")
    std = _number(parts[1].strip(), f"--prior {name} std")
    if not math.isfinite(value) or std < 0:
        raise InputError(f"--prior {name}: the value must be finite and the std >= 0 (inf: no prior)")
    return GaussianPrior.from_std(name, value, std, source="--prior")


def read_prior_file(path) -> GaussianPrior:
    """A Gaussian prior from a JSON file with a mean vector and a covariance.

    Accepted keys (the first present wins):

    - names: ``names`` (default, for 3 or 4 values: the gains ``g_x2, g_y1, g_y2``);
    - means: ``values``, ``mean``, ``gains``; a vector one longer than
      ``names`` whose first entry is 1 is read as ``(g_x1, g_x2, g_y1, g_y2)``
      relative gains (the gains JSON of ``psdcal gains``) and its first entry dropped;
    - spread: ``covariance`` (k x k, or ``{"names": [...], "matrix": [[...]]}``, whose names then
      name the means), else ``std`` (a list, or a dict by name).
    """
    from psdcal.io import read_json

    p = Path(path)
    d = read_json(p, "prior file")
    if not isinstance(d, dict):
        raise InputError("a prior file is a JSON object with names, values and covariance", path=p)
    values = next((d[k] for k in ("values", "mean", "gains") if k in d), None)
    if values is None:
        raise InputError("no 'values', 'mean' or 'gains' key", path=p)
    try:
        values = [float(v) for v in values]
    except (TypeError, ValueError):
        raise InputError("the means must be a list of numbers", path=p, field="values") from None
    cov_in = d.get("covariance")
    if isinstance(cov_in, dict):  # {"names": [...], "matrix": [[...]]}: the gains JSON of `psdcal gains`
        names_cov = cov_in.get("names")
        if d.get("names") is None and names_cov is not None:
            d = {**d, "names": names_cov}
        cov_in = cov_in.get("matrix")
        d = {**d, "covariance": cov_in}
    names = d.get("names")
    if names is None:
        if len(values) in (3, 4):
            names = list(GAIN_NAMES)
        else:
            raise InputError("no 'names' key (only 3 or 4 values default to the gains)", path=p, field="names")
    names = [str(n) for n in names]
    if names and names[0] == "g_x1" and len(names) == len(values):  # absolute list including the reference channel
        names, values = names[1:], values[1:]
        drop_first = True
    else:
        drop_first = False
    if len(values) == len(names) + 1 and set(names) <= set(GAIN_NAMES):
        if abs(values[0] - 1.0) > 1e-12:
            raise InputError("the gains must be relative to g_x1 (first value 1)", path=p, field="gains")
        values = values[1:]
        drop_first = True
    k = len(names)
    if len(values) != k:
        raise InputError(f"{len(values)} means for {k} names", path=p, field="values")
    if "covariance" in d:
        try:
            cov = np.array([[np.inf if v is None else float(v) for v in row] for row in d["covariance"]], dtype=float)
        except (TypeError, ValueError):
            raise InputError("the covariance must be a square list of lists of numbers", path=p, field="covariance") from None
        if drop_first and cov.shape == (k + 1, k + 1):
            cov = cov[1:, 1:]
    elif "std" in d:
        s = d["std"]
        try:
            s = [float(s[n]) for n in names] if isinstance(s, dict) else [float(v) for v in s]
        except (KeyError, TypeError, ValueError):
            raise InputError("'std' must give one number per name", path=p, field="std") from None
        if drop_first and len(s) == k + 1:
            s = s[1:]
        if len(s) != k:
            raise InputError(f"{len(s)} std for {k} names", path=p, field="std")
        cov = np.diag(np.square(s))
    else:
        raise InputError("no 'covariance' or 'std' key", path=p)
    if cov.shape != (k, k):
        raise InputError(f"the covariance must be {k}x{k}, got {cov.shape}", path=p, field="covariance")
    return GaussianPrior(tuple(names), values, cov, source=str(p))


def as_priors(priors) -> list:
    """Normalise the ``priors=`` argument: a GaussianPrior, a dict ``{name: (value, std)}``,
    a path to a prior file, or a list of these."""
    if priors is None:
        return []
    if isinstance(priors, (GaussianPrior, dict, str, Path)):
        priors = [priors]
    out = []
    for p in priors:
        if isinstance(p, GaussianPrior):
            out.append(p)
        elif isinstance(p, dict) and "names" in p and "covariance" in p:
            out.append(GaussianPrior.from_dict(p))
        elif isinstance(p, dict):
            for n, (v, s) in p.items():
                out.append(GaussianPrior.from_std(n, float(v), float(s)))
        elif isinstance(p, (str, Path)):
            out.append(read_prior_file(p))
        else:
            raise InputError(f"priors: cannot use {type(p).__name__} (GaussianPrior, dict, or a file path)", field="priors")
    return out


def split_priors(priors, fix: dict):
    """Zero-width 1-parameter priors become fixes, infinite ones vanish; returns (priors, fix)."""
    fix = dict(fix or {})
    kept = []
    for p in priors:
        if len(p.names) == 1 and p.covariance[0, 0] == 0.0:
            fix[p.names[0]] = float(p.mean[0])
            continue
        q = p.informative()
        if q is None:
            continue
        if np.any(np.diag(q.covariance) == 0):
            raise InputError(f"prior on {', '.join(q.names)}: a zero variance in a joint prior; fix that parameter instead",
                             path=q.source or None, field="covariance")
        kept.append(q)
    seen = {}
    for p in kept:
        for n in p.names:
            if n in fix:
                raise InputError(f"{n} is both fixed and given a prior", field=n)
            if n in seen:
                raise InputError(f"{n} has two priors ({seen[n] or 'argument'} and {p.source or 'argument'}); combine them in one",
                                 field=n)
            seen[n] = p.source
    return kept, fix


# -- the constrained fit ----------------------------------------------------------------------
def prior_rows(priors, names):
    """Whitened prior rows ``W theta - b`` over the free global parameters ``names``.

    Returns ``W`` (k, len(names)) and ``b`` (k,) with ``W^T W`` the prior
    information and ``W^T b`` its information-weighted mean.
    """
    Ws, bs = [], []
    for p in priors:
        missing = [n for n in p.names if n not in names]
        if missing:
            raise InputError(f"prior on {', '.join(missing)}, which the model does not estimate "
                             "(switch it on: --radial/--tangential/--psd-radial/--skew/--aspect/--fit-gains)",
                             path=p.source or None, field=missing[0])
        L = np.linalg.cholesky(p.covariance) if len(p.names) > 1 else np.sqrt(p.covariance)
        Linv = np.linalg.inv(L)
        E = np.zeros((len(p.names), len(names)))
        for i, n in enumerate(p.names):
            E[i, names.index(n)] = 1.0
        Ws.append(Linv @ E)
        bs.append(Linv @ p.mean)
    if not Ws:
        return np.zeros((0, len(names))), np.zeros(0)
    return np.vstack(Ws), np.concatenate(bs)


def _scaled_inverse(A):
    """Inverse of a symmetric positive definite ``A`` after Jacobi scaling (tight priors make
    its diagonal span many decades; the scaled matrix stays well conditioned)."""
    d = np.sqrt(np.maximum(np.diag(A), 1e-300))
    H = A / np.outer(d, d)
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        Hi = np.linalg.pinv(H)
    return Hi / np.outer(d, d)


@dataclass(frozen=True)
class PriorFit:
    """What the prior-weighted fit adds to a :class:`psdcal.calibration._refine.RefineResult`."""

    sigma2: float  # s^2 of the data residuals, unit of the cost squared
    dof: float  # m - n + t
    prior_dof: float  # t: parameters determined by the priors
    rounds: int  # refits until s was stable


def refine_with_priors(prob, intr0, dist0, gains0, rvecs0, tvecs0, priors, sigma2_start: float, options):
    """Minimise ``|r_data|^2 + s^2 |W theta - b|^2`` (see the module docstring), iterating ``s``.

    A thin wrapper around :func:`psdcal.calibration._lm.levenberg_marquardt`:
    the prior rows are appended to the residuals and Jacobian, and their
    information is added to the global block of the normal equations.

    Returns
    -------
    (RefineResult, PriorFit)
        ``covariance`` is ``s^2 (J^T J + s^2 W^T W)^-1`` of the full state,
        ``sigma2`` the data-only ``s^2``.
    """
    from psdcal.calibration._refine import Evaluator, _single_threaded_blas, levenberg_marquardt
    from psdcal.errors import DegenerateViewsError

    names = list(prob.names)
    W, b = prior_rows(priors, names)
    k, ng = W.shape
    ev = Evaluator(prob, intr0, dist0, gains0)
    z = prob.pack(intr0, dist0, gains0, rvecs0, tvecs0)
    m = 2 * len(ev.img_idx)
    n = z.size
    if m + k < n:
        raise DegenerateViewsError(f"{m // 2} observed points and {k} prior rows give {m + k} equations for {n} unknowns")
    s2 = max(float(sigma2_start), 1e-300)
    WtW = W.T @ W

    def run(s):
        def fun(x):
            return np.concatenate([ev.residuals(x), s * (W @ x[:ng] - b)])

        def jac(x):
            J = ev.jacobian(x)
            Jp = np.zeros((k, J.shape[1]))
            Jp[:, :ng] = s * W
            return np.vstack([J, Jp])

        def normal(J, r):
            A, g = ev.normal_equations(J[: J.shape[0] - k], r[: r.size - k])
            A = A.copy()
            g = g.copy()
            A[:ng, :ng] += s * s * WtW
            g[:ng] += s * (W.T @ r[r.size - k:])
            return A, g

        sol = levenberg_marquardt(fun, jac, z, replace(options, xtol=XTOL_FACTOR * options.xtol), normal=normal)
        return replace(sol, x=polish(fun, jac, normal, sol.x))

    rounds = 0
    with _single_threaded_blas():
        while True:
            rounds += 1
            sol = run(np.sqrt(s2))
            z = sol.x
            r, J = ev.evaluate(z)
            A = np.array(ev.normal_equations(J, r)[0], dtype=float)
            Aaug = A.copy()
            Aaug[:ng, :ng] += s2 * WtW
            Ai = _scaled_inverse(Aaug)
            t = float(np.trace(s2 * WtW @ Ai[:ng, :ng]))
            dof = max(m - n + t, 1e-12)
            s2_new = max(float(r @ r) / dof, 1e-300)
            done = abs(s2_new / s2 - 1.0) < 1e-10 or rounds >= 20
            s2 = s2_new
            if done:
                break
    Aaug = A.copy()
    Aaug[:ng, :ng] += s2 * WtW
    Ai = _scaled_inverse(Aaug)
    t = float(np.trace(s2 * WtW @ Ai[:ng, :ng]))
    dof = max(m - n + t, 1e-12)
    s2 = max(float(r @ r) / dof, 1e-300) if float(r @ r) > 0 else 0.0
    ref = _refined(prob, ev, z, r, J, s2 * Ai, s2, int(sol.njev), bool(sol.status > 0), str(sol.message), options)
    return ref, PriorFit(sigma2=s2, dof=dof, prior_dof=t, rounds=rounds)


def polish(fun, jac, normal, x, steps: int = 4):
    """A few Gauss-Newton steps from an LM solution (returns the improved state).

    LM stops on the relative cost reduction (1e-12), which leaves the
    parameters ~1e-5 standard errors from the optimum. The Gauss-Newton step
    ``-(J^T J)^-1 J^T r`` works on the gradient instead and converges (linearly,
    at the rate of the residual curvature) to round-off, so that the fixed and
    the tightly-constrained fits agree to 1e-9. A step is kept only when it
    does not raise the cost beyond round-off.
    """
    r = fun(x)
    F = float(r @ r)
    for _ in range(steps):
        A, g = normal(jac(x), r)
        d = np.sqrt(np.maximum(np.diag(A), 1e-300))
        try:
            L = np.linalg.cholesky(A / np.outer(d, d))
        except np.linalg.LinAlgError:
            break
        h = -np.linalg.solve(L.T, np.linalg.solve(L, g / d)) / d
        x_new = x + h
        r_new = fun(x_new)
        F_new = float(r_new @ r_new)
        if not np.isfinite(F_new) or F_new > F * (1 + 1e-10):  # the cost is known to ~1e-12 (Newton inverse of the distortion)
            break
        x, r, F = x_new, r_new, F_new
        if np.max(np.abs(h) / (np.abs(x) + 1e-12)) < 1e-15:
            break
    return x


def refine_fixed(prob, intr0, dist0, gains0, rvecs0, tvecs0, options):
    """:func:`psdcal.calibration._refine.refine` on a problem with fixed parameters, then :func:`polish`."""
    from psdcal.calibration._refine import Evaluator, _single_threaded_blas, refine

    ref = refine(prob, intr0, dist0, gains0, rvecs0, tvecs0, options)
    if not ref.converged:
        return ref
    ev = Evaluator(prob, intr0, dist0, gains0)
    with _single_threaded_blas():
        z = polish(ev.residuals, ev.jacobian, ev.normal_equations, ref.z)
        r, J = ev.evaluate(z)
        A = np.array(ev.normal_equations(J, r)[0], dtype=float)
        s2 = float(r @ r) / max(r.size - z.size, 1)
        return _refined(prob, ev, z, r, J, s2 * _scaled_inverse(A), s2, ref.iterations, ref.converged, ref.message,
                        options)


@dataclass(frozen=True)
class Refined:
    """The solver output :func:`psdcal.calibration.core._make_result` reads, from a dense
    full-state covariance (these fits are small): the full matrix and its global /
    pose / cross blocks, so that either form of the refinement's result is served."""

    z: np.ndarray
    intrinsics: object
    coeffs: np.ndarray
    gains: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray
    covariance: np.ndarray  # (n, n) full state
    covariance_global: np.ndarray
    pose_covariance: np.ndarray  # (n_images, 6, 6)
    cross_covariance: np.ndarray  # (n_images, n_global, 6)
    sigma2: float
    cost_rms: float
    iterations: int
    converged: bool
    message: str
    jacobian: np.ndarray
    residuals: np.ndarray
    model_mm: np.ndarray | None


def _refined(prob, ev, z, r, J, cov, s2, iterations, converged, message, options) -> Refined:
    intr, coef, gains, rv, tv = ev.unpack(z)
    ng = prob.n_global
    n = prob.n_images
    pose = np.stack([cov[ng + 6 * v: ng + 6 * v + 6, ng + 6 * v: ng + 6 * v + 6] for v in range(n)]) if n else np.zeros((0, 6, 6))
    cross = np.stack([cov[:ng, ng + 6 * v: ng + 6 * v + 6] for v in range(n)]) if n else np.zeros((0, ng, 6))
    return Refined(
        z=z, intrinsics=intr, coeffs=coef, gains=gains, rvecs=rv, tvecs=tv, covariance=cov,
        covariance_global=cov[:ng, :ng], pose_covariance=pose, cross_covariance=cross, sigma2=float(s2),
        cost_rms=float(np.sqrt(np.mean(r**2)) * np.sqrt(2.0)), iterations=int(iterations),
        converged=bool(converged) and bool(np.all(np.isfinite(z))) and int(iterations) <= options.max_iterations,
        message=str(message), jacobian=J, residuals=r,
        model_mm=ev.model_points(z) if prob.cost == "image" else None,
    )


def apply_fix(intr, dist, gains, fix: dict):
    """Starting values with the fixed parameters set: (Intrinsics, Distortion, gains (4,))."""
    from psdcal.model.params import Distortion

    iv = {n: v for n, v in fix.items() if n in ("f_mm", "cx_mm", "cy_mm", "skew", "fy_mm")}
    if iv:
        intr = replace(intr, **iv)
    dv = {n: v for n, v in fix.items() if n in DISTORTION_NAMES}
    if dv:
        dist = Distortion.from_array([dv.get(n, v) for n, v in zip(DISTORTION_NAMES, dist.as_array())])
    g = np.asarray(gains, dtype=float).copy()
    for n, i in _GAIN_INDEX.items():
        if n in fix:
            g[i] = fix[n]
    return intr, dist, g


def constrain(result, fix: dict, priors: list, solver, merged_gain_fix: dict | None = None):
    """Refit a free :class:`CalibrationResult` with parameters fixed and priors added.

    Starts from the free solution (fixed parameters set to their values). A
    fixed parameter outside the model is held at its value in the model
    (e.g. ``k3`` with ``radial=2``; ``skew``/``fy_mm`` switch the model's
    skew/aspect on, held fixed).
    """
    from psdcal.calibration._refine import Problem
    from psdcal.calibration.core import _make_result, inputs_from_record

    spec = result.model
    if "skew" in fix and not spec.skew:
        spec = replace(spec, skew=True)
    if "fy_mm" in fix and not spec.aspect:
        spec = replace(spec, aspect=True)
    gfix = [n for n in fix if n in GAIN_NAMES]
    if gfix and not spec.fit_gains:
        raise InputError(f"fix {gfix[0]}: the gains are fixed unless fitted; give known gains with gains=/--gains", field=gfix[0])
    p = result.problem
    T, X = inputs_from_record(p)
    sensor = tuple(result.sensor_mm)
    fixed = tuple(n for n in spec.global_names if n in fix)
    prob = Problem(T, X, spec, cost=result.cost, sensor_mm=sensor, fixed=fixed)
    intr0 = result.intrinsics
    if spec.aspect and intr0.fy_mm is None:
        intr0 = replace(intr0, fy_mm=intr0.f_mm)
    g_start = np.asarray(p["options"].get("gains", np.ones(4)), dtype=float) if not spec.fit_gains else result.gains
    intr0, dist0, g0 = apply_fix(intr0, result.distortion, g_start, fix)
    if priors:
        ref, pf = refine_with_priors(prob, intr0, dist0, g0, result.rvecs, result.tvecs_mm, priors,
                                     result.cost_rms**2 / 2.0, solver)
    else:
        ref, pf = refine_fixed(prob, intr0, dist0, g0, result.rvecs, result.tvecs_mm, solver), None
    st = result.stages
    start = _StartRecord(st)
    ids = result.image_ids
    out = _make_result(prob, ref, start, ids, result.point_ids, spec, result.cost,
                       np.asarray(p["options"].get("gains", np.ones(4)), dtype=float),
                       p["options"]["preliminary"], p["options"]["normalize"], solver)
    out = replace(out, stages=st, gains=result.gains if not spec.fit_gains else out.gains)
    record_fix = {n: float(v) for n, v in fix.items()}
    # the user's switches (fixing skew / fy_mm switched them on only for the refit): recalibrate re-runs the same
    # free fit, then the same constrained one
    options = {**out.problem["options"], "skew": result.model.skew, "aspect": result.model.aspect,
               "fix": record_fix, "priors": [q.to_dict() for q in priors]}
    if merged_gain_fix:
        options["fix_gains_applied"] = dict(merged_gain_fix)
    problem = {**result.problem, "options": options}
    if pf is not None:
        m = 2 * int(np.sum(prob.valid))
        if result.cost == "image":
            out = replace(out, sigma_mm=float(np.sqrt(pf.sigma2)))
        else:
            out = replace(out, sigma_mm=float(out.rms_mm / np.sqrt(2.0) * np.sqrt(m / pf.dof)))
        problem["prior_fit"] = {"sigma2": pf.sigma2, "dof": pf.dof, "prior_dof": pf.prior_dof, "rounds": pf.rounds}
    return replace(out, problem=problem)


class _StartRecord:
    """Adapter: ``_make_result`` reads the linear stage's values; the constrained refit keeps the free fit's."""

    def __init__(self, stages):
        pre = stages.get("preliminary", {})
        self.preliminary_k = np.array([pre.get("k1", 0.0), pre.get("k2", 0.0)])
        self.n_lines = int(pre.get("line_groups", 0))
        from psdcal.model.params import Intrinsics

        cf = stages.get("closed_form", {})
        self.intrinsics = Intrinsics(**{k: cf[k] for k in ("f_mm", "cx_mm", "cy_mm", "skew", "fy_mm") if k in cf})
        ie = stages.get("initial_extrinsics", [])
        self.rvecs = np.array([e["rvec"] for e in ie], dtype=float).reshape(-1, 3)
        self.tvecs_mm = np.array([e["tvec_mm"] for e in ie], dtype=float).reshape(-1, 3)


@dataclass(frozen=True)
class MapFit:
    """Outcome of :func:`map_fit`."""

    x: np.ndarray
    residuals: np.ndarray  # data residuals (m,)
    jacobian: np.ndarray  # data Jacobian (m, n)
    covariance: np.ndarray  # s^2 (J^T J + s^2 W^T W)^-1, (n, n)
    sigma2: float
    dof: float
    prior_dof: float
    rounds: int
    lm: object  # the last LMResult


def map_fit(fun, jac, x0, W, b, options, sigma2_start: float | None = None, polish_steps: int = 4) -> MapFit:
    """Least squares with optional whitened prior rows over the whole state (dense; small problems).

    Minimises ``|fun(x)|^2 + s^2 |W x - b|^2`` with ``s^2`` re-estimated from
    the data residuals (module docstring) until stable; with no prior rows
    (``W`` of shape (0, n)) it is plain LM + :func:`polish` with
    ``s^2 = |r|^2 / (m - n)``.
    """
    from psdcal.calibration._refine import levenberg_marquardt

    x = np.asarray(x0, dtype=float).copy()
    W = np.asarray(W, dtype=float).reshape(-1, x.size)
    b = np.asarray(b, dtype=float).reshape(-1)
    k, n = W.shape
    WtW = W.T @ W
    r0 = fun(x)
    m = r0.size
    s2 = float(sigma2_start) if sigma2_start is not None else max(float(r0 @ r0) / max(m - n, 1), 1e-300)
    rounds = 0
    while True:
        rounds += 1
        s = np.sqrt(s2)

        def f_aug(z):
            return np.concatenate([fun(z), s * (W @ z - b)])

        def j_aug(z):
            return np.vstack([jac(z), s * W])

        opts = replace(options, xtol=XTOL_FACTOR * options.xtol) if k else options
        sol = levenberg_marquardt(f_aug, j_aug, x, opts)
        x = polish(f_aug, j_aug, lambda J, r: (J.T @ J, J.T @ r), sol.x, steps=polish_steps)
        r = fun(x)
        J = jac(x)
        A = J.T @ J
        Ai = _scaled_inverse(A + s2 * WtW)
        t = float(np.trace(s2 * WtW @ Ai)) if k else 0.0
        dof = max(m - n + t, 1e-12)
        s2_new = float(r @ r) / dof
        if k == 0 or s2_new <= 0 or abs(s2_new / s2 - 1.0) < 1e-10 or rounds >= 20:
            s2 = s2_new
            break
        s2 = s2_new
    Ai = _scaled_inverse(A + s2 * WtW) if k else _scaled_inverse(A)
    return MapFit(x=x, residuals=r, jacobian=J, covariance=s2 * Ai, sigma2=s2, dof=dof, prior_dof=t, rounds=rounds, lm=sol)
