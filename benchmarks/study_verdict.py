#!/usr/bin/env python3
"""False-alarm and detection rates of the calibration verdict (``psdcal.calibration.verdict``).

Correct fits: random irregular-template cases (``psdcal.study.faults.random_case``),
Lens 1 or 2, 6-15 views, 0.2-10 um noise, fitted with a model that contains
the truth (switches drawn from :data:`CORRECT_MODELS`); a false alarm is a
verdict other than ``good`` (per check: a failed check).

Faults (each ``--faults`` cases): ``gains`` (raw amplitudes through the
paper's chain with R 1 %, C 15 % tolerances, SNR 40-60 dB, fitted without
``--fit-gains``), ``wrong_min`` (a single-start fit that stopped in a wrong
minimum, :func:`psdcal.study.faults.wrong_minimum`), ``swap`` (two template
LEDs swapped), ``mislabel`` (one view's labels shifted by one), ``metres``
(points and template in metres), ``no_k2`` (Lens 2 fitted with radial 1).
Detected: verdict not ``good``, or the calibration refused with an error.

Real sets (``--real``, default on): the six real calibration sets in
``tests/data`` (Zhang 1998, OpenCV's left/right samples, BoofCV's Sony HX5V and
Bumblebee2 left/right): the clean verdict with the checks that fail and the
largest effect, the time of the fit and of the verdict, and each fault of
:func:`psdcal.study.faults.plant_fault` (two LEDs swapped, one view's labels
mirrored, points in metres, f fixed 5 % off) with the check that names it.

Usage::

    .venv/bin/python benchmarks/study_verdict.py [--correct 500] [--faults 100] [--jobs 2] [--markdown]
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # benchmarks/_table.py, also when imported by the tests
from _table import print_skipped, print_table  # noqa: E402

CORRECT_MODELS = {
    "lens1": ({"radial": 1, "tangential": False}, {"radial": 2, "tangential": False}, {"radial": 2, "tangential": True}),
    "lens2": ({"radial": 2, "tangential": False}, {"radial": 3, "tangential": False}, {"radial": 2, "tangential": True}),
}
FAULT_KINDS = ("gains", "wrong_min", "swap", "mislabel", "metres", "no_k2")


def correct(seed: int) -> dict:
    from psdcal.calibration.core import calibrate
    from psdcal.calibration.verdict import assess
    from psdcal.study.faults import random_case

    lens = ("lens1", "lens2")[seed % 2]
    model = CORRECT_MODELS[lens][(seed // 2) % 3]
    c = random_case(50_000 + seed, lens=lens, model=model)
    t0 = time.perf_counter()
    r = calibrate(c.template_mm, c.points_mm, **model, verdict=False)
    t1 = time.perf_counter()
    v = assess(r, diagnose=False)
    t2 = time.perf_counter()
    vk = assess(r, noise_mm=c.noise_mm, diagnose=False)  # with the true noise stated
    return {"seed": seed, "verdict": v.verdict, "verdict_noise": vk.verdict,
            "failed": [x.name for x in vk.failed], "t_fit": t1 - t0, "t_verdict": t2 - t1}


def _planted_fit(kind, seed):
    """A planted-fault case and its fit: ``(case, result or None, the refusal's message or "")``."""
    from psdcal.calibration.core import calibrate
    from psdcal.errors import PsdcalError
    from psdcal.study.faults import random_case, wrong_minimum

    if kind == "wrong_min":
        c, r = wrong_minimum(seed)
        return c, r, ""
    c = random_case(90_000 + seed, fault=kind)
    try:
        return c, calibrate(c.template_mm, c.points_mm, **c.model, verdict=False), ""
    except PsdcalError as exc:
        return c, getattr(exc, "result", None), str(exc)


def faulty(args) -> dict:
    kind, seed = args
    from psdcal.calibration.core import calibrate
    from psdcal.calibration.verdict import assess

    c, r, refusal = _planted_fit(kind, seed)
    if r is None:
        return {"kind": kind, "seed": seed, "verdict": "refused", "failed": [refusal[:60]]}
    v = assess(r, diagnose=False, points_kind="amplitudes" if kind == "gains" else "points")
    out = {"kind": kind, "seed": seed, "verdict": v.verdict, "failed": [x.name for x in v.failed]}
    if kind == "no_k2":  # how many standard errors k2 is from 0 in the fit of the true model (its detectability)
        t = calibrate(c.template_mm, c.points_mm, radial=2, tangential=False, verdict=False)
        out["k2_z"] = float(t.distortion.k2 / t.std["k2"])
        out["noise_um"] = c.noise_mm * 1e3
    return out


def advice(args) -> dict:
    """Whether the diagnosis (advice of the failed checks, or the refusal's message) names the planted cause."""
    kind, seed = args
    from psdcal.calibration.verdict import assess

    c, r, text = _planted_fit(kind, seed)
    if r is not None:
        v = assess(r, points_kind="amplitudes" if kind == "gains" else "points")
        text += " " + " ".join(ch.advice for ch in v.failed)
    want = {"gains": ["--fit-gains"], "wrong_min": ["local minimum"], "metres": ["metres"], "no_k2": ["--radial 2"],
            "mislabel": [f"view {c.bad_image} "]}.get(kind)
    if kind == "swap":
        a, b = np.nonzero(np.any(c.template_mm != c.set.template_mm, axis=1))[0]
        want = [f"LEDs {a} and {b}", f"LEDs {b} and {a}"]
    return {"kind": kind, "seed": seed, "named": any(w in text for w in want), "text": text[:200]}


REAL_SETS = ("zhang1998", "opencv_left", "opencv_right", "boofcv_sony_hx5v", "boofcv_bumblebee2_left",
             "boofcv_bumblebee2_right")
#: The check that names each planted fault on a real set.
REAL_CHECK = {"swap": "leds", "reversed": "template_side", "metres": "scale", "fix_f": "held_values"}


def real(name: str) -> dict:
    """The verdict on one real set, clean and with each planted fault (times: fit and verdict, best of 3)."""
    from pathlib import Path

    from psdcal.calibration.core import calibrate, with_verdict
    from psdcal.calibration.verdict import Verdict, assess
    from psdcal.io import read_points, read_template
    from psdcal.study.faults import REAL_FAULTS, plant_fault

    data = Path(__file__).resolve().parent.parent / "tests" / "data"
    d = data / name if name == "zhang1998" else data / "chessboards" / name
    tids, txy = read_template(d / "template.csv")
    pf = read_points(d / "points.csv", tids)
    t_fit, t_ver = [], []
    for _ in range(3):
        t0 = time.perf_counter()
        r = calibrate(txy, pf.points_mm, image_ids=pf.image_ids, point_ids=tids, verdict=False)
        t1 = time.perf_counter()
        assess(r, diagnose=False)
        t_fit.append(t1 - t0)
        t_ver.append(time.perf_counter() - t1)
    res = with_verdict(r, points_kind="points")
    vv = Verdict.from_dict(res.verdict)
    eff = max((c.effect_sigma or 0.0 for c in vv.checks if c.name in ("structure", "model_terms", "views", "leds")),
              default=0.0)
    out = {"name": name, "verdict": vv.verdict, "failed": [c.name for c in vv.failed],
           "notes": [c.name for c in vv.notes], "effect": eff, "inflation": vv.inflation,
           "t_fit": min(t_fit), "t_verdict": min(t_ver), "f_mm": r.intrinsics.f_mm, "faults": {}}
    for fault in REAL_FAULTS:
        T, X, kw, _ = plant_fault(txy, pf.points_mm, fault, f_mm=r.intrinsics.f_mm)
        try:
            rf = calibrate(T, X, image_ids=pf.image_ids, point_ids=tids, verdict=False, **kw)
        except Exception as exc:  # noqa: BLE001
            rf = getattr(exc, "result", None)
        if rf is None:
            out["faults"][fault] = ("refused", True)
            continue
        vf = assess(rf, points_kind="points")
        named = any(c.name == REAL_CHECK[fault] for c in vf.failed) or (
            fault == "swap" and any("permutation" in c.advice for c in vf.failed))
        out["faults"][fault] = (vf.verdict, named)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--correct", type=int, default=500)
    ap.add_argument("--faults", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--markdown", action="store_true",
                    help="print the tables only, as Markdown (ids: correct, faults, real, advice)")
    ap.add_argument("--quick", action="store_true", help="a smoke run: 20 correct fits, 5 cases per fault, 2 advice")
    ap.add_argument("--advice", type=int, default=0, help="cases per fault whose diagnosis is checked (slower: refits)")
    ap.add_argument("--no-real", dest="real", action="store_false", help="skip the six real sets")
    a = ap.parse_args(argv)
    if a.quick:
        a.correct, a.faults, a.advice = 20, 5, min(a.advice, 2) if a.advice else 0
    from concurrent.futures import ProcessPoolExecutor

    ex = ProcessPoolExecutor(a.jobs) if a.jobs > 1 else None
    mp = ex.map if ex else map
    rows = list(mp(correct, range(a.correct)))
    frows = list(mp(faulty, [(k, s) for k in FAULT_KINDS for s in range(a.faults)]))
    arows = list(mp(advice, [(k, s) for k in FAULT_KINDS for s in range(a.advice)])) if a.advice else []
    rrows = list(mp(real, REAL_SETS)) if a.real else []
    if ex:
        ex.shutdown()
    fa = sum(r["verdict"] != "good" for r in rows)
    fan = sum(r["verdict_noise"] != "good" for r in rows)
    per = Counter(name for r in rows for name in r["failed"])
    md = a.markdown
    notes = []  # the details that are not table rows: after the tables

    def pct(k, m):
        return f"{100 * k / max(m, 1):.2f} %"

    print_table(["correct fits", "fits", "verdict not good", "rate", "checks failing (with the noise stated)"],
                [["no noise stated", str(len(rows)), str(fa), pct(fa, len(rows)) + " (false alarm)", ""],
                 ["true noise stated (`--noise-um`)", str(len(rows)), str(fan), pct(fan, len(rows)) + " (false alarm)",
                  ", ".join(f"{k} {v}" for k, v in per.most_common()) or "none"]], md, "correct")
    lines = []
    for k in FAULT_KINDS:
        rs = [r for r in frows if r["kind"] == k]
        det = sum(r["verdict"] != "good" for r in rs)
        cnt = Counter(r["verdict"] for r in rs)
        top = Counter(name for r in rs for name in r["failed"] if r["verdict"] != "refused").most_common(3)
        lines.append([FAULT_LABEL.get(k, k), str(len(rs)), str(det), f"{100 * det / max(len(rs), 1):.1f} %",
                      f"{cnt['wrong']} / {cnt['suspect']} / {cnt['refused']}", ", ".join(f"{a_} {b_}" for a_, b_ in top)])
        if k == "no_k2":
            for zmin in (3.0, 5.0):
                sub = [r for r in rs if abs(r["k2_z"]) >= zmin]
                d = sum(r["verdict"] != "good" for r in sub)
                lines.append([f"... where k2 is >= {zmin:g} standard errors from 0 in the true model's fit", str(len(sub)),
                              str(d), f"{100 * d / max(len(sub), 1):.1f} %", "", ""])
            missed = [r for r in rs if r["verdict"] == "good"]
            if missed:
                zs = sorted(abs(r["k2_z"]) for r in missed)
                notes.append(f"no_k2 missed: {len(missed)}, |k2| / its standard error in the true model's fit: "
                             + ", ".join(f"{z:.1f}" for z in zs))
        notes += [f"missed: {r}" for r in rs if r["verdict"] == "good" and k != "no_k2"]
    print()
    print_table(["planted fault", "cases", "detected (verdict not good, or refused)", "rate", "wrong / suspect / refused",
                 "checks failing most"], lines, md, "faults")
    if rrows:
        lines = []
        for r in rrows:
            cells = [f"{w} (`{REAL_CHECK[k]}` {'fails' if named else 'silent'})" for k, (w, named) in r["faults"].items()]
            lines.append([REAL_LABEL.get(r["name"], r["name"]), r["verdict"], ", ".join(r["failed"]) or "-",
                          ", ".join(r["notes"]) or "-", f"{r['effect']:.2g} sigma", f"{r['inflation']:.3g}", *cells])
        print()
        print_table(["real set", "clean verdict", "failed checks", "notes", "largest effect", "covariance x",
                     *(REAL_FAULT_LABEL.get(k, k) for k in REAL_CHECK)], lines, md, "real")
    elif md:
        print_skipped("real", "run without the real sets (--no-real)", md)
    if arows:
        print()
        print_table(["planted fault", "cases", "advice names the planted cause"],
                    [[FAULT_LABEL.get(k, k), str(len([r for r in arows if r["kind"] == k])),
                      str(sum(r["named"] for r in arows if r["kind"] == k))] for k in FAULT_KINDS], md, "advice")
        notes += [f"not named: {r}" for r in arows if not r["named"]]
    elif md:
        print_skipped("advice", "run without --advice", md)
    if rows:
        notes.append(f"median fit {np.median([r['t_fit'] for r in rows]) * 1e3:.1f} ms, "
                     f"verdict {np.median([r['t_verdict'] for r in rows]) * 1e3:.1f} ms")
    print()
    for line in notes:
        print(line)


FAULT_LABEL = {
    "gains": "ignored gain imbalance (R 1 %, C 15 %, SNR 40-60 dB)",
    "wrong_min": "wrong minimum (single-start fit stopped in a wrong minimum)",
    "swap": "two template LEDs swapped",
    "mislabel": "one view mislabelled (labels shifted by one)",
    "metres": "points (and template) in metres",
    "no_k2": "Lens 2 fitted without k2, all",
}
REAL_LABEL = {
    "zhang1998": "Zhang 1998",
}
REAL_FAULT_LABEL = {
    "swap": "two LEDs swapped",
    "reversed": "one view mirrored",
    "metres": "points in metres",
    "fix_f": "f fixed 5 % off",
}


if __name__ == "__main__":
    main()
