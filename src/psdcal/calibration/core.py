"""The calibration front door: ``psdcal.calibrate`` (the paper's Section 3, MODEL.md 6).

Steps, each usable on its own from its private module:

1. line-straightness preliminary distortion estimate (:mod:`._straightness`);
2. a homography per image by the DLT, Hartley-normalised (:mod:`._homography`);
3. closed-form intrinsics, then extrinsics (:mod:`._closed_form`);
4. Levenberg-Marquardt refinement on the ``image`` or ``template`` cost
   (:mod:`._refine`), with standard errors from the Jacobian.
"""
from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field, replace

import numpy as np

from psdcal import __version__
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


def _check_inputs(template_mm, points_mm, image_ids, min_images):
    T = np.asarray(template_mm, dtype=float)
    X = np.asarray(points_mm, dtype=float)
    if T.ndim != 2 or T.shape[1] != 2:
        raise InputError(f"template_mm must have shape (M, 2), got {T.shape}")
    if X.ndim != 3 or X.shape[2] != 2 or X.shape[1] != T.shape[0]:
        raise InputError(f"points_mm must have shape (n_images, {T.shape[0]}, 2), got {X.shape}")
    if not np.all(np.isfinite(T)):
        raise InputError("template_mm contains NaN or infinite values")
    # a point is missing only when both coordinates are NaN
    half = np.isnan(X).any(-1) & ~np.isnan(X).all(-1)
    if np.any(half) or np.any(np.isinf(X)):
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
        lines = find_lines(T, max_lines=MAX_STRAIGHTNESS_LINES)
        if lines:
            st = estimate_radial(X, lines, c_mm=c0, n_terms=min(2, radial_terms))
            k[: st.k.size] = st.k
            n_lines = st.n_lines
    coef = np.zeros(7)
    coef[:2] = k
    Xc = undistort(X, coef, c0) if n_lines else X
    Hs = homographies(T, Xc, normalize=normalize, labels=[f"image {i}" for i in ids])
    intr = intrinsics_from_homographies(Hs, skew=skew, aspect=aspect)
    extent = float(np.nanmax(np.abs(X))) * 2 if np.any(np.isfinite(X)) else 1.0
    if not (intr.f_mm < 1e3 * extent and np.hypot(intr.cx_mm, intr.cy_mm) < 10 * extent):
        raise DegenerateViewsError(
            f"the views do not determine the intrinsics (closed form gives f = {intr.f_mm:.3g} mm, "
            f"C = ({intr.cx_mm:.3g}, {intr.cy_mm:.3g}) mm): tilt the template differently between views"
        )
    return InitialEstimate(k, n_lines, Hs, intr, *poses_from_homographies(Hs, intr))


@dataclass(frozen=True)
class CalibrationResult:
    """A calibration: parameters, their uncertainty, residuals and how it was obtained.

    ``to_dict()`` is the calibration JSON of MODEL.md 9 (plus extra keys).

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
        """The calibration JSON (MODEL.md 9); extra keys keep their meaning across versions."""
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
            "software": {"name": "psdcal", "version": __version__},
            "created": self.created,
            "warnings": self.warnings(),
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
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"not a psdcal calibration ({type(exc).__name__}: {exc})", path=source) from None


def _plain(v):
    return v.item() if isinstance(v, np.generic) else v


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
) -> CalibrationResult:
    """Calibrate a PSD + lens sensor from views of a planar LED template.

    The adapted Zhang method of the paper (Section 3), with the corrections of
    MODEL.md 6: line-straightness preliminary distortion (3.2), Hartley
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

    with _single_threaded_blas():  # small dense linear algebra: one BLAS thread is fastest
        return _calibrate(
            template_mm, points_mm, cost=cost, radial=radial, tangential=tangential, psd_radial=psd_radial,
            skew=skew, preliminary=preliminary, normalize=normalize, aspect=aspect, fit_gains=fit_gains,
            gains=gains, image_ids=image_ids, point_ids=point_ids, sensor_mm=sensor_mm, solver=solver,
        )


def _calibrate(template_mm, points_mm, *, cost, radial, tangential, psd_radial, skew, preliminary, normalize,
               aspect, fit_gains, gains, image_ids, point_ids, sensor_mm, solver) -> CalibrationResult:
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
    if not fit_gains and not np.allclose(g0, 1.0):
        # Known gains held fixed: the raw readout is a homography of the equal-gain one
        # (psdcal.calibration.gains); map it back once, so that every stage sees corrected points.
        from psdcal.calibration.gains import correct_points

        known_gains, X, g0 = g0, correct_points(X, g0, *sensor_mm), np.ones(4)
    if fit_gains:
        # Raw readout through unequal gains is a homography of the sensor plane (psdcal.calibration.gains):
        # the single-f closed form may fail on it (f^2 < 0) or put C tens of mm off (the
        # projective part looks like a tilt); the general closed form absorbs it. Start from
        # its f with C at the electrical centre (a lens mount puts it within about 1 mm).
        start = initial_estimate(
            T, X, preliminary=preliminary, normalize=normalize, radial_terms=radial, skew=True, aspect=True, image_ids=ids
        )
        intr_s = Intrinsics(f_mm=float(np.sqrt(start.intrinsics.f_mm * start.intrinsics.fy)))
        rv_s, tv_s = poses_from_homographies(start.homographies, intr_s)
        start = replace(start, intrinsics=intr_s, rvecs=rv_s, tvecs_mm=tv_s)
    else:
        start = initial_estimate(
            T, X, preliminary=preliminary, normalize=normalize, radial_terms=radial, skew=skew, aspect=aspect, image_ids=ids
        )
    dist0 = start.distortion(radial)
    prob = Problem(T, X, spec, cost=cost, sensor_mm=tuple(sensor_mm))
    intr0 = start.intrinsics
    if aspect and intr0.fy_mm is None:
        intr0 = replace(intr0, fy_mm=intr0.f_mm)
    rv0, tv0 = start.rvecs, start.tvecs_mm
    staged = staged_start(spec)
    if staged is not None:
        # Stage 1: the core model (f, C, lens radial) from the linear start; the
        # PSD, tangential, skew, aspect and gain terms are then freed from its
        # solution. Freed all at once from the linear start, k1 and l1 (nearly
        # interchangeable when C is near the electrical centre) can drift into a
        # false minimum.
        p1 = Problem(T, X, staged, cost=cost, sensor_mm=tuple(sensor_mm))
        r1 = refine(p1, replace(intr0, fy_mm=None, skew=0.0), dist0, g0, rv0, tv0, _stage_solver(solver))
        if r1.converged and np.isfinite(r1.cost_rms):
            intr0 = replace(r1.intrinsics, fy_mm=r1.intrinsics.f_mm if aspect else None)
            dist0 = Distortion.from_array(r1.coeffs)
            rv0, tv0 = r1.rvecs, r1.tvecs
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
    ref = refine(prob, intr0, dist0, g0, rv0, tv0, solver)
    result = _make_result(prob, ref, start, ids, pids, spec, cost, g0, preliminary, normalize, solver)
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


def implausible(result: CalibrationResult) -> str:
    """Why a refined solution cannot be a real sensor ("" when it can).

    A focal length that is not positive and finite, or a template view that is
    not in front of the sensor (t_z <= 0), means the solver stopped in a
    meaningless stationary point, whatever its convergence test said.
    """
    intr = result.intrinsics
    values = [intr.f_mm, intr.fy, intr.cx_mm, intr.cy_mm, intr.skew, *result.distortion.as_array()]
    if not np.all(np.isfinite(values)):
        return "non-finite parameters"
    if not (intr.f_mm > 0 and intr.fy > 0):
        return f"focal length {intr.f_mm:.3g} mm"
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


def _make_result(prob, ref, start, ids, pids, spec, cost, g0, preliminary, normalize, solver):
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
    sq = np.where(valid, np.sum(np.nan_to_num(res) ** 2, axis=-1), 0.0)
    n_valid = valid.sum()
    rms = float(np.sqrt(sq.sum() / max(n_valid, 1)))
    per_image = np.sqrt(sq.sum(axis=1) / np.maximum(valid.sum(axis=1), 1))
    n_glob = prob.n_global
    cov = ref.covariance_global  # the reduced (Schur) system's inverse: no matrix of all poses
    std = {n: None for n in ("f_mm", "cx_mm", "cy_mm", "skew", *DISTORTION_NAMES)}
    if spec.aspect:
        std["fy_mm"] = None
    for k, n in enumerate(prob.names):
        std[n] = float(np.sqrt(max(cov[k, k], 0.0)))
    pose_std = np.sqrt(np.clip(np.einsum("naa->na", ref.pose_covariance), 0, None))
    m = 2 * n_valid
    dof = max(m - ref.z.size, 1)
    sigma_mm = float(np.sqrt(np.sum(sq) / dof)) if cost == "image" else float(rms / np.sqrt(2.0) * np.sqrt(m / dof))
    stages = {
        "preliminary": {"k1": float(start.preliminary_k[0]), "k2": float(start.preliminary_k[1]), "line_groups": start.n_lines, "applied": bool(preliminary and start.n_lines > 0)},
        "closed_form": {**start.intrinsics.to_dict(), "normalized": bool(normalize)},
        "initial_extrinsics": [{"image_id": _plain(i), "rvec": r.tolist(), "tvec_mm": t.tolist()} for i, r, t in zip(ids, start.rvecs, start.tvecs_mm)],
    }
    problem = {
        "template": {"point_ids": [_plain(p) for p in pids], "xy_mm": prob.template_mm.tolist()},
        "points": {"image_ids": [_plain(i) for i in ids], "xy_mm": _jsonable(X)},
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
        point_ids=tuple(_plain(p) for p in pids),
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


def recalibrate(calib: dict | CalibrationResult) -> CalibrationResult:
    """Re-run a calibration exactly from the problem record saved inside it."""
    d = calib.to_dict() if isinstance(calib, CalibrationResult) else calib
    p = d["problem"]
    o = p["options"]
    X = np.array([[[np.nan if v is None else v for v in pt] for pt in img] for img in p["points"]["xy_mm"]], dtype=float)
    return calibrate(
        np.array(p["template"]["xy_mm"], dtype=float),
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
        image_ids=p["points"]["image_ids"],
        point_ids=p["template"]["point_ids"],
        sensor_mm=tuple(o.get("sensor_mm", (LX_MM, LY_MM))),
        solver=SolverOptions(**o.get("solver", {})),
    )
