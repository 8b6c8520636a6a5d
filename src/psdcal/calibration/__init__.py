"""Calibration: the adapted Zhang method and what checks and extends it.

- :mod:`psdcal.calibration.core`: the validating front door ``calibrate``, ``CalibrationResult``,
  ``initial_estimate`` (the whole linear stage) and ``recalibrate``.
- private steps, each usable alone: ``_straightness`` (line straightness, Section 3.2),
  ``_homography`` (normalised DLT, Eq 17-18, 36-38), ``_closed_form`` (Eq 19-28),
  ``_refine`` (Levenberg-Marquardt, Eq 29 and the image-plane cost), ``_image_kernel`` (compiled kernels).
- :mod:`psdcal.calibration.gains`: the gain homography, electrical calibration and gain identifiability.
- :mod:`psdcal.calibration.outliers`, :mod:`psdcal.calibration.checks`: residual diagnostics.

Attributes are loaded lazily so that importing a step module stays light.
"""
from __future__ import annotations

_CORE = {"calibrate", "CalibrationResult", "InitialEstimate", "initial_estimate", "recalibrate", "implausible"}


def __getattr__(name):
    if name in _CORE:
        from psdcal.calibration import core

        return getattr(core, name)
    raise AttributeError(f"module 'psdcal.calibration' has no attribute {name!r}")


__all__ = sorted(_CORE)
