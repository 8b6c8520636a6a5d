"""The paper's simulation study (Section 4, Tables 1-10, Figure 9) and the gain remedies, re-run.

Split by concern:

- :mod:`~psdcal.study.reproduce.cases`: what is run (cases, table columns, ideal values);
- :mod:`~psdcal.study.reproduce.trials`: one trial of each kind (simulate, calibrate, score);
- :mod:`~psdcal.study.reproduce.run`: running every case a table needs (:func:`run_study`);
- :mod:`~psdcal.study.reproduce.paper`: the paper's numbers and ours beside them;
- :mod:`~psdcal.study.reproduce.render`: Markdown, CSV and PNG outputs (:func:`write_outputs`).

Every name below is importable from ``psdcal.study.reproduce`` itself.

Each table is a list of *cases* (a lens, an SNR, gain imbalance or not, PSD
distortion or not).  A case is a Monte Carlo setting run by
:func:`psdcal.study.montecarlo.run_trials` with :func:`case_trial`: per trial a
random set of 9 template views (:func:`psdcal.study.simulate.random_poses`, the
14-LED template of :func:`psdcal.study.simulate.default_template`), the signal chain
(:func:`psdcal.signal.chain.measure_points`: current split, Eq 43 gains drawn
within R 1 %, C 15 %, 1 kHz carrier + white noise at the SNR, the paper's
600 Hz Butterworth band-pass, Eq 1-2), and the paper's model
(``radial=2, tangential=False``) calibrated with its Eq 29 ``template`` cost.
The paper's numbers are transcribed in ``psdcal/data/paper_tables.csv``
(Tables 3-4 from the project's corrected ``tables.csv``, the others from the
paper's text with the misprints of docs/model.md#misprints-in-the-paper corrected; the ``note`` column
says where).

What is compared (:func:`compare_rows`): our mean and std of each parameter
beside the paper's, with standard errors from the Monte Carlo
(:class:`psdcal.study.montecarlo.ParameterSummary`), an *agreement* flag
``|ours - paper| <= 3 sqrt(se_ours^2 + se_paper^2)`` (the paper's SE from its
std and 200 trials; for its single-set values, the set-to-set std is the
error), and whether our mean is unbiased (``|mean - ideal| <= 3 sem``).

The gain remedies (part 4 of the issue; :func:`gain_trial`): on the same
imbalanced data (Tables 5-6 cases), (a) the paper's model ignoring the
imbalance, (b) an electrical calibration on the bare PSD
(:func:`psdcal.calibration.gains.simulate_electrical_calibration`) applied to the raw
amplitudes, (c) the joint calibration (``calibrate(fit_gains=True)``) and (d)
a general intrinsic matrix (``aspect=True, skew=True``), against the same
views through equal gains.  Each is scored by the angle of arrival of
held-out emitters (:func:`heldout_emitters`, not used in the calibration)
read out through the same electronics (:func:`aoa_error_deg`).
"""

from __future__ import annotations

from psdcal.study.reproduce.cases import (  # noqa: F401
    TABLE_PARAMS,
    PAPER_TRIALS,
    FIGURE9_S_MM,
    Case,
    Column,
    table_columns,
    ideal_values,
    required_cases,
    remedy_cases,
    figure9_cases,
    REMEDIES,
)
from psdcal.study.reproduce.trials import (  # noqa: F401
    TrialData,
    chain_settings,
    simulate_trial,
    heldout_emitters,
    rays_from_points,
    aoa_error_deg,
    heldout_readout,
    case_trial,
    gain_trial,
    initial_trial,
)
from psdcal.study.reproduce.run import (  # noqa: F401
    CaseResult,
    run_case,
    run_initial,
    Study,
    run_study,
)
from psdcal.study.reproduce.paper import (  # noqa: F401
    PaperValue,
    paper_values,
    ComparisonRow,
    compare_rows,
    figure9_errors,
    figure9_summary,
    pooled_rms,
    remedy_rows,
)
from psdcal.study.reproduce.render import (  # noqa: F401
    plot_figure9,
    table_markdown,
    gains_markdown,
    report_markdown,
    write_outputs,
    _reason,
)
from psdcal.study.simulate import LENSES  # noqa: F401  (the lens presets the cases name)

__all__ = [
    'TABLE_PARAMS',
    'PAPER_TRIALS',
    'FIGURE9_S_MM',
    'Case',
    'Column',
    'table_columns',
    'ideal_values',
    'required_cases',
    'remedy_cases',
    'figure9_cases',
    'REMEDIES',
    'TrialData',
    'chain_settings',
    'simulate_trial',
    'heldout_emitters',
    'rays_from_points',
    'aoa_error_deg',
    'heldout_readout',
    'case_trial',
    'gain_trial',
    'initial_trial',
    'CaseResult',
    'run_case',
    'run_initial',
    'Study',
    'run_study',
    'PaperValue',
    'paper_values',
    'ComparisonRow',
    'compare_rows',
    'figure9_errors',
    'figure9_summary',
    'pooled_rms',
    'remedy_rows',
    'plot_figure9',
    'table_markdown',
    'gains_markdown',
    'report_markdown',
    'write_outputs',
]
