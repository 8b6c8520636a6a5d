"""Monte Carlo throughput: calibrations per second per core, signal simulation included and excluded.

One trial is what ``psdcal reproduce`` runs for Tables 3-4: 9 random views of
the 14-LED template, the paper's signal chain (band-pass demodulation, Eq 43
gains, 50 kHz x 20 ms records) at 40 dB SNR, then a calibration with the
paper's model (k1, k2; template cost, preliminary correction, normalisation).
"Signal excluded" replaces the signal chain by Gaussian noise on the impact
points (the geometry-only simulator). The signal simulation is timed both
ways: the closed form the trials use (``measure_amplitudes(noise="closed-form")``:
the demodulator's outputs drawn from their exact law) and the sampled
reference (records drawn and demodulated); "sim/calib" is the closed-form
simulation's time over the calibration's (issue 11 target: <= 1). Times are CPU seconds of this one
process (one core); a process pool scales them by the number of cores
(``psdcal.study.montecarlo.run_trials``).

Run: ``.venv/bin/python benchmarks/bench_montecarlo.py [--trials N] [--markdown]``
"""
from __future__ import annotations

import os

# one BLAS thread, as every benchmark here: CPU time is process time, which also counts the busy-waiting of
# idle OpenBLAS worker threads (it made the simulation look 1.7x slower than it is)
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from psdcal.calibration.core import calibrate  # noqa: E402
from psdcal.errors import PsdcalError  # noqa: E402
from psdcal.study.reproduce import chain_settings, simulate_trial  # noqa: E402
from psdcal.signal.chain import channel_gains, measure_amplitudes  # noqa: E402
from psdcal.study.simulate import simulate_set  # noqa: E402


def _cpu(fn, n):
    fn(0)  # warm-up (imports, caches)
    t = time.process_time()
    fails = 0
    for i in range(n):
        fails += not fn(i + 1)
    return (time.process_time() - t) / n, fails


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=20, help="trials per row (default 20)")
    ap.add_argument("--markdown", action="store_true", help="print the table in Markdown instead")
    args = ap.parse_args(argv)
    n = args.trials
    gains = channel_gains(chain_settings(40.0))
    rows = []
    for lens in ("lens1", "lens2"):

        def sim_only(i, lens=lens):
            simulate_trial(np.random.default_rng(i), lens, 40.0, gains, False)
            return True

        def sim_sampled(i, lens=lens):
            # the trial, then its spots once more through the sampled reference path
            data = simulate_trial(np.random.default_rng(i), lens, 40.0, gains, False)
            measure_amplitudes(data.spots_mm, data.settings, gains, np.random.default_rng(i), 0.0)
            return True

        def with_signal(i, lens=lens):
            data = simulate_trial(np.random.default_rng(i), lens, 40.0, gains, False)
            try:
                calibrate(data.template_mm, data.points_mm, cost="template", radial=2, tangential=False)
                return True
            except PsdcalError:
                return False

        def geometry_only(i, lens=lens):
            s = simulate_set(lens, n_images=9, noise_mm=0.0007, seed=i)  # ~ the 40 dB impact-point noise
            try:
                calibrate(s.template_mm, s.points_mm, cost="template", radial=2, tangential=False)
                return True
            except PsdcalError:
                return False

        t_sim, _ = _cpu(sim_only, n)
        t_samp, _ = _cpu(sim_sampled, n)
        t_samp -= t_sim  # the sampled demodulation replaces the closed-form draw
        t_sig, f_sig = _cpu(with_signal, n)
        t_geo, f_geo = _cpu(geometry_only, n)
        # the calibration alone, timed on trials simulated beforehand (not as a difference of two noisy times)
        data = [simulate_trial(np.random.default_rng(i + 1), lens, 40.0, gains, False) for i in range(n)]

        def calib_only(i, data=data):
            try:
                d = data[i - 1] if i > 0 else data[0]
                calibrate(d.template_mm, d.points_mm, cost="template", radial=2, tangential=False)
                return True
            except PsdcalError:
                return False

        t_cal, _ = _cpu(calib_only, n)
        rows.append((lens, t_sim, t_samp, t_sig, f_sig, t_geo, f_geo, t_cal))
    print(f"Monte Carlo throughput, one core (CPU time), {n} trials per row; trial = 9 views x 14 LEDs, "
          "paper's model, template cost")
    if args.markdown:
        import sys

        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        from _table import print_table

        print_table(("lens", "signal simulation ms/trial", "sampled records ms (reference)", "calibration ms",
                     "simulation / calibration", "calibrations/s per core, signal included",
                     "calibrations/s per core, signal excluded", "failed"),
                    [(lens, f"{1e3 * t_sim:.2f}", f"{1e3 * t_samp:.2f}", f"{1e3 * t_cal:.2f}", f"{t_sim / t_cal:.2f}",
                      f"{1 / t_sig:.1f}", f"{1 / t_geo:.1f}", str(f_sig + f_geo))
                     for lens, t_sim, t_samp, t_sig, f_sig, t_geo, f_geo, t_cal in rows], markdown=True)
        return 0
    print(f"{'lens':6} {'sim ms/trial':>13} {'sampled ms':>11} {'calib ms':>9} {'sim/calib':>10} "
          f"{'calib/s, signal incl.':>22} {'calib/s, signal excl.':>22} {'failed':>7}")
    for lens, t_sim, t_samp, t_sig, f_sig, t_geo, f_geo, t_cal in rows:
        print(f"{lens:6} {1e3 * t_sim:13.2f} {1e3 * t_samp:11.2f} {1e3 * t_cal:9.2f} {t_sim / t_cal:10.2f} "
              f"{1 / t_sig:22.1f} {1 / t_geo:22.1f} {f_sig + f_geo:7d}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
