"""kill -9: outputs complete or absent, sets never mixed, no temporaries left.

Two ways: at random moments (the command's whole run), and deterministically
at every write event (``killhook.py``): after each output is staged and
before each rename of the commit, the windows a non-atomic writer (one that
writes in place, or renames without a journal) would leave mixed or broken.
"""
import pytest

from .killrun import SCENARIOS, run_kills, run_kills_at_every_write


def test_a_few_kills_leave_whole_sets(tmp_path):
    out = run_kills(tmp_path, 4, scenarios=["simulate", "errormap"], seed=1)
    assert sum(out.values()) == 4


def test_kill_between_staging_and_rename_leaves_a_whole_set(tmp_path):
    """simulate writes three files: a kill after each staged write and before each rename (7 points x 2)."""
    out = run_kills_at_every_write(tmp_path, "simulate")
    points = {k[0] for k in out}
    # the windows were hit: after every staged write, before the journal and before every output's rename
    assert {"written template.csv", "written points.csv", "written truth.json"} <= points
    assert {"rename (journal)", "rename template.csv", "rename points.csv", "rename truth.json"} <= points
    # over A: before the journal the old set stays (A); once the journal exists the next run rolls it forward (B)
    over = {k[0]: k[2] for k in out if k[1] == "over-A"}
    assert over["written truth.json"] == "A" and over["rename truth.json"] == "B"


@pytest.mark.slow
@pytest.mark.parametrize("name", ["errormap", "compare", "aoa"])
def test_kill_at_every_write_of_other_writers(tmp_path, name):
    """Over the A outputs only (the fresh case is simulate's above): every kill point of each writer."""
    out = run_kills_at_every_write(tmp_path, name, fresh_too=False)
    points = {k[0] for k in out}
    assert {p for p in points if p.startswith("written")} and {p for p in points if p.startswith("rename")}


@pytest.mark.slow
def test_random_kills_over_every_scenario(tmp_path):
    """Random kill times over every scenario (the deterministic tests above kill at every write event;
    the 60-kill campaign is benchmarks/kill9.py)."""
    out = run_kills(tmp_path, 12, scenarios=list(SCENARIOS), seed=2)
    assert sum(out.values()) == 12
