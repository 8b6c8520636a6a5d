"""A simulated set with chosen views made degenerate, for the tests of the homographies' errors."""
from __future__ import annotations

import numpy as np

from psdcal.study.simulate import simulate_set


def spoilt_set(spoil: dict):
    """``(T, points_mm)`` of 6 Lens-2 views with view ``i`` spoilt as ``spoil[i]`` says.

    ``"few"``: 3 points left; ``"none"``: no point; ``"line"``: only a row of the
    template (collinear on the plate and on the sensor); ``"line-template"``: every
    point on one line of the sensor; ``"rank"``: 4 points, 3 of them exactly on a
    line (not collinear, yet no unique homography).
    """
    s = simulate_set("lens2", n_images=6, noise_mm=0.002, seed=5)
    T, pts = s.template_mm, s.points_mm.copy()
    line = np.array([0, 1, 2, 3, 4])  # a row of the template
    for i, how in spoil.items():
        if how == "few":
            pts[i, 3:] = np.nan
        elif how == "none":
            pts[i] = np.nan
        elif how == "line":
            keep = np.zeros(T.shape[0], bool)
            keep[line] = True
            pts[i, ~keep] = np.nan
        elif how == "line-template":
            pts[i] = np.outer(np.linspace(-2, 2, T.shape[0]), [1.0, 0.5])
        elif how == "rank":
            pts[i] = np.nan
            pts[i, [0, 1, 2, 5]] = 0.05 * T[[0, 1, 2, 5]]
        else:
            raise ValueError(how)
    return T, pts
