"""psdcal reproduce: the paper's study re-run (tables, agreement flags, Figure 9, CLI)."""
import math

import numpy as np
import pytest

from psdcal.study import reproduce as R
from psdcal.study.montecarlo import ParameterSummary


def test_paper_values_transcribed_with_misprints_corrected():
    pv = {(p.table, p.case, p.param): p for p in R.paper_values()}
    assert len({p.table for p in pv.values()}) == 10
    # Tables 3-4 as in the project's corrected tables.csv
    assert pv[(4, "without_30", "k1")].mean == pytest.approx(9.873e-3)
    assert pv[(4, "with_40", "k2")].mean == pytest.approx(2.4541e-5)
    assert pv[(3, "with_50", "f_mm")].std == pytest.approx(5.4405e-3)
    # docs/model.md#misprints-in-the-paper lists: ideal f of Lens 1 in Tables 5, 9; Lens 2 ideal f and k2 in Table 8; exponents
    assert pv[(5, "imb_40", "f_mm")].ideal == 25 and pv[(9, "snr40", "f_mm")].ideal == 25
    assert pv[(8, "psd", "f_mm")].ideal == 8 and pv[(8, "psd", "k2")].ideal == 3e-5
    assert pv[(6, "imb_50", "k1")].mean == pytest.approx(1.012e-2)
    assert pv[(10, "snr50_psd", "k1")].mean == pytest.approx(8.7192e-3)
    assert pv[(10, "snr50_psd", "k2")].mean == pytest.approx(3.0093e-5)
    # every table column has its paper values
    for t in range(1, 11):
        for col in R.table_columns(t):
            assert (t, col.paper_case, "cx_mm") in pv, (t, col.paper_case)


def _summary(mean, std, n=200):
    return ParameterSummary("x", n, 0, mean, std, std / math.sqrt(n), std / math.sqrt(2 * (n - 1)), {})


def test_agreement_flags():
    case = R.table_columns(3)[0].case
    summ = {p: _summary(0.0, 1.0) for p in R.TABLE_PARAMS}
    summ["cx_mm"] = _summary(0.6581, 0.7162)  # the paper's own numbers: agree
    summ["f_mm"] = _summary(24.0, 0.4832)  # far from the paper's mean and biased
    res = R.CaseResult(case, "lens1", 200, {"paper": summ, "without": summ, "image": summ})
    results = {c.case.key: res for c in R.table_columns(3)}
    rows = {(r.column, r.param): r for r in R.compare_rows(3, results, R.paper_values())}
    r = rows[("with corrections, 30 dB", "cx_mm")]
    assert (r.mean_agrees, r.std_agrees) == ("yes", "yes")
    r = rows[("with corrections, 30 dB", "f_mm")]
    assert (r.mean_agrees, r.std_agrees, r.unbiased) == ("no", "yes", "no")
    assert "bias" in R._reason(r)
    assert rows[("with corrections, 30 dB", "iterations")].unbiased == "n/a"


@pytest.mark.parametrize("lens", ["lens1", "lens2"])
def test_table34_quick_means_unbiased_and_spreads_scale(lens):
    """Our Table 3-4 means are unbiased within Monte Carlo error; the spread falls with the SNR."""
    res = {snr: R.run_case(R.Case(lens, snr, kind="noise"), 12, 7, executor="serial", progress=False)
           for snr in (40.0, 50.0)}
    ideal = R.ideal_values(lens, False)
    for snr, r in res.items():
        for p in ("cx_mm", "cy_mm", "f_mm", "k1", "k2"):
            s = r.summaries["paper"][p]
            assert s.n == 12
            assert abs(s.mean - ideal[p]) <= 4 * s.sem, (snr, p, s.mean, s.sem)
    for p in ("cx_mm", "cy_mm", "f_mm", "k1"):
        ratio = res[40.0].summaries["paper"][p].std / res[50.0].summaries["paper"][p].std
        assert 1.5 < ratio < 6.5, (p, ratio)  # 10 dB: 3.16 for a spread proportional to the noise


def test_figure9_errors_vanish_at_the_truth_and_grow_with_the_spread():
    intr, dist = R.LENSES["lens1"]
    exact = {"f_mm": _summary(intr.f_mm, 0.0), "cx_mm": _summary(intr.cx_mm, 0.0), "cy_mm": _summary(intr.cy_mm, 0.0),
             "k1": _summary(dist.k1, 0.0), "k2": _summary(dist.k2, 0.0)}
    _, aoa, pos = R.figure9_errors("lens1", exact, psd=False)
    assert np.nanmax(aoa) < 1e-9 and np.nanmax(pos) < 1e-6
    spread = dict(exact, cx_mm=_summary(intr.cx_mm, 0.01))
    _, aoa, pos = R.figure9_errors("lens1", spread, psd=False)
    # 2 std = 0.02 mm of centre at f = 25 mm: about 0.046 deg, 4 mm at 5 m
    assert np.nanmedian(aoa) == pytest.approx(np.degrees(0.02 / 25), rel=0.1)
    assert np.nanmedian(pos) == pytest.approx(5000 * 0.02 / 25, rel=0.1)


def test_aoa_of_heldout_emitters_is_exact_for_the_true_model():
    rays, spots = R.heldout_emitters("lens2")
    intr, dist = R.LENSES["lens2"]
    assert len(rays) > 80
    err = R.aoa_error_deg(rays, R.rays_from_points(spots, intr, dist))
    assert np.max(err) < 1e-9


def test_reproduce_quick_cli_writes_its_files(tmp_path):
    from click.testing import CliRunner

    from psdcal.cli import _register, cli

    _register()
    out = tmp_path / "repro"
    result = CliRunner().invoke(cli, ["reproduce", "--quick", "--table", "2", "--table", "6", "--table", "10",
                                      "--out", str(out), "--workers", "2"])
    assert result.exit_code == 0, result.output
    for name in ("table_2.csv", "table_2.md", "table_6.csv", "table_6.md", "table_10.csv", "table_10.md",
                 "report.md", "gains.md", "gains.csv", "figure_9.png", "figure_9.csv"):
        assert (out / name).stat().st_size > 0, name
    md = (out / "table_6.md").read_text()
    assert "| imbalance, 40 dB | cx_mm | 0.5 |" in md and "mean agrees" in md
    gains_md = (out / "gains.md").read_text()
    assert "(c) joint calibration" in gains_md and "Identifiability" in gains_md
    header = (out / "table_10.csv").read_text().splitlines()[0]
    assert header.startswith("table,column,param,ideal,mean,std")
