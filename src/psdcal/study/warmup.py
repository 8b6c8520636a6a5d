"""Compile (or load from the cache) every numerical kernel once, by running each compiled path.

``python3 tasks.py`` calls :func:`warm_up` during the set-up, so that no later
command stalls on compilation. It lives here, above every layer whose kernels
it runs (calibration, measure, study), and not in :mod:`psdcal._jit`, which the
lowest layers import.
"""
from __future__ import annotations

import sys

from psdcal import _jit


#: The parts of :func:`warm_up`, which compile different kernels (``python3 tasks.py`` runs them in
#: parallel processes): the calibration's (the bulk), and the measuring side's (angles, CSV writer).
PARTS = ("calibration", "measure")


def warm_up(verbose: bool = True, part: str | None = None) -> float:
    """Compile (or load) the kernels once by running a small calibration, angles and locate; seconds taken.

    ``part``: one of :data:`PARTS` (None: all of them).
    """
    import time

    t0 = time.perf_counter()
    if part is not None and part not in PARTS:
        raise ValueError(f"part must be one of {PARTS} or None, got {part!r}")
    if not _jit.AVAILABLE:
        return 0.0
    if verbose:
        print("psdcal: compiling the numerical kernels (once per machine and version) ...", file=sys.stderr, flush=True)
    mode = _jit._MODE
    _jit.set_mode("always")  # every kernel, whatever the problems' sizes
    try:
        if part in (None, "calibration"):
            _calibration_kernels()
        if part in (None, "measure"):
            _measure_kernels()
    finally:
        _jit.set_mode(mode)
    dt = time.perf_counter() - t0
    if verbose:
        print(f"psdcal: kernels ready ({dt:.1f} s)", file=sys.stderr, flush=True)
    return dt


def _calibration_kernels() -> None:
    from psdcal.calibration.core import calibrate
    from psdcal.study.simulate import simulate_set

    s = simulate_set("lens2", n_images=6, noise_mm=0.002, seed=0)
    res = None
    for kw in (dict(radial=2, tangential=True), dict(radial=2, tangential=False, cost="template"),
               dict(radial=2, psd_radial=1, aspect=True), dict(radial=2, tangential=False, fit_gains=True)):
        try:
            r = calibrate(s.template_mm, s.points_mm, **kw)
            res = r if res is None else res
        except Exception:  # a warm-up: the kernels are compiled even when a fit fails
            pass
    if res is not None:  # the verdict's angle sensitivities (computed only when a check finds an effect)
        from psdcal.calibration._verdict_linear import angle_jacobians
        from psdcal.model.params import DISTORTION_NAMES

        angle_jacobians(res, s.points_mm[0][:4], ("f_mm", "cx_mm", "cy_mm", "skew", *DISTORTION_NAMES))
    # the p-values' loops (taken after a process's first hundred tails: psdcal._stats.COMPILED_AFTER)
    from psdcal import _stats

    _stats._beta_fraction_compiled(7.0, 0.5, 0.9)
    _stats._gamma_fraction_compiled(3.0, 9.0)
    _stats._gamma_p_sum_compiled(3.0, 1.0)


def _measure_kernels() -> None:
    import numpy as np

    from psdcal.measure.aoa import angles_from_points
    from psdcal.measure.sensor_model import SensorModel

    model = SensorModel.from_dict({"intrinsics": {"f_mm": 8.0, "cx_mm": 0.0, "cy_mm": 0.0}})
    angles_from_points(np.zeros((4, 2)), model, np.zeros((4, 2, 2)))
    # locate's lock-in (window sums on writable rows, as read from a file or a stream, and on read-only ones, as
    # a view of a memory map gives them; the per-window arithmetic) and its impact points
    from psdcal.measure._impact_kernel import impact_compiled
    from psdcal.signal.stream import MultiCarrierLockin

    rows = np.zeros((600, 4))
    ro = rows.copy()
    ro.flags.writeable = False
    for r in (rows, ro):
        lk = MultiCarrierLockin(10_000.0, (1000.0,), 0.03, compiled=True)
        lk.windows(*lk.fit_rows(0.0, r))
    impact_compiled(np.ones((2, 4)), np.ones(4), np.zeros((2, 4)), 9.0, 9.0)
    from psdcal.measure.channel_order import SumCheck

    SumCheck(np.ones(4), 9.0).add(np.ones((2, 4)), np.ones((2, 4)), compiled=True)
    from psdcal.measure._csvtext import rows_text  # locate's CSV writer

    rows_text([np.zeros(2), np.array(["a", "b"], dtype=object), np.arange(2)])


__all__ = ["PARTS", "warm_up"]
