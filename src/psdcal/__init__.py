"""psdcal: model, calibration and measurement toolkit for PSD + lens AoA sensors.

The reference model is Rodriguez-Navarro et al., Sensors 2016, 16(9), 1484,
with the conventions and corrections of ``docs/model.md``.
"""
from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("psdcal")
except PackageNotFoundError:  # pragma: no cover
    __version__ = "0.0.0+unknown"

from psdcal.errors import ConvergenceError, DegenerateViewsError, InputError, PsdcalError, ZeroSignalError
from psdcal.model.params import Distortion, Intrinsics, ModelSpec, Pose


def __getattr__(name):
    # Lazy: keeps `import psdcal` (and the CLI's argument parsing) light.
    if name in {"calibrate", "CalibrationResult"}:
        from psdcal.calibration import core as calibration

        return getattr(calibration, name)
    raise AttributeError(f"module 'psdcal' has no attribute {name!r}")


__all__ = [
    "__version__",
    "calibrate",
    "CalibrationResult",
    "ConvergenceError",
    "DegenerateViewsError",
    "Distortion",
    "InputError",
    "Intrinsics",
    "ModelSpec",
    "Pose",
    "PsdcalError",
    "ZeroSignalError",
]
