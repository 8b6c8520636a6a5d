"""Taking calibration views: predicted AoA uncertainty of a set of views, and the next best view.

The calibration's covariance of its global parameters (poses marginalised) is,
to first order, ``sigma^2 S^-1`` with ``S = sum_v S_v`` and, for each view
``v`` with Jacobian rows ``[G_v | P_v]`` (global | its own six pose columns)::

    S_v = G_v^T G_v - G_v^T P_v (P_v^T P_v)^-1 P_v^T G_v        (Schur complement)

so a view's information adds, and a candidate view is judged by adding its
``S_v`` to the current ``S``: no refit is needed.  The AoA covariance at a
sensor point follows as ``J S^-1 J^T sigma^2`` with ``J = d alpha / d p``
(:func:`psdcal.measure.aoa.angles_from_points`), the same propagation as
:func:`psdcal.report.compare.fov_uncertainty`.  The Jacobians come from the
calibration's own residual model (:class:`psdcal.calibration._refine.Evaluator`,
image cost).

A candidate view is a template pose a person can set up: a tilt about an axis
in the sensor plane, the spot of the template's centre at a point of the
sensor, and a distance.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psdcal.errors import InputError
from psdcal.model.params import Distortion, Intrinsics, ModelSpec
from psdcal.model.readout import LX_MM, LY_MM


def view_information(template_mm, intr: Intrinsics, dist: Distortion, spec: ModelSpec, rvecs, tvecs, *,
                     valid=None, sensor_mm=(LX_MM, LY_MM), margin_mm: float = 0.0) -> np.ndarray:
    """Information ``S_v`` (n_views, n_global, n_global) each view gives on the global parameters (unit noise).

    Parameters
    ----------
    template_mm : (M, 2)
    intr, dist, spec : the model at which the Jacobian is taken (its free parameters are ``spec.global_names``).
    rvecs, tvecs : (n_views, 3) template poses.
    valid : (n_views, M) bool, optional
        Which points are observed; by default those whose modelled spot falls on the sensor (within ``margin_mm``).

    Returns
    -------
    (n_views, n, n) ndarray, per mm^-2 of noise variance.
    """
    from psdcal.calibration._refine import Evaluator, Problem
    from psdcal.study.simulate import measured_points

    P = np.asarray(template_mm, dtype=float)
    rv = np.asarray(rvecs, dtype=float).reshape(-1, 3)
    tv = np.asarray(tvecs, dtype=float).reshape(-1, 3)
    ng = len(spec.global_names)
    out = np.zeros((len(rv), ng, ng))
    chunk = 64
    for s in range(0, len(rv), chunk):
        r, t = rv[s:s + chunk], tv[s:s + chunk]
        d = measured_points(P, intr, dist, r, t)
        half = np.array(sensor_mm) / 2 - margin_mm
        on = np.all(np.isfinite(d), axis=-1) & np.all(np.abs(np.nan_to_num(d, nan=1e9)) <= half, axis=-1)
        if valid is not None:
            on &= np.asarray(valid, dtype=bool)[s:s + chunk]
        pts = np.where(on[..., None], d, np.nan)
        keep = on.sum(axis=1) >= 1
        if not np.any(keep):
            continue
        prob = Problem(P, pts[keep], spec, cost="image", sensor_mm=tuple(sensor_mm))
        ev = Evaluator(prob, intr, dist, np.ones(4))
        z = prob.pack(intr, dist, np.ones(4), r[keep], t[keep])
        J = ev.jacobian(z)
        img = np.repeat(ev.img_idx, 2)
        idx = np.nonzero(keep)[0]
        for k, i in enumerate(idx):
            rows = img == k
            G = J[rows, :ng]
            Pp = J[rows, ng + 6 * k: ng + 6 * k + 6]
            A = Pp.T @ Pp
            GP = G.T @ Pp
            out[s + i] = G.T @ G - GP @ np.linalg.pinv(A) @ GP.T
    return out


def aoa_jacobian(intr: Intrinsics, dist: Distortion, names, grid_mm) -> np.ndarray:
    """``d alpha / d p`` (N, 2, n) at sensor points ``grid_mm`` (N, 2), rad per parameter unit."""
    from psdcal.measure.aoa import angles_from_points
    from psdcal.measure.sensor_model import SensorModel

    names = tuple(names)
    m = SensorModel(intrinsics=intr, distortion=dist, names=names, covariance=np.zeros((len(names), len(names))))
    a = angles_from_points(np.asarray(grid_mm, dtype=float), m)
    return a.dn_dp * a.dalpha_dn[..., None]


def worst_sigma_deg(S, J_alpha, noise_mm: float) -> np.ndarray:
    """Worst 1-sigma AoA uncertainty ``max_grid sqrt(var ax + var ay)`` (deg) for information ``S`` (..., n, n).

    Inf where ``S`` is singular (the views do not determine the parameters).
    """
    S = np.asarray(S, dtype=float)
    scale = np.sqrt(np.clip(np.diagonal(S, axis1=-2, axis2=-1), 1e-300, None))
    Sn = S / scale[..., :, None] / scale[..., None, :]
    w = np.linalg.eigvalsh(Sn)
    ok = w[..., 0] > 1e-12 * w[..., -1]
    cov = np.linalg.pinv(Sn) / scale[..., :, None] / scale[..., None, :] * noise_mm**2
    # var of alpha at each grid point: trace(J C J^T)
    v = np.einsum("gai,...ij,gaj->...g", J_alpha, cov, J_alpha)
    out = np.degrees(np.sqrt(np.clip(v, 0, None))).max(axis=-1)
    return np.where(ok, out, np.inf)


@dataclass(frozen=True)
class CandidateView:
    """A template pose stated as an instruction.

    Attributes
    ----------
    tilt_deg : tilt of the template plane from facing the sensor, degrees.
    axis_deg : direction of the tilt axis in the sensor plane, degrees from the sensor's +x (right-hand rule).
    centre_mm : (2,) where the template's centre is seen on the sensor (measured spot), mm.
    distance_mm : distance of the template's centre from the sensor along the optical axis, mm.
    rvec, tvec_mm : the pose (template to sensor frame).
    """

    tilt_deg: float
    axis_deg: float
    centre_mm: tuple
    distance_mm: float
    rvec: np.ndarray
    tvec_mm: np.ndarray

    def instruction(self) -> str:
        names = {0: "+x", 90: "+y", 180: "-x", 270: "-y"}
        if self.tilt_deg == 0:
            tilt = "template facing the sensor (no tilt)"
        else:
            ax = names.get(int(round(self.axis_deg)) % 360, f"the in-plane axis at {self.axis_deg:g} deg from +x")
            tilt = f"tilt {self.tilt_deg:g} deg about {ax} (right-hand rule)"
        return (f"{tilt}, template centre seen at ({self.centre_mm[0]:+.1f}, {self.centre_mm[1]:+.1f}) mm on the "
                f"sensor, distance {self.distance_mm:.0f} mm")


def candidate_views(template_mm, intr: Intrinsics, dist: Distortion, *, tilts_deg=(0, 20, 35, 50),
                    axes_deg=(0, 45, 90, 135, 180, 225, 270, 315), positions: int = 5, fills=(0.35, 0.5, 0.75),
                    sensor_mm=(LX_MM, LY_MM), margin_mm: float = 0.25) -> list[CandidateView]:
    """Template poses whose whole image falls on the sensor, over tilts, axes, positions and distances.

    ``fills`` are the fractions of the sensor's width the template's image
    spans (they set the distances); ``positions`` per side of a grid of
    centre points over the middle 70 % of the sensor.
    """
    from psdcal.model.distortion import undistort
    from psdcal.model.projection import R_from_r, r_from_R
    from psdcal.study.simulate import measured_points

    P = np.asarray(template_mm, dtype=float)
    ctr = P.mean(axis=0)
    width = float(np.ptp(P, axis=0).max())
    half = np.array(sensor_mm) / 2
    xs = np.linspace(-0.7, 0.7, positions) * half[0]
    ys = np.linspace(-0.7, 0.7, positions) * half[1]
    poses = []
    for fill in fills:
        Z = intr.f_mm * width / (fill * sensor_mm[0])
        for tilt in tilts_deg:
            for ax in (axes_deg if tilt else (0,)):
                a = np.radians(ax)
                R = R_from_r(np.array([np.cos(a), np.sin(a), 0.0]) * np.radians(tilt))
                for y in ys:
                    for x in xs:
                        xi = undistort(np.array([x, y]), dist, intr.c)  # the ideal point of the wanted spot
                        ny = (xi[1] - intr.cy_mm) / intr.fy
                        nx = (xi[0] - intr.cx_mm - intr.skew * ny) / intr.f_mm
                        t = Z * np.array([nx, ny, 1.0]) - R @ np.array([ctr[0], ctr[1], 0.0])
                        poses.append((tilt, ax, (x, y), Z, r_from_R(R), t))
    rv = np.array([p[4] for p in poses])
    tv = np.array([p[5] for p in poses])
    d = measured_points(P, intr, dist, rv, tv)
    ok = np.all(np.isfinite(d), axis=(1, 2)) & np.all(np.abs(np.nan_to_num(d, nan=1e9)) <= half - margin_mm, axis=(1, 2))
    return [CandidateView(float(p[0]), float(p[1]), (float(p[2][0]), float(p[2][1])), float(p[3]), p[4], p[5])
            for p, k in zip(poses, ok) if k]


@dataclass(frozen=True)
class NextView:
    """The ranking of candidate next views.

    Attributes
    ----------
    current_deg : worst 1-sigma AoA uncertainty over the sensor with the views taken, degrees.
    ranked : list of (CandidateView, predicted worst 1-sigma after adding it, deg), best first.
    min_gain : the relative improvement below which more views stop helping.
    """

    current_deg: float
    ranked: list
    min_gain: float

    @property
    def best_deg(self) -> float:
        return float(self.ranked[0][1]) if self.ranked else float("nan")

    @property
    def gain(self) -> float:
        """Predicted relative reduction of the worst AoA uncertainty by the best next view."""
        if not np.isfinite(self.current_deg):
            return 1.0
        return float(1.0 - self.best_deg / self.current_deg) if self.current_deg > 0 else 0.0

    @property
    def stop(self) -> bool:
        """True when the best next view improves the worst AoA uncertainty by less than ``min_gain``."""
        return self.gain < self.min_gain

    def verdict(self) -> str:
        cur = "undetermined (the views do not fix all parameters)" if not np.isfinite(self.current_deg) \
            else f"{self.current_deg:.3g} deg"
        if self.stop:
            return (f"stop: the best next view lowers the worst AoA 1-sigma from {cur} only to {self.best_deg:.3g} deg "
                    f"({100 * self.gain:.1f} % < {100 * self.min_gain:g} %); more views stop helping")
        return (f"take it: the best next view lowers the worst AoA 1-sigma from {cur} to {self.best_deg:.3g} deg "
                f"(-{100 * self.gain:.0f} %)")


def next_view(template_mm, intr, dist, spec, S_current, noise_mm: float, *, candidates=None, grid: int = 11,
              sensor_mm=(LX_MM, LY_MM), min_gain: float = 0.05, J_alpha=None, S_candidates=None,
              free=None) -> NextView:
    """Rank candidate views by the worst AoA uncertainty over the sensor after adding each.

    Parameters
    ----------
    S_current : (n, n) information of the views taken (:func:`view_information` summed).
    noise_mm : impact-point noise per coordinate, mm.
    candidates : list of CandidateView (default :func:`candidate_views`).
    grid : sensor grid points per side where the worst uncertainty is taken.
    min_gain : relative improvement below which :attr:`NextView.stop` is True.
    free : names of the free parameters, optional
        A subset of ``spec.global_names`` when some were held fixed (``calibrate --fix``): the information
        is then restricted to them (``S_current`` may be over either set of names).
    """
    from psdcal.model.readout import sensor_grid_mm

    if candidates is None:
        candidates = candidate_views(template_mm, intr, dist, sensor_mm=sensor_mm)
    if not candidates:
        raise InputError("no candidate view puts the whole template on the sensor; check the template and f")
    names = tuple(spec.global_names)
    keep = np.arange(len(names)) if free is None else np.array([names.index(n) for n in free], dtype=int)
    if J_alpha is None:
        J_alpha = aoa_jacobian(intr, dist, [names[k] for k in keep], sensor_grid_mm(sensor_mm, grid).reshape(-1, 2))
    if S_candidates is None:
        S_candidates = view_information(template_mm, intr, dist, spec, [c.rvec for c in candidates],
                                        [c.tvec_mm for c in candidates], sensor_mm=sensor_mm)
    if S_candidates.shape[-1] != len(keep):
        S_candidates = S_candidates[:, keep][:, :, keep]
    S_current = np.asarray(S_current, dtype=float)
    if S_current.shape[-1] != len(keep):
        S_current = S_current[keep][:, keep]
    cur = float(worst_sigma_deg(S_current, J_alpha, noise_mm))
    after = worst_sigma_deg(S_current[None] + S_candidates, J_alpha, noise_mm)
    order = np.argsort(after, kind="stable")
    return NextView(cur, [(candidates[i], float(after[i])) for i in order], float(min_gain))


def guided_sequence(template_mm, intr, dist, spec, S_start, noise_mm, n_views: int, *, candidates=None,
                    grid: int = 11, sensor_mm=(LX_MM, LY_MM)):
    """Greedy views: each the candidate that lowers the worst AoA uncertainty most. Returns (views, worst_deg list)."""
    from psdcal.model.readout import sensor_grid_mm

    if candidates is None:
        candidates = candidate_views(template_mm, intr, dist, sensor_mm=sensor_mm)
    J_alpha = aoa_jacobian(intr, dist, spec.global_names, sensor_grid_mm(sensor_mm, grid).reshape(-1, 2))
    Sc = view_information(template_mm, intr, dist, spec, [c.rvec for c in candidates],
                          [c.tvec_mm for c in candidates], sensor_mm=sensor_mm)
    S = np.array(S_start, dtype=float)
    views, worst = [], []
    for _ in range(n_views):
        after = worst_sigma_deg(S[None] + Sc, J_alpha, noise_mm)
        i = int(np.argmin(after))
        views.append(candidates[i])
        worst.append(float(after[i]))
        S = S + Sc[i]
    return views, worst


def grid_capture(candidates, n_views: int, *, tilt_deg: float = 35.0, step_mm: float | None = None) -> list:
    """A fixed capture protocol to compare with: tilt ``tilt_deg``, the axis turning by 90 deg each view, the
    template's centre stepping over a 3 x 3 grid of the sensor, each view as near as the template stays on it.

    ``candidates`` come from :func:`candidate_views` (its positions: the 3 x 3 grid takes the inner ones,
    ``+-step_mm``, by default the nearest to the middle but the middle itself).
    """
    xs = sorted({round(c.centre_mm[0], 6) for c in candidates})
    step = step_mm if step_mm is not None else min(abs(x) for x in xs if abs(x) > 1e-9)
    pos = [(x, y) for y in (-step, 0.0, step) for x in (-step, 0.0, step)]
    out = []
    for k in range(n_views):
        axis, at = float((90 * k) % 360), pos[k % 9]
        pool = [c for c in candidates if c.tilt_deg == tilt_deg and c.axis_deg == axis
                and np.allclose(c.centre_mm, at, atol=0.01)]
        if not pool:
            raise InputError(f"no candidate view at tilt {tilt_deg:g} deg about {axis:g} deg centred at {at} mm")
        out.append(min(pool, key=lambda c: c.distance_mm))
    return out


def information_of_calibration(result, *, margin_mm: float = 0.0) -> np.ndarray:
    """Summed information ``S`` (n, n) of the views of a calibration, at its solution (unit noise)."""
    from psdcal.calibration.core import inputs_from_record

    P, X = inputs_from_record(result.problem)
    valid = np.all(np.isfinite(X), axis=-1)
    spec = result.model
    S = view_information(P, result.intrinsics, result.distortion, spec, result.rvecs, result.tvecs_mm, valid=valid,
                         sensor_mm=result.sensor_mm, margin_mm=-1e3)
    return S.sum(axis=0)


__all__ = ["CandidateView", "NextView", "aoa_jacobian", "candidate_views", "grid_capture", "guided_sequence",
           "information_of_calibration", "next_view", "view_information", "worst_sigma_deg"]
