"""The HTML calibration report: content, provenance, self-containment, and a real headless browser."""
import hashlib
import html
import io
import os
import re
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest

from psdcal.cli import main
from psdcal.io import write_points, write_template
from psdcal.study.simulate import simulate_set

N_FIGURES = 8


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A points file with one planted outlier, its calibration with --reject 5, and the report of it."""
    d = tmp_path_factory.mktemp("report")
    s = simulate_set("lens2", n_images=8, noise_mm=0.003, seed=5)
    X = s.points_mm.copy()
    X[5, 8] += np.array([0.09, -0.12])  # 50 sigma
    write_template(d / "template.csv", list(range(14)), s.template_mm)
    write_points(d / "points.csv", list(range(8)), list(range(14)), X)
    assert main(["calibrate", str(d / "points.csv"), "-t", str(d / "template.csv"), "-o", str(d / "rej.json"),
                 "--reject", "5", "-q"]) == 0
    assert main(["calibrate", str(d / "points.csv"), "-t", str(d / "template.csv"), "-o", str(d / "raw.json"), "-q"]) == 0
    assert main(["report", str(d / "rej.json"), "--points", str(d / "points.csv"), "-t", str(d / "template.csv"),
                 "-o", str(d / "report.html"), "--title", "Sensor <A&B> \"report\""]) == 0
    return d


def test_report_content(made):
    text = (made / "report.html").read_text(encoding="utf-8")
    for section in ("summary", "parameters", "residuals", "outliers", "coverage", "distortion", "provenance"):
        assert f'id="{section}"' in text
    for fid in ("correlation", "residuals", "residual_histogram", "residuals_per_image", "per_image_rms", "coverage",
                "distortion_field", "aoa_uncertainty"):
        assert f'id="fig-{fid}"' in text
    # parameters with standard errors
    assert "f_mm" in text and "std error" in text
    # the removed outlier with its line in the points file (header = line 1)
    line = 1 + 5 * 14 + 8 + 1
    row = re.search(r"<tr class=\"bad\">(.*?removed by --reject.*?)</tr>", text, re.S)
    assert row and f">{line}<" in row.group(1)
    # provenance: the checksums of the input files, version, dates
    for name in ("points.csv", "template.csv", "rej.json"):
        digest = hashlib.sha256((made / name).read_bytes()).hexdigest()
        assert digest in text
    assert "matches the calibration&#x27;s record" in text
    assert "psdcal 0." in text and "report made" in text
    # the title is escaped
    assert html.escape('Sensor <A&B> "report"') in text and "<A&B>" not in text


def test_report_is_self_contained(made):
    text = (made / "report.html").read_text(encoding="utf-8")
    srcs = re.findall(r'\b(?:src|href)="([^"]*)"', text)
    assert len(srcs) == N_FIGURES and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert "<script" not in text and "@import" not in text and "url(" not in text


def test_report_flags_an_outlier_without_reject(made, tmp_path):
    out = tmp_path / "raw.html"
    assert main(["report", str(made / "raw.json"), "-o", str(out), "--force"]) == 0
    text = out.read_text(encoding="utf-8")
    assert "1 outlier point(s) above 5 robust sigma" in text
    assert "flagged (--reject 5 removes it)" in text


def test_report_errors_never_clobber(made, tmp_path, capsys):
    out = tmp_path / "r.html"
    out.write_text("old")
    rc = main(["report", str(made / "rej.json"), "--points", str(made / "points.csv"), "-o", str(out), "--force"])
    assert rc == 2 and "--template" in capsys.readouterr().err
    other = tmp_path / "other.csv"
    s = simulate_set("lens2", n_images=8, noise_mm=0.003, seed=99)
    write_points(other, list(range(8)), list(range(14)), s.points_mm)
    rc = main(["report", str(made / "rej.json"), "--points", str(other), "-t", str(made / "template.csv"), "-o", str(out), "--force"])
    assert rc == 2 and "differ" in capsys.readouterr().err
    rc = main(["report", str(tmp_path / "nope.json"), "-o", str(out), "--force"])
    assert rc == 2 and "nope.json" in capsys.readouterr().err
    blocker = tmp_path / "file"
    blocker.write_text("")
    rc = main(["report", str(made / "rej.json"), "-o", str(blocker / "r.html")])
    assert rc == 2 and "is a file, not a folder" in capsys.readouterr().err  # refused before any work
    assert out.read_text() == "old"


def _chromium():
    from browser import find_chromium

    return find_chromium()


def _on_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def _need_chromium() -> None:
    """Skip without Chromium on a workstation; on CI (CI=true, set by .ci/run) a missing Chromium FAILS."""
    if _chromium() is not None:
        return
    if _on_ci():
        pytest.fail("CI=true but no chromium on PATH: .ci/run must install it so that the browser tests run")
    pytest.skip("no chromium on this machine (apt-get install chromium); CI installs it and fails without it")


def test_ci_has_a_browser():
    if not _on_ci():
        pytest.skip("only enforced on CI (CI=true)")
    assert _chromium() is not None, "CI must install chromium (.ci/run) so that the browser test runs"


def test_ci_run_sets_ci_and_fails_without_chromium(tmp_path):
    """.ci/run exports CI=true (the browser tests then fail rather than skip) and stops when Chromium cannot be had."""
    import subprocess

    script = Path(__file__).resolve().parents[1] / ".ci" / "run"
    text = script.read_text()
    assert re.search(r"^export CI=true$", text, re.M)
    assert "|| echo" not in text and "|| true" not in text
    # its Chromium step alone, with no chromium on PATH and an apt-get that fails, or "succeeds" installing nothing
    step = text[text.index("# chromium-step-begin"):text.index("# chromium-step-end")]
    for rc in (100, 0):
        (tmp_path / "apt-get").write_text(f"#!/bin/sh\nexit {rc}\n")
        (tmp_path / "apt-get").chmod(0o755)
        proc = subprocess.run(["/bin/bash", "-c", "set -euo pipefail\n" + step + "\necho reached"],
                              env={"PATH": str(tmp_path), "HOME": str(tmp_path)}, capture_output=True, text=True,
                              timeout=60)
        assert proc.returncode != 0 and "reached" not in proc.stdout, (rc, proc.returncode, proc.stdout, proc.stderr)
    # and with a chromium on PATH the step passes without installing anything
    (tmp_path / "apt-get").write_text("#!/bin/sh\nexit 100\n")
    (tmp_path / "chromium").write_text("#!/bin/sh\nexit 0\n")
    (tmp_path / "chromium").chmod(0o755)
    proc = subprocess.run(["/bin/bash", "-c", "set -euo pipefail\n" + step + "\necho reached"],
                          env={"PATH": str(tmp_path), "HOME": str(tmp_path)}, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and "reached" in proc.stdout, (proc.stdout, proc.stderr)


def test_report_in_a_headless_browser(made):
    _need_chromium()
    from browser import inspect_page

    page = inspect_page(made / "report.html")
    assert page["errors"] == []
    figs = page["figures"]
    assert len(figs) == N_FIGURES
    img = mpimg.imread(io.BytesIO(page["screenshot"]), format="png")[..., :3]
    for f in figs:
        assert f["complete"] and f["natural"][0] > 100 and f["natural"][1] > 100, f
        x, y, w, h = (int(round(v)) for v in f["rect"])
        assert w > 100 and h > 100, f
        crop = img[y : y + h, x : x + w]
        assert crop.shape[0] > 50 and crop.shape[1] > 50, (f["alt"], crop.shape, img.shape)
        dark = np.mean(np.any(crop < 0.9, axis=-1))
        assert crop.std() > 0.05 and dark > 0.02, (f["alt"], crop.std(), dark)


def test_browser_check_catches_errors(tmp_path):
    """The harness itself: a page with a console error, an exception and a missing image is caught."""
    _need_chromium()
    from browser import inspect_page

    p = tmp_path / "bad.html"
    p.write_text('<!DOCTYPE html><html><body><img alt="x" src="missing.png">'
                 '<script>console.error("boom"); notDefined();</script></body></html>')
    page = inspect_page(p)
    text = " | ".join(page["errors"])
    assert "boom" in text and "notDefined" in text and "missing.png" in text
    assert page["figures"][0]["natural"] == [0, 0]


def test_report_of_a_minimal_calibration_file(made, tmp_path):
    """A calibration JSON with only the contract keys of docs/model.md#calibration-json (no problem record, residual rows or covariance)."""
    import json

    d = json.loads((made / "raw.json").read_text())
    keep = ("intrinsics", "distortion", "std", "extrinsics", "residuals", "cost", "iterations", "converged", "model",
            "software")
    d = {k: v for k, v in d.items() if k in keep}
    rms = d["residuals"]["rms_mm"]
    d["residuals"] = {"rms_mm": rms, "per_image_rms_mm": d["residuals"]["per_image_rms_mm"]}
    (tmp_path / "min.json").write_text(json.dumps(d))
    out = tmp_path / "min.html"
    assert main(["report", str(tmp_path / "min.json"), "-o", str(out), "--force"]) == 2  # no points anywhere
    assert main(["report", str(tmp_path / "min.json"), "--points", str(made / "points.csv"), "-t",
                 str(made / "template.csv"), "-o", str(out), "--force"]) == 0
    text = out.read_text(encoding="utf-8")
    assert f"{rms * 1e3:.3f} um" in text  # residuals recomputed from the parameters and poses agree
    assert "no covariance matrix" in text
    # without a problem record there is no trial refit: the planted point and the neighbours it pulls are flagged
    assert re.search(r"Warning: \d+ outlier point\(s\) above 5 robust sigma", text)


def test_identifiers_are_escaped():
    from psdcal.calibration.core import calibrate
    from psdcal.report.page import build_report

    s = simulate_set("lens2", n_images=4, noise_mm=0.003, seed=8)
    ids = ["<b>img&0</b>", "img'1", 'img"2', "img<3"]
    pids = [f"<i>p{j}</i>" for j in range(14)]
    r = calibrate(s.template_mm, s.points_mm, image_ids=ids, point_ids=pids)
    text = build_report(r)
    for raw in ("<b>img&0</b>", "<i>p0</i>", "img<3"):
        assert raw not in text
    assert html.escape("<b>img&0</b>") in text



def test_report_shows_the_verdicts_notes_and_inflation(made):
    """A good verdict with notes (effects below one sigma) names each, with its size and the covariance inflation.

    The fixture's raw calibration keeps the planted 50-sigma outlier: its verdict is good, with notes on the view
    and the LED that hold it; the calibration with ``--reject 5`` has none.
    """
    import math

    from psdcal.calibration.verdict import Verdict
    from psdcal.io import load_calibration
    from psdcal.report.page import build_report

    raw = load_calibration(made / "raw.json")
    v = Verdict.from_dict(raw.verdict)
    assert v.verdict == "good" and len(v.notes) >= 1 and v.inflation > 1.0
    page = build_report(raw)
    assert f"({len(v.notes)} note(s) below)" in page
    for c in v.notes:
        assert f"Note ({html.escape(c.name)}): {html.escape(c.message)}" in page
        assert f'<td class="">{c.effect_sigma:.3g}</td><td class="">x{c.inflation:.3g}</td>' in page
    assert f"Covariance inflated x{v.inflation:.3g} (standard errors x{math.sqrt(v.inflation):.3g})" in page
    rej = load_calibration(made / "rej.json")
    clean = build_report(rej)
    assert not Verdict.from_dict(rej.verdict).notes
    assert "note(s)" not in clean and "Covariance inflated" not in clean and "every self-check passed" in clean
