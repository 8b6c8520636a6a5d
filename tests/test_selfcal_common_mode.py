"""The tag pose's shared-error check (``tag_pose_common_mode``) and the covariance it adds.

Simulated rooms come from the independent simulator of ``tests/test_selfcal.py``;
the shared error (every sensor's two angles at one step shifted together) is
put in here, outside the code under test. The real-data test reads the
Lighthouse flights from the shared data folder beside the repository and skips
without them.
"""
from __future__ import annotations

import numpy as np
import pytest
from test_selfcal import (
    DATA,
    _csv,
    _lighthouse,
    _similarity,
    simulate_room,
    write_angles,
)

from psdcal.measure.angles_table import align_to_sensor, read_angles
from psdcal.measure.selfcal import self_calibrate
from psdcal.measure.tagpose import KnownSensor, Tag, tag_poses


def _with_shared_error(room, rng, sigma_rad):
    shift, rows = {}, []
    for t, s, e, a, b in room["rows"]:
        d = shift.setdefault((t, s), rng.normal(0, sigma_rad, 2))
        rows.append((t, s, e, a + d[0], b + d[1]))
    return {**room, "rows": rows}


def _rooms(tmp_path, n, seed0, sigma_shared=0.0, common_mode=True):
    """Tag poses with the true sensor poses: (list of TagPoses, list of position NEES (3 dof))."""
    out, nees = [], []
    for i in range(n):
        rng = np.random.default_rng(seed0 + i)
        room = simulate_room(rng, int(rng.integers(2, 5)), 20, 30, planar=i % 2 == 0)
        if sigma_shared > 0:
            room = _with_shared_error(room, rng, sigma_shared)
        table = read_angles(write_angles(tmp_path / "a.csv", room))
        tag = Tag(tuple(f"e{m}" for m in range(len(room["B"]))), room["B"])
        sens = [KnownSensor(f"s{k}", room["R"][k], room["c"][k]) for k in range(len(room["R"]))]
        tp = tag_poses(table, tag, sens, common_mode=common_mode)
        out.append(tp)
        for j, t in enumerate(tp.t_s):
            _, p = room["tag"][int(np.argmin(np.abs(room["t"] - t)))]
            err = p - tp.p_mm[j]
            nees.append(float(err @ np.linalg.solve(tp.cov[j][3:, 3:], err)))
    return out, np.array(nees)


def test_no_false_alarm_on_correct_rooms(tmp_path):
    """Correct data: the F test's p-values are uniform, at most one alarm in 40 rooms, sigmas unchanged."""
    res, nees = _rooms(tmp_path, 40, 81_000)
    p = np.array([r.common_mode.p_value for r in res])
    assert all(r.common_mode.passed is not None for r in res)
    # uniform p-values: mean 0.5, sd of the mean over 40 rooms 0.289 / sqrt(40) = 0.046; band +- 3 sd
    assert abs(p.mean() - 0.5) < 0.137, p.mean()
    # design rate 0.1 %: P(2 or more alarms in 40) = 0.08 %
    assert sum(r.common_mode.passed is False for r in res) <= 1
    assert sum(r.common_mode_sigma_rad > 0 for r in res) <= 1
    # positions' NEES (3 dof) over ~1200 steps: sd of the mean ~ sqrt(6 / 1200) = 0.07 (steps of one room
    # share no error: the sensors are the true ones); band +- 0.3
    assert len(nees) > 1000 and abs(nees.mean() - 3) < 0.3, nees.mean()


def test_shared_error_is_found_and_covered(tmp_path):
    """A shared error of 3x the angle noise: every room fails the check, its sigma is estimated, NEES ~ 3.

    Without the term (common_mode=False) the same positions' NEES is far above 3: the test fails if the
    term is not added.
    """
    sigma = 3e-4  # the simulator's noise is 1e-4 rad
    res, nees = _rooms(tmp_path, 20, 82_000, sigma_shared=sigma)
    assert all(r.common_mode.passed is False for r in res)
    est = np.array([r.common_mode_sigma_rad for r in res])
    # each room's estimate from ~30 steps x ~1-3 visible shared shifts: spread ~15 %; median within 20 %
    assert abs(np.median(est) / sigma - 1) < 0.2, np.median(est)
    assert all(r.common_mode.effect_sigma > 0.5 for r in res)
    # 20 rooms x 30 steps (about 600 NEES, sd of the mean ~0.1 plus the estimate's own error): band 2.4-4.0
    assert 2.4 < nees.mean() < 4.0, nees.mean()
    _, bare = _rooms(tmp_path, 20, 82_000, sigma_shared=sigma, common_mode=False)
    assert bare.mean() > 2.5 * nees.mean(), (bare.mean(), nees.mean())


# --------------------------------------------------------------------------- real data
SWEEPS = {"0": (-1 / 120, 0.0), "1": (-1 / 120, 0.0)}


def _nees_vs_mocap(folder, offsets):
    """The deck's positions (stations from the deck alone) against the mocap, the frame and the clock offset
    fitted on alternate 10 s blocks, scored on the others: (check, NEES medians before, after)."""
    tab, deck = _lighthouse(folder)
    al = align_to_sensor(tab, "1", max_gap_s=0.05, offsets_s=offsets)
    res = self_calibrate(al, deck)
    sens = [KnownSensor(nm, res.R[i], res.c_mm[i], res.cov[i]) for i, nm in enumerate(res.names)]
    after = tag_poses(al, deck, sens, cov_joint=res.cov_full)
    before = tag_poses(al, deck, sens, cov_joint=res.cov_full, common_mode=False)
    mc = _csv(DATA / folder / "mocap.csv")
    mt, M = mc["t_s"], np.c_[mc["X_m"], mc["Y_m"], mc["Z_m"]] * 1000

    def mocap_at(ts):
        j = np.clip(np.searchsorted(mt, ts), 1, len(mt) - 1)
        w = (ts - mt[j - 1]) / (mt[j] - mt[j - 1])
        ok = (ts > mt[0]) & (ts < mt[-1]) & (mt[j] - mt[j - 1] < 0.02)
        return (1 - w)[:, None] * M[j - 1] + w[:, None] * M[j], ok

    t, p = after.t_s, after.p_mm
    even = np.floor(t / 10).astype(int) % 2 == 0
    medians = {"before": [], "after": []}
    for fit_even in (True, False):
        best = None
        for d in np.arange(-0.03, 0.0301, 0.002):  # the clock offset, on the fitting half only
            tr, ok = mocap_at(t + d)
            f = ok & (even == fit_even)
            s, R, c = _similarity(p[f], tr[f])
            r = float(np.median(np.linalg.norm(p[f] @ R.T * s + c - tr[f], axis=1)))
            if best is None or r < best[0]:
                best = (r, d, s, R, c)
        _, d, s, R, c = best
        tr, ok = mocap_at(t + d)
        sc = ok & (even != fit_even)
        e = p[sc] @ R.T * s + c - tr[sc]
        for name, tp in (("before", before), ("after", after)):
            C = s * s * R @ tp.cov[sc][:, 3:, 3:] @ R.T
            medians[name].append(float(np.median(np.einsum("ti,ti->t", e, np.linalg.solve(C, e[..., None])[..., 0]))))
    return after.common_mode, medians


@pytest.mark.slow
def test_lighthouse_deck_sigmas_cover_the_mocap_difference():
    """flight_00, stations from the deck alone, frame and clock of the mocap fitted on the other half.

    Logged times (no sweep offsets): the shared error (the first sweep's 1/120 s on a moving deck, the
    photodiodes' correlated noise) is found, and the NEES median (3 dof; 2.37 ideal) falls from ~30-40 to
    3.4-4.4 (band 1.5-6). With the sweep offsets it falls ~7x but stays above (11-23, measured): a slowly
    varying difference remains (docs/guide/selfcal.md, "Real data").
    """
    folder = "lh1_crossingBeam_flight_00"
    if not (DATA / folder / "angles.csv").exists():
        pytest.skip("lighthouse-lh1 data not present")
    cm, med = _nees_vs_mocap(folder, None)
    assert cm.passed is False and cm.effect_sigma > 1
    assert min(med["before"]) > 20, med
    assert all(1.5 < m < 6.0 for m in med["after"]), med
    cm, med = _nees_vs_mocap(folder, SWEEPS)
    assert cm.passed is False
    assert all(a < b / 4 for a, b in zip(med["after"], med["before"])), med


def test_cli_reports_the_shared_error(tmp_path):
    """`selfcal --tag-poses` puts the tag poses' checks in its JSON; `tag-pose --json` writes them."""
    import json

    from test_selfcal import write_tag

    from psdcal.cli import main

    rng = np.random.default_rng(83)
    room = _with_shared_error(simulate_room(rng, 3, 20, 30), rng, 4e-4)
    write_angles(tmp_path / "a.csv", room)
    write_tag(tmp_path / "tag.csv", room["B"])
    out = tmp_path / "sensors.json"
    assert main(["selfcal", str(tmp_path / "a.csv"), "--tag", str(tmp_path / "tag.csv"), "-o", str(out),
                 "--tag-poses", str(tmp_path / "steps.csv"), "-q"]) == 0
    tp = json.loads(out.read_text())["selfcal"]["tag_poses"]
    assert [c["name"] for c in tp["checks"]] == ["tag_pose_chi2", "tag_pose_common_mode"]
    assert tp["checks"][1]["passed"] is False and tp["verdict"] == "suspect"
    assert 2e-4 < tp["common_mode_sigma_rad"] < 8e-4
    assert main(["tag-pose", str(tmp_path / "a.csv"), "--tag", str(tmp_path / "tag.csv"), "--sensors", str(out),
                 "-o", str(tmp_path / "poses.csv"), "--json", str(tmp_path / "poses.json"), "-q"]) == 0
    js = json.loads((tmp_path / "poses.json").read_text())
    assert js["checks"][1]["name"] == "tag_pose_common_mode" and js["checks"][1]["passed"] is False
    assert js["n_steps"] == len((tmp_path / "poses.csv").read_text().splitlines()) - 1
