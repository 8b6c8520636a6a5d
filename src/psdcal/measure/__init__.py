"""Measurement: from amplitudes or impact points to angles and positions.

- :mod:`psdcal.measure.sensor_model`: a calibration JSON read for measuring (no calibration machinery).
- :mod:`psdcal.measure.aoa`: impact points and angles of arrival with their uncertainty.
- :mod:`psdcal.measure.positioning`: position on a plane, triangulation by several sensors, error maps.
- :mod:`psdcal.measure.locate`: recordings -> angles and positions, streamed to CSV.
- :mod:`psdcal.measure.pose`: a sensor's pose in the room from emitters at known positions (PnP + ML).
- :mod:`psdcal.measure.bundle`: several sensors' poses and emitter positions in one bundle adjustment.
- :mod:`psdcal.measure.tracking`: constant-velocity Kalman filter per emitter.
- :mod:`psdcal.measure.planning`: coverage and position-uncertainty maps of an installation.
- :mod:`psdcal.measure.live`: locate on a live stream, rows as windows complete.
"""
