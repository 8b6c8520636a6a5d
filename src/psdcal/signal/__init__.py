"""Signals: the simulated analogue chain, demodulation and recordings.

- :mod:`psdcal.signal.chain`: photocurrents -> transimpedance gains (Eq 43) -> carrier + noise -> lock-in
  or band-pass -> amplitudes; the SNR definition.
- :mod:`psdcal.signal.chain_noise`: the impact point's noise from the SNR, predicted to first order and
  measured by simulation.
- :mod:`psdcal.signal.demod`: lock-in and band-pass amplitude estimators.
- :mod:`psdcal.signal.recording`: readers for NPY, CSV, HDF5 and TDMS recordings (chunked).
- :mod:`psdcal.signal.stream`: windowed multi-carrier lock-in and time-multiplexing segmentation.
- :mod:`psdcal.signal.live`: raw four-channel streams from stdin, a localhost socket or a NI DAQ.
"""
