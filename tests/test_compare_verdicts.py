"""benchmarks/compare_verdicts.py: the before/after comparison of the verdict's decisions counts what differs."""
from __future__ import annotations

import copy

from _bench import load_benchmark

from psdcal.calibration.core import calibrate
from psdcal.study.simulate import simulate_set


def test_diff_counts_each_kind_of_difference_and_the_largest_relative_change():
    cv = load_benchmark("compare_verdicts")
    s = simulate_set("lens2", n_images=6, noise_mm=2e-3, seed=1)
    rec = cv._record(calibrate(s.template_mm, s.points_mm, radial=1, tangential=False).verdict)
    assert [c[0] for c in rec["checks"]][:2] == ["noise", "structure"]
    before = {(k, 0): copy.deepcopy(rec) for k in "abc"}
    counts, worst, _ = cv.diff(before, copy.deepcopy(before))
    assert counts["cases"] == 3 and counts["checks"] == 3 * len(rec["checks"])
    assert all(v == 0 for k, v in counts.items() if k not in ("cases", "checks"))
    assert all(v == 0.0 for v in worst.values())

    after = copy.deepcopy(before)
    i = [c[0] for c in rec["checks"]].index("structure")
    a = list(after[("a", 0)]["checks"][i])
    a[cv.FIELDS.index("advice")] = "something else"
    a[cv.FIELDS.index("statistic")] = a[cv.FIELDS.index("statistic")] * (1 + 1e-6)
    after[("a", 0)]["checks"][i] = tuple(a)
    after[("b", 0)] = {**after[("b", 0)], "verdict": "wrong" if rec["verdict"] != "wrong" else "good"}
    counts, worst, examples = cv.diff(before, after)
    assert counts["advice"] == 1 and counts["verdict"] == 1
    assert counts["passed"] == counts["severity"] == counts["failed checks"] == 0
    assert 0.9e-6 < worst["statistic"] < 1.1e-6
    assert len(examples) == 2
