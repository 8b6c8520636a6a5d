"""The study's definitions: cases (settings), the columns of each of the paper's Tables 1-10, the ideal values.

No computation here: what the paper ran, as data (docs/model.md#paper-simulation-setup).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from psdcal.errors import InputError
from psdcal.study.simulate import LENSES, PAPER_L1


#: Parameters of the paper's tables, in their order.
TABLE_PARAMS = ("cx_mm", "cy_mm", "f_mm", "k1", "k2", "residual_mm", "iterations")


#: Trials the paper ran per setting (Sections 4.3-4.4).
PAPER_TRIALS = 200


#: Distance of the mobile agent's plane for Figure 9, mm (5 m).
FIGURE9_S_MM = 5000.0


@dataclass(frozen=True)
class Case:
    """One Monte Carlo setting of the study.

    Attributes
    ----------
    lens : "lens1" | "lens2"
    snr_db : float
        SNR, dB (docs/model.md#signal-chain); NaN for no noise.
    imbalance : bool
        Draw the four channels' R, C within their tolerances (Section 4.4).
    psd : bool
        PSD pin-cushion distortion l1 = -1.3058e-3 mm^-2 (Section 4.5).
    kind : "noise" | "gain" | "psd" | "plain"
        What the trial computes besides the paper's calibration: ``noise``
        also without the preliminary corrections and with the image cost
        (Tables 3-4); ``gain`` the four remedies (Tables 5-6); ``psd`` also
        the model with the PSD term l1 (``psd_radial=1``); ``plain`` only the
        paper's calibration.
    """

    lens: str
    snr_db: float = float("nan")
    imbalance: bool = False
    psd: bool = False
    kind: str = "plain"

    @property
    def key(self) -> str:
        snr = "none" if math.isnan(self.snr_db) else f"{self.snr_db:g}"
        return f"{self.lens}_snr{snr}{'_imb' if self.imbalance else ''}{'_psd' if self.psd else ''}_{self.kind}"

    @property
    def label(self) -> str:
        parts = ["no noise" if math.isnan(self.snr_db) else f"SNR {self.snr_db:g} dB"]
        if self.imbalance:
            parts.append("imbalance")
        if self.psd:
            parts.append("PSD distortion")
        return ", ".join(parts)


@dataclass(frozen=True)
class Column:
    """A column of a table: the paper's case name, our case and the variant of its trial."""

    paper_case: str
    title: str
    case: Case | None
    variant: str = "paper"


def _lens_of(table: int) -> str:
    return "lens1" if table % 2 == 1 else "lens2"


def table_columns(table: int) -> list[Column]:
    """The columns of the paper's Table ``table`` (1-10) and the cases that reproduce them."""
    lens = _lens_of(table)
    nan = float("nan")
    if table in (1, 2):
        return [Column(c, t, None, c) for c, t in (
            ("noprelim_dlt", "without preliminary correction, DLT"),
            ("noprelim_norm", "without preliminary correction, normalised DLT"),
            ("prelim_dlt", "with preliminary correction, DLT"),
            ("prelim_norm", "with preliminary correction and normalisation"))]
    if table in (3, 4):
        cols = []
        for variant, word in (("paper", "with"), ("without", "without")):
            for snr in (30.0, 40.0, 50.0):
                cols.append(Column(f"{word}_{snr:g}", f"{word} corrections, {snr:g} dB", Case(lens, snr, kind="noise"), variant))
        return cols
    if table in (5, 6):
        return [Column(f"imb_{n}", f"imbalance, {t}", Case(lens, s, True, False))
                for n, s, t in (("40", 40.0, "40 dB"), ("50", 50.0, "50 dB"), ("none", nan, "no noise"))]
    if table in (7, 8):
        return [
            Column("psd", "PSD distortion", Case(lens, nan, False, True)),
            Column("psd_40", "PSD distortion, 40 dB", Case(lens, 40.0, False, True)),
            Column("psd_imb", "PSD distortion, imbalance", Case(lens, nan, True, True)),
            Column("psd_imb_40", "PSD distortion, imbalance, 40 dB", Case(lens, 40.0, True, True)),
        ]
    if table in (9, 10):
        return [
            Column("snr40", "40 dB", Case(lens, 40.0, kind="noise")),
            Column("snr40_imb", "40 dB, imbalance", Case(lens, 40.0, True, False)),
            Column("snr40_psd", "40 dB, PSD distortion", Case(lens, 40.0, False, True)),
            Column("snr40_imb_psd", "40 dB, imbalance, PSD distortion", Case(lens, 40.0, True, True)),
            Column("snr50_psd", "50 dB, PSD distortion (practical case)", Case(lens, 50.0, False, True)),
        ]
    raise InputError(f"the paper's study has Tables 1-10, got {table}", field="table")


def ideal_values(lens: str, psd: bool) -> dict:
    """True parameter values of a case (k1 = lens k1 + PSD l1 when the PSD distorts, Section 4.5)."""
    intr, dist = LENSES[lens]
    k1 = dist.k1 + (PAPER_L1 if psd else 0.0)
    return {"cx_mm": intr.cx_mm, "cy_mm": intr.cy_mm, "f_mm": intr.f_mm, "k1": k1, "k2": dist.k2,
            "residual_mm": 0.0, "iterations": float("nan")}


def required_cases(tables) -> list:
    """The cases (and ``initial_<lens>`` runs) that the given tables need, without duplicates."""
    need: dict = {}
    for t in tables:
        for col in table_columns(int(t)):
            if col.case is None:
                need[f"initial_{_lens_of(int(t))}"] = None
            else:
                need[col.case.key] = col.case
    return list(need.items())


def remedy_cases(lens: str) -> list[Case]:
    """The Tables 5-6 settings on which the gain remedies are compared (40 dB, 50 dB, no noise)."""
    return [Case(lens, snr, True, False, "gain") for snr in (40.0, 50.0, float("nan"))]


def figure9_cases(lens: str) -> list[Column]:
    """The Table 9/10 columns Figure 9 draws."""
    return table_columns(9 if lens == "lens1" else 10)


#: Remedy variants of :func:`gain_trial`, in report order, with their descriptions.
REMEDIES = (
    ("balanced", "reference: equal gains, paper's model (image cost)"),
    ("paper", "(a) paper's model ignoring the imbalance, template cost (Tables 5-6)"),
    ("a", "(a) paper's model ignoring the imbalance, image cost"),
    ("b", "(b) electrical calibration (7x7 spots, bare PSD), amplitudes corrected"),
    ("c", "(c) joint calibration of gains + geometry (calibrate --fit-gains)"),
    ("d", "(d) general intrinsic matrix (fx, fy, skew) instead of gains"),
)
