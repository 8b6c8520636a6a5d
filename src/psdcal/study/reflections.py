"""Reflected paths in a simulated room: a wall or the floor as a mirror (docs/guide/positioning.md#reflections).

A reflection off a plane is the emitter mirrored in that plane (an image
source), seen through an attenuation: its power at a sensor is
``attenuation * |P - C|^2 / |P' - C|^2`` of the direct path's (the inverse
square of the longer path; ``P`` the emitter, ``P'`` its image, ``C`` the
sensor's centre).  Both the emitter and the sensor must be on the room's side
of the plane.

* A PSD front-end (:func:`psdcal.study.recordings.simulate_room`) adds the
  image's light to the direct light: the four photocurrents add, so the PSD
  reports the power-weighted centroid of the two spots (a biased angle, not a
  second spot).
* An angles front-end that separates spots may report the image's direction
  outright (a *ghost*): :func:`observed_rays` with ``mode="ghost"``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psdcal.errors import InputError

#: How a reflected path reaches the reported ray: the power-weighted centroid, or the image's direction alone.
MODES = ("centroid", "ghost")


@dataclass(frozen=True)
class Reflector:
    """A mirror plane ``(P - point_mm) . normal = 0``; ``normal`` (unit) points into the room.

    ``sensors`` / ``emitters``: the names it applies to (empty: all).
    """

    point_mm: tuple
    normal: tuple
    attenuation: float
    sensors: tuple = ()
    emitters: tuple = ()

    def applies(self, sensor: str, emitter: str) -> bool:
        return (not self.sensors or sensor in self.sensors) and (not self.emitters or emitter in self.emitters)

    def mirror(self, P_mm) -> np.ndarray:
        """The image ``P'`` (..., 3) of points ``P_mm`` (..., 3), mm."""
        P = np.asarray(P_mm, dtype=float)
        n = np.asarray(self.normal, dtype=float)
        d = (P - np.asarray(self.point_mm, dtype=float)) @ n
        return P - 2.0 * d[..., None] * n

    def weight(self, P_mm, centre_mm) -> np.ndarray:
        """Power of the reflected path over the direct one (...), 0 where the emitter or sensor is behind the plane."""
        P = np.asarray(P_mm, dtype=float)
        C = np.asarray(centre_mm, dtype=float)
        n = np.asarray(self.normal, dtype=float)
        p0 = np.asarray(self.point_mm, dtype=float)
        front = ((P - p0) @ n > 0) & (float((C - p0) @ n) > 0)
        d1 = np.sum((P - C) ** 2, -1)
        d2 = np.sum((self.mirror(P) - C) ** 2, -1)
        return np.where(front, self.attenuation * d1 / np.maximum(d2, 1e-30), 0.0)

    def to_dict(self) -> dict:
        return {"point_mm": list(self.point_mm), "normal": list(self.normal), "attenuation": self.attenuation,
                "sensors": list(self.sensors), "emitters": list(self.emitters)}


def parse_reflection(spec: str, room_mm) -> Reflector:
    """``AXIS=VALUE_M:ATTENUATION[:SENSORS[:EMITTERS]]``, e.g. ``z=0:0.3`` (the floor) or ``x=6:0.2:s2:tag``.

    The plane is perpendicular to the axis at that coordinate (metres); its
    normal points towards the room's centre.  SENSORS and EMITTERS are
    comma-separated names (empty or missing: all).

    Raises
    ------
    InputError
        Naming the field ``reflection``.
    """
    parts = str(spec).split(":")
    try:
        axis, value = parts[0].split("=")
        ax = "xyz".index(axis.strip().lower())
        v_mm = float(value) * 1000.0
        att = float(parts[1])
        assert len(parts) <= 4 and np.isfinite(v_mm) and 0.0 <= att <= 1.0
    except (ValueError, IndexError, AssertionError):
        raise InputError(f"reflection {spec!r}: expected AXIS=VALUE_M:ATTENUATION[:SENSORS[:EMITTERS]] with AXIS "
                         "x, y or z and 0 <= ATTENUATION <= 1 (e.g. z=0:0.3 for the floor)",
                         field="reflection") from None
    centre = np.asarray(room_mm, dtype=float) / 2.0
    if abs(centre[ax] - v_mm) < 1e-9:
        raise InputError(f"reflection {spec!r}: the plane goes through the room's centre", field="reflection")
    normal = np.zeros(3)
    normal[ax] = 1.0 if centre[ax] > v_mm else -1.0
    point = np.zeros(3)
    point[ax] = v_mm

    def names(i):
        return tuple(x.strip() for x in parts[i].split(",") if x.strip()) if len(parts) > i else ()

    return Reflector(tuple(point.tolist()), tuple(normal.tolist()), att, names(2), names(3))


def sensor_centre_mm(rvec, tvec_mm) -> np.ndarray:
    """Projection centre (3,) of a pose ``Pc = R Pw + t``, mm."""
    from psdcal.model.projection import R_from_r

    R = R_from_r(np.asarray(rvec, dtype=float))
    return -R.T @ np.asarray(tvec_mm, dtype=float)


def observed_rays(n_direct, n_image, weight, mode: str = "centroid") -> np.ndarray:
    """The ray a front-end reports (..., 2) from the direct and the image's normalised coordinates.

    ``centroid``: ``(n_direct + w n_image) / (1 + w)`` (a PSD: the power-weighted
    centroid, exact on the sensor plane of an undistorted lens); ``ghost``:
    ``n_image`` where ``w > 0``.  Where the image is out of view (NaN) the
    direct ray is returned.
    """
    if mode not in MODES:
        raise InputError(f"unknown reflection mode {mode!r}; use one of {', '.join(MODES)}", field="mode")
    nd = np.asarray(n_direct, dtype=float)
    ni = np.asarray(n_image, dtype=float)
    w = np.asarray(weight, dtype=float)[..., None]
    seen = np.all(np.isfinite(ni), -1, keepdims=True) & (w > 0)
    if mode == "ghost":
        return np.where(seen, ni, nd)
    return np.where(seen, (nd + w * np.nan_to_num(ni)) / (1.0 + w), nd)


__all__ = ["MODES", "Reflector", "observed_rays", "parse_reflection", "sensor_centre_mm"]
