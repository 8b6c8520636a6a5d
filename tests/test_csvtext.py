"""The compiled CSV writer (psdcal.measure._csvtext) against Python's own ``%`` formatting, byte for byte."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from psdcal import _jit
from psdcal.measure._csvtext import rows_text, rows_text_reference

pytestmark = pytest.mark.skipif(not _jit.enabled(), reason="the compiled writer needs numba")


def _same(cols):
    fast, ref = rows_text(cols), rows_text_reference(cols)
    if fast != ref:  # name the first differing row
        for a, b in zip(fast.splitlines(), ref.splitlines()):
            assert a == b
    assert fast == ref


def test_random_doubles_of_every_exponent_and_bit_pattern():
    rng = np.random.default_rng(0)
    n = 60_000
    bits = rng.integers(0, 2**63, n, dtype=np.int64) * rng.choice([1, -1], n)
    _same([
        rng.standard_normal(n) * 10.0 ** rng.integers(-40, 40, n),  # every decimal exponent near the range used
        np.frombuffer(bits.tobytes(), dtype=np.float64),  # any double: subnormals, 1e+308, NaN payloads
        np.round(rng.standard_normal(n) * 1e6) / 1e3,  # short decimals: trailing zeros dropped
        rng.uniform(-1e-4, 1e-4, n),  # the switch to exponent notation (1e-05)
        rng.uniform(1e9, 2e10, n),  # and above 10 digits (e+10)
    ])


def test_edges_and_rounding_ties():
    special = [0.0, -0.0, np.nan, -np.nan, np.inf, -np.inf, 5e-324, -5e-324, 2.2250738585072014e-308,
               1.7976931348623157e308, 1e-300, 1e300, 1e-280, 1e290, 1e-5, 1e-4, 9.99999999949e-5, 9.99999999951e-5,
               0.1, 0.2, 0.3, 1.0, 10.0, 100.0, 1e9, 1e10, 1e15, 1e16, 1e22, 1e23, 1e-22, 1e-23,
               9999999999.0, 9999999999.4, 9999999999.5, 9999999999.6, 999999999.5, 99999999995.0, 0.5, 1.5, 2.5]
    # exact ties at the 11th digit (round half to even): integers and binary fractions with 11 digits
    ties = [12345678905.0, 12345678915.0, 10000000005.0, 99999999995.0, 1.0000000005, 2.0000000005,
            0.12345678905, 1234567.89055, 0.000152587890625, 1.52587890625e-05, 3.0517578125e-05]
    k = np.arange(1, 2000, dtype=np.float64)
    near_ties = np.concatenate([(k * 10 + 5) * 10.0 ** e for e in (-12, -5, 0, 3, 8)])
    halves = np.ldexp(np.arange(1, 4000, 2, dtype=np.float64), -np.arange(1, 4000, 2) % 40)  # exact binary fractions
    vals = np.array(special + ties + [np.nextafter(t, np.inf) for t in ties] + [np.nextafter(t, -np.inf) for t in ties])
    _same([vals, -vals])
    _same([near_ties, np.resize(halves, len(near_ties))])


def test_integers_booleans_text_and_other_dtypes():
    n = 1000
    rng = np.random.default_rng(1)
    ints = np.array([np.iinfo(np.int64).min, np.iinfo(np.int64).max, 0, -1, 7, -10**12] * (n // 6 + 1))[:n]
    names = np.array(["1000Hz", "1300Hz", "émetteur 3", "a,b"] * (n // 4), dtype=object)
    _same([rng.standard_normal(n), names, ints, rng.random(n) > 0.5, rng.integers(0, 255, n).astype(np.uint8),
           rng.standard_normal(n).astype(np.float32), np.array([f"p{i}" for i in range(n)]), np.arange(n)])
    # an object column that is not all text (1 and 1.0 must stay "1" and "1.0"): Python's formatting
    _same([np.array([1, 1.0, "x", None] * 5, dtype=object), np.arange(20.0)])
    assert rows_text([np.zeros(0), np.zeros(0, dtype=object)]) == ""


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=1, max_size=40),
       st.integers(min_value=-2**63, max_value=2**63 - 1))
def test_any_double_hypothesis(xs, i):
    a = np.array(xs, dtype=np.float64)
    _same([a, np.full(a.shape, i, dtype=np.int64), np.array(["e"] * len(a), dtype=object), a[::-1].copy()])


def test_text_arrays_of_few_and_many_distinct_values():
    """Text arrays (numpy ``str``, as locate's emitter column) coded by vectorised comparisons: one, two,
    three, 16 and 17 distinct values in any order, empty and non-ASCII text, next to object text."""
    rng = np.random.default_rng(3)
    n = 700
    names = ["1000Hz", "1300Hz", "", "émetteur 3", "a,b"] + [f"e{i}" for i in range(12)]
    for k in (1, 2, 3, 16, 17):
        col = np.array(names[:k])[rng.integers(0, k, n)]
        _same([rng.standard_normal(n), col, np.arange(n)])
        _same([col, col[::-1].copy(), np.array(list(col), dtype=object), rng.standard_normal(n)])
