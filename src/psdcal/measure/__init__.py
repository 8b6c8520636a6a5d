"""Measurement: from amplitudes or impact points to angles and positions.

- :mod:`psdcal.measure.sensor_model`: a calibration JSON read for measuring (no calibration machinery).
- :mod:`psdcal.measure.aoa`: impact points and angles of arrival with their uncertainty.
- :mod:`psdcal.measure.positioning`: position on a plane, triangulation by several sensors, error maps.
- :mod:`psdcal.measure.locate`: recordings -> angles and positions, streamed to CSV.
"""
