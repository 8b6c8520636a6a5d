"""The calibration report: one self-contained HTML page to accept or reject a calibration.

The page holds, with every figure inline (PNG as ``data:`` URIs; no script,
no font, no style sheet from the network):

* the parameters with standard errors and their correlation matrix;
* the residual vectors of every point on the sensor (all images, and per
  image), their histogram against the noise the fit implies;
* the per-image RMS, with outlier images and points flagged
  (:mod:`psdcal.calibration.outliers`), and the points an outlier rejection removed;
* the coverage of the sensor by calibration points, with a warning for
  cells of the measurement region without data (:mod:`psdcal.calibration.checks`);
* the distortion field and the AoA uncertainty over the field of view
  (:mod:`psdcal.report.compare`), in degrees;
* the provenance: input files with their SHA-256, the options, the software
  versions and the dates.

Use :func:`build_report` for the HTML text and :func:`write_report` to write
it atomically; ``psdcal report`` is the command-line front.
"""
from __future__ import annotations

import base64
import datetime as _dt
import hashlib
import html
import io
import json
import math
import platform
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from psdcal import __version__
from psdcal.errors import InputError
from psdcal.calibration.outliers import DEFAULT_K

#: Units of the global parameters, for the tables.
UNITS = {
    "f_mm": "mm", "fy_mm": "mm", "cx_mm": "mm", "cy_mm": "mm", "skew": "mm",
    "k1": "mm^-2", "k2": "mm^-4", "k3": "mm^-6", "p1": "mm^-1", "p2": "mm^-1", "l1": "mm^-2", "l2": "mm^-4",
    "g_x2": "1", "g_y1": "1", "g_y2": "1",
}

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;margin:0 auto;max-width:1100px;
padding:1.2em 2em 3em;color:#1d2327;line-height:1.4}
h1{font-size:1.6em;margin-bottom:.2em}h2{font-size:1.25em;border-bottom:2px solid #d0d7de;padding-bottom:.2em;margin-top:1.8em}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}th,td{border:1px solid #d0d7de;padding:.25em .6em;text-align:right}
th{background:#f2f4f6}td{white-space:nowrap}td.l,th.l{text-align:left}tr.bad td{background:#fde8e8}
figure{margin:.8em 0;text-align:center}figure img{max-width:100%;height:auto;border:1px solid #e4e7ea}
figcaption{font-size:.85em;color:#57606a;max-width:900px;margin:.3em auto}
.warn{background:#fff4e5;border-left:4px solid #e8590c;padding:.5em .9em;margin:.4em 0}
.ok{background:#e8f6ec;border-left:4px solid #2b8a3e;padding:.5em .9em;margin:.4em 0}
.note{background:#eef3fb;border-left:4px solid #1c7ed6;padding:.5em .9em;margin:.4em 0}
.info{color:#57606a;font-size:.9em}code,pre{font-family:ui-monospace,Menlo,Consolas,monospace;font-size:.85em}
pre{background:#f6f8fa;padding:.6em;overflow-x:auto;text-align:left}
.grid{display:flex;flex-wrap:wrap;gap:1em;justify-content:center;align-items:flex-start}.grid figure{flex:1 1 460px}.side{flex:0 1 440px}
"""


def sha256_file(path) -> str:
    """SHA-256 (hex) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass(frozen=True)
class ReportInputs:
    """The files a report was made from (all optional) and how the command was called.

    Attributes
    ----------
    calibration : path of the calibration JSON, or None (a result in memory).
    points, template : paths of the points and template CSV, or None.
    command : the command line, for the provenance table.
    """

    calibration: str | None = None
    points: str | None = None
    template: str | None = None
    command: str | None = None
    extra: dict = field(default_factory=dict)


def _esc(v) -> str:
    return html.escape(str(v), quote=True)


def _fig(fig, alt: str, caption: str, fid: str) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return (f'<figure id="fig-{_esc(fid)}"><img class="figure" alt="{_esc(alt)}" '
            f'src="data:image/png;base64,{data}"><figcaption>{_esc(caption)}</figcaption></figure>')


def _fmt(v, fmt="{:.6g}") -> str:
    if v is None:
        return "fixed"
    try:
        f = float(v)
    except (TypeError, ValueError):
        return _esc(v)
    return "-" if not np.isfinite(f) else fmt.format(f)


def _table(head, rows, classes=None, left=(0,)) -> str:
    out = ["<table><tr>" + "".join(f'<th class="{"l" if i in left else ""}">{_esc(h)}</th>' for i, h in enumerate(head)) + "</tr>"]
    for r, row in enumerate(rows):
        cls = f' class="{classes[r]}"' if classes and classes[r] else ""
        out.append(f"<tr{cls}>" + "".join(f'<td class="{"l" if i in left else ""}">{c}</td>' for i, c in enumerate(row)) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _files_and_points(result, inputs: ReportInputs):
    """Read the optional points/template files.

    Returns (result, points_mm or None, line_numbers or None, file records); the result is aligned to the
    files when it has no problem record of its own.
    """
    from psdcal.io import read_points, read_template

    files = []
    pts = lines = None
    if (inputs.points is None) != (inputs.template is None):
        missing = "--template" if inputs.template is None else "--points"
        raise InputError(f"{missing} is needed too: the points file is read against its template", field=missing)
    if inputs.points is not None:
        tids, txy = read_template(inputs.template)
        if "template" in (result.problem or {}) and tuple(tids) != tuple(result.point_ids):
            raise InputError(f"template point ids {list(tids)[:6]}... do not match the calibration's "
                             f"{list(result.point_ids)[:6]}...", path=inputs.template)
        prob_t = np.asarray(result.problem.get("template", {}).get("xy_mm", txy), dtype=float)
        if prob_t.shape == txy.shape and not np.allclose(prob_t, txy, atol=1e-6):
            raise InputError("template coordinates differ from those the calibration used", path=inputs.template)
        pf = read_points(inputs.points, tids, sensor_mm=result.sensor_mm)
        index = {iid: i for i, iid in enumerate(pf.image_ids)}
        missing = [i for i in result.image_ids if i not in index]
        if missing:
            raise InputError(f"image(s) {missing[:5]} of the calibration are not in the points file", path=inputs.points,
                             field="image_id")
        order = [index[i] for i in result.image_ids]
        pts = pf.points_mm[order]
        lines = pf.line_numbers[order]
        if "template" not in (result.problem or {}):
            from psdcal.calibration.checks import with_points

            result = with_points(result, tids, txy, pts)
        if "points" in result.problem:
            from psdcal.calibration.checks import measured_points_mm

            used = measured_points_mm(result)
            both = np.all(np.isfinite(used), axis=-1)
            if pts.shape != used.shape or not np.allclose(pts[both], used[both], atol=1e-6):
                raise InputError("the points differ from those the calibration used (another data set?)",
                                 path=inputs.points)
        files += [("template", inputs.template), ("points", inputs.points)]
    if inputs.calibration is not None:
        files.insert(0, ("calibration", inputs.calibration))
    return result, pts, lines, [(role, str(p), sha256_file(p), Path(p).stat().st_size) for role, p in files]


def report_verdict(result):
    """The calibration's verdict (:class:`psdcal.calibration.verdict.Verdict`): the one saved in it, else assessed now.

    None when the file holds no problem record to assess.
    """
    from psdcal.calibration.verdict import Verdict, assess

    if getattr(result, "verdict", None):
        return Verdict.from_dict(result.verdict)
    if not (result.problem or {}).get("points"):
        return None
    try:
        return assess(result)
    except Exception:  # noqa: BLE001 -- an old or partial file: the report goes on without a verdict
        return None


def _verdict_html(verdict) -> list:
    """The report's first section: the verdict, its advice and notes, the covariance inflation, the checks.

    The notes are the checks that passed with an effect below one standard error: the effect is stated in its
    own sigmas and the covariance inflation it brings (``1 + effect^2``) is named, as the text summary does.
    """
    if verdict is None:
        return ['<h2 id="verdict">Verdict</h2>', '<div class="warn">No verdict: the calibration file holds no problem '
                'record (points, template) to check it against.</div>']
    cls = {"good": "ok", "suspect": "warn", "wrong": "warn"}[verdict.verdict]
    notes = verdict.notes
    good = "GOOD: every self-check passed" + (f" ({len(notes)} note(s) below)" if notes else "")
    head = {"good": good, "suspect": "SUSPECT: " + "; ".join(verdict.reasons),
            "wrong": "WRONG: " + "; ".join(verdict.reasons)}[verdict.verdict]
    out = ['<h2 id="verdict">Verdict</h2>', f'<div class="{cls}"><b>{_esc(head)}</b></div>']
    out += [f'<div class="warn">Advice ({_esc(c.name)}): {_esc(c.advice)}</div>' for c in verdict.failed if c.advice]
    out += [f'<div class="note">Note ({_esc(c.name)}): {_esc(c.message)}</div>' for c in notes]
    f = verdict.inflation
    if f > 1.0:
        why = ", ".join(c.name for c in verdict.checks if (c.inflation or 1.0) == f)
        out.append(f'<div class="note">Covariance inflated x{f:.3g} (standard errors x{math.sqrt(f):.3g}) to cover '
                   f'the effect found by {_esc(why)}: the uncertainties in this report include it.</div>')
    rows = []
    for c in verdict.checks:
        state = "n/a" if c.passed is None else ("passed" if c.passed else "FAILED")
        rows.append([_esc(c.name), state, "-" if c.p_value is None else f"{c.p_value:.2g}",
                     f"{c.false_alarm:.2g}" if c.false_alarm else "rule",
                     "-" if c.effect_sigma is None else f"{c.effect_sigma:.3g}",
                     "-" if not c.inflation or c.inflation <= 1.0 else f"x{c.inflation:.3g}", _esc(c.message)])
    out.append(_table(["check", "result", "p-value", "false-alarm rate", "effect (sigma)", "covariance inflation",
                       "finding"], rows, left=(0, 1, 6)))
    return out


def build_report(result, inputs: ReportInputs = ReportInputs(), *, k: float = DEFAULT_K, n_cells: int = 6,
                 region_mm=None, title: str | None = None) -> str:
    """The calibration report as one self-contained HTML document.

    Parameters
    ----------
    result : CalibrationResult
        A calibration (e.g. :func:`psdcal.io.load_calibration`); its problem
        record gives the measured points unless ``inputs.points`` does.
    inputs : ReportInputs
        Paths of the files for provenance (checksums) and, with both
        ``points`` and ``template``, the measured points and their line numbers.
    k : float
        Outlier threshold in robust standard deviations.
    n_cells : int
        Coverage cells per side of the sensor.
    region_mm : (x0, x1, y0, y1), optional
        The part of the sensor used for measurement (default all of it).
    title : str, optional

    Returns
    -------
    str
        The HTML text (UTF-8).

    Raises
    ------
    InputError
        Files that do not match the calibration, or a calibration without points.
    """
    from psdcal.report import plots
    from psdcal.report.compare import fov_uncertainty
    from psdcal.calibration.checks import align_to_problem, coverage, measured_points_mm
    from psdcal.calibration.outliers import flag_outliers, removed_points

    result = align_to_problem(result)
    result, pts, lines, files = _files_and_points(result, inputs)
    X = measured_points_mm(result) if pts is None else pts
    flags = flag_outliers(result, k, refit=True)
    cov = coverage(X, result.sensor_mm, n_cells=n_cells, region_mm=region_mm)
    fov = fov_uncertainty(result)
    removed = removed_points(result)
    figs = plots.all_figures(result, k=k, n_cells=n_cells, region_mm=region_mm, flags=flags, points_mm=X)
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    name = Path(inputs.calibration).name if inputs.calibration else "calibration"
    title = title or f"psdcal calibration report: {name}"

    # -- verdict --------------------------------------------------------------------
    warnings = []
    if not result.converged:
        warnings.append(f"the refinement did not converge ({result.message})")
    verdict = report_verdict(result)
    systematic = verdict is not None and any(c.name == "structure" and c.passed is False for c in verdict.checks)
    if flags.n_points and systematic:
        warnings.append(f"{flags.n_points} point(s) above {k:g} robust sigma, but the misfit is systematic (see the "
                        "verdict): --reject would delete good points; fix the cause first")
    elif flags.n_points:
        warnings.append(f"{flags.n_points} outlier point(s) above {k:g} robust sigma (see Outliers); "
                        f"psdcal calibrate --reject {k:g} removes them and refits")
    if flags.images.any():
        ids = [str(result.image_ids[i]) for i in np.nonzero(flags.images)[0]]
        warnings.append(f"image(s) {', '.join(ids)} fit worse than the noise allows (chi-square test)")
    warnings += cov.warnings()
    warnings += result.warnings()
    if np.asarray(result.covariance).size == 0:
        warnings.append("the calibration file holds no covariance matrix: the AoA uncertainty uses the standard errors "
                        "alone (correlations ignored)")
    corr = result.correlation() if len(result.param_names) else np.zeros((0, 0))
    strong = [(result.param_names[i], result.param_names[j], corr[i, j]) for i in range(len(corr))
              for j in range(i + 1, len(corr)) if abs(corr[i, j]) > 0.95]

    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{_esc(title)}</title>",
             '<meta name="viewport" content="width=device-width, initial-scale=1">', f"<style>{_CSS}</style></head><body>",
             f"<h1>{_esc(title)}</h1>",
             f'<p class="info">{len(result.image_ids)} images, {int(np.isfinite(result.residuals_mm[..., 0]).sum())} points, '
             f"{_esc(result.cost)} cost; calibrated {_esc(result.created or 'unknown')}; report made {_esc(now)} "
             f"by psdcal {_esc(__version__)}.</p>"]
    parts += _verdict_html(verdict)
    parts.append("<h2 id=\"summary\">Summary</h2>")
    s_tot = fov.sigma_total_deg
    parts.append(_table(["quantity", "value"], [
        ["residual RMS on the sensor", f"{result.rms_mm * 1e3:.3f} um"],
        ["noise implied by the fit (per coordinate)", f"{result.sigma_mm * 1e3:.3f} um"],
        ["robust noise estimate (median |r|)", f"{flags.sigma_mm * 1e3:.3f} um"],
        ["solver", f"{result.iterations} iterations, {'converged' if result.converged else 'NOT converged'}"],
        ["outlier points / images", f"{flags.n_points} / {int(flags.images.sum())} (threshold {k:g} sigma)"],
        ["points removed by --reject", str(len(removed))],
        ["coverage of the measurement region", f"{cov.fraction_covered * 100:.0f} % of {int(cov.in_region.sum())} cells"],
        ["AoA uncertainty (1 sigma, calibration)",
         f"{np.min(s_tot):.3g} deg (best) / {np.median(s_tot):.3g} deg (median) / {np.max(s_tot):.3g} deg (worst)"],
    ]))
    if warnings:
        parts += [f'<div class="warn">Warning: {_esc(w)}</div>' for w in warnings]
    else:
        parts.append('<div class="ok">No warning: residuals consistent with the noise, no outlier, the measurement '
                     'region covered.</div>')

    # -- parameters -------------------------------------------------------------------
    parts.append("<h2 id=\"parameters\">Parameters</h2>")
    rows = []
    names = list(dict.fromkeys([*result.param_names, *result.std.keys()]))
    for n in names:
        try:
            v = result.parameter(n)
        except (AttributeError, KeyError):
            continue
        sd = result.std.get(n)
        rel = "-" if sd is None or v == 0 else f"{abs(sd / v) * 100:.2g} %"
        rows.append([_esc(n), _fmt(v, "{:.8g}"), _fmt(sd, "{:.3g}"), rel, _esc(UNITS.get(n, ""))])
    parts.append('<div class="grid"><div class="side">' + _table(["parameter", "value", "std error", "relative", "unit"], rows,
                                                      left=(0, 4)))
    parts.append('<p class="info">Standard errors from the Jacobian at the solution, scaled by the implied noise; '
                 'the poses are marginalised. "fixed": not estimated in this model.</p></div>')
    parts.append(_fig(figs["correlation"], "correlation matrix", "Correlation matrix of the free parameters.",
                      "correlation") + "</div>")
    if strong:
        parts.append('<p class="info">Strongly correlated (|r| &gt; 0.95): '
                     + ", ".join(f"{_esc(a)}-{_esc(b)} {c:+.3f}" for a, b, c in strong)
                     + ". Their individual values are poorly determined; their combined effect is not.</p>")

    # -- residuals ------------------------------------------------------------------------
    parts.append("<h2 id=\"residuals\">Residuals</h2>")
    parts.append('<div class="grid">' + _fig(figs["residuals"], "residual vectors on the sensor",
                 "Measured minus modelled impact point, all images (colour per image); circles: outliers, "
                 "crosses: removed points.", "residuals")
                 + _fig(figs["residual_histogram"], "residual histogram",
                        "Residual components against the normal density with the noise the fit implies.",
                        "residual_histogram") + "</div>")
    parts.append(_fig(figs["residuals_per_image"], "residual vectors per image", "Residuals per image, same arrow scale.",
                      "residuals_per_image"))

    # -- per image and outliers ---------------------------------------------------------
    parts.append("<h2 id=\"outliers\">Per-image RMS and outliers</h2>")
    parts.append(_fig(figs["per_image_rms"], "per-image RMS", "RMS residual per image; red: image flagged by the "
                      "chi-square test, hatched: holds an outlier point; dashed: expected RMS.", "per_image_rms"))
    valid = np.all(np.isfinite(result.residuals_mm), axis=-1)
    rows, cls = [], []
    for i, iid in enumerate(result.image_ids):
        rows.append([_esc(iid), str(int(valid[i].sum())), f"{result.per_image_rms_mm[i] * 1e3:.3f}",
                     f"{flags.image_p_values[i]:.2g}", str(int(flags.points[i].sum())),
                     "outlier" if flags.images[i] else ""])
        cls.append("bad" if flags.images[i] else "")
    parts.append(_table(["image", "points", "RMS [um]", "p-value", "outlier points", "flag"], rows, cls, left=(0, 5)))
    rows = []
    for i, j in zip(*np.nonzero(flags.points)):
        r = result.residuals_mm[i, j]
        line = "-" if lines is None or not lines[i, j] else str(int(lines[i, j]))
        rows.append([_esc(result.image_ids[i]), _esc(result.point_ids[j]), f"{X[i, j, 0]:.4f}", f"{X[i, j, 1]:.4f}",
                     f"{np.hypot(*r) * 1e3:.2f}", f"{flags.ratio[i, j]:.1f}", line, f"flagged (--reject {k:g} removes it)"])
    for p in removed:
        line = "-" if p.line is None else str(p.line)
        rows.append([_esc(p.image_id), _esc(p.point_id), f"{p.x_mm:.4f}", f"{p.y_mm:.4f}", f"{p.residual_mm * 1e3:.2f}",
                     f"{p.ratio:.1f}", line, "removed by --reject, refitted without it"])
    if rows:
        parts.append(_table(["image", "point", "x [mm]", "y [mm]", "|r| [um]", "|r| / sigma", "line", "status"], rows,
                            ["bad"] * len(rows), left=(0, 1, 7)))
    else:
        parts.append(f'<p class="ok">No point above {k:g} robust standard deviations.</p>')
    parts.append(f'<p class="info">Robust noise sigma = median |r| / sqrt(2 ln 2) = {flags.sigma_mm * 1e3:.3f} um; a point is '
                 f"an outlier above {k:g} sigma (chance {np.exp(-k * k / 2):.1g} per clean point), confirmed by a trial "
                 "refit without it.</p>")

    # -- coverage -----------------------------------------------------------------------
    parts.append("<h2 id=\"coverage\">Coverage of the sensor</h2>")
    parts.append(_fig(figs["coverage"], "coverage map", "Calibration points per cell of the sensor; dashed blue: the "
                      "measurement region; red hatching: region cells without any calibration point.", "coverage"))
    cw = cov.warnings()
    parts += [f'<div class="warn">Warning: {_esc(w)}</div>' for w in cw] or [
        '<div class="ok">Every cell of the measurement region holds calibration points.</div>']

    # -- distortion and AoA uncertainty ---------------------------------------------------------
    parts.append("<h2 id=\"distortion\">Distortion field and angle-of-arrival uncertainty</h2>")
    parts.append('<div class="grid">' + _fig(figs["distortion_field"], "distortion field",
                 "Correction undistort(d) - d over the sensor (lens and PSD), colour its length.", "distortion_field")
                 + _fig(figs["aoa_uncertainty"], "AoA uncertainty map",
                        "1-sigma uncertainty of the angle of arrival from the calibration covariance "
                        "(sqrt(var alpha_x + var alpha_y)), over the field of view, degrees. This error is systematic: "
                        "the same for every measurement.", "aoa_uncertainty") + "</div>")

    # -- provenance ------------------------------------------------------------------------------
    parts.append("<h2 id=\"provenance\">Provenance</h2>")
    rec = (result.problem or {}).get("files", {}) or {}
    rows = []
    for role, p, digest, size in files:
        match = ""
        if role in rec and isinstance(rec[role], dict) and rec[role].get("sha256"):
            match = "matches the calibration's record" if rec[role]["sha256"] == digest else "DIFFERS from the calibration's record"
        rows.append([_esc(role), f"<code>{_esc(p)}</code>", f"<code>{digest}</code>", str(size), _esc(match)])
    for role, d in rec.items():
        if isinstance(d, dict) and not any(role == f[0] for f in files):
            rows.append([_esc(role) + " (recorded)", f"<code>{_esc(d.get('path', ''))}</code>",
                         f"<code>{_esc(d.get('sha256', ''))}</code>", "-", "recorded when calibrating"])
    if rows:
        parts.append(_table(["file", "path", "SHA-256", "bytes", "check"], rows, left=(0, 1, 2, 4)))
    try:
        import matplotlib
        import scipy
        vers = f"numpy {np.__version__}, scipy {scipy.__version__}, matplotlib {matplotlib.__version__}"
    except ImportError:  # pragma: no cover
        vers = f"numpy {np.__version__}"
    soft = {}
    if inputs.calibration is not None:
        try:
            soft = json.loads(Path(inputs.calibration).read_text(encoding="utf-8")).get("software", {}) or {}
        except (OSError, ValueError, AttributeError):
            soft = {}
    rows = [["calibrated with", _esc(f"psdcal {soft.get('version', '') or 'see the calibration file'}")],
            ["calibration created", _esc(result.created or "unknown")],
            ["report made with", _esc(f"psdcal {__version__}; Python {platform.python_version()}; {vers}")],
            ["report made", _esc(now)]]
    if inputs.command:
        rows.append(["command", f"<code>{_esc(inputs.command)}</code>"])
    for key, v in inputs.extra.items():
        rows.append([_esc(key), _esc(v)])
    parts.append(_table(["software and dates", ""], rows, left=(0, 1)))
    opts = dict((result.problem or {}).get("options", {}))
    rej = (result.problem or {}).get("outlier_rejection")
    if rej:
        opts["outlier_rejection"] = {k_: v for k_, v in rej.items() if k_ != "removed"}
    opts["report"] = {"k": k, "n_cells": n_cells, "region_mm": None if region_mm is None else list(region_mm)}
    rows = [[_esc(key), f"<code>{_esc(json.dumps(v, default=str))}</code>"] for key, v in opts.items()]
    parts.append("<p>Options of the calibration (and of this report):</p>" + _table(["option", "value"], rows, left=(0, 1)))
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def write_report(path, result, inputs: ReportInputs = ReportInputs(), **kwargs) -> None:
    """Build the report (:func:`build_report`) and write it atomically to ``path``.

    An existing file at ``path`` is replaced only when the whole report was built.
    """
    from psdcal._atomic import write_text_atomic

    text = build_report(result, inputs, **kwargs)
    try:
        write_text_atomic(path, text)
    except OSError as exc:
        raise InputError(f"cannot write the report: {exc.strerror or exc}", path=path, field="--output") from None


__all__ = ["ReportInputs", "UNITS", "build_report", "sha256_file", "write_report"]
