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


@pytest.fixture(scope="session")
def lens2_radial1_fit():
    """Lens 2 (8 simulated views, 1 um noise) fitted with radial 1, no verdict: a fit with a systematic effect
    (the structure and terms checks find the missing terms). Shared by the verdict's kernel tests."""
    from psdcal.calibration.core import calibrate
    from psdcal.study.simulate import simulate_set

    s = simulate_set("lens2", n_images=8, noise_mm=1e-3, seed=4)
    return calibrate(s.template_mm, s.points_mm, radial=1, tangential=False, verdict=False)
