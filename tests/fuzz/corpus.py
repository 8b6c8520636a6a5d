"""Hostile-input corpus: valid base files for every command, and the cases that spoil one thing each.

``build_base(dir)`` writes a small, valid set of inputs (template, points,
calibration with covariance, recording, schedule, emitters, sensors file,
directions, prior, locate output). ``cases()`` lists the hostile cases: each
is a command line (``{base}``-relative paths) plus the files it plants; the
runner (``test_fuzz.py``) asserts exit 2, exactly one ``psdcal: error:``
line, and that no input or pre-existing output changed.

Classes (the ``cls`` of a case): ``text`` (a broken CSV/JSON in an input slot),
``calib-json`` (wrong types and ranges in a calibration), ``recording``
(corrupt recordings), ``option`` (bad option values, usage errors),
``output`` (outputs that are inputs, exist, sit in a file, are folders, have
the wrong extension), ``resource`` (sizes that would not fit in memory).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import numpy as np

RATE_HZ = 20000.0
CARRIER_HZ = 1000.0


@dataclass(frozen=True)
class Case:
    id: str
    cls: str
    argv: tuple
    plant: dict = field(default_factory=dict)  # relative name -> bytes | "DIR" | ("LINK", target)
    names_file: str | None = None  # the error line must name this file


def build_base(d, main) -> None:
    """Write the valid base files into ``d`` (uses the CLI itself for the simulated set)."""
    d = str(d)
    assert main(["simulate", "--images", "5", "--seed", "1", "-o", os.path.join(d, "sim")]) == 0
    assert main(["calibrate", f"{d}/sim/points.csv", "-t", f"{d}/sim/template.csv", "-o", f"{d}/calib.json", "-q",
                 "--sensor-id", "base"]) == 0
    t = np.arange(int(0.05 * RATE_HZ)) / RATE_HZ
    c = np.cos(2 * np.pi * CARRIER_HZ * t)
    rec = np.stack([1.0 * c, 0.8 * c, 0.9 * c, 1.1 * c], axis=1) + 1e-3 * np.random.default_rng(0).normal(size=(t.size, 4))
    np.save(f"{d}/rec.npy", rec)
    with open(f"{d}/rec.csv", "w") as fh:
        fh.write("vx1,vx2,vy1,vy2\n")
        fh.write("\n".join(",".join(f"{v:.6g}" for v in row) for row in rec[:400]) + "\n")
    with open(f"{d}/schedule.csv", "w") as fh:
        fh.write("emitter,t_start_s,t_end_s\na,0.0,0.02\nb,0.025,0.045\n")
    with open(f"{d}/emitters.csv", "w") as fh:
        fh.write("emitter,X_m,Y_m,Z_m,carrier_hz\na1,0,0,2,1000\na2,1,0,2,1150\na3,0,1,2,1300\na4,1,1,2.5,1450\n")
    with open(f"{d}/located.csv", "w") as fh:
        fh.write("t_s,emitter,alpha_x_deg,alpha_y_deg,sigma_alpha_x_deg,sigma_alpha_y_deg\n")
        fh.write("\n".join(f"{k * 0.01:.2f},e,{0.1 * k:.3f},{-0.05 * k:.3f},0.01,0.01" for k in range(20)) + "\n")
    sensors = {"sensors": [{"name": "s1", "calib": "calib.json", "rvec": [0, 0, 0], "tvec_mm": [0, 0, 0]},
                           {"name": "s2", "calib": "calib.json", "rvec": [0, 0.3, 0], "tvec_mm": [-500, 0, 0]}]}
    with open(f"{d}/sensors.json", "w") as fh:
        json.dump(sensors, fh)
    with open(f"{d}/directions.csv", "w") as fh:
        fh.write("az_deg,el_deg,x_mm,y_mm\n")
        fh.write("\n".join(f"{az},{el},{0.1 * az:.3f},{0.1 * el:.3f}" for az in (-10, 0, 10) for el in (-10, 0, 10)) + "\n")
    with open(f"{d}/prior.json", "w") as fh:
        json.dump({"names": ["f_mm"], "values": [8.0], "std": [0.1]}, fh)
    # gains: spots at known places on a bare PSD and their four amplitudes (a duo-lateral readout, gains 1)
    spots = [(x, y) for x in (-3.0, 0.0, 3.0) for y in (-3.0, 0.0, 3.0)]
    with open(f"{d}/spots.csv", "w") as fh:
        fh.write("point_id,x_mm,y_mm\n" + "".join(f"s{i},{x},{y}\n" for i, (x, y) in enumerate(spots)))
    with open(f"{d}/bench.csv", "w") as fh:
        fh.write("point_id,vx1,vx2,vy1,vy2\n")
        fh.write("".join(f"s{i},{0.5 - x / 9:.6f},{0.5 + x / 9:.6f},{0.5 - y / 9:.6f},{0.5 + y / 9:.6f}\n"
                         for i, (x, y) in enumerate(spots)))
    # module: a text recording 't_s , x , y , sum' of two LEDs in turn with dark samples between
    rng = np.random.default_rng(1)
    with open(f"{d}/module.txt", "w") as fh:
        for k in range(600):
            slot, i = divmod(k, 6)
            lx, ly, ls = ((0.9, 0.4, 4.3), (-0.55, 1.7, 1.9))[slot % 2] if i < 5 else (0.0, 0.0, 0.03)
            fh.write(f"{0.002 * (k + 1):.3f} , {lx + 4e-4 * rng.standard_normal():.4f} , "
                     f"{ly + 4e-4 * rng.standard_normal():.4f} , {ls:.4f}\n")
    # bundle: two sensors' locate outputs (x_mm, y_mm on the PSD) and the known emitters
    with open(f"{d}/known.csv", "w") as fh:
        fh.write("emitter,X_m,Y_m,Z_m\na1,0,0,2\na2,1,0,2\na3,0,1,2\na4,1,1,2.5\n")
    for name, shift in (("s1", 0.0), ("s2", 0.4)):
        with open(f"{d}/located_{name}.csv", "w") as fh:
            fh.write("t_s,emitter,x_mm,y_mm,sigma_x_mm,sigma_y_mm\n")
            fh.write("".join(f"{0.01 * w:.2f},{e},{shift + 0.8 * (i % 2) - 0.4:.4f},{0.8 * (i // 2) - 0.4:.4f},"
                             "0.001,0.001\n" for w in range(3) for i, e in enumerate(("a1", "a2", "a3", "a4"))))

    # selfcal / tag-pose: a 4-emitter tag seen by s1 and s2 of sensors.json (psdcal's alpha convention)
    from scipy.spatial.transform import Rotation

    tag = np.array([[-60.0, -30.0, 0.0], [60.0, -30.0, 0.0], [60.0, 30.0, 10.0], [-60.0, 30.0, 0.0]])
    with open(f"{d}/tag.csv", "w") as fh:
        fh.write("emitter,X_mm,Y_mm,Z_mm\n" + "".join(f"t{i},{x},{y},{z}\n" for i, (x, y, z) in enumerate(tag)))
    cams = [(Rotation.from_rotvec(s["rvec"]).as_matrix(), np.array(s["tvec_mm"], float)) for s in sensors["sensors"]]
    lines = []
    for k in range(24):
        Rt = Rotation.from_rotvec([0.2 * np.sin(0.3 * k), 0.15 * np.cos(0.2 * k), 0.1 * k]).as_matrix()
        Pw = tag @ Rt.T + [300 * np.sin(0.25 * k) - 250, 200 * np.cos(0.25 * k), 2000 + 100 * np.sin(0.1 * k)]
        for name, (Rc, tc) in zip(("s1", "s2"), cams):
            Pc = Pw @ Rc.T + tc
            for i, q in enumerate(Pc):
                ax, ay = np.degrees(np.arctan(q[:2] / q[2]))
                lines.append(f"{0.05 * k:.2f},{name},t{i},{ax:.6f},{ay:.6f},0.002,0.002")
    with open(f"{d}/angles.csv", "w") as fh:
        fh.write("t_s,sensor,emitter,alpha_x_deg,alpha_y_deg,sigma_alpha_x_deg,sigma_alpha_y_deg\n")
        fh.write("\n".join(lines) + "\n")
    # record: a raw float64 stream of frames (vx1, vx2, vy1, vy2) read as a live source 'file:PATH'
    rec[:400].astype("<f8").tofile(f"{d}/raw.bin")
    # dashboard: multi-sensor locate rows
    with open(f"{d}/xyz.csv", "w") as fh:
        fh.write("t_s,emitter,X_mm,Y_mm,Z_mm,sigma_X_mm,sigma_Y_mm,sigma_Z_mm,n_sensors,chi2\n")
        fh.write("".join(f"{0.05 * k:.2f},tag,{10.0 * k:.1f},{-5.0 * k:.1f},2000,2,2,3,2,0.8\n" for k in range(20)))


# ------------------------------------------------------------------ broken text files
def _long_field():
    return b"point_id,X_mm,Y_mm\n" + b"1," + b"9" * 131_072 + b",0\n"


TEXT_KINDS = {
    "empty": b"",
    "blank": b"\n\n   \n",
    "nul": b"a,b\x00c\n1,2\n",
    "binary": bytes(range(256)) * 8,
    "utf16": "x_mm,y_mm\n1,2\n".encode("utf-16"),
    "latin1": "image_id,point_id,x_mm,y_mm\n0,\xe9,1,2\n".encode("latin-1"),
    "long-field": _long_field(),
    "long-line": b"a," * 70_000 + b"\n",
    "garbage": b"%PDF-1.4\n\xe2\xe3\xcf\xd3 obj <<>>\n",
    "bom-garbage": b"\xef\xbb\xbfnot,a,psdcal,file\n1\n",
    "quote": b'"unterminated,1,2\n3,4\n',
    "json-trunc": b'{"intrinsics": {"f_mm": 8',
    "json-list": b"[1, 2, 3]",
    "json-nan": b'{"intrinsics": {"f_mm": NaN, "cx_mm": 0, "cy_mm": 0}}',
    "nested": b"[" * 100_000 + b"]" * 100_000,
    "html": b"<html><body>404</body></html>\n",
}
PATH_KINDS = {"missing": None, "dir": "DIR", "devzero": ("LINK", "/dev/zero"), "dirlink": ("LINK", "/")}

# command templates with one input slot {X}: (name, argv, extension of X)
TEXT_SLOTS = [
    ("calibrate-points", ["calibrate", "{X}", "-t", "{b}/sim/template.csv", "-o", "{b}/out.json"], ".csv"),
    ("calibrate-template", ["calibrate", "{b}/sim/points.csv", "-t", "{X}", "-o", "{b}/out.json"], ".csv"),
    ("calibrate-prior", ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--prior-file", "{X}",
                         "-o", "{b}/out.json"], ".json"),
    ("report", ["report", "{X}", "-o", "{b}/out.html"], ".json"),
    ("compare-a", ["compare", "{X}", "{b}/calib.json"], ".json"),
    ("compare-b", ["compare", "{b}/calib.json", "{X}"], ".json"),
    ("errormap", ["errormap", "--calib", "{X}", "--grid", "5", "-o", "{b}/out.png"], ".json"),
    ("aoa-points", ["aoa", "{X}", "--calib", "{b}/calib.json", "-o", "{b}/out.csv"], ".csv"),
    ("aoa-calib", ["aoa", "{b}/sim/points.csv", "--calib", "{X}", "-o", "{b}/out.csv"], ".json"),
    ("locate-calib", ["locate", "{b}/rec.npy", "--calib", "{X}", "--rate-hz", "20000", "--carrier-hz", "1000",
                      "-o", "{b}/out.csv"], ".json"),
    ("locate-sensors", ["locate", "--sensors", "{X}", "{b}/rec.npy", "{b}/rec.npy", "--rate-hz", "20000",
                        "--carrier-hz", "1000", "-o", "{b}/out.csv"], ".json"),
    ("amplitudes-schedule", ["amplitudes", "{b}/rec.npy", "--rate-hz", "20000", "--carrier-hz", "1000",
                             "--schedule", "{X}", "-o", "{b}/out.csv"], ".csv"),
    ("simulate-template", ["simulate", "--template", "{X}", "-o", "{b}/newsim"], ".csv"),
    ("pose-emitters", ["pose", "{b}/located.csv", "--calib", "{b}/calib.json", "--emitters", "{X}",
                       "-o", "{b}/out.json"], ".csv"),
    ("pose-calib", ["pose", "{b}/located.csv", "--calib", "{X}", "--emitters", "{b}/emitters.csv",
                    "-o", "{b}/out.json"], ".json"),
    ("track", ["track", "{X}", "-o", "{b}/out.csv"], ".csv"),
    ("plan-sensors", ["plan", "--sensors", "{X}", "--room-m", "4", "4", "3", "-o", "{b}/out.png"], ".json"),
    ("directions", ["calibrate-directions", "{X}", "-o", "{b}/out.json"], ".csv"),
    ("amplitudes-rec-csv", ["amplitudes", "{X}", "--rate-hz", "20000", "--carrier-hz", "1000", "-o", "{b}/out.csv"],
     ".csv"),
    ("bundle-located", ["bundle", "s1={X}", "s2={b}/located_s2.csv", "--calib", "{b}/calib.json", "--known",
                        "{b}/known.csv", "-o", "{b}/out.json"], ".csv"),
    ("bundle-known", ["bundle", "s1={b}/located_s1.csv", "s2={b}/located_s2.csv", "--calib", "{b}/calib.json",
                      "--known", "{X}", "-o", "{b}/out.json"], ".csv"),
    ("bundle-calib", ["bundle", "s1={b}/located_s1.csv", "s2={b}/located_s2.csv", "--calib", "{X}", "--known",
                      "{b}/known.csv", "-o", "{b}/out.json"], ".json"),
    ("export-calib", ["export", "{X}", "--format", "opencv-yaml", "-o", "{b}/out.yaml"], ".json"),
    ("gains-amplitudes", ["gains", "{X}", "--positions", "{b}/spots.csv", "-o", "{b}/out.json"], ".csv"),
    ("gains-positions", ["gains", "{b}/bench.csv", "--positions", "{X}", "-o", "{b}/out.json"], ".csv"),
    ("module", ["module", "{X}", "-o", "{b}/out.csv"], ".txt"),
    ("module-calib", ["module", "{b}/module.txt", "--calib", "{X}", "-o", "{b}/out.csv"], ".json"),
    ("next-view-calib", ["next-view", "{X}"], ".json"),
    ("next-view-points", ["next-view", "{X}", "-t", "{b}/sim/template.csv"], ".csv"),
    ("next-view-template", ["next-view", "{b}/sim/points.csv", "-t", "{X}"], ".csv"),
    ("selfcal-angles", ["selfcal", "{X}", "--tag", "{b}/tag.csv", "-o", "{b}/out.json"], ".csv"),
    ("selfcal-tag", ["selfcal", "{b}/angles.csv", "--tag", "{X}", "-o", "{b}/out.json"], ".csv"),
    ("tag-pose-angles", ["tag-pose", "{X}", "--tag", "{b}/tag.csv", "--sensors", "{b}/sensors.json",
                         "-o", "{b}/out.csv"], ".csv"),
    ("tag-pose-sensors", ["tag-pose", "{b}/angles.csv", "--tag", "{b}/tag.csv", "--sensors", "{X}",
                          "-o", "{b}/out.csv"], ".json"),
    ("locate-angles", ["locate", "--angles", "{X}", "--sensors", "{b}/sensors.json", "-o", "{b}/out.csv"], ".csv"),
    ("dashboard-rows", ["dashboard", "{X}", "--export", "{b}/out.html"], ".csv"),
    ("dashboard-sensors", ["dashboard", "{b}/xyz.csv", "--sensors", "{X}", "--export", "{b}/out.html"], ".json"),
]

# ------------------------------------------------------------------ calibration JSON with wrong types/ranges
def _calib_variants(base: dict) -> dict:
    import copy

    def with_(fn):
        d = copy.deepcopy(base)
        fn(d)
        return json.dumps(d).encode()

    def setk(path, value):
        def fn(d):
            obj = d
            for k in path[:-1]:
                obj = obj[k]
            obj[path[-1]] = value
        return fn

    n = len(base["covariance"]["names"])
    nan_cov = [[float("nan")] * n for _ in range(n)]
    neg_cov = (-np.eye(n)).tolist()
    nonpd = np.ones((n, n)).tolist()
    if n >= 2:
        nonpd[0][1] = nonpd[1][0] = 2.0
    return {
        "intrinsics-list": with_(setk(["intrinsics"], [8.0, 0.0, 0.0])),
        "intrinsics-missing": with_(lambda d: d.pop("intrinsics")),
        "f-zero": with_(setk(["intrinsics", "f_mm"], 0.0)),
        "f-negative": with_(setk(["intrinsics", "f_mm"], -8.0)),
        "f-string": with_(setk(["intrinsics", "f_mm"], "8")),
        "f-null": with_(setk(["intrinsics", "f_mm"], None)),
        "f-bool": with_(setk(["intrinsics", "f_mm"], True)),
        "cx-missing": with_(lambda d: d["intrinsics"].pop("cx_mm")),
        "residuals-string": with_(setk(["residuals"], "small")),
        "distortion-list": with_(setk(["distortion"], [0.1])),
        "k1-string": with_(setk(["distortion", "k1"], "x")),
        "cov-nan": json.dumps({**base, "covariance": {"names": base["covariance"]["names"], "matrix": nan_cov}})
        .replace("NaN", "NaN").encode(),
        "cov-negative": with_(setk(["covariance", "matrix"], neg_cov)),
        "cov-not-pd": with_(setk(["covariance", "matrix"], nonpd)),
        "cov-shape": with_(setk(["covariance", "matrix"], [[1.0]])),
        "cov-names-int": with_(setk(["covariance", "names"], list(range(n)))),
        "cov-string": with_(setk(["covariance"], "none")),
        "sensor-negative": with_(setk(["sensor", "lx_mm"], -9.0)),
        "gains-short": with_(setk(["gains"], [1.0, 1.0])),
        "gains-zero": with_(setk(["gains"], [1.0, 0.0, 1.0, 1.0])),
        "future-major": with_(setk(["software", "version"], "99.0.0")),
        "software-list": with_(setk(["software"], ["psdcal"])),
        "sensor-id-int": with_(setk(["sensor_id"], 7)),
        "std-negative": with_(lambda d: d.__setitem__("std", {**d["std"], "f_mm": -1.0})),
    }


CALIB_SLOTS = ["report", "compare-a", "compare-b", "errormap", "aoa-calib", "locate-calib", "pose-calib",
               "export-calib", "next-view-calib", "bundle-calib", "module-calib"]

# ------------------------------------------------------------------ recordings
def _npy_bytes(arr) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def _recording_variants() -> dict:
    good = _npy_bytes(np.ones((100, 4)))
    out = {
        "npy-truncated-header": good[:20],
        "npy-bad-magic": b"\x93NUMPX" + good[6:],
        "npy-header-garbage": good[:10] + b"{'descr': '<f8', 'fortran_order': False, 'shape': (1e9" + good[60:],
        "npy-truncated-data": good[: len(good) // 2],
        "npy-complex": _npy_bytes(np.ones((100, 4), dtype=complex)),
        "npy-nan": _npy_bytes(np.full((100, 4), np.nan)),
        "npy-1d": _npy_bytes(np.ones(100)),
        "npy-3cols": _npy_bytes(np.ones((100, 3))),
        "npy-strings": _npy_bytes(np.array([["a"] * 4] * 10)),
        "npy-empty-file": b"",
    }
    return out


REC_SLOTS = [
    ("locate", ["locate", "{X}", "--calib", "{b}/calib.json", "--rate-hz", "20000", "--carrier-hz", "1000",
                "-o", "{b}/out.csv"]),
    ("amplitudes", ["amplitudes", "{X}", "--rate-hz", "20000", "--carrier-hz", "1000", "-o", "{b}/out.csv"]),
    ("pose", ["pose", "{X}", "--calib", "{b}/calib.json", "--emitters", "{b}/emitters.csv", "--rate-hz", "20000",
              "-o", "{b}/out.json"]),
    ("inspect", ["inspect", "{X}", "--rate-hz", "20000", "--carrier-hz", "1000"]),
]


def _h5_variants(tmpdir) -> dict:
    try:
        import h5py
    except ImportError:
        return {}
    out = {}

    def make(name, fn):
        p = os.path.join(tmpdir, name + ".h5")
        with h5py.File(p, "w") as f:
            fn(f)
        with open(p, "rb") as fh:
            out[name] = fh.read()
        os.unlink(p)

    make("h5-group-for-dataset", lambda f: [f.create_group(n) for n in ("vx1", "vx2", "vy1", "vy2")])
    make("h5-rate-text", lambda f: (f.create_dataset("signals", data=np.ones((100, 4))),
                                    f.attrs.__setitem__("rate_hz", "fast")))
    make("h5-rate-empty", lambda f: (f.create_dataset("signals", data=np.ones((100, 4))),
                                     f.attrs.__setitem__("rate_hz", np.array([]))))
    make("h5-rate-negative", lambda f: (f.create_dataset("signals", data=np.ones((100, 4))),
                                        f.attrs.__setitem__("rate_hz", -5.0)))
    make("h5-no-data", lambda f: f.create_group("nothing"))
    make("h5-strings", lambda f: f.create_dataset("signals", data=np.array([[b"a"] * 4] * 10)))
    return out


# ------------------------------------------------------------------ options and outputs
OPTION_CASES = [
    ["simulate", "--images", "1"], ["simulate", "--images", "0"], ["simulate", "--images", "100000"],
    ["simulate", "--noise-mm", "-1"], ["simulate", "--noise-mm", "nan"], ["simulate", "--seed", "-3"],
    ["simulate", "--f-mm", "-8"], ["simulate", "--f-mm", "nan"], ["simulate", "--snr-db", "nan", "--amplitudes"],
    ["simulate", "--lens", "lens9"], ["simulate", "--bogus"], ["simulate", "--r-tol", "2"],
    ["calibrate"], ["calibrate", "{b}/sim/points.csv"], ["calibrate", "{b}/sim", "-t", "{b}/sim/template.csv"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--sensor-mm", "nan", "9"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--sensor-mm", "-9", "9"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--radial", "7"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--reject", "-2"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--reject", "nan"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--fix", "f_mm"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--fix", "nope=1"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--prior", "f_mm=8"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--noise-um", "0"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--sensor-id", "a\nb", "-o", "{b}/o.json"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--cost", "magic"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--max-iterations", "0"],
    ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "--fit-gains"],
    ["aoa", "{b}/sim/points.csv", "--calib", "{b}/calib.json", "--sigma-d-mm", "-1", "-o", "{b}/o.csv"],
    ["aoa", "{b}/sim/points.csv", "--calib", "{b}/calib.json", "--sigma-d-mm", "nan", "-o", "{b}/o.csv"],
    ["aoa", "{b}/sim/points.csv", "--calib", "{b}/calib.json", "--distance-mm", "-5", "-o", "{b}/o.csv"],
    ["aoa", "{b}/sim/points.csv", "--calib", "{b}/calib.json", "--expect-sensor", "other", "-o", "{b}/o.csv"],
    ["aoa", "{b}/sim/points.csv", "--calib", "{b}/sim/truth.json", "-o", "{b}/o.csv"],
    ["aoa", "{b}/sim/points.csv", "-o", "{b}/o.csv"],
    ["locate", "{b}/rec.npy", "--calib", "{b}/calib.json", "--carrier-hz", "1000", "-o", "{b}/o.csv"],
    ["locate", "{b}/rec.npy", "--calib", "{b}/calib.json", "--rate-hz", "nan", "--carrier-hz", "1000", "-o", "{b}/o.csv"],
    ["locate", "{b}/rec.npy", "--calib", "{b}/calib.json", "--rate-hz", "-20000", "--carrier-hz", "1000",
     "-o", "{b}/o.csv"],
    ["locate", "{b}/rec.npy", "--calib", "{b}/calib.json", "--rate-hz", "20000", "--carrier-hz", "1000",
     "--expect-sensor", "lens1", "-o", "{b}/o.csv"],
    ["locate", "{b}/rec.npy", "--calib", "{b}/sim/truth.json", "--rate-hz", "20000", "--carrier-hz", "1000",
     "-o", "{b}/o.csv"],
    ["locate", "{b}/rec.npy", "--calib", "{b}/calib.json", "--rate-hz", "20000", "--carrier-hz", "1000",
     "--channels", "a,a,b,c", "-o", "{b}/o.csv"],
    ["locate", "{b}/rec.npy", "--calib", "{b}/calib.json", "--rate-hz", "20000", "--carrier-hz", "1000",
     "--channels", "a,b", "-o", "{b}/o.csv"],
    ["locate", "{b}/rec.npy", "{b}/rec.npy", "--calib", "{b}/calib.json", "--rate-hz", "20000", "--carrier-hz",
     "1000", "-o", "{b}/o.csv"],
    ["locate", "{b}/rec.npy", "--calib", "{b}/calib.json", "--sensors", "{b}/sensors.json", "--rate-hz", "20000",
     "--carrier-hz", "1000", "-o", "{b}/o.csv"],
    ["amplitudes", "{b}/rec.npy", "--rate-hz", "20000", "--carrier-hz", "1000", "--tdm", "--n-emitters", "0",
     "-o", "{b}/o.csv"],
    ["amplitudes", "{b}/rec.npy", "--rate-hz", "20000", "--carrier-hz", "1000", "--tdm", "--n-emitters", "-2",
     "-o", "{b}/o.csv"],
    ["amplitudes", "{b}/rec.npy", "--rate-hz", "20000", "--carrier-hz", "1000", "--image-id", "a,b", "-o", "{b}/o.csv"],
    ["amplitudes", "{b}/rec.npy", "--rate-hz", "20000", "--carrier-hz", "1000", "--image-id", "a\nb",
     "-o", "{b}/o.csv"],
    ["amplitudes", "{b}/rec.npy", "--rate-hz", "20000", "--carrier-hz", "1000", "--image-id", 'a"b', "-o", "{b}/o.csv"],
    ["amplitudes", "{b}/rec.npy", "--rate-hz", "20000", "--carrier-hz", "nan", "-o", "{b}/o.csv"],
    ["amplitudes", "{b}/rec.npy", "--rate-hz", "20000", "--carrier-hz", "1000", "--window-s", "nan", "-o", "{b}/o.csv"],
    ["amplitudes", "{b}/rec.npy", "--rate-hz", "20000", "--carrier-hz", "1000", "--chunk-samples", "0",
     "-o", "{b}/o.csv"],
    ["amplitudes", "{b}/rec.npy", "--rate-hz", "20000", "--carrier-hz", "1000", "--min-snr", "-1", "-o", "{b}/o.csv"],
    ["errormap", "--calib", "{b}/calib.json", "--grid", "0", "-o", "{b}/o.png"],
    ["errormap", "--calib", "{b}/calib.json", "--distance-mm", "nan", "-o", "{b}/o.png"],
    ["errormap", "--calib", "{b}/calib.json", "--mode", "worst", "-o", "{b}/o.png"],
    ["compare", "{b}/calib.json", "{b}/calib.json", "--grid", "2"],
    ["compare", "{b}/calib.json", "{b}/calib.json", "--distance-mm", "-1"],
    ["compare", "{b}/calib.json"],
    ["report", "{b}/calib.json"],
    ["report", "{b}/calib.json", "-o", "{b}/o.html", "--cells", "0"],
    ["report", "{b}/calib.json", "-o", "{b}/o.html", "--outlier-k", "nan"],
    ["reproduce", "--workers", "0"], ["reproduce", "--table", "11"], ["reproduce", "--trials", "1"],
    ["signal-noise", "--trials", "1"], ["signal-noise", "--snr-db", "nan"], ["signal-noise", "--seed", "-1"],
    ["signal-noise", "--method", "fft"],
    ["track", "{b}/located.csv", "-o", "{b}/o.csv", "--q", "nan"],
    ["plan", "--sensors", "{b}/sensors.json", "--room-m", "nan", "4", "3", "-o", "{b}/o.png"],
    ["plan", "--sensors", "{b}/sensors.json", "--room-m", "4", "4", "3", "--grid-mm", "-5", "-o", "{b}/o.png"],
    ["pose", "{b}/located.csv", "--calib", "{b}/calib.json", "--emitters", "{b}/emitters.csv"],
    ["calibrate-directions", "{b}/directions.csv", "--radial", "9"],
    ["calibrate-directions", "{b}/directions.csv", "--distance-mm", "-1"],
    ["simulate-recording", "template", "-o", "{b}/r", "--views", "1"],
    ["simulate-recording", "template", "-o", "{b}/r", "--rate-hz", "nan"],
    ["simulate-recording", "template", "-o", "{b}/r", "--gain-imbalance", "0.9"],
    ["simulate-recording", "room", "-o", "{b}/r", "--duration-s", "nan"],
    ["simulate-recording", "nothing"],
    ["bundle", "s1={b}/located_s1.csv", "--calib", "{b}/calib.json", "--known", "{b}/known.csv", "-o", "{b}/o.json"],
    ["bundle", "s1={b}/located_s1.csv", "s1={b}/located_s2.csv", "--calib", "{b}/calib.json", "--known",
     "{b}/known.csv", "-o", "{b}/o.json"],
    ["bundle", "s1{b}/located_s1.csv", "s2={b}/located_s2.csv", "--calib", "{b}/calib.json", "--known",
     "{b}/known.csv", "-o", "{b}/o.json"],
    ["bundle", "s1={b}/located_s1.csv", "s2={b}/located_s2.csv", "--calib", "s1={b}/calib.json", "--known",
     "{b}/known.csv", "-o", "{b}/o.json"],
    ["export", "{b}/calib.json", "--format", "matlab", "-o", "{b}/o.yaml"],
    ["export", "{b}/calib.json", "--format", "opencv-yaml", "--pixel-um", "0", "-o", "{b}/o.yaml"],
    ["export", "{b}/calib.json", "--format", "opencv-yaml", "--coeffs", "6", "-o", "{b}/o.yaml"],
    ["export", "{b}/calib.json", "--format", "opencv-yaml", "--grid", "2", "-o", "{b}/o.yaml"],
    ["export", "--format", "opencv-yaml", "-o", "{b}/o.yaml"],
    ["gains", "{b}/bench.csv", "--positions", "{b}/spots.csv", "--lx-mm", "-9", "-o", "{b}/o.json"],
    ["gains", "{b}/bench.csv", "--positions", "{b}/spots.csv", "--ly-mm", "nan", "-o", "{b}/o.json"],
    ["gains", "{b}/bench.csv", "-o", "{b}/o.json"],
    ["inspect", "{b}/rec.npy"],
    ["inspect", "{b}/rec.npy", "--rate-hz", "-1"],
    ["inspect", "{b}/rec.npy", "--rate-hz", "20000", "--max-samples", "0"],
    ["inspect", "{b}/rec.npy", "--rate-hz", "20000", "--window-s", "nan"],
    ["inspect", "{b}/rec.npy", "--rate-hz", "20000", "--carrier-hz", "15000"],
    ["module", "{b}/module.txt", "--channels", "t,x,y", "-o", "{b}/o.csv"],
    ["module", "{b}/module.txt", "--channels", "t,x,x,sum", "-o", "{b}/o.csv"],
    ["module", "{b}/module.txt", "--mm-per-unit", "0", "-o", "{b}/o.csv"],
    ["module", "{b}/module.txt", "--mm-per-unit", "nan", "-o", "{b}/o.csv"],
    ["module", "{b}/module.txt", "--n-emitters", "3", "-o", "{b}/o.csv"],
    ["module", "{b}/module.txt", "--channels", "x,y,sum,-", "-o", "{b}/o.csv"],
    ["next-view", "{b}/calib.json", "--noise-um", "0"],
    ["next-view", "{b}/calib.json", "--min-gain", "2"],
    ["next-view", "{b}/calib.json", "--grid", "1"],
    ["next-view", "{b}/calib.json", "--max-tilt-deg", "95"],
    ["next-view", "{b}/sim/points.csv"],
    ["demo", "--cost", "magic"], ["demo", "--bogus"],
    ["selfcal", "{b}/angles.csv", "-o", "{b}/o.json"],
    ["selfcal", "{b}/angles.csv", "--tag", "{b}/tag.csv", "--convention", "polar", "-o", "{b}/o.json"],
    ["selfcal", "{b}/angles.csv", "--tag", "{b}/tag.csv", "--reference", "s9", "-o", "{b}/o.json"],
    ["selfcal", "{b}/angles.csv", "--tag", "{b}/tag.csv", "--sigma-rad", "0", "-o", "{b}/o.json"],
    ["tag-pose", "{b}/angles.csv", "--tag", "{b}/tag.csv", "-o", "{b}/o.csv"],
    ["tag-pose", "{b}/angles.csv", "--tag", "{b}/tag.csv", "--sensors", "{b}/sensors.json", "--convention", "x",
     "-o", "{b}/o.csv"],
    ["locate", "--angles", "{b}/angles.csv", "-o", "{b}/o.csv"],
    ["locate", "--angles", "{b}/angles.csv", "--sensors", "{b}/sensors.json", "--convention", "polar",
     "-o", "{b}/o.csv"],
    ["dashboard", "{b}/xyz.csv", "--speed", "0", "--export", "{b}/o.html"],
    ["dashboard", "{b}/xyz.csv", "--host", "0.0.0.0", "--port", "0"],
    ["dashboard", "{b}/xyz.csv", "--host", "0.0.0.0", "--allow-remote", "--token", "short", "--port", "0"],
    ["dashboard", "{b}/no-such.csv", "--replay", "--export", "{b}/o.html"],
    ["record", "--rate-hz", "20000", "-o", "{b}/o.psdsession"],
    ["record", "file:{b}/raw.bin", "--rate-hz", "nan", "-o", "{b}/o.psdsession"],
    ["record", "file:{b}/raw.bin", "--rate-hz", "20000", "--raw-scale", "nan", "-o", "{b}/o.psdsession"],
    ["record", "file:{b}/no-such.bin", "--rate-hz", "20000", "-o", "{b}/o.psdsession"],
    ["record", "file:{b}/raw.bin", "file:{b}/raw.bin", "--rate-hz", "20000", "--names", "a", "-o", "{b}/o.psdsession"],
    ["no-such-command"], ["--no-such-flag"],
]

RESOURCE_CASES = [
    ["errormap", "--calib", "{b}/calib.json", "--grid", "2000000", "-o", "{b}/o.png"],
    ["errormap", "--calib", "{b}/calib.json", "--grid", "20000", "-o", "{b}/o.png"],
    ["simulate-recording", "room", "-o", "{b}/r", "--duration-s", "1e9"],
    ["simulate-recording", "template", "-o", "{b}/r", "--on-s", "1e7"],
    ["amplitudes", "{b}/rec.npy", "--rate-hz", "20000", "--carrier-hz", "1000", "--window-s", "1e12",
     "-o", "{b}/o.csv"],
    ["locate", "{b}/rec.npy", "--calib", "{b}/calib.json", "--rate-hz", "20000", "--carrier-hz", "1000",
     "--window-s", "1e12", "-o", "{b}/o.csv"],
    ["plan", "--sensors", "{b}/sensors.json", "--room-m", "4000", "4000", "3", "--grid-mm", "0.01", "-o", "{b}/o.png"],
]

# writing commands: (name, argv with {O} the output, output extension, input used for the 'is-input' case)
WRITERS = [
    ("calibrate", ["calibrate", "{b}/sim/points.csv", "-t", "{b}/sim/template.csv", "-o", "{O}"], ".json",
     "{b}/sim/points.csv"),
    ("report", ["report", "{b}/calib.json", "-o", "{O}"], ".html", None),
    ("errormap", ["errormap", "--calib", "{b}/calib.json", "--grid", "5", "-o", "{O}"], ".png", None),
    ("errormap-csv", ["errormap", "--calib", "{b}/calib.json", "--grid", "5", "-o", "{b}/m.png", "--csv", "{O}"],
     ".csv", "{b}/calib.json"),
    ("compare", ["compare", "{b}/calib.json", "{b}/calib.json", "-o", "{O}"], ".png", None),
    ("compare-json", ["compare", "{b}/calib.json", "{b}/calib.json", "--json", "{O}"], ".json", "{b}/calib.json"),
    ("aoa", ["aoa", "{b}/sim/points.csv", "--calib", "{b}/calib.json", "-o", "{O}"], ".csv", "{b}/sim/points.csv"),
    ("locate", ["locate", "{b}/rec.npy", "--calib", "{b}/calib.json", "--rate-hz", "20000", "--carrier-hz", "1000",
                "-o", "{O}"], ".csv", "{b}/calib.json"),
    ("amplitudes", ["amplitudes", "{b}/rec.csv", "--rate-hz", "20000", "--carrier-hz", "1000", "-o", "{O}"], ".csv",
     "{b}/rec.csv"),
    ("track", ["track", "{b}/located.csv", "-o", "{O}"], ".csv", "{b}/located.csv"),
    ("pose", ["pose", "{b}/located.csv", "--calib", "{b}/calib.json", "--emitters", "{b}/emitters.csv", "-o", "{O}"],
     ".json", "{b}/emitters.csv"),
    ("plan", ["plan", "--sensors", "{b}/sensors.json", "--room-m", "4", "4", "3", "-o", "{O}"], ".png", None),
    ("plan-csv", ["plan", "--sensors", "{b}/sensors.json", "--room-m", "4", "4", "3", "-o", "{b}/p.png", "--csv", "{O}"],
     ".csv", "{b}/sensors.json"),
    ("directions", ["calibrate-directions", "{b}/directions.csv", "-o", "{O}"], ".json", "{b}/directions.csv"),
    ("demo", ["demo", "-o", "{O}"], ".json", None),
    ("bundle", ["bundle", "s1={b}/located_s1.csv", "s2={b}/located_s2.csv", "--calib", "{b}/calib.json", "--known",
                "{b}/known.csv", "-o", "{O}"], ".json", "{b}/calib.json"),
    ("bundle-points", ["bundle", "s1={b}/located_s1.csv", "s2={b}/located_s2.csv", "--calib", "{b}/calib.json",
                       "--known", "{b}/known.csv", "-o", "{b}/o.json", "--points-out", "{O}"], ".csv",
     "{b}/known.csv"),
    ("export", ["export", "{b}/calib.json", "--format", "opencv-yaml", "-o", "{O}"], ".yaml", "{b}/calib.json"),
    ("gains", ["gains", "{b}/bench.csv", "--positions", "{b}/spots.csv", "-o", "{O}"], ".json", "{b}/bench.csv"),
    ("module", ["module", "{b}/module.txt", "-o", "{O}"], ".csv", "{b}/module.txt"),
    ("next-view", ["next-view", "{b}/calib.json", "--json", "{O}"], ".json", "{b}/calib.json"),
    ("selfcal", ["selfcal", "{b}/angles.csv", "--tag", "{b}/tag.csv", "-o", "{O}"], ".json", "{b}/angles.csv"),
    ("selfcal-poses", ["selfcal", "{b}/angles.csv", "--tag", "{b}/tag.csv", "-o", "{b}/o.json", "--tag-poses", "{O}"],
     ".csv", "{b}/tag.csv"),
    ("tag-pose", ["tag-pose", "{b}/angles.csv", "--tag", "{b}/tag.csv", "--sensors", "{b}/sensors.json", "-o", "{O}"],
     ".csv", "{b}/angles.csv"),
    ("locate-angles", ["locate", "--angles", "{b}/angles.csv", "--sensors", "{b}/sensors.json", "-o", "{O}"], ".csv",
     "{b}/angles.csv"),
    ("dashboard", ["dashboard", "{b}/xyz.csv", "--export", "{O}"], ".html", "{b}/xyz.csv"),
    ("record", ["record", "file:{b}/raw.bin", "--rate-hz", "20000", "-o", "{O}"], ".psdsession", "{b}/raw.bin"),
]
#: Commands whose output is replaced on every run (psdcal.cli.REPLACING_COMMANDS).
REPLACING = {"demo"}

DIR_WRITERS = [
    ("simulate", ["simulate", "--images", "4", "-o", "{O}"], ("template.csv", "points.csv", "truth.json")),
    ("sim-template", ["simulate-recording", "template", "--views", "3", "-o", "{O}"], ("template.csv", "truth.json")),
    ("sim-room", ["simulate-recording", "room", "--duration-s", "0.05", "-o", "{O}"], ("sensors.json", "truth.json")),
    ("reproduce", ["reproduce", "--quick", "--table", "1", "--out", "{O}"], ("report.md",)),
]


def cases(base_dir, tmpdir_for_h5) -> list[Case]:
    """Every hostile case (needs the base files for the calibration variants)."""
    out: list[Case] = []
    for slot, argv, ext in TEXT_SLOTS:
        for kind, content in TEXT_KINDS.items():
            name = f"hostile-{slot}-{kind}{ext}"
            a = tuple(x.replace("{X}", "{b}/" + name) for x in argv)
            out.append(Case(f"text/{slot}/{kind}", "text", a, {name: content}, names_file=name))
        for kind, spec in PATH_KINDS.items():
            name = f"hostile-{slot}-{kind}{ext}"
            a = tuple(x.replace("{X}", "{b}/" + name) for x in argv)
            plant = {} if spec is None else {name: spec}
            out.append(Case(f"path/{slot}/{kind}", "text", a, plant, names_file=name))
    with open(os.path.join(str(base_dir), "calib.json")) as fh:
        base_calib = json.load(fh)
    slots = {s: (argv, ext) for s, argv, ext in TEXT_SLOTS}
    for kind, content in _calib_variants(base_calib).items():
        for slot in CALIB_SLOTS:
            argv, ext = slots[slot]
            name = f"calib-{slot}-{kind}.json"
            a = tuple(x.replace("{X}", "{b}/" + name) for x in argv)
            out.append(Case(f"calib-json/{slot}/{kind}", "calib-json", a, {name: content}, names_file=name))
    recs = {**{k: (v, ".npy") for k, v in _recording_variants().items()},
            **{k: (v, ".h5") for k, v in _h5_variants(tmpdir_for_h5).items()},
            "tdms-garbage": (b"TDSm" + b"\x00" * 40, ".tdms"), "unknown-ext": (b"1,2,3,4\n", ".wav")}
    for kind, (content, ext) in recs.items():
        for slot, argv in REC_SLOTS:
            name = f"rec-{slot}-{kind}{ext}"
            a = tuple(x.replace("{X}", "{b}/" + name) for x in argv)
            out.append(Case(f"recording/{slot}/{kind}", "recording", a, {name: content}, names_file=name))
    for slot, argv in REC_SLOTS:
        name = f"rec-{slot}-devzero.npy"
        a = tuple(x.replace("{X}", "{b}/" + name) for x in argv)
        out.append(Case(f"recording/{slot}/devzero", "recording", a, {name: ("LINK", "/dev/zero")}, names_file=name))
    for k, argv in enumerate(OPTION_CASES):
        out.append(Case(f"option/{k:02d}-{argv[0]}", "option", tuple(argv)))
    for k, argv in enumerate(RESOURCE_CASES):
        out.append(Case(f"resource/{k}-{argv[0]}", "resource", tuple(argv)))
    for name, argv, ext, an_input in WRITERS:
        def w(target, force=True):
            a = tuple(x.replace("{O}", target) for x in argv)
            return a + (("--force",) if force else ())
        if name not in REPLACING:  # `demo` replaces its own output by design (its inputs are never written)
            out.append(Case(f"output/{name}/exists", "output", w("{b}/precious" + ext, force=False),
                            {"precious" + ext: b"precious\n"}))
        out.append(Case(f"output/{name}/parent-is-file", "output", w("{b}/afile/o" + ext), {"afile": b"x"}))
        out.append(Case(f"output/{name}/is-dir", "output", w("{b}/adir" + ext), {"adir" + ext: "DIR"}))
        out.append(Case(f"output/{name}/wrong-ext", "output", w("{b}/o.jpg")) if ext in (".png", ".html") else
                   Case(f"output/{name}/under-devnull", "output", w("/dev/null/o" + ext)))
        if an_input is not None:
            out.append(Case(f"output/{name}/is-input", "output", w(an_input)))
            out.append(Case(f"output/{name}/is-input-via-link", "output", w("{b}/inlink" + ext),
                            {"inlink" + ext: ("LINK", an_input)}))
    for name, argv, files in DIR_WRITERS:
        a = tuple(x.replace("{O}", "{b}/od") for x in argv)
        out.append(Case(f"output/{name}/exists", "output", a, {"od": "DIR", f"od/{files[0]}": b"precious\n"}))
        out.append(Case(f"output/{name}/out-is-file", "output", a + ("--force",), {"od": b"a file"}))
        out.append(Case(f"output/{name}/parent-is-file", "output",
                        tuple(x.replace("{O}", "{b}/afile/od") for x in argv) + ("--force",), {"afile": b"x"}))
    return out
