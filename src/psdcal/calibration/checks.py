"""Numbers behind the calibration report: where the data are, and which points to trust.

Plain functions over a :class:`psdcal.calibration.core.CalibrationResult`; the
figures are in :mod:`psdcal.report.plots`, the page in :mod:`psdcal.report.page`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psdcal.errors import InputError


def align_to_problem(result):
    """The result with its residual columns in the order of its problem record's template.

    A calibration read back from JSON orders its point ids as the residual
    rows list them; the problem record keeps the template's order. Reports
    and refits index both the same way, so this puts the residuals
    (n_images, M, 2) in the template's order (NaN for a point with no
    residual anywhere). Returns the result itself when they already agree.
    """
    import dataclasses

    try:
        pids = tuple(result.problem["template"]["point_ids"])
    except (KeyError, TypeError):
        return result
    if pids == tuple(result.point_ids):
        return result
    index = {p: j for j, p in enumerate(result.point_ids)}
    R0 = np.asarray(result.residuals_mm, dtype=float)
    R = np.full((R0.shape[0], len(pids), 2), np.nan)
    for j, p in enumerate(pids):
        if p in index:
            R[:, j] = R0[:, index[p]]
    return dataclasses.replace(result, point_ids=pids, residuals_mm=R)


def with_points(result, point_ids, template_mm, points_mm):
    """The result aligned to a template and points given from files (for results without a problem record).

    The residual columns are put in the order of ``point_ids``; when the
    calibration file carries no per-point residuals (docs/model.md#calibration-json does not
    require them), they are computed from its parameters and poses
    (``points_mm - distort(project(P))``), with the RMS values.  The template
    and the points are added to the problem record (without options: such a
    result cannot be refitted).

    Parameters
    ----------
    result : CalibrationResult
    point_ids : sequence (M,)
    template_mm : (M, 2) array_like, mm
    points_mm : (n_images, M, 2) array_like, mm, NaN where missing; images in ``result.image_ids`` order.

    Returns
    -------
    CalibrationResult
    """
    import dataclasses


    pids = tuple(point_ids)
    X = np.asarray(points_mm, dtype=float)
    T = np.asarray(template_mm, dtype=float)
    R0 = np.asarray(result.residuals_mm, dtype=float)
    changes = {}
    if R0.ndim == 3 and R0.shape[1] > 0:
        index = {p: j for j, p in enumerate(result.point_ids)}
        R = np.full(X.shape, np.nan)
        for j, p in enumerate(pids):
            if p in index:
                R[:, j] = R0[:, index[p]]
    else:
        if len(result.rvecs) != X.shape[0]:
            raise InputError(f"the calibration has {len(result.rvecs)} poses for {X.shape[0]} images", field="extrinsics")
        R = X - model_points_mm(result, T)
        ok = np.all(np.isfinite(R), axis=-1)
        sq = np.where(ok, np.sum(np.nan_to_num(R) ** 2, axis=-1), 0.0)
        changes["rms_mm"] = float(np.sqrt(sq.sum() / max(ok.sum(), 1)))
        changes["per_image_rms_mm"] = np.sqrt(sq.sum(axis=1) / np.maximum(ok.sum(axis=1), 1))
        if not np.isfinite(result.sigma_mm):
            dof = max(2 * int(ok.sum()) - len(result.param_names) - 6 * X.shape[0], 1)
            changes["sigma_mm"] = float(np.sqrt(sq.sum() / dof))
    problem = dict(result.problem or {})
    problem.setdefault("template", {"point_ids": list(pids), "xy_mm": T.tolist()})
    problem.setdefault("points", {"image_ids": list(result.image_ids),
                                  "xy_mm": [[[None if not np.isfinite(v) else float(v) for v in pt] for pt in img] for img in X]})
    return dataclasses.replace(result, point_ids=pids, residuals_mm=R, problem=problem, **changes)


def measured_points_mm(result) -> np.ndarray:
    """The measured impact points the calibration used, (n_images, M, 2) mm, NaN where missing.

    Read from the problem record saved in the calibration (``problem.points.xy_mm``).

    Raises
    ------
    InputError
        When the calibration holds no points (pass the points file instead).
    """
    try:
        xy = result.problem["points"]["xy_mm"]
    except (KeyError, TypeError):
        raise InputError("the calibration holds no measured points (problem.points); pass --points and --template",
                         field="problem.points") from None
    from psdcal.calibration.core import points_from_record

    X = points_from_record(xy)
    if X.ndim != 3 or X.shape[:2] != np.asarray(result.residuals_mm).shape[:2]:
        raise InputError(f"problem.points has shape {X.shape}, the residuals {np.shape(result.residuals_mm)}",
                         field="problem.points")
    return X


@dataclass(frozen=True)
class Coverage:
    """Occupancy of the sensor by calibration points.

    Attributes
    ----------
    x_edges_mm, y_edges_mm : (n + 1,) ndarray
        Cell edges, mm.
    counts : (n, n) int ndarray
        Points per cell; ``counts[iy, ix]``.
    in_region : (n, n) bool ndarray
        Cells whose centre lies in the measurement region.
    region_mm : (x0, x1, y0, y1)
        The measurement region, mm.
    """

    x_edges_mm: np.ndarray
    y_edges_mm: np.ndarray
    counts: np.ndarray
    in_region: np.ndarray
    region_mm: tuple

    @property
    def empty(self) -> np.ndarray:
        """(n, n) bool: cells in the measurement region with no calibration point."""
        return self.in_region & (self.counts == 0)

    @property
    def fraction_covered(self) -> float:
        """Fraction of the measurement region's cells that hold at least one point."""
        n = int(self.in_region.sum())
        return float(((self.counts > 0) & self.in_region).sum() / n) if n else float("nan")

    def empty_cells_mm(self) -> list:
        """The empty cells of the region as ``(x0, x1, y0, y1)`` tuples in mm."""
        out = []
        for iy, ix in zip(*np.nonzero(self.empty)):
            out.append((float(self.x_edges_mm[ix]), float(self.x_edges_mm[ix + 1]),
                        float(self.y_edges_mm[iy]), float(self.y_edges_mm[iy + 1])))
        return out

    def warnings(self) -> list:
        """Sentences for the report: one per problem found (empty list when none)."""
        cells = self.empty_cells_mm()
        if not cells:
            return []
        w = (self.x_edges_mm[1] - self.x_edges_mm[0])
        txt = ", ".join(f"x {c[0]:+.1f}..{c[1]:+.1f}, y {c[2]:+.1f}..{c[3]:+.1f}" for c in cells[:12])
        more = f" and {len(cells) - 12} more" if len(cells) > 12 else ""
        return [f"{len(cells)} cell(s) of {w:.2g} mm in the measurement region hold no calibration point "
                f"({txt}{more} mm): the distortion there is extrapolated; add views that image the template there"]


def coverage(points_mm, sensor_mm=(9.0, 9.0), *, n_cells: int = 6, region_mm=None) -> Coverage:
    """Where on the sensor a calibration has data.

    Parameters
    ----------
    points_mm : (..., 2) array_like
        Measured impact points, mm (NaN rows ignored).
    sensor_mm : (Lx, Ly), mm
    n_cells : int
        Cells per side over the sensor.
    region_mm : (x0, x1, y0, y1), optional
        The part of the sensor used for measurement (default: all of it).

    Returns
    -------
    Coverage
    """
    if n_cells < 1:
        raise InputError(f"n_cells must be >= 1, got {n_cells}", field="n_cells")
    hx, hy = sensor_mm[0] / 2, sensor_mm[1] / 2
    region = (-hx, hx, -hy, hy) if region_mm is None else tuple(float(v) for v in region_mm)
    if len(region) != 4 or not (region[0] < region[1] and region[2] < region[3]):
        raise InputError(f"region must be x0 x1 y0 y1 with x0 < x1, y0 < y1; got {region}", field="region_mm")
    P = np.asarray(points_mm, dtype=float).reshape(-1, 2)
    P = P[np.all(np.isfinite(P), axis=1)]
    xe = np.linspace(-hx, hx, n_cells + 1)
    ye = np.linspace(-hy, hy, n_cells + 1)
    H, _, _ = np.histogram2d(P[:, 1], P[:, 0], bins=[ye, xe])
    xc, yc = 0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1])
    inside = ((xc[None, :] >= region[0]) & (xc[None, :] <= region[1]) & (yc[:, None] >= region[2]) & (yc[:, None] <= region[3]))
    return Coverage(xe, ye, H.astype(int), inside, region)


def model_points_mm(result, template_mm=None) -> np.ndarray:
    """Modelled measured points (n_images, M, 2), mm, of every template point in every view.

    ``distort(project(P))`` with the result's parameters and poses (and the
    channel gains when they are not all one): what the calibration predicts
    the sensor reads, also where the point is missing or was removed.

    Parameters
    ----------
    result : CalibrationResult
    template_mm : (M, 2) array_like, optional
        Template points, mm (default: the result's problem record).
    """
    from psdcal.model.distortion import distort
    from psdcal.model.projection import project
    from psdcal.model.readout import gain_map

    T = np.asarray(result.problem["template"]["xy_mm"] if template_mm is None else template_mm, dtype=float)
    x = np.stack([project(T, result.intrinsics, r, t) for r, t in zip(result.rvecs, result.tvecs_mm)])
    m = distort(x, result.distortion, result.intrinsics.c).d_mm
    if not np.allclose(result.gains, 1.0):
        m = gain_map(m, result.gains, *result.sensor_mm)
    return m


__all__ = ["Coverage", "align_to_problem", "coverage", "measured_points_mm", "model_points_mm", "with_points"]


#: Eigenvalue of the scaled reduced information (:func:`undetermined_parameters`) below which a direction of
#: the global parameters counts as not determined by the views: round-off level. Well-posed sets give 6e-6 and
#: more (the smallest of 60 simulated Lens 1 and Lens 2 sets of 3 to 40 views); views all parallel to the sensor
#: give 1e-25. False alarms: 0 in 78 calibrations (72 simulated: both lenses, 4-15 views, 0.5-10 um noise, five
#: models incl. PSD l1, k3 and fy; Zhang's data and the five real chessboard sets).
UNDETERMINED_EIGENVALUE = 1e-12


def undetermined_parameters(result) -> list[str]:
    """Global parameters along a direction that the views do not determine (empty when every one is determined).

    The poses are eliminated from the normal equations at the solution (the
    reduced system ``S = U - sum_v W_v V_v^-1 W_v^T``, as in the refinement),
    and ``S`` is scaled by the diagonal of the global block ``U``: an
    eigenvalue of ``D^-1/2 S D^-1/2`` (``D = diag U``) is the fraction of a
    direction's information that the poses do not explain. Where it is at
    round-off (:data:`UNDETERMINED_EIGENVALUE`), a combination of parameters
    trades off exactly against the poses (every view parallel to the sensor:
    ``f`` against the distances), and its standard error is whatever
    round-off made it. Returns the (at most two) parameters with the largest
    share of each such direction.

    Parameters
    ----------
    result : CalibrationResult with its problem record (``[]`` without one)
    """
    from psdcal.calibration._refine import Evaluator, Problem
    from psdcal.calibration.core import inputs_from_record

    try:
        T, X = inputs_from_record(result.problem)
    except (KeyError, TypeError, ValueError):
        return []
    spec = result.model
    names = tuple(result.param_names)
    fixed = tuple(n for n in spec.global_names if n not in names)
    try:
        prob = Problem(T, X, spec, cost=result.cost, sensor_mm=tuple(result.sensor_mm), fixed=fixed)
        if prob.names != names or X.shape[0] != len(result.rvecs):
            return []
        ev = Evaluator(prob, result.intrinsics, result.distortion, result.gains)
        z = prob.pack(result.intrinsics, result.distortion, result.gains, result.rvecs, result.tvecs_mm)
        r, Jc = ev.evaluate_compact(z)
        bs = ev.block_system(Jc, r)
    except (ValueError, np.linalg.LinAlgError, FloatingPointError):
        return []
    U, W, V = bs.U, bs.W, bs.V
    S = U - np.einsum("vij,vkj->ik", W @ np.linalg.pinv(V), W)  # sum over the views of W_v V_v^+ W_v^T
    d = np.sqrt(np.maximum(np.diag(U), 0.0))
    keep = d > 0
    out = [n for n, k in zip(names, keep) if not k]  # a column with no information at all
    if keep.sum() == 0:
        return out
    Ss = S[np.ix_(keep, keep)] / np.outer(d[keep], d[keep])
    if not np.all(np.isfinite(Ss)):
        return list(names)
    w, vec = np.linalg.eigh(0.5 * (Ss + Ss.T))
    sub = [n for n, k in zip(names, keep) if k]
    # at round-off, of either sign: an exact trade-off. A clearly negative eigenvalue is a solution that is
    # itself broken (a pose with next to no information, a focal length near 0): the verdict names its cause.
    for j in np.flatnonzero(np.abs(w) < UNDETERMINED_EIGENVALUE):
        for i in np.argsort(-np.abs(vec[:, j]))[:2]:
            if sub[i] not in out:
                out.append(sub[i])
    return out
