#!/usr/bin/env python3
"""The verdict's decisions before and after a change: dump every check of the verdict study's cases, then compare.

Speed work on the verdict (:mod:`psdcal.calibration.verdict`) must not move
its decisions. ``dump`` runs the cases of ``benchmarks/study_verdict.py`` with
the ``psdcal`` on the path and writes every check of every verdict (name,
passed, severe, advice, message, statistic, p-value, ``effect_sigma``,
``inflation``) to a pickle:

- ``--correct`` correct fits (its ``correct`` cases): the verdict without a
  stated noise, with the true noise, and the one ``calibrate`` attaches by
  default (``with_verdict``, the covariance inflation included);
- ``--faults`` cases of each planted fault (its ``faulty`` cases), and the
  first ``--diagnose`` of them with the diagnosis (its refits and advice);
- the six real sets of ``tests/data`` with the diagnosis, clean and with each
  planted fault of :func:`psdcal.study.faults.plant_fault`.

``diff`` compares two dumps case by case: the number of cases whose verdict,
failed checks, severity, advice, pass/fail of any check or message differ
(each should be 0) and the largest relative change of the statistics,
p-values, effects and inflations.

Usage::

    PYTHONPATH=<old checkout>/src .venv/bin/python benchmarks/compare_verdicts.py dump before.pkl
    PYTHONPATH=src .venv/bin/python benchmarks/compare_verdicts.py dump after.pkl
    .venv/bin/python benchmarks/compare_verdicts.py diff before.pkl after.pkl [--markdown]
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import pickle  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import print_table  # noqa: E402

FIELDS = ("name", "passed", "severe", "advice", "message", "statistic", "p_value", "effect_sigma", "inflation")
NUMBERS = ("statistic", "p_value", "effect_sigma", "inflation")


def _record(v) -> dict:
    """A verdict (``Verdict`` or its dict) as {"verdict", "checks": [tuple of FIELDS]}."""
    d = v if isinstance(v, dict) else v.to_dict()
    return {"verdict": d["verdict"], "checks": [tuple(bool(c.get(f)) if f == "severe" else c.get(f) for f in FIELDS)
                                               for c in d["checks"]]}


def dump(n_correct: int, n_faults: int, n_diagnose: int) -> dict:
    """{case key: record} over the verdict study's cases."""
    import study_verdict as sv

    from psdcal.calibration.core import calibrate
    from psdcal.calibration.verdict import assess
    from psdcal.io import read_points, read_template
    from psdcal.study.faults import REAL_FAULTS, plant_fault, random_case

    out = {}
    for seed in range(n_correct):
        lens = ("lens1", "lens2")[seed % 2]
        model = sv.CORRECT_MODELS[lens][(seed // 2) % 3]
        c = random_case(50_000 + seed, lens=lens, model=model)
        r = calibrate(c.template_mm, c.points_mm, **model, verdict=False)
        out[("correct", seed)] = _record(assess(r, diagnose=False))
        out[("correct, noise stated", seed)] = _record(assess(r, noise_mm=c.noise_mm, diagnose=False))
        out[("correct, calibrate's default", seed)] = _record(calibrate(c.template_mm, c.points_mm, **model).verdict)
    for kind in sv.FAULT_KINDS:
        for seed in range(n_faults):
            c, r, refusal = sv._planted_fit(kind, seed)
            if r is None:
                out[(kind, seed)] = {"verdict": "refused: " + refusal, "checks": []}
                continue
            pk = "amplitudes" if kind == "gains" else "points"
            out[(kind, seed)] = _record(assess(r, diagnose=False, points_kind=pk))
            if seed < n_diagnose:
                out[(kind + ", diagnosed", seed)] = _record(assess(r, points_kind=pk))
    data = Path(__file__).resolve().parent.parent / "tests" / "data"
    for name in sv.REAL_SETS:
        d = data / name if name == "zhang1998" else data / "chessboards" / name
        tids, txy = read_template(d / "template.csv")
        pf = read_points(d / "points.csv", tids)
        r = calibrate(txy, pf.points_mm, image_ids=pf.image_ids, point_ids=tids, verdict=False)
        out[("real", name)] = _record(assess(r, points_kind="points"))
        for fault in REAL_FAULTS:
            T, X, kw, _ = plant_fault(txy, pf.points_mm, fault, f_mm=r.intrinsics.f_mm)
            try:
                rf = calibrate(T, X, image_ids=pf.image_ids, point_ids=tids, verdict=False, **kw)
            except Exception as exc:  # noqa: BLE001 (a refused calibration carries its result, or none)
                rf = getattr(exc, "result", None)
            out[("real, " + fault, name)] = ({"verdict": "refused", "checks": []} if rf is None
                                             else _record(assess(rf, points_kind="points")))
    return out


def _rel(a, b) -> float:
    if a is None or b is None:
        return 0.0 if a is b else math.inf
    a, b = float(a), float(b)
    if a == b or (math.isnan(a) and math.isnan(b)):
        return 0.0
    if not (math.isfinite(a) and math.isfinite(b)):
        return math.inf
    return abs(a - b) / max(abs(a), abs(b), 1e-300)


def diff(before: dict, after: dict) -> tuple[dict, dict, list]:
    """(counts of cases with each kind of difference, largest relative change of each number, examples)."""
    counts = dict.fromkeys(("cases", "checks", "verdict", "failed checks", "severity", "advice", "passed",
                            "message", "check names"), 0)
    worst = dict.fromkeys(NUMBERS, 0.0)
    examples = []
    for key in sorted(set(before) | set(after), key=str):
        counts["cases"] += 1
        a, b = before.get(key), after.get(key)
        if a is None or b is None or a["verdict"] != b["verdict"]:
            counts["verdict"] += 1
            examples.append((key, a and a["verdict"], b and b["verdict"]))
            continue
        ca, cb = a["checks"], b["checks"]
        if [c[0] for c in ca] != [c[0] for c in cb]:
            counts["check names"] += 1
            continue
        if [c[0] for c in ca if c[1] is False] != [c[0] for c in cb if c[1] is False]:
            counts["failed checks"] += 1
        for kind, i in (("passed", 1), ("severity", 2), ("advice", 3), ("message", 4)):
            if any(x[i] != y[i] for x, y in zip(ca, cb)):
                counts[kind] += 1
                if kind != "message":
                    examples.append((key, kind))
        for x, y in zip(ca, cb):
            counts["checks"] += 1
            for n in NUMBERS:
                worst[n] = max(worst[n], _rel(x[FIELDS.index(n)], y[FIELDS.index(n)]))
    return counts, worst, examples


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("dump", help="write the verdicts of the study's cases to a pickle")
    d.add_argument("out", type=Path)
    d.add_argument("--correct", type=int, default=1000)
    d.add_argument("--faults", type=int, default=100)
    d.add_argument("--diagnose", type=int, default=10)
    c = sub.add_parser("diff", help="compare two dumps")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    for p in (d, c):
        p.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    a = ap.parse_args(argv)
    if a.cmd == "dump":
        recs = dump(a.correct, a.faults, a.diagnose)
        with open(a.out, "wb") as fh:
            pickle.dump(recs, fh)
        print(f"{len(recs)} verdicts written to {a.out}")
        return 0
    with open(a.before, "rb") as fh:
        before = pickle.load(fh)  # noqa: S301 (the user's own dumps)
    with open(a.after, "rb") as fh:
        after = pickle.load(fh)  # noqa: S301
    counts, worst, examples = diff(before, after)
    rows = [[k, str(v)] for k, v in counts.items()] + [[f"largest relative change of {k}", f"{v:.3g}"]
                                                       for k, v in worst.items()]
    print_table(["compared", "cases that differ (or count)"], rows, a.markdown)
    for e in examples[:20]:
        print("  differs:", e)
    return 0 if all(v == 0 for k, v in counts.items() if k not in ("cases", "checks")) else 1


if __name__ == "__main__":
    raise SystemExit(main())
