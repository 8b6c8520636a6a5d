"""Synthetic calibration data with known truth (the paper's Section 4.1).

Geometry only: template points through poses, the pinhole model and the
distortion model (the measured point is ``distort(project(P))``), plus
Gaussian noise on the impact points in mm. The signal-level simulator is
:mod:`psdcal.signal.chain`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psdcal.model.distortion import distort
from psdcal.errors import InputError
from psdcal.model.params import Distortion, Intrinsics
from psdcal.model.projection import project
from psdcal.model.readout import LX_MM, LY_MM

#: Optical centre offset from the electrical centre used by the paper, mm (Section 4.1).
PAPER_CENTRE_MM = (0.5, -0.7)

#: The paper's two lenses (Section 4.1); k in powers of mm (docs/model.md#frames-and-units).
LENSES: dict[str, tuple[Intrinsics, Distortion]] = {
    "lens1": (Intrinsics(f_mm=25.0, cx_mm=0.5, cy_mm=-0.7), Distortion(k1=2e-3)),
    "lens2": (Intrinsics(f_mm=8.0, cx_mm=0.5, cy_mm=-0.7), Distortion(k1=1e-2, k2=3e-5)),
}

#: The paper's PSD pin-cushion coefficient (Section 4.5), mm^-2.
PAPER_L1 = -1.3058e-3


def default_template() -> np.ndarray:
    """The 14-LED planar template used by default, (14, 2) in mm.

    Three staggered rows (5, 4, 5 LEDs, 40 mm pitch, rows 60 mm apart): the
    points are "unaligned" in columns, as the paper's Figure 7 asks, yet the
    rows and several diagonals are lines of >= 3 points for the
    line-straightness step.
    """
    rows = [(-60.0, [-80, -40, 0, 40, 80]), (0.0, [-60, -20, 20, 60]), (60.0, [-80, -40, 0, 40, 80])]
    return np.array([(x, y) for y, xs in rows for x in xs], dtype=float)


@dataclass(frozen=True)
class SimulatedSet:
    """A synthetic calibration set with its truth.

    Attributes
    ----------
    template_mm : (M, 2)
    points_mm : (n_images, M, 2) measured impact points (noisy), NaN where off the sensor.
    intrinsics, distortion : the truth.
    rvecs, tvecs_mm : (n_images, 3) the true poses.
    noise_mm : float, standard deviation of the noise added to each coordinate.
    ideal_points_mm : (n_images, M, 2) the noiseless measured points.
    """

    template_mm: np.ndarray
    points_mm: np.ndarray
    intrinsics: Intrinsics
    distortion: Distortion
    rvecs: np.ndarray
    tvecs_mm: np.ndarray
    noise_mm: float
    ideal_points_mm: np.ndarray = field(repr=False)

    def truth_dict(self) -> dict:
        return {
            "intrinsics": self.intrinsics.to_dict(),
            "distortion": self.distortion.to_dict(),
            "noise_mm": self.noise_mm,
            "extrinsics": [
                {"image_id": i, "rvec": self.rvecs[i].tolist(), "tvec_mm": self.tvecs_mm[i].tolist()}
                for i in range(len(self.rvecs))
            ],
        }


def measured_points(template_mm, intr: Intrinsics, dist: Distortion, rvecs, tvecs):
    """Noiseless measured points (n_images, M, 2) = distort(project(P)); NaN where the inverse fails."""
    P = np.asarray(template_mm, dtype=float)
    x = np.stack([project(P, intr, r, t) for r, t in zip(rvecs, tvecs)])
    return distort(x, dist, intr.c).d_mm


def random_poses(
    template_mm,
    intr: Intrinsics,
    dist: Distortion,
    n_images: int,
    rng: np.random.Generator,
    *,
    max_tilt_deg: float = 35.0,
    fill: tuple[float, float] = (0.45, 0.85),
    margin_mm: float = 0.25,
    sensor_mm: tuple[float, float] = (LX_MM, LY_MM),
    max_tries: int = 2000,
):
    """Random template poses whose whole projection falls on the sensor.

    Each view tilts the template by up to ``max_tilt_deg`` about a random axis
    in its plane, spins it about its normal, places it so that its image spans
    ``fill`` of the sensor width, and offsets it at random across the sensor,
    so that a set of views covers the PSD surface (Section 4.1, Figure 8).

    Returns
    -------
    rvecs, tvecs_mm : (n_images, 3) arrays.
    """
    from psdcal.model.projection import R_from_r, pinhole, r_from_R

    P = np.asarray(template_mm, dtype=float)
    P3 = np.concatenate([P - P.mean(0), np.zeros((len(P), 1))], axis=1)
    Pfull = np.concatenate([P, np.zeros((len(P), 1))], axis=1)
    mean3 = np.concatenate([P.mean(0), [0.0]])
    width = float(np.ptp(P, axis=0).max())
    half = np.array(sensor_mm) / 2 - margin_mm
    rv, tv = [], []
    tries = 0
    # Candidates are screened in batches (one vectorised projection + distortion);
    # each try consumes the same 7 uniform draws, in the same order, as
    # _random_poses_reference, and the generator is left where the accepted tries
    # end, so both give the same poses and leave ``rng`` in the same state.
    budget = max(max_tries, 20 * n_images)  # the budget grows with the views asked for (as the reference's)
    while len(rv) < n_images:
        if tries >= budget:
            raise InputError(f"could not place {n_images} template views on the sensor; relax fill or tilt")
        batch = min(budget - tries, max(16, 6 * (n_images - len(rv))))
        state = rng.bit_generator.state
        u = rng.random((batch, 7))
        tilt = np.deg2rad(5.0 + (max_tilt_deg - 5.0) * u[:, 0])
        phi = 2 * np.pi * u[:, 1]
        spin = -np.pi + 2 * np.pi * u[:, 2]
        scale = (fill[0] + (fill[1] - fill[0]) * u[:, 3]) * sensor_mm[0]
        off = (-1.0 + 2.0 * u[:, 4:6]) * half * (1 - (fill[0] + (fill[1] - fill[0]) * u[:, 6:7]) * 0.8)
        R = _rodrigues(np.stack([np.cos(phi), np.sin(phi), np.zeros(batch)], axis=1) * tilt[:, None]) @ _rodrigues(
            np.stack([np.zeros(batch), np.zeros(batch), spin], axis=1))
        Z = intr.f_mm * width / scale
        t = np.stack([(off[:, 0] - intr.cx_mm) * Z / intr.f_mm, (off[:, 1] - intr.cy_mm) * Z / intr.f_mm, Z], axis=1)
        front = np.all(np.einsum("mj,bij->bmi", P3, R)[..., 2] + t[:, None, 2] > 0, axis=1)
        tvec = t - R @ mean3
        with np.errstate(all="ignore"):
            d = distort(pinhole(np.einsum("mj,bij->bmi", Pfull, R) + tvec[:, None, :], intr), dist, intr.c).d_mm
        ok = front & np.all(np.isfinite(d) & (np.abs(d) <= half), axis=(1, 2))
        used = batch
        for k in np.flatnonzero(ok):
            # the accepted pose exactly as the reference computes it
            Rk = R_from_r(np.array([np.cos(phi[k]), np.sin(phi[k]), 0.0]) * tilt[k]) @ R_from_r(
                np.array([0, 0, spin[k]]))
            rvec = r_from_R(Rk)
            rv.append(rvec)
            tv.append(t[k] - Rk @ mean3)
            if len(rv) == n_images:
                used = k + 1
                break
        if used < batch:
            rng.bit_generator.state = state
            rng.random(7 * used)
        tries += used
    return np.array(rv), np.array(tv)


def _rodrigues(r: np.ndarray) -> np.ndarray:
    """Rotation matrices (B, 3, 3) of rotation vectors (B, 3) (Rodrigues' formula, batched)."""
    theta = np.linalg.norm(r, axis=1)
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -r[:, 2], r[:, 1], -r[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = r[:, 2], -r[:, 1], r[:, 0]
    safe = np.where(theta < 1e-12, 1.0, theta)
    a = np.where(theta < 1e-12, 1.0, np.sin(theta) / safe)
    b = np.where(theta < 1e-12, 0.0, (1 - np.cos(theta)) / safe**2)
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def _random_poses_reference(
    template_mm,
    intr: Intrinsics,
    dist: Distortion,
    n_images: int,
    rng: np.random.Generator,
    *,
    max_tilt_deg: float = 35.0,
    fill: tuple[float, float] = (0.45, 0.85),
    margin_mm: float = 0.25,
    sensor_mm: tuple[float, float] = (LX_MM, LY_MM),
    max_tries: int = 2000,
):
    """:func:`random_poses`, one candidate at a time (the tested reference)."""
    from psdcal.model.projection import R_from_r, r_from_R

    P = np.asarray(template_mm, dtype=float)
    P3 = np.concatenate([P - P.mean(0), np.zeros((len(P), 1))], axis=1)
    width = float(np.ptp(P, axis=0).max())
    half = np.array(sensor_mm) / 2 - margin_mm
    rv, tv = [], []
    tries = 0
    while len(rv) < n_images:
        tries += 1
        if tries > max(max_tries, 20 * n_images):  # the budget grows with the views asked for
            raise InputError(f"could not place {n_images} template views on the sensor; relax fill or tilt")
        tilt = np.deg2rad(rng.uniform(5.0, max_tilt_deg))
        phi = rng.uniform(0, 2 * np.pi)
        spin = rng.uniform(-np.pi, np.pi)
        R = R_from_r(np.array([np.cos(phi), np.sin(phi), 0.0]) * tilt) @ R_from_r(np.array([0, 0, spin]))
        scale = rng.uniform(*fill) * sensor_mm[0]
        Z = intr.f_mm * width / scale
        off = rng.uniform(-1, 1, 2) * half * (1 - rng.uniform(*fill) * 0.8)
        t = np.array([(off[0] - intr.cx_mm) * Z / intr.f_mm, (off[1] - intr.cy_mm) * Z / intr.f_mm, Z])
        # template centre at the origin of its own frame
        t = t - R @ np.concatenate([P.mean(0), [0.0]]) * 0.0
        Pc = P3 @ R.T + t
        if np.any(Pc[:, 2] <= 0):
            continue
        rvec = r_from_R(R)
        tvec = t - R @ np.concatenate([P.mean(0), [0.0]])
        d = measured_points(P, intr, dist, [rvec], [tvec])[0]
        if np.all(np.isfinite(d)) and np.all(np.abs(d) <= half):
            rv.append(rvec)
            tv.append(tvec)
    return np.array(rv), np.array(tv)


def simulate_set(
    lens: str | tuple[Intrinsics, Distortion] = "lens2",
    n_images: int = 12,
    noise_mm: float = 0.0,
    seed: int | np.random.Generator | None = 0,
    *,
    template_mm=None,
    psd_l1: float = 0.0,
    tangential: tuple[float, float] = (0.0, 0.0),
    **pose_kwargs,
) -> SimulatedSet:
    """A synthetic calibration set (geometry only) with Gaussian noise on the impact points.

    Parameters
    ----------
    lens : "lens1" | "lens2" | (Intrinsics, Distortion)
    n_images : int
    noise_mm : float
        Standard deviation of the noise on each coordinate of each impact point, mm.
    seed : int or Generator
    template_mm : (M, 2), default :func:`default_template`
    psd_l1 : float
        PSD radial coefficient l1 added to the lens' distortion (mm^-2).
    tangential : (p1, p2) added to the lens' distortion (mm^-1).
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    if isinstance(lens, str):
        if lens not in LENSES:
            raise InputError(f"unknown lens preset {lens!r}; choose one of {sorted(LENSES)}")
        intr, dist = LENSES[lens]
    else:
        intr, dist = lens
    from dataclasses import replace

    dist = replace(dist, l1=dist.l1 + psd_l1, p1=dist.p1 + tangential[0], p2=dist.p2 + tangential[1])
    P = default_template() if template_mm is None else np.asarray(template_mm, dtype=float)
    rv, tv = random_poses(P, intr, dist, n_images, rng, **pose_kwargs)
    ideal = measured_points(P, intr, dist, rv, tv)
    noisy = ideal + rng.normal(0.0, noise_mm, ideal.shape) if noise_mm > 0 else ideal.copy()
    return SimulatedSet(P, noisy, intr, dist, rv, tv, float(noise_mm), ideal)
