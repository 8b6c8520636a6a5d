"""A calibrated sensor as the measurement side needs it (docs/model.md#calibration-json).

:class:`SensorModel` reads the calibration JSON written by ``psdcal calibrate``
and keeps what angle-of-arrival measurement needs: the intrinsics, the
undistortion coefficients, the relative channel gains, the PSD size and the
covariance of the calibration's global free parameters.  It depends only on
the file contract, not on the calibration code.

Keys read (others are ignored)::

    intrinsics  {f_mm, cx_mm, cy_mm, skew[, fy_mm]}            required
    distortion  {k1, k2, k3, p1, p2, l1, l2}                     0 where absent
    covariance  {names: [...], matrix: [[...]]}                   optional
    std         {name: value or null}                             used when no covariance
    sensor      {lx_mm, ly_mm}                                    default 9 x 9
    gains       [g_x1, g_x2, g_y1, g_y2]                          default equal

Covariance names are taken from :data:`PARAMETER_NAMES`; poses are not part of
it (they are marginalised out by the calibration).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from psdcal.errors import InputError
from psdcal.model.params import DISTORTION_NAMES, Distortion, Intrinsics

#: Every global parameter a calibration covariance may name, with its meaning.
PARAMETER_NAMES = (
    "f_mm",
    "cx_mm",
    "cy_mm",
    "skew",
    "fy_mm",
    *DISTORTION_NAMES,
    "g_x2",
    "g_y1",
    "g_y2",
)
INTRINSIC_NAMES = ("f_mm", "cx_mm", "cy_mm", "skew", "fy_mm")
GAIN_NAMES = ("g_x2", "g_y1", "g_y2")


@dataclass(frozen=True)
class SensorModel:
    """One calibrated PSD + lens sensor.

    Attributes
    ----------
    intrinsics : Intrinsics
    distortion : Distortion
    names : tuple of str
        Names of the parameters the covariance is over (subset of
        :data:`PARAMETER_NAMES`, in the file's order).
    covariance : (n, n) ndarray
        Covariance of those parameters (units: mm^2 for lengths, the squares
        of the coefficient units for distortion, dimensionless for gains).
    gains : (4,) ndarray
        Relative channel gains ``(g_x1, g_x2, g_y1, g_y2)``; the signals are
        divided by them before Eq 1-2.
    lx_mm, ly_mm : float
        PSD active lengths.
    source : str or None
        The file it was read from.
    sensor_id : str or None
        The calibrated sensor's identity (calibration JSON ``sensor_id``), when recorded.
    """

    intrinsics: Intrinsics
    distortion: Distortion = field(default_factory=Distortion)
    names: tuple = ()
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    gains: np.ndarray = field(default_factory=lambda: np.ones(4))
    lx_mm: float = 9.0
    ly_mm: float = 9.0
    source: str | None = None
    sensor_id: str | None = None

    def __post_init__(self):
        cov = np.array(self.covariance, dtype=float).reshape(len(self.names), len(self.names))
        cov.setflags(write=False)
        g = np.array(self.gains, dtype=float).reshape(4)
        g.setflags(write=False)
        object.__setattr__(self, "covariance", cov)
        object.__setattr__(self, "gains", g)
        object.__setattr__(self, "names", tuple(self.names))

    @property
    def has_uncertainty(self) -> bool:
        """True when the calibration carries a covariance or standard errors (some variance > 0)."""
        return bool(self.covariance.size and np.any(np.diag(self.covariance) > 0))

    def require_uncertainty(self, allow: bool = False, option: str = "--allow-no-covariance") -> None:
        """InputError when the calibration has no uncertainty (sigmas would read 0) unless ``allow``."""
        if allow or self.has_uncertainty:
            return
        raise InputError("the calibration has no covariance and no standard errors: every sigma would omit its "
                         f"uncertainty (a calibration's truth.json?); give {option} to accept that",
                         path=self.source, field="covariance")

    @property
    def has_gains(self) -> bool:
        """True when the channel gains are not all equal."""
        return bool(np.ptp(self.gains) > 0)

    def value(self, name: str) -> float:
        """Current value of a global parameter named as in :data:`PARAMETER_NAMES`."""
        intr = self.intrinsics
        if name == "fy_mm":
            return intr.fy
        if name in ("f_mm", "cx_mm", "cy_mm", "skew"):
            return float(getattr(intr, name))
        if name in DISTORTION_NAMES:
            return float(getattr(self.distortion, name))
        if name in GAIN_NAMES:
            return float(self.gains[1 + GAIN_NAMES.index(name)])
        raise KeyError(name)

    def std(self) -> np.ndarray:
        """Standard errors (n,) of the parameters in :attr:`names`."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def with_values(self, values: dict) -> "SensorModel":
        """A copy with some global parameters set (names of :data:`PARAMETER_NAMES`)."""
        intr = self.intrinsics.to_dict()
        dist = self.distortion.to_dict()
        gains = self.gains.copy()
        for name, v in values.items():
            if name in INTRINSIC_NAMES:
                intr[name] = float(v)
            elif name in DISTORTION_NAMES:
                dist[name] = float(v)
            elif name in GAIN_NAMES:
                gains[1 + GAIN_NAMES.index(name)] = float(v)
            else:
                raise KeyError(name)
        return SensorModel(
            intrinsics=Intrinsics(**intr),
            distortion=Distortion(**dist),
            names=self.names,
            covariance=self.covariance,
            gains=gains,
            lx_mm=self.lx_mm,
            ly_mm=self.ly_mm,
            source=self.source,
            sensor_id=self.sensor_id,
        )

    # ------------------------------------------------------------------ I/O
    @classmethod
    def from_dict(cls, data: dict, *, source=None) -> "SensorModel":
        """Build from a parsed calibration JSON (docs/model.md#calibration-json).

        Raises
        ------
        InputError
            Naming ``source`` and the offending key when a key is missing or
            malformed.
        """
        src = None if source is None else str(source)

        def bad(msg, key):
            return InputError(msg, path=src, field=key)

        if not isinstance(data, dict):
            raise bad("a calibration must be a JSON object", None)
        intr_d = data.get("intrinsics")
        if not isinstance(intr_d, dict):
            raise bad("missing or malformed 'intrinsics' object", "intrinsics")

        def num(obj, key, where, default=None, *, positive=False):
            v = obj.get(key, default)
            if v is None:
                if default is None:
                    raise bad(f"missing number '{key}'", f"{where}.{key}")
                v = default
            try:
                v = float(v)
            except (TypeError, ValueError, OverflowError):
                raise bad(f"'{key}' must be a number, got {v!r}", f"{where}.{key}") from None
            if not math.isfinite(v) or (positive and v <= 0):
                raise bad(f"'{key}' must be a finite{' positive' if positive else ''} number, got {v}", f"{where}.{key}")
            return v

        fy = intr_d.get("fy_mm")
        intr = Intrinsics(
            f_mm=num(intr_d, "f_mm", "intrinsics", positive=True),
            cx_mm=num(intr_d, "cx_mm", "intrinsics"),
            cy_mm=num(intr_d, "cy_mm", "intrinsics"),
            skew=num(intr_d, "skew", "intrinsics", 0.0),
            fy_mm=None if fy is None else num(intr_d, "fy_mm", "intrinsics", positive=True),
        )
        dist_d = data.get("distortion", {}) or {}
        if not isinstance(dist_d, dict):
            raise bad("'distortion' must be an object", "distortion")
        dist = Distortion(**{n: num(dist_d, n, "distortion", 0.0) for n in DISTORTION_NAMES})

        sensor = data.get("sensor", {}) or {}
        if not isinstance(sensor, dict):
            raise bad("'sensor' must be an object", "sensor")
        lx = num(sensor, "lx_mm", "sensor", 9.0, positive=True)
        ly = num(sensor, "ly_mm", "sensor", 9.0, positive=True)

        gains = data.get("gains")
        if gains is None:
            g = np.ones(4)
        else:
            try:
                g = np.asarray(gains, dtype=float)
            except (TypeError, ValueError, OverflowError):
                raise bad("'gains' must be a list of 4 numbers", "gains") from None
            if g.shape != (4,) or not np.all(np.isfinite(g)) or np.any(g <= 0):
                raise bad(f"'gains' must be 4 positive numbers [g_x1, g_x2, g_y1, g_y2], got {gains!r}", "gains")

        cov_d = data.get("covariance")
        if cov_d is not None:
            if not isinstance(cov_d, dict) or "names" not in cov_d or "matrix" not in cov_d:
                raise bad("'covariance' must be an object with 'names' and 'matrix'", "covariance")
            names = cov_d["names"]
            if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
                raise bad("'covariance.names' must be a list of strings", "covariance.names")
            unknown = [n for n in names if n not in PARAMETER_NAMES]
            if unknown:
                raise bad(
                    f"unknown parameter name(s) {unknown}; expected names from {list(PARAMETER_NAMES)}",
                    "covariance.names",
                )
            if len(set(names)) != len(names):
                raise bad("repeated parameter name", "covariance.names")
            try:
                cov = np.asarray(cov_d["matrix"], dtype=float)
            except (TypeError, ValueError, OverflowError):
                raise bad("'covariance.matrix' must be a square list of lists of numbers", "covariance.matrix") from None
            n = len(names)
            if n == 0 and cov.size == 0:  # no free parameter: an empty matrix, however it was written
                cov = cov.reshape(0, 0)
            if cov.shape != (n, n):
                raise bad(f"'covariance.matrix' must be {n}x{n} (one row per name), got shape {cov.shape}", "covariance.matrix")
            if not np.all(np.isfinite(cov)):
                raise bad("'covariance.matrix' has non-finite entries", "covariance.matrix")
            if np.any(np.diag(cov) < 0) or not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-300):
                raise bad("'covariance.matrix' must be symmetric with a non-negative diagonal", "covariance.matrix")
            cov = 0.5 * (cov + cov.T)
            from psdcal.io import check_covariance

            check_covariance(cov, src, "covariance.matrix")
        else:
            # Fall back to the standard errors alone (no correlations).
            std_d = data.get("std", {}) or {}
            if not isinstance(std_d, dict):
                raise bad("'std' must be an object", "std")
            names, var = [], []
            for n in PARAMETER_NAMES:
                v = std_d.get(n)
                if v is None:
                    continue
                v = num(std_d, n, "std")
                names.append(n)
                var.append(v * v)
            cov = np.diag(var) if var else np.zeros((0, 0))
        if "fy_mm" in names and intr.fy_mm is None:
            raise bad("the covariance names 'fy_mm' but 'intrinsics' has no 'fy_mm'", "covariance.names")
        # every reader of a sensor's calibration (a calibration file, a sensors file's entries) refuses a
        # distortion no lens has (k1 = 1e300: every sigma overflows)
        from psdcal.io import check_plausible_distortion

        check_plausible_distortion(intr.to_dict(), dist.to_dict(), {"lx_mm": lx, "ly_mm": ly}, src)
        return cls(
            intrinsics=intr,
            distortion=dist,
            names=tuple(names),
            covariance=cov,
            gains=g,
            lx_mm=lx,
            ly_mm=ly,
            source=src,
            sensor_id=_sensor_id(data, src),
        )

    @classmethod
    def load(cls, path) -> "SensorModel":
        """Read a calibration JSON file; errors name the file and the key."""
        from psdcal.io import read_json, validate_calibration_dict

        path = Path(path)
        data = read_json(path, "calibration file")
        if isinstance(data, dict) and isinstance(data.get("intrinsics"), dict):
            validate_calibration_dict(data, path)
        return cls.from_dict(data, source=path)

    def to_dict(self) -> dict:
        """The subset of the calibration JSON this class reads (round-trips through :meth:`from_dict`)."""
        return {
            "intrinsics": self.intrinsics.to_dict(),
            "distortion": self.distortion.to_dict(),
            "covariance": {"names": list(self.names), "matrix": self.covariance.tolist()},
            "sensor": {"lx_mm": self.lx_mm, "ly_mm": self.ly_mm},
            "gains": self.gains.tolist(),
        }


def _sensor_id(data: dict, src):
    v = data.get("sensor_id")
    if v is None:
        return None
    if not isinstance(v, str) or not v.strip():
        raise InputError(f"'sensor_id' must be a non-empty string, got {v!r}", path=src, field="sensor_id")
    return v
