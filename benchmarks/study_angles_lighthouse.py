#!/usr/bin/env python3
"""``locate --angles`` on the real Lighthouse flights against motion capture (the table of docs/guide/positioning.md).

Two Lighthouse V1 base stations (their poses from the data set's ``geometry.json``), the four
photodiodes of a Crazyflie's deck as emitters, the angles read as a ``lighthouse`` table with the
README's noise at rest (70 urad). The deck centre (the mean of the photodiodes at each step) is
scored against motion capture on the steps where the Crazyflie logged its own estimate, the frame
fitted rigidly on alternate 10 s blocks and scored on the others, beside the Crazyflie's estimate on
the same steps. Three pairings of the two stations' frames: interpolated to station 1's times
(``--align-to 1``, what the command line does), the same with each station's first sweep 1/120 s
earlier (``--time-offset``), and station 0's latest frame at each station-1 frame (the firmware's).
The steps and the scoring are those of ``tests/test_angles_in.py`` (imported from it).

Needs ``lighthouse-lh1`` in the shared data folder beside the repository; without it the table is
skipped (its region in the docs stays as it was).

    .venv/bin/python benchmarks/study_angles_lighthouse.py [--markdown]     (about half a minute)
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # benchmarks/_table.py
sys.path.insert(0, str(HERE.parent / "tests"))
from _table import print_skipped, print_table  # noqa: E402

FLIGHTS = ("lh1_crossingBeam_flight_00", "lh1_crossingBeam_flight_01")
#: A Lighthouse V1 station sweeps its first angle 1/120 s before its second (the logged time is the second's).
SWEEPS = {"0": (-1 / 120, 0.0), "1": (-1 / 120, 0.0)}


def _tests():
    spec = importlib.util.spec_from_file_location("_angles_in_test", HERE.parent / "tests" / "test_angles_in.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def latest_frame(raw):
    """Station 0's latest frame at or before each station-1 frame (no interpolation), as the firmware pairs them."""
    from psdcal.measure.angles_table import AnglesTable

    t1 = np.unique(raw.t_s[raw.sensor == "1"])
    t0 = np.unique(raw.t_s[raw.sensor == "0"])
    j = np.searchsorted(t0, t1, side="right") - 1
    later = {}
    for jj, tt in zip(j, t1):
        if jj >= 0 and tt - t0[jj] < 0.05:
            later.setdefault(t0[jj], []).append(tt)
    idx, T = [], []
    for i in range(len(raw)):
        for tt in ([raw.t_s[i]] if raw.sensor[i] == "1" else later.get(raw.t_s[i], [])):
            idx.append(i)
            T.append(tt)
    idx = np.array(idx)
    return AnglesTable(np.array(T), raw.sensor[idx], raw.emitter[idx], raw.n[idx], raw.cov_n[idx], raw.convention)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--quick", action="store_true", help="the first flight only")
    a = ap.parse_args(argv)
    t = _tests()
    if not all((t.DATA / f / "angles.csv").exists() for f in FLIGHTS):
        print_skipped("1", "lighthouse-lh1 is not in the shared data folder", a.markdown)
        return 0
    from psdcal.measure.angles_locate import load_angle_sensors, triangulate_table
    from psdcal.measure.angles_table import align_to_sensor, read_angles

    lines = []
    with tempfile.TemporaryDirectory() as d:
        stations = Path(d) / "stations.json"
        t.stations_file(stations)
        sensors = load_angle_sensors(stations)
        for folder in FLIGHTS[:1] if a.quick else FLIGHTS:
            raw = read_angles(t.DATA / folder / "angles.csv", "lighthouse", sigma_rad=7e-5,
                              columns={"sensor": "station", "emitter": "sensor"})
            for label, table in (("`--align-to 1`", align_to_sensor(raw, "1", max_gap_s=0.05)),
                                 ("`--align-to 1`, sweeps 1/120 s apart",
                                  align_to_sensor(raw, "1", max_gap_s=0.05, offsets_s=SWEEPS)),
                                 ("latest frame (the firmware's pairing)", latest_frame(raw))):
                res = triangulate_table(table, sensors)
                cols = res.columns()
                rows = [{k: cols[k][i] for k in ("t_s", "X_mm", "Y_mm", "Z_mm")} for i in range(len(res))]
                for half, ((med, p95), (cf_med, cf_p95), n) in t.score_against_mocap(folder, rows).items():
                    lines.append([f"`{folder.replace('lh1_crossingBeam_', '')}`", label, f"{half} blocks", str(n),
                                  f"{med:.2f} / {p95:.2f}", f"{cf_med:.2f} / {cf_p95:.2f}", f"{med / cf_med:.2f}"])
    print_table(["flight", "pairing of the stations' frames", "frame fitted on", "steps scored",
                 "psdcal: median / p95 (mm)", "Crazyflie's estimate: median / p95 (mm)", "ratio of medians"],
                lines, a.markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
