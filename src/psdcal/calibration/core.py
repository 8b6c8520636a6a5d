"""The calibration front door: ``psdcal.calibrate`` (the paper's Section 3, docs/model.md#calibration).

Steps, each usable on its own from its private module:

1. line-straightness preliminary distortion estimate (:mod:`._straightness`);
2. a homography per image by the DLT, Hartley-normalised (:mod:`._homography`);
3. closed-form intrinsics, then extrinsics (:mod:`._closed_form`);
4. Levenberg-Marquardt refinement on the ``image`` or ``template`` cost
   (:mod:`._refine`), with standard errors from the Jacobian.
"""
from __future__ import annotations

import datetime as _dt
import math
import functools
import threading
from dataclasses import dataclass, field, replace

import numpy as np

from psdcal.calibration._closed_form import intrinsics_from_homographies, poses_from_homographies
from psdcal.calibration._homography import homographies
from psdcal.calibration._refine import Problem, SolverOptions, refine
from psdcal.calibration._straightness import estimate_radial, find_lines
from psdcal.model.distortion import distort, undistort
from psdcal.errors import ConvergenceError, DegenerateViewsError, InputError
from psdcal.model.params import DISTORTION_NAMES, Distortion, Intrinsics, ModelSpec
from psdcal.model.projection import project
from psdcal.model.readout import LX_MM, LY_MM, gain_map

COSTS = ("image", "template")
#: The line-straightness step uses at most this many template lines (the longest):
#: a dense grid (Zhang's 256 corners) has hundreds, mostly short diagonals.
MAX_STRAIGHTNESS_LINES = 40
#: ... and at most this many points of each line (spread along it, both ends kept): the curvature of a
#: line is fixed by a few of its points, and a 16-point chessboard row costs twice 8 for no better start.
MAX_LINE_POINTS = 8
_ALL_INTR = ("f_mm", "cx_mm", "cy_mm", "skew")


@dataclass(frozen=True)
class InitialEstimate:
    """What the linear stages produce (the start of the refinement; the paper's Tables 1-2).

    Attributes
    ----------
    preliminary_k : (2,) k1, k2 of the line-straightness step (zeros when skipped).
    n_lines : int, number of (image, line) groups the step used.
    homographies : (n_images, 3, 3)
    intrinsics : Intrinsics from the closed form.
    rvecs, tvecs_mm : (n_images, 3) poses from the homographies.
    """

    preliminary_k: np.ndarray
    n_lines: int
    homographies: np.ndarray
    intrinsics: Intrinsics
    rvecs: np.ndarray
    tvecs_mm: np.ndarray

    def distortion(self, radial: int) -> Distortion:
        """The preliminary k1, k2 as a start for a model with ``radial`` lens terms."""
        return Distortion(k1=float(self.preliminary_k[0]) if radial >= 1 else 0.0,
                          k2=float(self.preliminary_k[1]) if radial >= 2 else 0.0)


def _software_version() -> str:
    """psdcal's version, read on first use (not at import: a process that writes no calibration never reads it)."""
    from psdcal import __version__

    return __version__


def _check_inputs(template_mm, points_mm, image_ids, min_images):
    try:
        T = np.asarray(template_mm, dtype=float)
        X = np.asarray(points_mm, dtype=float)
    except (ValueError, TypeError) as exc:  # ragged nested lists, non-numbers
        raise InputError(f"template_mm and points_mm must be numeric arrays of shape (M, 2) and "
                         f"(n_images, M, 2): {exc}") from None
    if T.ndim != 2 or T.shape[1] != 2:
        raise InputError(f"template_mm must have shape (M, 2), got {T.shape}")
    if X.ndim != 3 or X.shape[2] != 2 or X.shape[1] != T.shape[0]:
        raise InputError(f"points_mm must have shape (n_images, {T.shape[0]}, 2), got {X.shape}")
    if not np.all(np.isfinite(T)):
        raise InputError("template_mm contains NaN or infinite values")
    # a point is missing only when both coordinates are NaN (nothing to look at when all are finite)
    if not np.isfinite(X).all():
        nan = np.isnan(X)
        if np.any(nan.any(-1) & ~nan.all(-1)) or np.any(np.isinf(X)):
            raise InputError("points_mm: a point must be either two finite coordinates or two NaN (missing)")
    ids = list(range(X.shape[0])) if image_ids is None else list(image_ids)
    if len(ids) != X.shape[0]:
        raise InputError(f"image_ids has {len(ids)} entries for {X.shape[0]} images")
    if X.shape[0] < min_images:
        raise DegenerateViewsError(f"{X.shape[0]} images; calibration needs at least {min_images}")
    return T, X, ids


def initial_estimate(
    template_mm,
    points_mm,
    *,
    preliminary: bool = True,
    normalize: bool = True,
    radial_terms: int = 2,
    skew: bool = False,
    aspect: bool = False,
    image_ids=None,
) -> InitialEstimate:
    """The first, linear stage of the calibration (Sections 3.1-3.3).

    Parameters
    ----------
    template_mm : (M, 2)
    points_mm : (n_images, M, 2), NaN where missing.
    preliminary : apply the line-straightness distortion estimate first.
    normalize : Hartley-normalise the DLT.
    radial_terms : how many of k1, k2 the preliminary step estimates (0-2).
    """
    T, X, ids = _check_inputs(template_mm, points_mm, image_ids, 3 if (skew or aspect) else 2)
    k = np.zeros(2)
    n_lines = 0
    c0 = np.zeros(2)
    if preliminary and radial_terms > 0:
        lines = _straightness_lines(T)
        if lines:
            st = estimate_radial(X, lines, c_mm=c0, n_terms=min(2, radial_terms))
            k[: st.k.size] = st.k
            n_lines = st.n_lines
    coef = np.zeros(7)
    coef[:2] = k
    if n_lines:
        from psdcal import _jit

        if _jit.use_compiled(X.shape[0] * X.shape[1]):
            from psdcal.calibration._image_kernel import undistort_points

            Xc = undistort_points(X, coef, c0)  # undistort's arithmetic, compiled (tests/test_lm_kernel.py)
        else:
            Xc = undistort(X, coef, c0)
    else:
        Xc = X
    Hs = homographies(T, Xc, normalize=normalize, labels=[f"image {i}" for i in ids])
    intr = intrinsics_from_homographies(Hs, skew=skew, aspect=aspect)
    extent = _extent(X)
    if not (intr.f_mm < 1e3 * extent and np.hypot(intr.cx_mm, intr.cy_mm) < 10 * extent):
        raise DegenerateViewsError(
            f"the views do not determine the intrinsics (closed form gives f = {intr.f_mm:.3g} mm, "
            f"C = ({intr.cx_mm:.3g}, {intr.cy_mm:.3g}) mm): tilt the template differently between views"
        )
    return InitialEstimate(k, n_lines, Hs, intr, *poses_from_homographies(Hs, intr))


def _extent(X) -> float:
    """Twice the largest |coordinate| of the finite points (1.0 when there is none), mm: a scale of the sensor."""
    m = float(np.fmax.reduce(np.abs(X), axis=None)) if X.size else math.nan  # fmax skips NaN (missing points)
    return 2.0 * m if math.isfinite(m) else 1.0


def _straightness_lines(T) -> list:
    """The template lines of the straightness step, thinned (:func:`_thin_lines`); cached per template."""
    return [ln.copy() for ln in _lines_of(*_template_key(T), MAX_STRAIGHTNESS_LINES, MAX_LINE_POINTS)]


def _template_key(T) -> tuple:
    """``(shape, bytes)`` of a float template: a hashable key for the per-template caches."""
    T = np.ascontiguousarray(T, dtype=float)
    return T.shape, T.tobytes()


def _template_of(shape, data) -> np.ndarray:
    """The template of a :func:`_template_key` (read-only)."""
    return np.frombuffer(data, dtype=float).reshape(shape)


@functools.lru_cache(maxsize=8)
def _lines_of(shape, data, max_lines, max_points) -> tuple:
    T = _template_of(shape, data)
    return tuple(_thin_lines(T, find_lines(T, max_lines=max_lines), max_points))


def _thin_lines(T, lines, k: int) -> list:
    """The lines with at most ``k`` indices each, spread evenly along the line (both ends kept), sorted.

    All lines at once: each line's direction is the principal axis of its
    points (2 x 2 scatter in closed form), its points are ordered along it
    and ``k`` of them taken at evenly spaced ranks.
    """
    lines = [np.asarray(ln) for ln in lines]
    if not lines or max(ln.size for ln in lines) <= k:
        return lines
    n = np.array([ln.size for ln in lines])
    start = np.concatenate([[0], np.cumsum(n)[:-1]])
    idx = np.concatenate(lines)
    owner = np.repeat(np.arange(len(lines)), n)
    P = T[idx]
    P = P - (np.add.reduceat(P, start, axis=0) / n[:, None])[owner]
    sxx, sxy, syy = (np.add.reduceat(P[:, 0] * P[:, 0], start), np.add.reduceat(P[:, 0] * P[:, 1], start),
                     np.add.reduceat(P[:, 1] * P[:, 1], start))
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)[owner]
    order = np.lexsort((P[:, 0] * np.cos(theta) + P[:, 1] * np.sin(theta), owner))  # by line, then along it
    out = []
    for j, ln in enumerate(lines):
        if ln.size <= k:
            out.append(ln)
            continue
        along = idx[order[start[j]: start[j] + n[j]]]
        out.append(np.sort(along[np.round(np.linspace(0, n[j] - 1, k)).astype(int)]))
    return out


@dataclass(frozen=True)
class CalibrationResult:
    """A calibration: parameters, their uncertainty, residuals and how it was obtained.

    ``to_dict()`` is the calibration JSON of docs/model.md#calibration-json (plus extra keys).

    Attributes
    ----------
    intrinsics : Intrinsics
    distortion : Distortion (0 for terms not in the model)
    gains : (4,) relative channel gains (g_x1 = 1), ones unless fitted
    model : ModelSpec
    cost : "image" | "template"
    param_names : names of the free global parameters (order of ``covariance``)
    covariance : (n, n) covariance of the free global parameters (poses marginalised)
    std : dict name -> standard error (None where fixed)
    image_ids, point_ids : identifiers of the images and template points
    rvecs, tvecs_mm : (n_images, 3) poses; pose_std : (n_images, 6)
    residuals_mm : (n_images, M, 2) measured minus modelled point on the sensor, NaN where missing
    rms_mm, per_image_rms_mm : sensor-plane RMS distance (all, per image)
    cost_rms : RMS residual distance of the minimised cost in its own unit (mm on the sensor or plate)
    sigma_mm : noise standard deviation per coordinate implied by the fit (sensor, mm)
    iterations, converged, message : of the LM solver
    stages : starting values each step produced
    problem : the inputs and options, enough to re-run the calibration exactly
    """

    intrinsics: Intrinsics
    distortion: Distortion
    gains: np.ndarray
    model: ModelSpec
    cost: str
    param_names: tuple
    covariance: np.ndarray
    std: dict
    image_ids: tuple
    point_ids: tuple
    rvecs: np.ndarray
    tvecs_mm: np.ndarray
    pose_std: np.ndarray
    residuals_mm: np.ndarray
    rms_mm: float
    per_image_rms_mm: np.ndarray
    cost_rms: float
    sigma_mm: float
    iterations: int
    converged: bool
    message: str
    stages: dict = field(default_factory=dict)
    problem: dict = field(default_factory=dict)
    sensor_mm: tuple = (LX_MM, LY_MM)
    created: str = ""
    verdict: dict | None = None  # psdcal.calibration.verdict.Verdict.to_dict(): {"verdict", "checks"}

    # -- use --------------------------------------------------------------------------
    def undistort(self, d_mm):
        """Ideal pinhole points (..., 2) of measured impact points (..., 2), mm."""
        return undistort(d_mm, self.distortion, self.intrinsics.c)

    def parameter(self, name: str) -> float:
        """Value of a global parameter by name (``f_mm``, ``k1``, ``g_x2`` ...)."""
        if name in ("g_x2", "g_y1", "g_y2"):
            return float(self.gains[{"g_x2": 1, "g_y1": 2, "g_y2": 3}[name]])
        if name == "fy_mm":
            return float(self.intrinsics.fy)
        if name in _ALL_INTR:
            return float(getattr(self.intrinsics, name))
        return float(getattr(self.distortion, name))

    def warnings(self) -> list[str]:
        """What looks wrong with this calibration although the solver converged (empty when nothing).

        A residual RMS above :data:`MISFIT_FRACTION` of the measured points'
        spread is far beyond any PSD noise (micrometres on a sensor of
        millimetres) or lens-model mismatch: the solver found the best fit of
        data that the model cannot explain, typically a wrong template, point
        ids that do not match it, or swapped coordinates.
        """
        out = []
        xy = self.problem.get("points", {}).get("xy_mm", []) if self.problem else []
        pts = np.asarray(xy, dtype=float).reshape(-1, 2)  # None (missing) -> NaN
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if len(pts) >= 2:
            spread = float(np.max(np.ptp(pts, axis=0)))
            if spread > 0 and self.rms_mm > MISFIT_FRACTION * spread:
                out.append(
                    f"the residual RMS ({self.rms_mm * 1e3:.3g} um) is {100 * self.rms_mm / spread:.2g} % of the points' "
                    f"spread ({spread:.3g} mm): far above any PSD noise; check the template, the point ids and the "
                    "coordinates' order and units"
                )
        return out

    def correlation(self) -> np.ndarray:
        """Correlation matrix of the free global parameters."""
        s = np.sqrt(np.diag(self.covariance))
        return self.covariance / np.outer(s, s)

    # -- serialisation ------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The calibration JSON (docs/model.md#calibration-json); extra keys keep their meaning across versions."""
        valid = np.all(np.isfinite(self.residuals_mm), axis=-1)
        pts = []
        for i, iid in enumerate(self.image_ids):
            for j, pid in enumerate(self.point_ids):
                if valid[i, j]:
                    pts.append([_plain(iid), _plain(pid), float(self.residuals_mm[i, j, 0]), float(self.residuals_mm[i, j, 1])])
        std = {n: (None if v is None else float(v)) for n, v in self.std.items()}
        return {
            "intrinsics": self.intrinsics.to_dict(),
            "distortion": self.distortion.to_dict(),
            "std": std,
            "extrinsics": [
                {
                    "image_id": _plain(iid),
                    "rvec": self.rvecs[i].tolist(),
                    "tvec_mm": self.tvecs_mm[i].tolist(),
                    "std": self.pose_std[i].tolist(),
                }
                for i, iid in enumerate(self.image_ids)
            ],
            "residuals": {
                "rms_mm": float(self.rms_mm),
                "per_image_rms_mm": [float(v) for v in self.per_image_rms_mm],
                "cost_rms": float(self.cost_rms),
                "sigma_mm": float(self.sigma_mm),
                "points": {"columns": ["image_id", "point_id", "dx_mm", "dy_mm"], "rows": pts},
            },
            "cost": self.cost,
            "iterations": int(self.iterations),
            "converged": bool(self.converged),
            "message": self.message,
            "model": {
                "radial": self.model.radial,
                "tangential": self.model.tangential,
                "psd_radial": self.model.psd_radial,
                "skew": self.model.skew,
                "aspect": self.model.aspect,
                "fit_gains": self.model.fit_gains,
            },
            "gains": [float(g) for g in self.gains],
            "covariance": {"names": list(self.param_names), "matrix": self.covariance.tolist()},
            "sensor": {"lx_mm": float(self.sensor_mm[0]), "ly_mm": float(self.sensor_mm[1])},
            "stages": _jsonable(self.stages),
            "problem": _jsonable(self.problem),
            "software": {"name": "psdcal", "version": _software_version()},
            "created": self.created,
            "warnings": self.warnings(),
            **({"verdict": self.verdict["verdict"], "checks": self.verdict["checks"]} if self.verdict else {}),
        }

    @classmethod
    def from_dict(cls, d: dict, *, source: str = "calibration") -> "CalibrationResult":
        """Rebuild a result from its JSON dict (as written by :meth:`to_dict`)."""
        try:
            intr = Intrinsics(**{k: float(v) for k, v in d["intrinsics"].items() if k in ("f_mm", "cx_mm", "cy_mm", "skew", "fy_mm")})
            dist = Distortion(**{k: float(d["distortion"].get(k, 0.0)) for k in DISTORTION_NAMES})
            m = d.get("model", {})
            spec = ModelSpec(
                radial=int(m.get("radial", 2)),
                tangential=bool(m.get("tangential", False)),
                psd_radial=int(m.get("psd_radial", 0)),
                skew=bool(m.get("skew", False)),
                aspect=bool(m.get("aspect", "fy_mm" in d["intrinsics"])),
                fit_gains=bool(m.get("fit_gains", False)),
            )
            ext = d.get("extrinsics", [])
            cov = d.get("covariance", {})
            names = tuple(cov.get("names", ()))
            matrix = np.array(cov.get("matrix", np.zeros((0, 0))), dtype=float).reshape(len(names), len(names))
            res = d.get("residuals", {})
            image_ids = tuple(e["image_id"] for e in ext)
            rows = res.get("points", {}).get("rows", [])
            point_ids = tuple(sorted({r[1] for r in rows}, key=lambda v: (str(type(v)), v)))
            pindex = {p: j for j, p in enumerate(point_ids)}
            iindex = {p: i for i, p in enumerate(image_ids)}
            R = np.full((len(image_ids), len(point_ids), 2), np.nan)
            for r in rows:
                if r[0] in iindex:
                    R[iindex[r[0]], pindex[r[1]]] = r[2:4]
            sensor = d.get("sensor", {})
            return cls(
                intrinsics=intr,
                distortion=dist,
                gains=np.array(d.get("gains", [1.0, 1.0, 1.0, 1.0]), dtype=float),
                model=spec,
                cost=str(d.get("cost", "image")),
                param_names=names,
                covariance=matrix,
                std=dict(d.get("std", {})),
                image_ids=image_ids,
                point_ids=point_ids,
                rvecs=np.array([e["rvec"] for e in ext], dtype=float).reshape(-1, 3),
                tvecs_mm=np.array([e["tvec_mm"] for e in ext], dtype=float).reshape(-1, 3),
                pose_std=np.array([e.get("std", [np.nan] * 6) for e in ext], dtype=float).reshape(-1, 6),
                residuals_mm=R,
                rms_mm=float(res.get("rms_mm", np.nan)),
                per_image_rms_mm=np.array(res.get("per_image_rms_mm", []), dtype=float),
                cost_rms=float(res.get("cost_rms", np.nan)),
                sigma_mm=float(res.get("sigma_mm", np.nan)),
                iterations=int(d.get("iterations", 0)),
                converged=bool(d.get("converged", True)),
                message=str(d.get("message", "")),
                stages=d.get("stages", {}),
                problem=d.get("problem", {}),
                sensor_mm=(float(sensor.get("lx_mm", LX_MM)), float(sensor.get("ly_mm", LY_MM))),
                created=str(d.get("created", "")),
                verdict={"verdict": d["verdict"], "checks": list(d.get("checks", []))} if "verdict" in d else None,
            )
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
            raise InputError(f"not a psdcal calibration ({type(exc).__name__}: {exc})", path=source) from None


def _plain(v):
    return v.item() if isinstance(v, np.generic) else v


def _plain_ids(ids) -> tuple:
    """``ids`` as a tuple of plain Python values (numpy scalars converted)."""
    ids = tuple(ids)
    return tuple(_plain(v) for v in ids) if any(isinstance(v, np.generic) for v in ids) else ids


def _frozen(a) -> np.ndarray:
    """A read-only float copy of ``a``."""
    out = np.array(a, dtype=float)
    out.flags.writeable = False
    return out


def inputs_from_record(problem) -> tuple[np.ndarray, np.ndarray]:
    """The template (M, 2) and the measured points (n_images, M, 2) of a problem record, mm (NaN where missing)."""
    return np.asarray(problem["template"]["xy_mm"], dtype=float), points_from_record(problem["points"]["xy_mm"])


def points_from_record(xy) -> np.ndarray:
    """The measured points (n_images, M, 2) of a problem record's ``points.xy_mm``, mm, NaN where missing.

    Accepts the array kept in a :class:`CalibrationResult` and the nested lists
    (``null`` for a missing coordinate) of its JSON file.
    """
    if isinstance(xy, np.ndarray):
        return np.array(xy, dtype=float)
    return np.array([[[np.nan if v is None else v for v in pt] for pt in img] for img in xy], dtype=float)


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind == "f":  # fast path: non-finite -> None without walking the nested lists
            bad = ~np.isfinite(obj)
            if not bad.any():
                return obj.tolist()
            out = obj.astype(object)
            out[bad] = None
            return out.tolist()
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


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
        as ``result.verdict`` (JSON ``verdict`` and ``checks``); about 2 ms.
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
    # BLAS_THREADS_MIN_POINTS points makes no BLAS call that OpenBLAS would thread (its work is in the compiled
    # kernels and 9 x 9 factorisations), and the limit itself would cost some 6 us.
    needed = verdict or _n_points(points_mm) >= BLAS_THREADS_MIN_POINTS
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


def _n_points(points_mm) -> float:
    """n_images x M of a points array (inf when it has no such shape: the checks report that)."""
    try:
        shape = np.shape(points_mm)
    except ValueError:  # ragged
        return math.inf
    return shape[0] * shape[1] if len(shape) >= 2 else math.inf


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
    if old != new:
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
        res = replace(res, covariance=np.asarray(res.covariance, dtype=float) * k, std=std,
                      pose_std=np.asarray(res.pose_std, dtype=float) * sk, stages=stages)
    return replace(res, verdict=v.to_dict())


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
    spec = ModelSpec(radial=radial, tangential=tangential, psd_radial=psd_radial, skew=skew, aspect=aspect, fit_gains=fit_gains)
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
    primary, cands = linear_starts(
        T, X, preliminary=preliminary, normalize=normalize, radial=radial, skew=skew, aspect=aspect,
        general=fit_gains, f_guess_mm=f_guess_mm, image_ids=ids, point_ids=pids,
    )
    start = primary
    g0_start = g0
    prob = Problem(T, X, spec, cost=cost, sensor_mm=tuple(sensor_mm))
    staged = staged_start(spec)
    # Every start is refined on the image cost with the core model (or the model itself
    # when it has nothing beyond the core); the lowest cost wins (global minimum).
    first = staged if staged is not None else spec
    # Many points per view (a chessboard): the starts are compared on a spread subset of each view's points
    # (the basins of the cost are those of the whole set), and the final refinement takes every point.
    Xs = subsample_views(T, X)
    sub = Xs is not None
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


#: Below this many observations (and without the verdict) :func:`calibrate` does not ask threadpoolctl for one
#: BLAS thread: no BLAS call of such a problem is large enough for OpenBLAS to thread.
BLAS_THREADS_MIN_POINTS = 1000

#: Points per view on which the starts of the refinement are compared when a view has more than twice as
#: many (:func:`subsample_views`); the final refinement always takes every point.
SUBSAMPLE_POINTS = 32


def subsample_views(T, X, k: int = SUBSAMPLE_POINTS):
    """``X`` with all but about ``k`` spread points of each view set to NaN; None when no view has more than ``2 k``.

    The points are chosen once on the template: the one nearest the centre of
    each cell of a ``g x g`` grid over the plate, ``g = ceil(sqrt(k))``, so they
    cover the whole plate, corners included (where distortion shows most). A
    view that keeps fewer than ``k / 2`` of them (a partly seen template)
    keeps all its points.

    Parameters
    ----------
    T : (M, 2) template points, mm
    X : (n_images, M, 2) measured points, mm, NaN where missing
    """
    T = np.asarray(T, dtype=float)
    valid = np.all(np.isfinite(X), axis=-1)  # (n_images, M)
    if T.shape[0] <= 2 * k or not np.any(valid.sum(axis=1) > 2 * k):
        return None
    keep = valid & _subsample_mask(*_template_key(T), k)[None, :]
    few = (keep.sum(axis=1) < k // 2) | (valid.sum(axis=1) <= 2 * k)
    keep[few] = valid[few]
    return np.where(keep[..., None], X, np.nan)


@functools.lru_cache(maxsize=8)
def _subsample_mask(shape, data, k) -> np.ndarray:
    """(M,) bool, read-only: the template points :func:`subsample_views` keeps (cached per template)."""
    T = _template_of(shape, data)
    # one point per cell of a g x g grid over the plate (the one nearest the cell's centre)
    g = int(np.ceil(np.sqrt(k)))
    lo, hi = T.min(axis=0), T.max(axis=0)
    size = np.where(hi > lo, (hi - lo) / g, 1.0)
    cell = np.minimum(((T - lo) / size).astype(np.int64), g - 1)
    off = np.sum(((T - lo) / size - cell - 0.5) ** 2, axis=1)
    key = cell[:, 0] * g + cell[:, 1]
    order = np.lexsort((off, key))
    first = np.ones(order.size, dtype=bool)
    first[1:] = key[order[1:]] != key[order[:-1]]
    chosen = np.zeros(T.shape[0], dtype=bool)
    chosen[order[first]] = True
    chosen.flags.writeable = False
    return chosen


#: LM iterations a further start runs before it is compared with the best solution so far
#: (:func:`_refine_starts`).
PROBE_ITERATIONS = 3


def _fc(intr) -> np.ndarray:
    """(f, cx, cy) of an Intrinsics, mm."""
    return np.array([intr.f_mm, intr.cx_mm, intr.cy_mm])


def _gap(a, b) -> float:
    """Distance between two (f, cx, cy) in the valley's terms: C in mm plus f in 1 % steps of 0.1 mm."""
    return float(np.hypot(np.hypot(a[1] - b[1], a[2] - b[2]), 10.0 * (a[0] - b[0]) / abs(b[0])))


def _same_basin(start, probe, solution) -> bool:
    """Whether a probe heads into a solution's valley: within 0.05 mm of it, or half-way there."""
    g = _gap(probe, solution)
    return g < 0.05 or g < 0.5 * _gap(start, solution)


def _refine_starts(pfirst, first, cands, g0, solver):
    """Refine every start; ``[(label, RefineResult, ok)]``.

    The first start is refined to convergence. Each further start first runs
    :data:`PROBE_ITERATIONS` iterations: when it is then in the valley of a
    solution already found (:func:`_same_basin`) it can only end there and
    stops; otherwise it is refined to convergence from where it is. So the
    usual case (every start in one valley) costs a few iterations per start,
    and a start in another valley gets its full refinement.
    """
    tried = []
    probe = _probe_solver(solver)
    seen = []  # (start (f, C), solution (f, C)) of the converged refinements
    for label, i0, d0, rv, tv in cands:
        if first.aspect and i0.fy_mm is None:
            i0 = replace(i0, fy_mm=i0.f_mm)
        if not (first.aspect or first.skew):
            i0 = replace(i0, fy_mm=None, skew=0.0)
        d0 = _restrict(d0, first)
        x0 = _fc(i0)
        if any(_gap(x0, a) < 0.02 for a, _ in seen):
            continue  # the same start as one already refined
        try:
            if seen:
                r = refine(pfirst, i0, d0, g0, rv, tv, probe)
                if r.converged or any(_same_basin(x0, _fc(r.intrinsics), b) for _, b in seen):
                    tried.append((label, r, False))  # a probe: never chosen over the converged solution of its valley
                    continue
                i0, d0, g0r, rv, tv = r.intrinsics, Distortion.from_array(r.coeffs), r.gains, r.rvecs, r.tvecs
            else:
                g0r = g0
            r = refine(pfirst, i0, d0, g0r, rv, tv, solver)
        except (np.linalg.LinAlgError, FloatingPointError, ValueError):  # a start that breaks the solver is not a candidate
            continue
        ok = bool(r.converged and np.isfinite(r.cost_rms) and r.intrinsics.f_mm > 0 and np.all(r.tvecs[:, 2] > 0))
        tried.append((label, r, ok))
        if ok:
            seen.append((x0, _fc(r.intrinsics)))
    # A probe or an unconverged refinement below the best converged cost is in a lower valley (a converged
    # solution is a local minimum: points of its own valley cost more): refine it on, from where it stopped.
    for _ in range(2):
        best = min((t[1].cost_rms for t in tried if t[2]), default=np.inf)
        lower = [t for t in tried if not t[2] and np.isfinite(t[1].cost_rms) and t[1].cost_rms < best * (1 - 1e-6)]
        if not lower:
            break
        label, r0, _ = min(lower, key=lambda t: t[1].cost_rms)
        try:
            r = refine(pfirst, r0.intrinsics, Distortion.from_array(r0.coeffs), r0.gains, r0.rvecs, r0.tvecs,
                       replace(solver, max_iterations=2 * solver.max_iterations))
        except (np.linalg.LinAlgError, FloatingPointError, ValueError):
            break
        ok = bool(r.converged and np.isfinite(r.cost_rms) and r.intrinsics.f_mm > 0 and np.all(r.tvecs[:, 2] > 0))
        tried = [t for t in tried if t[1] is not r0] + [(label + "+", r, ok)]
        if not ok and not r.cost_rms < r0.cost_rms:
            break
    return tried


#: Focal lengths (mm) tried when neither the closed form nor any single view gives one.
F_GRID_MM = (4.0, 8.0, 16.0, 32.0, 64.0)


def focal_from_homographies(Hs, c_mm=(0.0, 0.0)) -> np.ndarray:
    """Focal length (n,) of each view with the optical centre known, mm (NaN where the view does not fix it).

    With ``C`` known, ``H' = T(-C) H`` is ``diag(f, f, 1) [r1 r2 t]`` up to
    scale, and the orthonormality of ``r1, r2`` (Zhang's Eq 22 with the
    principal point fixed) gives two estimates of ``f^2`` per view::

        f^2 = -(h11 h12 + h21 h22) / (h31 h32)
        f^2 = -(h11^2 + h21^2 - h12^2 - h22^2) / (h31^2 - h32^2)

    combined by least squares in ``1/f^2``. A view parallel to the sensor
    (``h31 = h32 = 0``) does not fix ``f``; neither does a solution with
    ``f^2 <= 0`` (noise, distortion): both give NaN, never an error.
    """
    Hs = np.asarray(Hs, dtype=float).reshape(-1, 3, 3)
    from psdcal import _jit

    if _jit.use_compiled(Hs.shape[0]):  # one compiled call; the numpy lines below are its reference
        from psdcal.calibration._homography import linear_kernels

        return linear_kernels().focal_from_homographies_kernel(np.ascontiguousarray(Hs), float(c_mm[0]), float(c_mm[1]))
    Tc = np.array([[1.0, 0.0, -c_mm[0]], [0.0, 1.0, -c_mm[1]], [0.0, 0.0, 1.0]])
    G = Tc @ Hs
    G = G / np.linalg.norm(G[:, :, :2], axis=(1, 2))[:, None, None]
    h1, h2 = G[:, :, 0], G[:, :, 1]
    a = np.stack([h1[:, 0] * h2[:, 0] + h1[:, 1] * h2[:, 1],
                  h1[:, 0] ** 2 + h1[:, 1] ** 2 - h2[:, 0] ** 2 - h2[:, 1] ** 2], axis=1)
    b = np.stack([h1[:, 2] * h2[:, 2], h1[:, 2] ** 2 - h2[:, 2] ** 2], axis=1)
    den = np.sum(a * a, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(den > 0, -np.sum(a * b, axis=1) / np.where(den > 0, den, 1.0), np.nan)  # 1/f^2: a w + b = 0
        return np.where(np.isfinite(w) & (w > 0), 1.0 / np.sqrt(np.where(w > 0, w, 1.0)), np.nan)


def _restrict(dist: Distortion, spec: ModelSpec) -> Distortion:
    """``dist`` with the terms that ``spec`` does not estimate set to zero."""
    free = set(spec.distortion_names)
    return Distortion(**{n: v for n, v in dist.to_dict().items() if n in free})


def template_hint(T, X, Hs, point_ids=None) -> str:
    """A message naming template LEDs that no view's homography fits ("" when none stands out).

    Each view's residuals from its homography (lens distortion makes them
    smooth in the image, different from view to view) are divided by that
    view's median; an LED whose median over the views is far above the other
    LEDs' is off in every view: a wrong template coordinate, or a permutation
    of the LED order (two LEDs swapped, a row listed in reverse). When
    swapping the two worst LEDs makes the homographies fit, say so.
    """
    from psdcal.calibration._homography import apply_homography

    T = np.asarray(T, dtype=float)
    ids = list(range(len(T))) if point_ids is None else list(point_ids)

    def per_led(Tm):
        Hm = homographies(Tm, X, normalize=True)
        res = np.stack([np.hypot(*(apply_homography(H, Tm) - x).T) for H, x in zip(Hm, X)])  # (n_images, M)
        res = res / np.maximum(np.nanmedian(res, axis=1, keepdims=True), 1e-300)
        return np.nanmedian(res, axis=0), float(np.nansum(res ** 2))

    try:
        led, total = per_led(T)
    except (DegenerateViewsError, np.linalg.LinAlgError):
        return ""
    order = [int(k) for k in np.argsort(-led)[:8]]

    def misfit(Tm):
        Hm = homographies(Tm, X, normalize=True)
        return sum(float(np.nansum(np.sum((apply_homography(H, Tm) - x) ** 2, axis=-1))) for H, x in zip(Hm, X))

    try:
        base = misfit(T)
        # a row listed in reverse: each line of >= 3 template points reversed
        best_row = (base, None)
        for line in find_lines(T, max_lines=MAX_STRAIGHTNESS_LINES):
            idx = np.asarray(line, dtype=int)
            T2 = T.copy()
            T2[idx] = T[idx[::-1]]
            m2 = misfit(T2)
            if m2 < best_row[0]:
                best_row = (m2, idx)
        # swapped LEDs: up to three swaps among the least consistent LEDs, the best one each time
        cur, swaps, best = T.copy(), [], base
        for _ in range(3):
            step = (best, None)
            for i in range(len(order)):
                for j in range(i + 1, len(order)):
                    T2 = cur.copy()
                    T2[[order[i], order[j]]] = T2[[order[j], order[i]]]
                    m2 = misfit(T2)
                    if m2 < step[0]:
                        step = (m2, (order[i], order[j]))
            if step[1] is None or step[0] > 0.5 * best:
                break
            a, b = step[1]
            cur[[a, b]] = cur[[b, a]]
            swaps.append(step[1])
            best = step[0]
            if best < base / 1e3:
                break
    except (DegenerateViewsError, np.linalg.LinAlgError):
        best, swaps, best_row = np.inf, [], (np.inf, None)
        base = np.inf
    if best_row[1] is not None and best_row[0] < base / 10 and best_row[0] <= best:
        row = ", ".join(str(ids[k]) for k in best_row[1])
        return (f"a template permutation fits: the row of LEDs {row} looks listed in reverse (check the LED order "
                "in the template), not the views")
    if swaps and best < base / 10:
        pairs = " and ".join(f"LEDs {ids[a]} and {ids[b]}" for a, b in swaps)
        return (f"a template permutation fits: {pairs} look swapped (check the LED order in the "
                "template: swapped LEDs or a row listed in reverse), not the views")
    if led[order[0]] > 4.0 * np.median(led):
        a, b = order[0], order[1]
        return (f"template LEDs {ids[a]} and {ids[b]} are off the projective fit in every view: check the template "
                "(LED order: swapped LEDs or a row listed in reverse; coordinates), not the views")
    return ""


def linear_starts(T, X, *, preliminary=True, normalize=True, radial=2, skew=False, aspect=False, general=False,
                  f_guess_mm=None, image_ids=None, point_ids=None):
    """Starts of the refinement from the linear stages, the first that fail being replaced by ones that cannot.

    Returns ``(primary, starts)``: ``primary`` is the :class:`InitialEstimate`
    recorded in the result's stages (the closed form when it works, else the
    first fallback); ``starts`` is a list of ``(label, Intrinsics,
    Distortion, rvecs, tvecs_mm)``:

    - ``closed-form``: Zhang's closed form after the line-straightness step
      (the general one, sqrt(fx fy) and C at the electrical centre, with
      ``general`` for raw readouts through unequal gains);
    - ``closed-form-raw``: the same without the preliminary step, when the
      closed form after that step fails (without lines in the template the
      step does nothing and the closed form is this one); when both work the
      raw one is the worse start of the same method (distorted points bias
      its f by several %) and is not tried;
    - ``centre``: C at the electrical centre and the median of the focal
      lengths each homography gives with that C (:func:`focal_from_homographies`):
      the closed form's C is unreliable on distorted points without lines
      (irregular templates), where it lands in another valley of the cost;
    - ``f-guess``: C at the electrical centre and ``f_guess_mm``;
    - ``f-grid``: C at the electrical centre and each of :data:`F_GRID_MM`,
      only when nothing above gave a start.

    Raises DegenerateViewsError only when the views are degenerate in fact:
    collinear template points (no homography) or no view tilted enough to
    fix a focal length, and no ``f_guess_mm``.
    """
    T = np.asarray(T, dtype=float)
    X = np.asarray(X, dtype=float)
    ids = list(range(X.shape[0])) if image_ids is None else list(image_ids)
    starts = []
    primary = None
    closed_error = None
    labels = [f"image {i}" for i in ids]
    try:
        est = initial_estimate(T, X, preliminary=preliminary, normalize=normalize, radial_terms=radial,
                               skew=skew or general, aspect=aspect or general, image_ids=ids)
    except DegenerateViewsError as exc:
        closed_error, est = exc, None
    # the views' homographies (after the preliminary step when it applied: the better start); raises on collinear
    # points, views that are degenerate in fact
    Hs_raw = est.homographies if est is not None else homographies(T, X, normalize=normalize, labels=labels)
    raw_too = False
    if est is None and preliminary and radial > 0:
        raw_too = True  # the closed form failed after the preliminary step: try it on the raw points
    for est_i, label in ((est, "closed-form"), (None if not raw_too else "raw", "closed-form-raw")):
        if est_i is None:
            continue
        if est_i == "raw":
            try:
                intr = intrinsics_from_homographies(Hs_raw, skew=skew or general, aspect=aspect or general)
            except DegenerateViewsError as exc:
                closed_error = exc
                continue
            est_i = InitialEstimate(np.zeros(2), 0, Hs_raw, intr, *poses_from_homographies(Hs_raw, intr))
        elif est_i.n_lines == 0:
            label = "closed-form-raw"
        if general:
            i_s = Intrinsics(f_mm=float(np.sqrt(est_i.intrinsics.f_mm * est_i.intrinsics.fy)))
            est_i = replace(est_i, intrinsics=i_s, rvecs=poses_from_homographies(est_i.homographies, i_s)[0],
                            tvecs_mm=poses_from_homographies(est_i.homographies, i_s)[1])
        if primary is None:
            primary = est_i
        starts.append((label, est_i.intrinsics, est_i.distortion(radial), est_i.rvecs, est_i.tvecs_mm))
    fs = focal_from_homographies(Hs_raw)
    fs = fs[np.isfinite(fs)]
    extent = _extent(X)
    fs = fs[fs < 1e3 * extent]
    zero = est.distortion(radial) if est is not None else Distortion()  # the preliminary k with its homographies
    fallback = []
    if fs.size:
        fs = np.sort(fs)  # their median (np.median's arithmetic, without its overhead on a few numbers)
        h = fs.size // 2
        fallback.append(("centre", float(fs[h]) if fs.size % 2 else float((fs[h - 1] + fs[h]) / 2.0)))
    if f_guess_mm is not None:
        fallback.append(("f-guess", float(f_guess_mm)))
    if not starts and not fallback:
        if closed_error is not None and fs.size == 0:
            hint = template_hint(T, X, Hs_raw, point_ids)
            if hint:
                raise DegenerateViewsError(f"no camera fits these views: {hint}")
            raise DegenerateViewsError(
                f"the views do not determine the intrinsics ({closed_error}; no single view fixes a focal length): "
                "tilt the template differently between views, or give a nominal focal length with --f-guess"
            )
        fallback += [("f-grid", f) for f in F_GRID_MM]
    for label, f in fallback:
        i0 = Intrinsics(f_mm=f)
        rv, tv = poses_from_homographies(Hs_raw, i0)
        starts.append((label, i0, zero, rv, tv))
        if primary is None:
            primary = InitialEstimate(np.zeros(2), 0, Hs_raw, i0, rv, tv)
    return primary, starts


def implausible(result: CalibrationResult) -> str:
    """Why a refined solution cannot be a real sensor ("" when it can).

    A focal length that is not positive and finite, or a template view that is
    not in front of the sensor (t_z <= 0), means the solver stopped in a
    meaningless stationary point, whatever its convergence test said.
    """
    intr = result.intrinsics
    dist = result.distortion
    values = (intr.f_mm, intr.fy, intr.cx_mm, intr.cy_mm, intr.skew, *(getattr(dist, n) for n in DISTORTION_NAMES))
    if not all(math.isfinite(v) for v in values):
        return "non-finite parameters"
    if not (intr.f_mm > 0 and intr.fy > 0):
        return f"focal length {intr.f_mm:.3g} mm"
    if (result.problem or {}).get("kind") == "directions":  # the one pose is the stage's rotation and offsets
        return ""
    tz = np.asarray(result.tvecs_mm, dtype=float)[:, 2]
    if np.any(~np.isfinite(tz)) or np.any(tz <= 0):
        i = int(np.argmin(np.nan_to_num(tz, nan=-np.inf)))
        return f"image {result.image_ids[i]} behind the sensor (t_z = {tz[i]:.3g} mm)"
    return ""


#: A converged fit whose residual RMS exceeds this fraction of the measured
#: points' spread is flagged by :meth:`CalibrationResult.warnings` (1 % of a
#: 9 mm PSD is 90 um, some 30 times the noise at the paper's lowest SNR).
MISFIT_FRACTION = 0.01

#: Offsets (in units of the sensor's size) of the optical-centre starts tried
#: when PSD terms are estimated (see :func:`_psd_multistart`).
PSD_CENTRE_STARTS = ((0.0, 0.0), (1, 1), (1, -1), (-1, 1), (-1, -1))
PSD_CENTRE_STEP = 1.0 / 12.0


def _psd_multistart(T, X, spec, sensor_mm, start, intr0, dist0, g0, rv0, tv0, solver):
    """Best image-cost fit over several starts of the optical centre (PSD terms free).

    With the PSD's own radial terms free, the cost has long valleys: to first
    order the data fix only k1 + l1, the decentring term k1 C and the
    principal point, and from the linear stage's centre (1-2 mm off for a
    long lens) the refinement can settle where k1 and l1 trade against C.
    Refining also from C at the electrical centre and at four points around
    it (+-Lx/12, +-Ly/12; poses from the homographies for each start) and
    keeping the lowest cost reached the truth on all of 60 simulated Lens 1
    and Lens 2 sets with the paper's l1, where the single start failed on
    most. Costs five more refinements, for this model only.
    """
    pimg = Problem(T, X, spec, cost="image", sensor_mm=tuple(sensor_mm))
    cands = [refine(pimg, intr0, dist0, g0, rv0, tv0, solver)]
    lin = start.distortion(spec.radial)
    for ox, oy in PSD_CENTRE_STARTS:
        i0 = replace(intr0, cx_mm=ox * PSD_CENTRE_STEP * sensor_mm[0], cy_mm=oy * PSD_CENTRE_STEP * sensor_mm[1])
        cands.append(refine(pimg, i0, lin, g0, *poses_from_homographies(start.homographies, i0), solver))
    ok = [c for c in cands if c.converged and np.isfinite(c.cost_rms)]
    return min(ok, key=lambda c: c.cost_rms) if ok else None


@functools.lru_cache(maxsize=16)
def _probe_solver(solver: SolverOptions) -> SolverOptions:
    """``solver`` limited to :data:`PROBE_ITERATIONS` iterations (a probe of a further start)."""
    return replace(solver, max_iterations=min(PROBE_ITERATIONS, solver.max_iterations))


@functools.lru_cache(maxsize=16)
def _stage_solver(solver: SolverOptions) -> SolverOptions:
    """Tolerances of a start stage: its solution only seeds the final refinement, which
    converges to the same optimum, so it stops at a relative cost change of 1e-7
    (the parameters are then within ~1e-3 standard errors of its optimum)."""
    return replace(solver, ftol=max(solver.ftol, 1e-7), xtol=max(solver.xtol, 1e-8))


def staged_start(spec: ModelSpec) -> ModelSpec | None:
    """The core model refined first when ``spec`` has terms beyond it (None otherwise)."""
    core = ModelSpec(radial=min(spec.radial, 2), tangential=False, psd_radial=0, skew=False, aspect=False, fit_gains=False)
    extra = spec.psd_radial > 0 or spec.skew or spec.aspect or spec.fit_gains or spec.radial > 2
    return core if extra else None


def _make_result(prob, ref, start, ids, pids, spec, cost, g0, preliminary, normalize, solver, extra_stages=None):
    X = prob.points_mm
    intr = ref.intrinsics
    dist = Distortion.from_array(ref.coeffs)
    # modelled measured points on the sensor, whichever cost was minimised
    if ref.model_mm is not None:  # the image cost already has them
        model = np.full(X.shape, np.nan)
        model[prob.valid] = ref.model_mm
    else:
        x = np.stack([project(prob.template_mm, intr, r, t) for r, t in zip(ref.rvecs, ref.tvecs)])
        model = distort(x, dist, intr.c, d0_mm=X).d_mm
        if spec.fit_gains or not np.allclose(ref.gains, 1.0):
            model = gain_map(model, ref.gains, *prob.sensor_mm)
    res = X - model
    valid = prob.valid
    # squared residual of each valid point (0 elsewhere; a non-finite residual counts as 0, as nan_to_num makes it)
    rv = res[valid]
    if not np.isfinite(rv).all():
        rv = np.nan_to_num(rv)
    sq = np.zeros(valid.shape)
    sq[valid] = rv[:, 0] ** 2 + rv[:, 1] ** 2
    n_valid = int(valid.sum())
    rms = math.sqrt(float(sq.sum()) / max(n_valid, 1))
    per_image = np.sqrt(sq.sum(axis=1) / np.maximum(valid.sum(axis=1), 1))
    cov = ref.covariance_global  # the reduced (Schur) system's inverse: no matrix of all poses
    std = {n: None for n in ("f_mm", "cx_mm", "cy_mm", "skew", *DISTORTION_NAMES)}
    if spec.aspect:
        std["fy_mm"] = None
    for k, n in enumerate(prob.names):
        std[n] = float(np.sqrt(max(cov[k, k], 0.0)))
    pose_std = np.sqrt(np.maximum(np.einsum("naa->na", ref.pose_covariance), 0.0))
    m = 2 * n_valid
    dof = max(m - ref.z.size, 1)
    sigma_mm = math.sqrt(float(sq.sum()) / dof) if cost == "image" else float(rms / np.sqrt(2.0) * np.sqrt(m / dof))
    stages = {
        "preliminary": {"k1": float(start.preliminary_k[0]), "k2": float(start.preliminary_k[1]), "line_groups": start.n_lines, "applied": bool(preliminary and start.n_lines > 0)},
        "closed_form": {**start.intrinsics.to_dict(), "normalized": bool(normalize)},
        "initial_extrinsics": [{"image_id": _plain(i), "rvec": r.tolist(), "tvec_mm": t.tolist()} for i, r, t in zip(ids, start.rvecs, start.tvecs_mm)],
        **(extra_stages or {}),
    }
    pids = _plain_ids(pids)
    # the inputs are kept as (read-only) arrays; to_dict() writes them as lists, NaN as null
    problem = {
        "template": {"point_ids": list(pids), "xy_mm": _frozen(prob.template_mm)},
        "points": {"image_ids": [_plain(i) for i in ids], "xy_mm": _frozen(X)},
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
            "gains": [float(g) for g in g0],
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
        image_ids=tuple(_plain(i) for i in ids),
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
