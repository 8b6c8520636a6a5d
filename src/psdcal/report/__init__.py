"""Reports: the HTML calibration report, figures, comparisons and console tables.

- :mod:`psdcal.report.page`: the self-contained HTML report.
- :mod:`psdcal.report.plots`: one function per figure (matplotlib, imported only here).
- :mod:`psdcal.report.compare`: AoA fields and the comparison of two calibrations.
- :mod:`psdcal.report.text`: the console table of a calibration.
"""
