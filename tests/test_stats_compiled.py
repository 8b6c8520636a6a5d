"""The incomplete beta's and gamma's loops compiled (psdcal._stats, used once numba is loaded) against the Python
loops they compile: the same operations in the same order, so the same numbers to the bit."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from psdcal import _jit, _stats

pytestmark = pytest.mark.skipif(not _jit.AVAILABLE, reason="numba not available")


def _compiled(name: str = "_beta_fraction"):
    f = getattr(_stats, name + "_compiled")
    return f.compiled() if hasattr(f, "compiled") else f


def _same(a: float, b: float) -> bool:
    return a == b or (math.isnan(a) and math.isnan(b))


@settings(max_examples=300, deadline=None)
@given(st.floats(0.05, 5e4), st.floats(0.05, 5e4), st.floats(0.0, 1.0))
def test_compiled_fraction_is_the_python_loop(a, b, x):
    assert _same(_compiled()(a, b, x), _stats._beta_fraction(a, b, x))


def test_f_tails_and_critical_values_are_the_same_with_and_without_the_compiled_fraction(monkeypatch):
    """3000 F tails over the verdict's degrees of freedom (1-600 by 20-5000) and 20 critical values: bit-identical,
    and the compiled fraction is the one taken when numba is loaded."""
    rng = np.random.default_rng(3)
    args = [(float(rng.uniform(0.0, 12.0)), float(rng.integers(1, 600)), float(rng.integers(20, 5000)))
            for _ in range(3000)]
    args += [(float(rng.uniform(0.0, 12.0)), float(rng.uniform(0.5, 700.0)), float(rng.uniform(5.0, 3000.0)))
             for _ in range(500)]
    _compiled()  # numba loaded: f_sf takes the compiled fraction
    assert _jit.loaded()
    monkeypatch.setattr(_stats, "COMPILED_AFTER", 0)
    calls = []
    real = _stats._beta_fraction_compiled
    monkeypatch.setattr(_stats, "_beta_fraction_compiled", lambda *a: calls.append(a) or real(*a))
    fast = [_stats.f_sf(*a) for a in args]
    crit = [_stats.f_isf(1e-3, d1, d2) for d1, d2 in ((14, 2508), (1, 2521), (2, 2520), (9.7, 2512), (40, 100))]
    assert len(calls) >= len(args)
    monkeypatch.setattr(_stats, "_beta_fraction_compiled", _stats._beta_fraction)
    monkeypatch.setattr(_jit, "loaded", lambda: False)
    slow = [_stats.f_sf(*a) for a in args]
    crit_slow = [_stats.f_isf(1e-3, d1, d2) for d1, d2 in ((14, 2508), (1, 2521), (2, 2520), (9.7, 2512), (40, 100))]
    assert all(_same(p, q) for p, q in zip(fast, slow))
    assert crit == crit_slow


@settings(max_examples=300, deadline=None)
@given(st.floats(0.05, 2e4), st.floats(0.0, 3.0))
def test_compiled_gamma_loops_are_the_python_loops(a, t):
    x = a * t
    if x < a + 1.0:
        assert _same(_compiled("_gamma_p_sum")(a, x), _stats._gamma_p_sum(a, x))
    else:
        assert _same(_compiled("_gamma_fraction")(a, x), _stats._gamma_fraction(a, x))


def test_chi2_tails_and_critical_values_are_the_same_with_and_without_the_compiled_loops(monkeypatch):
    """4000 chi-squared tails (1-6000 dof, both sides of the series/fraction switch) and 5 critical values."""
    rng = np.random.default_rng(5)
    args = [(float(rng.uniform(0.0, 3.0)) * k, float(k)) for k in rng.integers(1, 6000, 3000)]
    args += [(float(rng.uniform(0.0, 60.0)), float(rng.uniform(0.5, 40.0))) for _ in range(1000)]
    dofs = (1, 2, 14, 2520, 40000)
    _compiled("_gamma_p_sum"), _compiled("_gamma_fraction")
    assert _jit.loaded()
    monkeypatch.setattr(_stats, "COMPILED_AFTER", 0)
    fast = [_stats.chi2_sf(x, k) for x, k in args]
    crit = [_stats.chi2_isf(1e-3, k) for k in dofs]
    monkeypatch.setattr(_jit, "loaded", lambda: False)
    assert all(_same(p, _stats.chi2_sf(x, k)) for p, (x, k) in zip(fast, args))
    assert crit == [_stats.chi2_isf(1e-3, k) for k in dofs]
    assert _stats.chi2_sf(2.0, 2) == pytest.approx(math.exp(-1.0), rel=1e-14)


def test_the_first_tails_of_a_process_take_the_python_loops(monkeypatch):
    """A one-shot command's dozen tails never load the compiled loops; from COMPILED_AFTER tails on they are used
    (numba loaded)."""
    _compiled()
    calls = []
    real = _stats._beta_fraction_compiled
    monkeypatch.setattr(_stats, "_beta_fraction_compiled", lambda *a: calls.append(a) or real(*a))
    monkeypatch.setattr(_stats, "COMPILED_AFTER", 5)
    monkeypatch.setattr(_stats, "_n_tails", 0)
    p = [_stats.f_sf(2.0, 14.0, 2508.0) for _ in range(8)]
    assert len(calls) == 3 and len(set(p)) == 1
