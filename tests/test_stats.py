"""psdcal._stats (chi-squared and F tails without scipy) against scipy.special, an independent implementation."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import special

from psdcal import _stats


@settings(max_examples=300, deadline=None)
@given(k=st.floats(0.5, 5000), q=st.floats(1e-6, 0.999999))
def test_chi2_sf_matches_scipy(k, q):
    x = float(special.chdtri(k, q))  # a point where the true tail probability is q
    assert _stats.chi2_sf(x, k) == pytest.approx(float(special.chdtrc(k, x)), rel=1e-9, abs=1e-300)


@settings(max_examples=300, deadline=None)
@given(d1=st.floats(0.5, 2000), d2=st.floats(0.5, 20000), q=st.floats(1e-6, 0.999999))
def test_f_sf_matches_scipy(d1, d2, q):
    x = float(special.fdtri(d1, d2, 1.0 - q))
    assert _stats.f_sf(x, d1, d2) == pytest.approx(float(special.fdtrc(d1, d2, x)), rel=1e-9, abs=1e-300)


@pytest.mark.parametrize("alpha", [1e-12, 1e-6, 1e-3, 0.05, 0.5, 0.9])
@pytest.mark.parametrize("k", [1, 2, 7, 30, 300, 3000])
def test_chi2_isf_matches_scipy(alpha, k):
    assert _stats.chi2_isf(alpha, k) == pytest.approx(float(special.chdtri(k, alpha)), rel=1e-9)


@pytest.mark.parametrize("alpha", [1e-12, 1e-6, 1e-3, 0.05, 0.5])
@pytest.mark.parametrize("d1,d2", [(1, 1), (1, 50), (4, 300), (30, 30), (50, 2000), (300, 5)])
def test_f_isf_matches_scipy(alpha, d1, d2):
    # scipy's fdtri takes 1 - alpha, which loses digits for small alpha: check through its fdtrc instead
    x = _stats.f_isf(alpha, d1, d2)
    assert float(special.fdtrc(d1, d2, x)) == pytest.approx(alpha, rel=1e-9)
    if alpha >= 1e-6:
        assert x == pytest.approx(float(special.fdtri(d1, d2, 1 - alpha)), rel=1e-8)


def test_closed_forms_and_edges():
    # chi2 with 2 dof: sf = exp(-x/2); F(2, 2): sf = 1 / (1 + x)
    for x in (0.0, 0.1, 3.0, 40.0, 700.0):
        assert _stats.chi2_sf(x, 2) == pytest.approx(math.exp(-x / 2), rel=1e-12)
        assert _stats.f_sf(x, 2, 2) == pytest.approx(1 / (1 + x), rel=1e-12)
    assert _stats.f_sf(math.inf, 3, 4) == 0.0 and _stats.chi2_sf(-1.0, 3) == 1.0
    with pytest.raises(ValueError):
        _stats.chi2_sf(1.0, 0)
    with pytest.raises(ValueError):
        _stats.f_isf(1.5, 1, 1)
    assert np.isfinite(_stats.chi2_isf(1e-12, 1))
