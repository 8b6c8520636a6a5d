"""The result of a calibration (:class:`CalibrationResult`) and the helpers of its record (the JSON file).

Kept apart from :mod:`psdcal.calibration.core` (the front door that makes results): a result is read
back from its file (:meth:`CalibrationResult.from_dict`) without the fitting code; ``core`` re-exports
every name here.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psdcal.errors import InputError
from psdcal.model.distortion import undistort
from psdcal.model.params import DISTORTION_NAMES, Distortion, Intrinsics, ModelSpec
from psdcal.model.readout import LX_MM, LY_MM

#: The intrinsic parameters' names (``fy_mm`` apart: a model option).
_ALL_INTR = ("f_mm", "cx_mm", "cy_mm", "skew")
#: A converged fit whose residual RMS exceeds this fraction of the measured
#: points' spread is flagged by :meth:`CalibrationResult.warnings` (1 % of a
#: 9 mm PSD is 90 um, some 30 times the noise at the paper's lowest SNR).
MISFIT_FRACTION = 0.01


def _software_version() -> str:
    """psdcal's version, read on first use (not at import: a process that writes no calibration never reads it)."""
    from psdcal import __version__

    return __version__


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
    # the types present, found at C speed (a chessboard has hundreds of ids, almost always plain ints)
    if any(issubclass(t, np.generic) for t in set(map(type, ids))):
        return tuple(_plain(v) for v in ids)
    return ids


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
