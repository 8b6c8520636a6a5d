"""Simulated sensors and recordings with known truth, for the locate tests (now in the package)."""
from psdcal.study.recordings import BASE, NAMES, STD, amplitudes, calib_dict, model, signals, spot_for_angles  # noqa: F401
