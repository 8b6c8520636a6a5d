"""kill -9 at random moments: outputs complete or absent, sets never mixed, no temporaries left."""
import pytest

from .killrun import SCENARIOS, run_kills


def test_a_few_kills_leave_whole_sets(tmp_path):
    out = run_kills(tmp_path, 4, scenarios=["simulate", "errormap"], seed=1)
    assert sum(out.values()) == 4


@pytest.mark.slow
def test_sixty_kills_over_every_scenario(tmp_path):
    out = run_kills(tmp_path, 60, scenarios=list(SCENARIOS), seed=2)
    assert sum(out.values()) == 60
