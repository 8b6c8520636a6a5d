"""Compiled inner loops (numba), with the numpy code as the reference.

The model is evaluated on a few hundred points per LM iteration; in numpy
that is some 300 small array operations, whose per-call overhead, not the
arithmetic, dominates a calibration. The hot loops (the image cost's
residuals and Jacobian with the Newton inverse of the distortion, the
block normal equations and their Schur complement, the line-straightness
cost) are therefore also written as scalar loops compiled by numba. The
numpy functions stay the documented, tested reference; the compiled ones are
checked against them in the tests.

``PSDCAL_JIT=0`` in the environment (or numba missing) selects the numpy
code everywhere. Compiled functions are cached on disk (``cache=True``):
the first calibration on a machine compiles them (some seconds; ``python3
tasks.py`` does it once during the set-up, see :func:`psdcal.study.warmup.warm_up`), later
processes load them.

numba is imported only when a compiled kernel is first needed (importing it
and loading the kernels costs some 0.4 s per process). :func:`set_mode`
``("auto")``, used by the command line for its one-shot runs, keeps small
problems on the numpy path, where a whole calibration costs less than that
loading; the library's default (``"always"``) compiles whenever it can.
Where no cache can be written (a read-only install run by a user without a
writable home), the functions are compiled in memory for each process
instead: slower to start, never a crash.
"""
from __future__ import annotations

import importlib.util
import os
import sys

_WANTED = os.environ.get("PSDCAL_JIT", "1").strip().lower() not in ("0", "false", "no", "off")

#: numba is installed and not disabled (checked without importing it)
AVAILABLE = bool(_WANTED and importlib.util.find_spec("numba") is not None)

_numba = None
_MODE = "always"

#: In ``"auto"`` mode, problems with fewer observations than this run on the numpy path
#: (unless the kernels are already loaded in this process).
AUTO_MIN_OBSERVATIONS = 3000


def _load_numba():
    global _numba
    if _numba is None:
        import numba

        _numba = numba
    return _numba


def enabled() -> bool:
    """True when the compiled kernels can be used (numba installed and not disabled)."""
    return AVAILABLE


def set_mode(mode: str) -> None:
    """``"always"``: compiled kernels whenever available (default); ``"auto"``: only for
    problems large enough to pay for loading them, or once they are loaded."""
    global _MODE
    if mode not in ("always", "auto"):
        raise ValueError(f"mode must be 'always' or 'auto', got {mode!r}")
    _MODE = mode


def use_compiled(n_observations: int) -> bool:
    """Whether a problem of ``n_observations`` points should use the compiled kernels."""
    if not AVAILABLE:
        return False
    if _MODE == "always":
        return True
    return n_observations >= AUTO_MIN_OBSERVATIONS or "psdcal.calibration._image_kernel" in sys.modules


def njit(fn):
    """Compile ``fn`` with numba (no Python objects, cached on disk); identity without numba.

    numba is imported here, when the module defining the kernel is imported:
    keep such modules out of the import path of light commands.
    """
    return _compile(fn)


def njit_inline(fn):
    """As :func:`njit` for a helper that compiled kernels call: inlined into them (numba's
    ``inline="always"``), so no per-call passing of its array arguments."""
    return _compile(fn, inline="always")


def _compile(fn, **options):
    """``numba.njit`` of ``fn`` with the project's settings (and ``options``); ``fn`` itself without numba."""
    if not AVAILABLE:
        return fn
    numba = _load_numba()
    try:
        return numba.njit(cache=True, nogil=True, error_model="numpy", **options)(fn)
    except (RuntimeError, OSError):  # numba: "cannot cache function ...: no locator available"
        return numba.njit(cache=False, nogil=True, error_model="numpy", **options)(fn)


class _Lazy:
    """A kernel compiled on its first call (numba imported then)."""

    def __init__(self, fn):
        self.py_func = fn
        self._compiled = None
        self.__doc__ = fn.__doc__
        self.__name__ = fn.__name__
        self.__wrapped__ = fn

    def __call__(self, *args):
        if self._compiled is None:
            self._compiled = njit(self.py_func)
        return self._compiled(*args)


def lazy_njit(fn):
    """As :func:`njit`, but numba is imported and the kernel loaded at its first call.

    For kernels called from Python only (a compiled function cannot call it).
    """
    if not AVAILABLE:
        return fn
    return _Lazy(fn)


def cache_is_warm() -> bool:
    """Whether the compiled image-cost kernel of this source is in numba's disk cache.

    A cheap check without importing numba: the index file numba names after the
    kernel's first line (``_image_kernel.image_model-<line>.py<ver>.nbi``), newer
    than the source file, in ``NUMBA_CACHE_DIR`` or next to the module.
    """
    from pathlib import Path

    src = Path(__file__).resolve().parent / "calibration" / "_image_kernel.py"
    try:
        lines = src.read_text(encoding="utf-8").splitlines()
        line = next(k for k, t in enumerate(lines, start=1) if t.startswith("def image_model(")) - 1  # the decorator
        src_mtime = src.stat().st_mtime
    except (OSError, StopIteration):
        return False
    name = f"_image_kernel.image_model-{line}.py{sys.version_info[0]}{sys.version_info[1]}.nbi"
    places = [Path(os.environ["NUMBA_CACHE_DIR"])] if os.environ.get("NUMBA_CACHE_DIR") else [src.parent / "__pycache__"]
    for p in places:
        try:
            if any(f.stat().st_mtime >= src_mtime for f in p.rglob(name)):
                return True
        except OSError:
            continue
    return False
