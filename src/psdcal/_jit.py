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
and loading the kernels costs some 0.5-0.7 s per process); modules whose kernels
are declared with :func:`deferred_njit` do not import it at all until one is
called. :func:`set_mode` ``("auto")``, used by the command line for its
one-shot runs (``calibrate`` and ``demo``; ``locate``, ``amplitudes``,
``aoa``, ``errormap`` and ``pose`` on files, see :func:`set_mode_for`), keeps
small problems on the numpy path, where the whole work costs less than that
loading; the library's default (``"always"``) compiles whenever it can, and
so do the live paths.
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
#: In ``"auto"`` mode (unless numba is already loaded), fewer impact points than this get their
#: angles from the numpy code, and fewer rows than :data:`AUTO_MIN_CSV_ROWS` are written as CSV by
#: Python's formatting: importing numba and loading the kernels costs a fresh process some 0.5-0.7 s
#: of CPU, what the numpy code takes for some 500,000 points or 400,000 rows (numpy 1.0-1.2 us a
#: point with its covariance, 0.08-0.1 us compiled; CSV 2.2-2.9 us a row of 10 columns, 0.9-1.3
#: us compiled; one run, benchmarks/bench_startup.py). The thresholds are below the break-even:
#: from them on, the compiled path costs at most about the loading more.
AUTO_MIN_ANGLES = 200_000
AUTO_MIN_CSV_ROWS = 200_000


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


def use_compiled(n_observations: int, auto_min: int | None = None) -> bool:
    """Whether a problem of ``n_observations`` points should use the compiled kernels.

    In ``"auto"`` mode: the calibration's kernels (``auto_min`` None) from
    :data:`AUTO_MIN_OBSERVATIONS` observations or once the image-cost kernel's
    module is loaded; other kernels from ``auto_min`` items (their break-even
    size against importing numba and loading the kernels, e.g.
    :data:`AUTO_MIN_ANGLES`) or once numba is loaded in this process.
    """
    if not AVAILABLE:
        return False
    if _MODE == "always":
        return True
    if auto_min is None:
        return n_observations >= AUTO_MIN_OBSERVATIONS or "psdcal.calibration._image_kernel" in sys.modules
    return n_observations >= auto_min or _numba is not None


def set_mode_for(n_items: int | None) -> None:
    """A one-shot command's mode for ``n_items`` angles or rows in all (None: not known).

    ``"auto"`` (numpy for calls below :data:`AUTO_MIN_ANGLES` / :data:`AUTO_MIN_CSV_ROWS`,
    and for the calibration's small problems) when the whole work is below those
    thresholds; else ``"always"``: a long input pays for loading the kernels once,
    whatever the size of the blocks it is processed in.
    """
    small = n_items is not None and n_items < min(AUTO_MIN_ANGLES, AUTO_MIN_CSV_ROWS)
    set_mode("auto" if small else "always")


def loaded() -> bool:
    """Whether numba has been imported by a kernel of this process."""
    return _numba is not None


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


def njit_sum(fn):
    """As :func:`njit` for a kernel of long sums (dot products, Gram matrices): its floating-point additions may
    be reassociated and multiply-adds fused (numba's ``fastmath={"reassoc", "contract"}``, no other fast-math
    assumption: NaN and infinities keep their meaning), so that the compiler can split a sum over several SIMD
    accumulators. The sums then differ from a sequential loop's at rounding level only; keep such kernels to
    sums whose order does not matter beyond rounding, and compare them with their reference to a tolerance."""
    return _compile(fn, fastmath={"reassoc", "contract"})


def _compile(fn, **options):
    """``numba.njit`` of ``fn`` with the project's settings (and ``options``); ``fn`` itself without numba."""
    if not AVAILABLE:
        return fn
    numba = _load_numba()
    options = {"nogil": True, "error_model": "numpy", **options}
    try:
        return numba.njit(cache=True, **options)(fn)
    except (RuntimeError, OSError):  # numba: "cannot cache function ...: no locator available"
        return numba.njit(cache=False, **options)(fn)


class _Lazy:
    """A kernel compiled at its first call (numba imported then); see :func:`deferred_njit`."""

    def __init__(self, fn, options=None):
        self.py_func = fn
        self.options = dict(options or {})
        self._compiled = None
        self.__doc__ = fn.__doc__
        self.__name__ = fn.__name__
        self.__wrapped__ = fn

    def compiled(self):
        """The numba dispatcher (created on first use, with every deferred kernel it can call)."""
        if self._compiled is None:
            self._compiled = _compile(self.py_func, **self.options)
            g = self.py_func.__globals__
            if g.get(self.__name__) is self:
                g[self.__name__] = self._compiled  # compiled callers see the dispatcher, not this wrapper
            for name, value in list(g.items()):  # the deferred helpers it may call (same module or imported)
                if isinstance(value, _Lazy):
                    g[name] = value.compiled()
        return self._compiled

    def __call__(self, *args, **kwargs):
        return (self._compiled or self.compiled())(*args, **kwargs)


def lazy_njit(fn):
    """As :func:`njit`, but numba is imported and the kernel loaded at its first call.

    For kernels called from Python only (a compiled function cannot call it).
    """
    if not AVAILABLE:
        return fn
    return _Lazy(fn)


def deferred_njit(fn):
    """As :func:`njit`, but numba is imported (and the kernel loaded) only when it is first called.

    A module of such kernels costs nothing to import, so a command that takes its
    numpy path never imports numba. At the first call, the kernel and every
    deferred kernel in its module's namespace (:func:`deferred_njit_inline`
    helpers it calls, defined there or imported there) become numba dispatchers
    in that namespace, so compiled code calls compiled code.
    """
    if not AVAILABLE:
        return fn
    if _numba is not None:  # numba already loaded: nothing to save
        return _compile(fn)
    return _Lazy(fn)


def deferred_njit_inline(fn):
    """:func:`njit_inline` deferred like :func:`deferred_njit` (a helper of deferred kernels)."""
    if not AVAILABLE:
        return fn
    if _numba is not None:
        return _compile(fn, inline="always")
    return _Lazy(fn, {"inline": "always"})


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
