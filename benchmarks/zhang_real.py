#!/usr/bin/env python3
"""psdcal on Zhang's five real views against Zhang's published intrinsics (the table of docs/benchmarks.md).

The fit and the published values are those of ``tests/test_zhang_real.py`` (one focal length, the
skew free, k1, k2, image cost; points on a nominal 10 um pitch of a 6.4 x 4.8 mm "sensor"), read
from that test so that the table and the test cannot drift apart.

    .venv/bin/python benchmarks/zhang_real.py [--markdown]      (a second)
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # benchmarks/_table.py
from _table import print_table  # noqa: E402


def _test_module():
    spec = importlib.util.spec_from_file_location("_zhang_real_test", HERE.parent / "tests" / "test_zhang_real.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--quick", action="store_true", help="(the same: it is one fit)")
    a = ap.parse_args(argv)
    t = _test_module()
    res = t._calibration("image")
    intr = res.intrinsics
    lines = []
    for label, name, published, tol in (("f, mm", "f_mm", t.F_MM, t.TOL_F_MM), ("Cx, mm", "cx_mm", t.CX_MM, t.TOL_C_MM),
                                        ("Cy, mm", "cy_mm", t.CY_MM, t.TOL_C_MM),
                                        ("skew, mm", "skew", t.SKEW_MM, t.TOL_SKEW_MM)):
        ours, se = getattr(intr, name), res.std[name]
        lines.append([label, f"{ours:.6g}", f"{published:.6g}", f"{se:.2g}", f"{(ours - published) / se:+.2f}",
                      f"{abs(ours - published) / t.PITCH_MM:.3f}", f"{tol:g}"])
    k1_expected = -t.K1_ZHANG / (0.5 * (t.ALPHA + t.BETA) * t.PITCH_MM) ** 2
    lines.append(["k1, mm^-2 (first-order conversion `-k1_Zhang / f^2`)", f"{res.distortion.k1:.5g}",
                  f"{k1_expected:.5g}", f"{res.std['k1']:.2g}",
                  f"{100 * (res.distortion.k1 / k1_expected - 1):+.1f} %", "", "5 %"])
    lines.append(["RMS residual", f"{res.rms_mm:.6f} mm = {res.rms_mm / t.PITCH_MM:.3f} px", "about 0.34 px", "", "",
                  "", f"{t.RMS_RANGE_MM[0]:g}-{t.RMS_RANGE_MM[1]:g} mm"])
    print_table(["", "psdcal", "Zhang (converted)", "psdcal std. error", "difference / std. error",
                 "difference (px)", "test tolerance"], lines, a.markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
