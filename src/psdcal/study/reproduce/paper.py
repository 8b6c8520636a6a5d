"""Our numbers beside the paper's: its transcribed tables, the agreement rows, Figure 9 and the remedy summary.

The paper's values are read from ``psdcal/data/paper_tables.csv`` (misprints corrected,
docs/model.md#misprints-in-the-paper).
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, replace
from importlib import resources
from typing import TYPE_CHECKING

import numpy as np

from psdcal.model.params import Distortion, Intrinsics
from psdcal.study.montecarlo import ParameterSummary
from psdcal.study.reproduce.cases import FIGURE9_S_MM, PAPER_TRIALS, REMEDIES, TABLE_PARAMS, _lens_of, figure9_cases, ideal_values, table_columns
from psdcal.study.reproduce.trials import aoa_error_deg, rays_from_points
from psdcal.study.simulate import LENSES, PAPER_L1

if TYPE_CHECKING:  # annotations only: run imports this module
    from psdcal.study.reproduce.run import Study


@dataclass(frozen=True)
class PaperValue:
    """A number of the paper's tables (misprints corrected; ``note`` says where)."""

    table: int
    lens: str
    case: str
    param: str
    ideal: float
    mean: float
    std: float
    note: str


def paper_values() -> list[PaperValue]:
    """All transcribed values of the paper's Tables 1-10 (``psdcal/data/paper_tables.csv``)."""
    text = resources.files("psdcal").joinpath("data/paper_tables.csv").read_text(encoding="utf-8")
    out = []

    def num(v):
        return float(v) if v.strip() else float("nan")

    for row in csv.DictReader(text.splitlines()):
        out.append(PaperValue(int(row["table"]), row["lens"], row["case"], row["param"], num(row["ideal"]),
                              num(row["mean"]), num(row["std"]), row.get("note", "") or ""))
    return out


@dataclass(frozen=True)
class ComparisonRow:
    """One row of a table: our summary beside the paper's number."""

    table: int
    column: str
    param: str
    ideal: float
    mean: float
    std: float
    sem: float
    se_std: float
    n: int
    n_failed: int
    paper_mean: float
    paper_std: float
    mean_agrees: str
    std_agrees: str
    unbiased: str
    note: str

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def _agree(ours: float, ours_se: float, paper: float, paper_se: float) -> str:
    if not (np.isfinite(ours) and np.isfinite(paper) and np.isfinite(ours_se)):
        return "n/a"
    se = math.hypot(ours_se, paper_se if np.isfinite(paper_se) else 0.0)
    return "yes" if abs(ours - paper) <= 3.0 * se else "no"


def compare_rows(table: int, results: dict, paper: list[PaperValue]) -> list[ComparisonRow]:
    """Rows of Table ``table``: each column's parameters, ours beside the paper's.

    Parameters
    ----------
    results : dict
        ``Case.key`` (or ``"initial_<lens>"``) -> :class:`CaseResult`.
    """
    lens = _lens_of(table)
    pv = {(p.case, p.param): p for p in paper if p.table == table}
    rows = []
    for col in table_columns(table):
        if col.case is None:
            res = results[f"initial_{lens}"]
            params = ("cx_mm", "cy_mm", "f_mm")
            ideal = ideal_values(lens, False)
        else:
            res = results[col.case.key]
            params = TABLE_PARAMS
            ideal = ideal_values(lens, col.case.psd)
        summ = res.summaries.get(col.variant, {})
        for param in params:
            s: ParameterSummary | None = summ.get(param)
            p = pv.get((col.paper_case, param))
            mean = s.mean if s else float("nan")
            std = s.std if s else float("nan")
            sem = s.sem if s else float("nan")
            se_std = s.se_std if s else float("nan")
            pm = p.mean if p else float("nan")
            ps = p.std if p else float("nan")
            note = p.note if p else ""
            if p is not None and not np.isfinite(ps):
                # a single set in the paper: compare with our set-to-set spread
                mean_ok = _agree(mean, math.hypot(std, sem) if np.isfinite(std) else float("nan"), pm, 0.0)
                std_ok = "n/a"
            else:
                mean_ok = _agree(mean, sem, pm, ps / math.sqrt(PAPER_TRIALS))
                std_ok = _agree(std, se_std, ps, ps / math.sqrt(2 * (PAPER_TRIALS - 1)))
            if param in ("residual_mm", "iterations"):
                unb = "n/a"
            else:
                iv = ideal[param]
                unb = "n/a" if not (np.isfinite(sem) and sem > 0) else ("yes" if abs(mean - iv) <= 3 * sem else "no")
            rows.append(ComparisonRow(table, col.title, param, ideal.get(param, float("nan")), mean, std, sem, se_std,
                                      s.n if s else 0, s.n_failed if s else 0, pm, ps, mean_ok, std_ok, unb, note))
    return rows


def figure9_errors(lens: str, summaries: dict, psd: bool, *, s_mm: float = FIGURE9_S_MM, n: int = 61):
    """AoA (deg) and position (mm) error maps over the sensor for "mean + 2 std" parameters.

    As the paper's Figure 9: the calibrated ``f, C, k1, k2`` set to their mean
    plus twice their standard deviation over the trials; each impact point
    ``d`` of an ``n x n`` grid over the active area is mapped to a ray by the
    true model (lens distortion, plus the PSD's l1 when ``psd``) and by the
    perturbed model; the AoA error is the angle between the two rays, the
    position error that of a transmitter on the plane at distance ``s_mm``
    (``X = S x_n``, ``Y = S y_n``, Section 3.4).

    Returns
    -------
    d_mm : (n, n, 2), aoa_deg : (n, n), position_mm : (n, n)
    """
    intr, dist = LENSES[lens]
    true_dist = replace(dist, l1=PAPER_L1 if psd else 0.0)

    def val(p):
        s = summaries[p]
        return s.mean + 2.0 * (s.std if np.isfinite(s.std) else 0.0)

    est_intr = Intrinsics(f_mm=val("f_mm"), cx_mm=val("cx_mm"), cy_mm=val("cy_mm"))
    est_dist = Distortion(k1=val("k1"), k2=val("k2"))
    g = np.linspace(-4.5, 4.5, n)
    X, Y = np.meshgrid(g, g)
    d = np.stack([X, Y], axis=-1).reshape(-1, 2)
    r_true = rays_from_points(d, intr, true_dist)
    r_est = rays_from_points(d, est_intr, est_dist)
    aoa = aoa_error_deg(r_true, r_est)
    pos = s_mm * np.linalg.norm(r_est[:, :2] / r_est[:, 2:3] - r_true[:, :2] / r_true[:, 2:3], axis=1)
    return d.reshape(n, n, 2), aoa.reshape(n, n), pos.reshape(n, n)


def figure9_summary(study: Study) -> list[dict]:
    """Max and RMS of the Figure 9 error maps for each lens and Table 9/10 column available."""
    out = []
    for lens in ("lens1", "lens2"):
        for col in figure9_cases(lens):
            res = study.results.get(col.case.key)
            if res is None or "paper" not in res.summaries:
                continue
            _, aoa, pos = figure9_errors(lens, res.summaries["paper"], col.case.psd)
            out.append({"lens": lens, "case": col.title, "aoa_max_deg": float(np.nanmax(aoa)),
                        "aoa_rms_deg": float(np.sqrt(np.nanmean(aoa**2))), "position_max_cm": float(np.nanmax(pos)) / 10,
                        "position_rms_cm": float(np.sqrt(np.nanmean(pos**2))) / 10})
    return out


def pooled_rms(values) -> tuple[float, float]:
    """RMS over trials of per-trial RMS values, and its standard error (delta method)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size < 2:
        return float("nan"), float("nan")
    ms = np.mean(v**2)
    se_ms = np.std(v**2, ddof=1) / np.sqrt(v.size)
    rms = float(np.sqrt(ms))
    return rms, float(se_ms / (2 * rms)) if rms > 0 else float("nan")


def remedy_rows(study: Study) -> list[dict]:
    """One row per remedy case and remedy: parameters (mean, std) and the held-out AoA error."""
    rows = []
    for res in study.remedies:
        base, _ = pooled_rms(res.values.get("balanced", {}).get("aoa_rms_deg", []))
        for name, desc in REMEDIES:
            summ = res.summaries.get(name, {})
            vals = res.values.get(name, {})
            rms, se = pooled_rms(vals.get("aoa_rms_deg", []))
            row = {"lens": res.lens, "case": res.case.label, "remedy": name, "description": desc,
                   "n": summ["f_mm"].n if "f_mm" in summ else 0,
                   "n_failed": summ["f_mm"].n_failed if "f_mm" in summ else 0,
                   "aoa_rms_deg": rms, "aoa_rms_se_deg": se, "ratio_to_reference": rms / base if base > 0 else float("nan")}
            for p in ("f_mm", "cx_mm", "cy_mm", "k1", "k2", "fy_mm", "skew", "g_x2_err", "g_y1_err", "g_y2_err"):
                if p in summ:
                    row[f"{p}_mean"] = summ[p].mean
                    row[f"{p}_std"] = summ[p].std
            rows.append(row)
    return rows
