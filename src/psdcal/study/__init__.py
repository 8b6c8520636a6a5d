"""Studies: simulated data sets, Monte Carlo trials and the paper's reproduction.

- :mod:`psdcal.study.simulate`: synthetic template views with known truth.
- :mod:`psdcal.study.recordings`: simulated four-channel recordings (template views, rooms) and their writers.
- :mod:`psdcal.study.montecarlo`: seeded trials over any ``concurrent.futures.Executor``.
- :mod:`psdcal.study.reproduce`: the paper's Tables 1-10 and Figure 9.
"""
