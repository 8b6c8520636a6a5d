"""The sensor model: PSD readout, distortion, projection and the parameter types.

Data flow: ``model`` -> ``calibration`` -> ``signal`` -> ``measure`` -> ``study`` -> ``report``.
This sub-package imports nothing from the others.

- :mod:`psdcal.model.params`: frozen parameter dataclasses (``Intrinsics``, ``Distortion``, ``Pose``, ``ModelSpec``).
- :mod:`psdcal.model.readout`: four amplitudes -> impact point (paper Eq 1-2), its inverse and the gain map.
- :mod:`psdcal.model.distortion`: the undistortion model (PSD and lens terms) and its Newton inverse.
- :mod:`psdcal.model.projection`: pinhole projection (Eq 3-4), back-projection, rotations.
"""
