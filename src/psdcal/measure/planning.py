"""Planning an installation: coverage and position uncertainty over a floor plane.

For candidate sensor poses (a sensors file) and a horizontal plane at height
``z`` in the room, at every grid point ``P``:

* **coverage**: how many sensors see ``P`` (in front of the sensor, and its
  spot on the active area, through the calibrated model);
* **position uncertainty** (dilution of precision): with the sensors that see
  it, the covariance of the triangulated point is ``(sum_j J_j^T W_j J_j)^-1``
  with ``J_j = d pi / d P`` and ``W_j^-1`` the covariance of the normalised
  coordinates the sensor reports there (its calibration covariance and an
  impact-point noise ``sigma_d_mm``, as :func:`psdcal.measure.aoa.angles_from_points`
  propagates them), plus each sensor's pose covariance when it has one.
  This is the same information matrix as :func:`psdcal.measure.positioning.triangulate`'s.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psdcal.errors import InputError


@dataclass(frozen=True)
class PlanMap:
    """Coverage and position uncertainty on a plane.

    Attributes
    ----------
    x_mm, y_mm : (nx,), (ny,) ndarrays
        Grid, world mm.
    z_mm : float
    count : (ny, nx) int ndarray
        Sensors that see each point.
    cov_mm2 : (ny, nx, 3, 3) ndarray
        Triangulated position covariance (NaN where fewer than two sensors).
    sensors : list of str
    centers_mm : (S, 3) ndarray
    """

    x_mm: np.ndarray
    y_mm: np.ndarray
    z_mm: float
    count: np.ndarray
    cov_mm2: np.ndarray
    sensors: list
    centers_mm: np.ndarray

    @property
    def sigma_mm(self) -> np.ndarray:
        """``sqrt(trace cov)`` (ny, nx), mm: the 3D position 1-sigma."""
        return np.sqrt(np.trace(self.cov_mm2, axis1=-2, axis2=-1))

    @property
    def sigma_xyz_mm(self) -> np.ndarray:
        """Per-axis 1-sigma (ny, nx, 3), mm."""
        return np.sqrt(np.diagonal(self.cov_mm2, axis1=-2, axis2=-1))


def plan_map(sensors, room_mm, *, z_mm: float = 1000.0, grid_mm: float = 100.0, sigma_d_mm: float = 1e-3,
             margin: float = 1.0) -> PlanMap:
    """Coverage and position-uncertainty maps on the plane ``Z = z_mm``.

    Parameters
    ----------
    sensors : sequence of SensorPose
        From :func:`psdcal.measure.positioning.load_sensors` (``cov_pose`` used when present).
    room_mm : (3,) array_like
        Room extent ``X, Y, Z`` (the grid spans ``[0, X] x [0, Y]``), mm.
    z_mm : float
        Height of the plane, mm.
    grid_mm : float
        Grid spacing, mm.
    sigma_d_mm : float
        Impact-point noise (isotropic 1-sigma), mm.
    margin : float
        Fraction of the active area that counts as "in view".
    """
    from psdcal.measure.aoa import angles_from_points
    from psdcal.measure._geometry import project_world, skews, spot_for_normalised

    room = np.asarray(room_mm, dtype=float)
    if room.shape != (3,) or not np.all(room > 0) or not grid_mm > 0:
        raise InputError("the room needs three positive sizes and the grid a positive spacing", field="room")
    xs = np.arange(grid_mm / 2, room[0], grid_mm)
    ys = np.arange(grid_mm / 2, room[1], grid_mm)
    XX, YY = np.meshgrid(xs, ys)
    P = np.stack([XX, YY, np.full_like(XX, float(z_mm))], -1).reshape(-1, 3)
    info = np.zeros((len(P), 3, 3))
    count = np.zeros(len(P), int)
    for s in sensors:
        m = s.model
        n, z = project_world(P, s.rvec, s.tvec_mm)
        front = z > 0
        d = spot_for_normalised(m, np.where(front[:, None], n, 0.0))
        with np.errstate(invalid="ignore"):
            vis = front & np.all(np.isfinite(d), -1) & (np.abs(d[:, 0]) < margin * m.lx_mm / 2) \
                & (np.abs(d[:, 1]) < margin * m.ly_mm / 2)
        if not vis.any():
            continue
        count += vis
        dv = d[vis]
        res = angles_from_points(dv, m, np.broadcast_to(sigma_d_mm**2 * np.eye(2), dv.shape + (2,)), derivatives=False)
        C = res.cov_n + 1e-30 * np.eye(2)
        R = s.R
        pc = (P[vis] @ R.T) + np.asarray(s.tvec_mm, float)
        zz = pc[:, 2]
        dpi = np.zeros((len(zz), 2, 3))
        dpi[:, 0, 0] = dpi[:, 1, 1] = 1 / zz
        dpi[:, 0, 2] = -n[vis, 0] / zz
        dpi[:, 1, 2] = -n[vis, 1] / zz
        if getattr(s, "cov_pose", None) is not None:
            rp = pc - np.asarray(s.tvec_mm, float)
            Jp = np.concatenate([-dpi @ skews(rp), dpi], -1)
            C = C + Jp @ np.asarray(s.cov_pose) @ np.swapaxes(Jp, 1, 2)
        J = dpi @ R
        info[vis] += np.swapaxes(J, 1, 2) @ np.linalg.inv(C) @ J
    cov = np.full((len(P), 3, 3), np.nan)
    ok = count >= 2
    if ok.any():
        # parallel rays (sensors at one place) leave the depth undetermined: infinite sigma
        good = np.linalg.cond(info[ok]) < 1e12
        idx = np.flatnonzero(ok)
        cov[idx[good]] = np.linalg.inv(info[idx[good]])
        cov[idx[~good]] = np.where(np.eye(3, dtype=bool), np.inf, 0.0)
    ny, nx = XX.shape
    return PlanMap(xs, ys, float(z_mm), count.reshape(ny, nx), cov.reshape(ny, nx, 3, 3), [s.name for s in sensors],
                   np.stack([s.center_w_mm for s in sensors]))


def write_plan_csv(pm: PlanMap, path) -> None:
    """CSV ``X_m,Y_m,Z_m,n_sensors,sigma_mm,sigma_X_mm,sigma_Y_mm,sigma_Z_mm`` (atomically)."""
    from psdcal._atomic import write_text_atomic

    XX, YY = np.meshgrid(pm.x_mm, pm.y_mm)
    s = pm.sigma_mm
    sx = pm.sigma_xyz_mm
    lines = ["X_m,Y_m,Z_m,n_sensors,sigma_mm,sigma_X_mm,sigma_Y_mm,sigma_Z_mm"]
    for k in np.ndindex(XX.shape):
        vals = ",".join("" if not np.isfinite(v) else f"{v:.6g}" for v in (s[k], *sx[k]))
        lines.append(f"{XX[k] / 1000:.6g},{YY[k] / 1000:.6g},{pm.z_mm / 1000:.6g},{pm.count[k]},{vals}")
    write_text_atomic(path, "\n".join(lines) + "\n")


def plot_plan(pm: PlanMap, path, *, title: str | None = None) -> None:
    """Coverage and position-sigma maps side by side, sensors marked (PNG, written atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    from psdcal._atomic import atomic_path

    x, y = pm.x_mm / 1000, pm.y_mm / 1000
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), constrained_layout=True)
    k = int(pm.count.max()) if pm.count.size else 0
    im = axes[0].pcolormesh(x, y, pm.count, shading="auto", cmap=plt.get_cmap("viridis", k + 1), vmin=-0.5,
                            vmax=k + 0.5)
    fig.colorbar(im, ax=axes[0], ticks=range(k + 1), label="sensors that see the point")
    axes[0].set_title(f"coverage at Z = {pm.z_mm / 1000:g} m")
    s = np.ma.masked_invalid(pm.sigma_mm)
    if s.count():
        im2 = axes[1].pcolormesh(x, y, s, shading="auto", cmap="magma_r",
                                 norm=LogNorm(vmin=max(float(s.min()), 1e-6), vmax=max(float(s.max()), 2e-6)))
        fig.colorbar(im2, ax=axes[1], label="position 1-sigma (mm)")
        cs = axes[1].contour(x, y, s.filled(np.nan), colors="k", linewidths=0.5, levels=6)
        axes[1].clabel(cs, fontsize=7, fmt="%.3g")
    axes[1].set_title("position uncertainty (>= 2 sensors)")
    for ax in axes:
        ax.plot(pm.centers_mm[:, 0] / 1000, pm.centers_mm[:, 1] / 1000, "r^", ms=9)
        for nm, c in zip(pm.sensors, pm.centers_mm):
            ax.annotate(nm, (c[0] / 1000, c[1] / 1000), textcoords="offset points", xytext=(4, 4), color="r")
        ax.set_aspect("equal")
        ax.set_xlabel("X (m)")
        ax.set_ylabel("Y (m)")
    fig.suptitle(title or "installation plan")
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
