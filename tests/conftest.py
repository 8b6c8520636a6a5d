import os

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

# CI is deterministic (derandomize); local runs explore new examples each time.
settings.register_profile("ci", max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("dev", max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("ci" if os.environ.get("CI") else "dev")


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(autouse=True)
def _restore_jit_mode():
    """A command run in-process sets psdcal._jit's mode for its one-shot run ("auto"): not for the next test."""
    from psdcal import _jit

    mode = _jit._MODE
    yield
    _jit._MODE = mode
