"""Frozen parameter records of the sensor model (docs/model.md#pinhole-model, #distortion).

Change them with :func:`dataclasses.replace`; they are never mutated.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from psdcal._cache import cached_attribute

DISTORTION_NAMES = ("k1", "k2", "k3", "p1", "p2", "l1", "l2")


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics (Eq 4, 21), all in mm on the sensor.

    ``x = f Xc/Zc + skew Yc/Zc + cx``, ``y = fy Yc/Zc + cy`` with ``fy = f``
    unless a separate vertical focal length ``fy_mm`` is given.
    """

    f_mm: float
    cx_mm: float = 0.0
    cy_mm: float = 0.0
    skew: float = 0.0
    fy_mm: float | None = None

    @property
    def fy(self) -> float:
        return self.f_mm if self.fy_mm is None else self.fy_mm

    @property
    def c(self) -> np.ndarray:
        """Optical centre ``(cx_mm, cy_mm)``, shape (2,)."""
        return np.array([self.cx_mm, self.cy_mm])

    def matrix(self) -> np.ndarray:
        """The intrinsic matrix A (3, 3) of Eq 4 (with skew in A[0, 1])."""
        return np.array([[self.f_mm, self.skew, self.cx_mm], [0.0, self.fy, self.cy_mm], [0.0, 0.0, 1.0]])

    def to_dict(self) -> dict:
        d = {"f_mm": self.f_mm, "cx_mm": self.cx_mm, "cy_mm": self.cy_mm, "skew": self.skew}
        if self.fy_mm is not None:
            d["fy_mm"] = self.fy_mm
        return d


@dataclass(frozen=True)
class Distortion:
    """Undistortion coefficients (docs/model.md#distortion).

    k1 [mm^-2], k2 [mm^-4], k3 [mm^-6]: lens radial about the optical centre;
    p1, p2 [mm^-1]: lens tangential; l1 [mm^-2], l2 [mm^-4]: PSD radial about
    the electrical centre (0, 0).
    """

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    l1: float = 0.0
    l2: float = 0.0

    def as_array(self) -> np.ndarray:
        """Coefficients in the order of :data:`DISTORTION_NAMES`, shape (7,)."""
        return np.array((self.k1, self.k2, self.k3, self.p1, self.p2, self.l1, self.l2), dtype=float)  # (no getattr loop)

    @classmethod
    def from_array(cls, a) -> "Distortion":
        return cls(**dict(zip(DISTORTION_NAMES, np.asarray(a, dtype=float).tolist())))  # (tolist: plain floats in one call)

    def to_dict(self) -> dict:
        """``{name: value}`` in the order of :data:`DISTORTION_NAMES` (as ``dataclasses.asdict``, without its deep copies)."""
        return {n: getattr(self, n) for n in DISTORTION_NAMES}


def _short(v) -> str:
    """``repr(v)``, cut to 40 characters."""
    r = repr(v)
    return r if len(r) <= 40 else r[:37] + "..."


def _is_count(v, hi: int) -> bool:
    """``v`` is a whole number 0..hi (an int, or a float with no fraction; not a bool)."""
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
        return False
    return bool(0 <= v <= hi and float(v).is_integer())


@dataclass(frozen=True)
class ModelSpec:
    """Which parameters a calibration estimates (the model switches).

    Attributes
    ----------
    radial : int
        Number of lens radial terms k1..k3 (0-3).
    tangential : bool
        Estimate p1, p2.
    psd_radial : int
        Number of PSD radial terms l1, l2 (0-2).
    skew : bool
        Estimate the skew.
    aspect : bool
        Estimate a separate vertical focal length fy (general intrinsic matrix).
    fit_gains : bool
        Estimate three relative channel gains with the geometry (needs raw amplitudes).
    """

    radial: int = 2
    tangential: bool = True
    psd_radial: int = 0
    skew: bool = False
    aspect: bool = False
    fit_gains: bool = False

    def __post_init__(self):
        from psdcal.errors import InputError

        # an error a user can cause (psdcal.calibrate(radial=4), a calibration JSON's 'model'): InputError
        for name, hi in (("radial", 3), ("psd_radial", 2)):
            v = getattr(self, name)
            if not _is_count(v, hi):
                raise InputError(f"{name} must be an integer 0..{hi}, got {_short(v)}", field=name)
            object.__setattr__(self, name, int(v))
        for name in ("tangential", "skew", "aspect", "fit_gains"):
            v = getattr(self, name)
            if not (isinstance(v, (bool, np.bool_)) or (isinstance(v, (int, np.integer)) and v in (0, 1))):
                raise InputError(f"{name} must be true or false, got {_short(v)}", field=name)
            object.__setattr__(self, name, bool(v))

    @cached_attribute
    def intrinsic_names(self) -> tuple[str, ...]:
        names = ["f_mm", "cx_mm", "cy_mm"]
        if self.skew:
            names.append("skew")
        if self.aspect:
            names.append("fy_mm")
        return tuple(names)

    @cached_attribute
    def distortion_names(self) -> tuple[str, ...]:
        names = [f"k{i + 1}" for i in range(self.radial)]
        if self.tangential:
            names += ["p1", "p2"]
        names += [f"l{i + 1}" for i in range(self.psd_radial)]
        return tuple(names)

    @cached_attribute
    def gain_names(self) -> tuple[str, ...]:
        return ("g_x2", "g_y1", "g_y2") if self.fit_gains else ()

    @cached_attribute
    def global_names(self) -> tuple[str, ...]:
        """Names of the free parameters shared by all images, in state order."""
        return self.intrinsic_names + self.distortion_names + self.gain_names

    def to_dict(self) -> dict:
        """The six switches by name (as ``dataclasses.asdict``, without its deep copies)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class Pose:
    """Pose of the template in the sensor frame: ``Pc = R(rvec) P + tvec_mm``."""

    rvec: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tvec_mm: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1000.0]))
