"""The calibration's stages use memory linear in the number of points.

Real templates can carry hundreds of points per view (Zhang's data: 256), so
no stage may build anything of size (points x points). Memory is measured
with :mod:`tracemalloc` (numpy reports its array buffers to it), which is
deterministic where timings on a shared machine are not.
"""
from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from psdcal.calibration._homography import homographies
from psdcal.model.params import Intrinsics
from psdcal.model.projection import project

def _views(n_points: int):
    """Template (n_points, 2) and its exact images in two views (2, n_points, 2)."""
    rng = np.random.default_rng(0)
    src = rng.uniform(-100.0, 100.0, (n_points, 2))
    intr = Intrinsics(f_mm=8.0)
    poses = [(np.array([0.1, 0.2, 0.0]), np.array([0.0, 0.0, 500.0])), (np.array([-0.2, 0.1, 0.3]), np.array([5.0, 0.0, 600.0]))]
    dst = np.stack([project(src, intr, r, t) for r, t in poses])
    return src, dst


def _peak_mb(fn) -> float:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1] / 1e6
    finally:
        tracemalloc.stop()


def test_batched_dlt_memory_is_linear_in_points():
    src, dst = _views(2000)
    H = homographies(src, dst)
    assert H.shape == (2, 3, 3)
    # the DLT matrix itself is 2 x 4000 x 9 doubles = 0.6 MB; a (4000 x 4000) U per view is 256 MB
    assert _peak_mb(lambda: homographies(src, dst)) < 20.0


def test_verdict_memory_is_linear_in_views(monkeypatch):
    """The verdict works from the compact block Jacobian: no (points x all poses) matrix.

    With the compiled kernels (the library's default; an in-process `psdcal calibrate` of an
    earlier test leaves the "auto" mode, where problems this small take the numpy reference path,
    whose Jacobian is dense)."""
    from psdcal import _jit
    from psdcal.calibration.core import calibrate, with_verdict
    from psdcal.study.simulate import simulate_set

    if not _jit.AVAILABLE:
        pytest.skip("numba is not installed")
    monkeypatch.setattr(_jit, "_MODE", "always")

    peaks = []
    for n in (50, 200):
        s = simulate_set("lens2", n_images=n, noise_mm=0.002, seed=0)
        r = calibrate(s.template_mm, s.points_mm, verdict=False)
        peaks.append(_peak_mb(lambda: with_verdict(r, diagnose=False)))
    # a dense Jacobian would be 2 x 14 n rows x 6 n columns: 0.5 MB -> 54 MB (x 100); linear is x 4
    assert peaks[1] < 6.0 * peaks[0] + 1.0, peaks
