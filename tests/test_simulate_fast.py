"""The batched pose sampler against its one-candidate-at-a-time reference (psdcal.study.simulate)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from psdcal.errors import InputError
from psdcal.study.simulate import LENSES, PAPER_L1, _random_poses_reference, default_template, random_poses


@pytest.mark.parametrize("lens", ["lens1", "lens2"])
@pytest.mark.parametrize("l1", [0.0, PAPER_L1])
def test_random_poses_equal_the_reference_and_leave_the_generator_alike(lens, l1):
    """Same poses, bit for bit, and the generator in the same state afterwards (the noise that follows is the same)."""
    intr, dist = LENSES[lens]
    dist = replace(dist, l1=l1)
    T = default_template()
    for seed in range(12):
        g_fast, g_ref = np.random.default_rng(seed), np.random.default_rng(seed)
        n = 1 + seed % 12
        r_fast, t_fast = random_poses(T, intr, dist, n, g_fast)
        r_ref, t_ref = _random_poses_reference(T, intr, dist, n, g_ref)
        assert np.array_equal(r_fast, r_ref) and np.array_equal(t_fast, t_ref)
        assert g_fast.bit_generator.state == g_ref.bit_generator.state


def test_random_poses_options_and_failure_match_the_reference():
    intr, dist = LENSES["lens2"]
    T = default_template()
    kw = dict(max_tilt_deg=50.0, fill=(0.3, 0.6), margin_mm=0.5)
    a = random_poses(T, intr, dist, 7, np.random.default_rng(5), **kw)
    b = _random_poses_reference(T, intr, dist, 7, np.random.default_rng(5), **kw)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    # impossible placement (template larger than the sensor): both give up with an InputError
    for fn in (random_poses, _random_poses_reference):
        with pytest.raises(InputError):
            fn(T * 100, intr, dist, 3, np.random.default_rng(0), fill=(2.0, 2.1), max_tries=50)
