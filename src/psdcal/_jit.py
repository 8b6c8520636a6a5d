"""Compiled inner loops (numba), with the numpy code as the reference.

The model is evaluated on a few hundred points per LM iteration; in numpy
that is some 300 small array operations, whose per-call overhead, not the
arithmetic, dominates a calibration. The hot loops (the image cost's
residuals and Jacobian with the Newton inverse of the distortion, the
line-straightness cost) are therefore also written as scalar loops compiled
by numba. The numpy functions stay the documented, tested reference; the
compiled ones are checked against them in the tests.

``PSDCAL_JIT=0`` in the environment (or numba missing) selects the numpy
code everywhere. Compiled functions are cached on disk (``cache=True``):
the first calibration on a machine compiles them (a few seconds), later
processes load them. Where no cache can be written (a read-only install
run by a user without a writable home), the functions are compiled in
memory for each process instead: slower to start, never a crash.
"""
from __future__ import annotations

import os

_WANTED = os.environ.get("PSDCAL_JIT", "1").strip().lower() not in ("0", "false", "no", "off")

try:  # numba is a dependency, but the package still works (slower) without it
    if not _WANTED:
        raise ImportError("disabled by PSDCAL_JIT")
    import numba as _numba

    AVAILABLE = True
except ImportError:  # pragma: no cover - exercised with PSDCAL_JIT=0
    _numba = None
    AVAILABLE = False


def enabled() -> bool:
    """True when the compiled kernels are used (numba importable and not disabled)."""
    return AVAILABLE


def njit(fn):
    """Compile ``fn`` lazily with numba (no Python objects, cached on disk); identity without numba."""
    if _numba is None:
        return fn
    try:
        return _numba.njit(cache=True, nogil=True, error_model="numpy")(fn)
    except (RuntimeError, OSError):  # numba: "cannot cache function ...: no locator available"
        return _numba.njit(cache=False, nogil=True, error_model="numpy")(fn)
