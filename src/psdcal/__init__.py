"""psdcal: model, calibration and measurement toolkit for PSD + lens AoA sensors.

The reference model is Rodriguez-Navarro et al., Sensors 2016, 16(9), 1484,
with the conventions and corrections of ``docs/model.md``.

The public API, importable from ``psdcal`` itself (``psdcal.__all__``).
Everything but the errors is loaded on first use (``__version__`` too), so
``import psdcal`` stays light (no numpy, matplotlib, scipy, numba or click).

Calibration
    ``calibrate`` (the validating front door), ``CalibrationResult``,
    ``initial_estimate`` (the linear stage alone), ``recalibrate`` (re-run a
    calibration JSON's problem record).
Model (plain functions over arrays; docs/model.md)
    ``impact_point`` and ``photocurrents`` (Eq 1-2 and their inverse),
    ``undistort`` and ``distort`` (Eq 7-16 and their numerical inverse),
    ``project`` (Eq 3-4); parameter records ``Intrinsics``, ``Distortion``,
    ``ModelSpec``, ``Pose``.
Files
    ``read_template``, ``read_points``, ``load_calibration``,
    ``save_calibration`` (docs/model.md#file-formats).
Measurement
    ``SensorModel`` (a calibration as the measuring side needs it),
    ``angles_from_points``, ``angles_from_amplitudes`` (angles of arrival with
    their covariance), ``plane_position``, ``triangulate``.
Studies and reports
    ``simulate_set`` (synthetic views with known truth), ``run_trials``,
    ``TrialTable`` (seeded Monte Carlo), ``compare`` (two calibrations),
    ``build_report``, ``write_report`` (the HTML report).
Errors
    ``PsdcalError`` and its subclasses ``InputError``, ``DegenerateViewsError``,
    ``ZeroSignalError``, ``ConvergenceError``.

Sub-packages follow the data flow ``model`` -> ``calibration`` -> ``signal``
-> ``measure`` -> ``study`` -> ``report``; the command line is ``psdcal.cli``.
"""
from __future__ import annotations

from importlib import import_module

from psdcal.errors import ConvergenceError, DegenerateViewsError, InputError, PsdcalError, ZeroSignalError

#: Lazily imported public names -> the module that defines them.
_LAZY = {
    "Intrinsics": "psdcal.model.params",
    "Distortion": "psdcal.model.params",
    "ModelSpec": "psdcal.model.params",
    "Pose": "psdcal.model.params",
    "calibrate": "psdcal.calibration.core",
    "CalibrationResult": "psdcal.calibration.core",
    "initial_estimate": "psdcal.calibration.core",
    "recalibrate": "psdcal.calibration.core",
    "impact_point": "psdcal.model.readout",
    "photocurrents": "psdcal.model.readout",
    "undistort": "psdcal.model.distortion",
    "distort": "psdcal.model.distortion",
    "project": "psdcal.model.projection",
    "read_template": "psdcal.io",
    "read_points": "psdcal.io",
    "load_calibration": "psdcal.io",
    "save_calibration": "psdcal.io",
    "SensorModel": "psdcal.measure.sensor_model",
    "angles_from_points": "psdcal.measure.aoa",
    "angles_from_amplitudes": "psdcal.measure.aoa",
    "plane_position": "psdcal.measure.positioning",
    "triangulate": "psdcal.measure.positioning",
    "simulate_set": "psdcal.study.simulate",
    "run_trials": "psdcal.study.montecarlo",
    "TrialTable": "psdcal.study.montecarlo",
    "compare": "psdcal.report.compare",
    "build_report": "psdcal.report.page",
    "write_report": "psdcal.report.page",
}


def _package_version() -> str:
    v = _dist_info_version()
    if v is not None:
        return v
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("psdcal")
    except PackageNotFoundError:  # pragma: no cover
        return "0.0.0+unknown"


def _dist_info_version() -> str | None:
    """The ``Version:`` of the first ``psdcal-*.dist-info/METADATA`` on ``sys.path`` (where importlib.metadata finds
    it) without importing importlib.metadata (some 30 ms of a fresh process); None when the first psdcal metadata on
    the path is anything else (an egg-info, a zip), for importlib.metadata to read."""
    import os
    import sys

    for entry in sys.path:
        base = entry or "."
        try:
            names = os.listdir(base)
        except OSError:
            continue
        for n in names:
            low = n.lower()
            if not low.startswith("psdcal-"):
                continue
            if not low.endswith(".dist-info"):
                if low.endswith(".egg-info"):
                    return None
                continue
            try:
                with open(os.path.join(base, n, "METADATA"), encoding="utf-8") as fh:
                    for line in fh:
                        if line.startswith("Version:"):
                            return line.split(":", 1)[1].strip()
                        if not line.strip():  # end of the headers
                            break
            except OSError:
                pass
            return None
    return None


def __getattr__(name: str):
    if name == "__version__":  # read from the installed metadata on first use (importlib.metadata is not light)
        globals()[name] = value = _package_version()
        return value
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'psdcal' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "__version__",
    # errors
    "PsdcalError",
    "InputError",
    "DegenerateViewsError",
    "ZeroSignalError",
    "ConvergenceError",
    # lazily loaded: the parameter records, then the rest
    *_LAZY,
]
