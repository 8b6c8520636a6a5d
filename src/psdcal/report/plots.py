"""Figures of a calibration for people: residuals, coverage, distortion, AoA uncertainty.

Every function returns a :class:`matplotlib.figure.Figure` built without
pyplot (no global state, safe on a headless machine with the Agg backend);
show it in a notebook by leaving it as a cell's value, or save it with
``fig.savefig("name.png")``.

Examples
--------
>>> from psdcal.study.simulate import simulate_set
>>> from psdcal import calibrate
>>> from psdcal import plots
>>> s = simulate_set("lens2", n_images=9, noise_mm=0.003, seed=1)
>>> res = calibrate(s.template_mm, s.points_mm)
>>> fig = plots.residuals(res)            # every residual vector on the sensor
>>> fig = plots.aoa_uncertainty(res)      # 1-sigma AoA error over the field of view, degrees

Units: positions on the sensor in mm, residuals in micrometres (um),
angles in degrees.
"""
from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from psdcal.calibration.checks import coverage as _coverage
from psdcal.calibration.checks import align_to_problem, measured_points_mm
from psdcal.calibration.outliers import DEFAULT_K, flag_outliers, removed_points

_UM = 1e3  # um per mm


def _new(figsize=(7.0, 5.6)):
    fig = Figure(figsize=figsize, dpi=100, layout="constrained")
    return fig


def _sensor_axes(ax, sensor_mm):
    hx, hy = sensor_mm[0] / 2, sensor_mm[1] / 2
    ax.add_patch(_rect(-hx, -hy, 2 * hx, 2 * hy))
    ax.set_xlim(-hx * 1.06, hx * 1.06)
    ax.set_ylim(-hy * 1.06, hy * 1.06)
    ax.set_aspect("equal")
    ax.set_xlabel("x on the sensor [mm]")
    ax.set_ylabel("y on the sensor [mm]")


def _rect(x, y, w, h, **kw):
    from matplotlib.patches import Rectangle

    kw = {"fill": False, "edgecolor": "0.3", "linewidth": 1.0, **kw}
    return Rectangle((x, y), w, h, **kw)


def _auto_scale(r_mm, sensor_mm):
    """Arrow scale (sensor mm per residual mm) so that the 95th percentile arrow is ~0.6 mm long."""
    n = np.sqrt(np.nansum(np.asarray(r_mm) ** 2, axis=-1))
    n = n[np.isfinite(n) & (n > 0)]
    ref = float(np.percentile(n, 95)) if n.size else 1e-3
    return 0.6 / max(ref, 1e-12)


def _nice(v):
    """A round number near v (1, 2, 5 x 10^k)."""
    if not np.isfinite(v) or v <= 0:
        return 1.0
    e = np.floor(np.log10(v))
    m = v / 10**e
    return float((1 if m < 1.5 else 2 if m < 3.5 else 5 if m < 7.5 else 10) * 10**e)


def _draw_residuals(ax, X, R, sensor_mm, scale, colors, flagged=None, removed=(), key=True, cap_mm=1.5):
    """Quiver of residuals R at points X; arrows longer than ``cap_mm`` are cut there and labelled."""
    _sensor_axes(ax, sensor_mm)
    ok = np.all(np.isfinite(X), axis=-1) & np.all(np.isfinite(R), axis=-1)
    U = R * scale
    L = np.sqrt(np.sum(np.where(ok[..., None], U, 0.0) ** 2, axis=-1))
    long_ = ok & (L > cap_mm)
    U = np.where(long_[..., None], U * (cap_mm / np.maximum(L, 1e-300))[..., None], U)
    q = None
    for i in range(X.shape[0]):
        m = ok[i]
        if not m.any():
            continue
        c = colors[i % len(colors)]
        ax.plot(X[i, m, 0], X[i, m, 1], ".", ms=2.5, color=c)
        q = ax.quiver(X[i, m, 0], X[i, m, 1], U[i, m, 0], U[i, m, 1], angles="xy", scale_units="xy", scale=1.0,
                      color=c, width=0.004)
    for i, j in zip(*np.nonzero(long_)):
        ax.annotate(f"{np.hypot(*R[i, j]) * _UM:.0f} um", (X[i, j, 0] + U[i, j, 0], X[i, j, 1] + U[i, j, 1]),
                    fontsize=7, color="red", ha="center", va="bottom")
    if flagged is not None and np.any(flagged & ok):
        f = flagged & ok
        ax.plot(X[f, 0], X[f, 1], "o", mfc="none", mec="red", ms=11, mew=1.8, label="outlier")
    if removed:
        ax.plot([p.x_mm for p in removed], [p.y_mm for p in removed], "x", color="red", ms=10, mew=2.2,
                label="removed (--reject)")
        for p in removed:
            ax.annotate(f"{p.ratio:.0f} sigma", (p.x_mm, p.y_mm), xytext=(5, -11), textcoords="offset points",
                        fontsize=7, color="red")
    if key and q is not None:
        length_mm = _nice(0.6 / scale)
        ax.quiverkey(q, 0.93, 1.03, length_mm * scale, f"{length_mm * _UM:g} um", labelpos="W", coordinates="axes",
                     color="k")
    if (flagged is not None and np.any(flagged & ok)) or removed:
        ax.legend(loc="lower left", fontsize=8)


def _residual_inputs(result, points_mm, scale):
    """The aligned result, measured points (n, M, 2), residuals (n, M, 2) and arrow scale of a residual plot."""
    result = align_to_problem(result)
    X = measured_points_mm(result) if points_mm is None else np.asarray(points_mm, dtype=float)
    R = np.asarray(result.residuals_mm, dtype=float)
    return result, X, R, (_auto_scale(R, result.sensor_mm) if scale is None else scale)


def _palette(n):
    """Image colours without the reds and pinks, which mark outliers."""
    from matplotlib import colormaps

    cmap = colormaps["tab20" if n > 10 else "tab10"]
    reds = {6, 7, 12, 13} if cmap.N == 20 else {3, 6}
    cols = [cmap(i) for i in range(cmap.N) if i not in reds]
    return [cols[i % len(cols)] for i in range(max(n, 1))]


def _outlier_mask(result, k, flags):
    if flags is False:
        return None
    if flags is None:
        flags = flag_outliers(result, k)
    return flags.points


def residuals(result, *, scale=None, k: float = DEFAULT_K, flags=None, points_mm=None) -> Figure:
    """Residual vectors (measured minus model) of every point of every image on the sensor.

    Parameters
    ----------
    result : CalibrationResult
    scale : float, optional
        Arrow length on the sensor (mm) per mm of residual; automatic when None.
    k : float
        Outlier threshold (robust sigmas) for the red circles.
    flags : OutlierFlags or ``False``, optional
        Points to circle (default: :func:`psdcal.calibration.outliers.flag_outliers` at ``k``;
        ``False``: none).
    points_mm : (n_images, M, 2) array_like, optional
        Measured points (default: the calibration's own record).

    Returns
    -------
    Figure
    """
    result, X, R, scale = _residual_inputs(result, points_mm, scale)
    fig = _new((7.0, 6.4))
    ax = fig.add_subplot()
    _draw_residuals(ax, X, R, result.sensor_mm, scale, _palette(X.shape[0]), _outlier_mask(result, k, flags),
                    removed_points(result))
    ax.set_title(f"Residuals of all {X.shape[0]} images (arrows x{scale:.0f}); RMS {result.rms_mm * _UM:.2f} um",
                 fontsize=10, loc="left")
    return fig


def residuals_per_image(result, *, scale=None, ncols: int = 4, k: float = DEFAULT_K, flags=None,
                        points_mm=None) -> Figure:
    """Residual vectors on the sensor, one small panel per image (same arrow scale in all).

    Parameters
    ----------
    result : CalibrationResult
    scale, k, flags, points_mm : as :func:`residuals`.
    ncols : int, panels per row.

    Returns
    -------
    Figure
    """
    result, X, R, scale = _residual_inputs(result, points_mm, scale)
    mask = _outlier_mask(result, k, flags)
    removed = removed_points(result)
    n = X.shape[0]
    ncols = max(1, min(ncols, n))
    nrows = int(np.ceil(n / ncols))
    fig = Figure(figsize=(2.6 * ncols, 2.7 * nrows + 0.4), dpi=100)  # fixed layout: fast with many panels
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.6 / (2.7 * nrows + 0.4), top=1 - 0.7 / (2.7 * nrows + 0.4),
                        wspace=0.12, hspace=0.32)
    colors = _palette(n)
    first = None
    for i in range(n):
        ax = fig.add_subplot(nrows, ncols, i + 1, sharex=first, sharey=first)
        first = first or ax
        iid = result.image_ids[i]
        rem = tuple(p for p in removed if p.image_id == iid)
        _draw_residuals(ax, X[i : i + 1], R[i : i + 1], result.sensor_mm, scale, [colors[i]],
                        None if mask is None else mask[i : i + 1], rem, key=(i == 0))
        if ax.get_legend() is not None:
            ax.get_legend().remove()
        ax.set_title(f"image {iid}: {result.per_image_rms_mm[i] * _UM:.2f} um", fontsize=9, loc="left")
        ax.tick_params(labelsize=7, labelbottom=i + ncols >= n, labelleft=i % ncols == 0)
        ax.set_xlabel("x [mm]" if i + ncols >= n else "", fontsize=8)
        ax.set_ylabel("y [mm]" if i % ncols == 0 else "", fontsize=8)
    fig.suptitle(f"Residuals per image (arrows x{scale:.0f}; red: outliers)", fontsize=10)
    return fig


def residual_histogram(result, *, bins: int = 40) -> Figure:
    """Histogram of the residual components against the Gaussian the fit implies.

    The curve is the normal density with the fit's implied noise
    ``sigma_mm`` (per coordinate), scaled to the counts; the dashed lines
    mark +-3 sigma.

    Returns
    -------
    Figure
    """
    R = np.asarray(result.residuals_mm, dtype=float).reshape(-1, 2)
    R = R[np.all(np.isfinite(R), axis=1)] * _UM
    sigma = float(result.sigma_mm) * _UM
    if not np.isfinite(sigma):
        sigma = 0.0
    fig = _new((7.0, 4.4))
    ax = fig.add_subplot()
    comps = R.ravel()
    lim = max(4.5 * sigma, float(np.percentile(np.abs(comps), 99.5)) if comps.size else 1.0)
    edges = np.linspace(-lim, lim, bins + 1)
    ax.hist([R[:, 0], R[:, 1]], bins=edges, stacked=True, color=["tab:blue", "tab:orange"], label=["dx", "dy"],
            alpha=0.8)
    x = np.linspace(-lim, lim, 400)
    width = edges[1] - edges[0]
    if sigma > 0:
        ax.plot(x, comps.size * width * np.exp(-0.5 * (x / sigma) ** 2) / (sigma * np.sqrt(2 * np.pi)), "k-", lw=1.6,
                label=f"implied noise N(0, {sigma:.2f} um)")
        for s in (-3, 3):
            ax.axvline(s * sigma, color="k", ls="--", lw=0.8)
    out = np.abs(comps) > lim
    if out.any():
        ax.text(0.99, 0.95, f"{int(out.sum())} component(s) beyond +-{lim:.1f} um", transform=ax.transAxes,
                ha="right", va="top", color="red", fontsize=9)
    ax.set_xlabel("residual component (measured - model) [um]")
    ax.set_ylabel("count")
    ax.set_title(f"Residual distribution ({len(R)} points, {2 * len(R)} components)", fontsize=10)
    ax.legend(fontsize=8, loc="upper left")
    return fig


def per_image_rms(result, *, k: float = DEFAULT_K, flags=None) -> Figure:
    """Per-image RMS residual, with the images flagged as outliers in red.

    The dashed line is the RMS expected from the fit's implied noise
    (``sqrt(2) sigma``); a red bar is an image whose residuals fail the
    chi-square test of :func:`psdcal.calibration.outliers.flag_images`; a hatched bar holds
    an outlier point.

    Returns
    -------
    Figure
    """
    if flags is None:
        flags = flag_outliers(result, k)
    rms = np.asarray(result.per_image_rms_mm, dtype=float) * _UM
    n = len(rms)
    fig = _new((max(5.0, 0.45 * n + 2.0), 3.8))
    ax = fig.add_subplot()
    colors = ["tab:red" if f else "tab:blue" for f in flags.images]
    hatches = ["//" if p else "" for p in flags.points.any(axis=1)]
    bars = ax.bar(np.arange(n), rms, color=colors)
    for b, h in zip(bars, hatches):
        b.set_hatch(h)
    ax.axhline(np.sqrt(2) * result.sigma_mm * _UM, color="k", ls="--", lw=1, label="expected from the implied noise")
    ax.set_xticks(np.arange(n), [str(i) for i in result.image_ids], fontsize=8, rotation=90 if n > 25 else 0)
    ax.set_xlabel("image")
    ax.set_ylabel("RMS residual [um]")
    removed = removed_points(result)
    for p in removed:
        if p.image_id in result.image_ids:
            i = list(result.image_ids).index(p.image_id)
            ax.plot(i, rms[i], "x", color="red", ms=9, mew=2)
    gone = f", {len(removed)} removed: red x" if removed else ""
    ax.set_title(f"Per-image RMS ({int(flags.images.sum())} image(s) flagged, {flags.n_points} point(s) above "
                 f"{flags.k:g} sigma{gone})", fontsize=10)
    ax.legend(fontsize=8)
    return fig


def coverage(result, *, n_cells: int = 6, region_mm=None, points_mm=None) -> Figure:
    """Where on the sensor the calibration has data.

    Cells of the sensor coloured by their number of calibration points;
    cells of the measurement region without any point are hatched red
    (:func:`psdcal.calibration.checks.coverage`); the points are drawn on top with
    the convex hull of all of them.

    Returns
    -------
    Figure
    """
    X = measured_points_mm(result) if points_mm is None else np.asarray(points_mm, dtype=float)
    cov = _coverage(X, result.sensor_mm, n_cells=n_cells, region_mm=region_mm)
    fig = _new((6.6, 5.8))
    ax = fig.add_subplot()
    m = ax.pcolormesh(cov.x_edges_mm, cov.y_edges_mm, cov.counts, cmap="Greens", vmin=0,
                      vmax=max(1, cov.counts.max()))
    fig.colorbar(m, ax=ax, label="calibration points per cell", shrink=0.85)
    _sensor_axes(ax, result.sensor_mm)
    x0, x1, y0, y1 = cov.region_mm
    ax.add_patch(_rect(x0, y0, x1 - x0, y1 - y0, edgecolor="tab:blue", linewidth=1.5, linestyle="--"))
    for c in cov.empty_cells_mm():
        ax.add_patch(_rect(c[0], c[2], c[1] - c[0], c[3] - c[2], hatch="xx", edgecolor="red", linewidth=0.8))
    P = X.reshape(-1, 2)
    P = P[np.all(np.isfinite(P), axis=1)]
    ax.plot(P[:, 0], P[:, 1], ".", color="k", ms=2)
    if len(P) >= 3:
        from scipy.spatial import ConvexHull, QhullError

        try:
            h = ConvexHull(P)
            v = np.append(h.vertices, h.vertices[0])
            ax.plot(P[v, 0], P[v, 1], "-", color="0.2", lw=0.8)
        except QhullError:
            pass
    ax.set_title(f"Coverage: {cov.fraction_covered * 100:.0f} % of the measurement region's cells hold data "
                 f"({int(cov.empty.sum())} empty, red)", fontsize=10)
    return fig


def distortion_field(result, *, n: int = 15) -> Figure:
    """The distortion correction over the sensor: arrows ``undistort(d) - d``, colour its length.

    Returns
    -------
    Figure
    """
    from psdcal.model.readout import sensor_grid_mm

    d = sensor_grid_mm(result.sensor_mm, n)
    corr = result.undistort(d) - d
    mag = np.linalg.norm(corr, axis=-1) * _UM
    fig = _new((6.8, 5.8))
    ax = fig.add_subplot()
    dense = sensor_grid_mm(result.sensor_mm, 81)
    dm = np.linalg.norm(result.undistort(dense) - dense, axis=-1) * _UM
    m = ax.contourf(dense[..., 0], dense[..., 1], dm, levels=14, cmap="viridis")
    fig.colorbar(m, ax=ax, label="|correction| [um]", shrink=0.85)
    peak = max(float(mag.max()), 1e-9)
    scale = 0.8 * (result.sensor_mm[0] / (n - 1)) / peak  # the longest arrow spans ~0.8 grid step
    ax.quiver(d[..., 0], d[..., 1], corr[..., 0] * _UM * scale, corr[..., 1] * _UM * scale, angles="xy",
              scale_units="xy", scale=1.0, color="white", width=0.004)
    ax.plot(*result.intrinsics.c, "r+", ms=12, mew=2, label="optical centre")
    _sensor_axes(ax, result.sensor_mm)
    ax.legend(fontsize=8, loc="lower left")
    ax.set_title(f"Distortion correction undistort(d) - d (max {peak:.0f} um)", fontsize=10)
    return fig


def aoa_uncertainty(result, *, n: int = 41) -> Figure:
    """1-sigma calibration uncertainty of the angle of arrival over the field of view, degrees.

    ``sqrt(var alpha_x + var alpha_y)`` from the calibration covariance
    (:func:`psdcal.report.compare.fov_uncertainty`), drawn at the angles each
    sensor point sees.

    Returns
    -------
    Figure
    """
    from psdcal.report.compare import fov_uncertainty

    f = fov_uncertainty(result, n)
    a = f.alpha_deg
    s = f.sigma_total_deg
    fig = _new((6.8, 5.8))
    ax = fig.add_subplot()
    m = ax.pcolormesh(a[..., 0], a[..., 1], s, shading="gouraud", cmap="magma_r")
    fig.colorbar(m, ax=ax, label="AoA 1-sigma [deg]", shrink=0.85)
    cs = ax.contour(a[..., 0], a[..., 1], s, levels=6, colors="k", linewidths=0.6)
    ax.clabel(cs, fmt="%.3g", fontsize=7)
    ax.set_aspect("equal")
    ax.set_xlabel("alpha_x [deg]")
    ax.set_ylabel("alpha_y [deg]")
    ax.set_title(f"AoA uncertainty from the calibration: {s.min():.3g}-{s.max():.3g} deg", fontsize=10)
    return fig


def correlation(result) -> Figure:
    """Correlation matrix of the calibration's free global parameters, annotated.

    Returns
    -------
    Figure
    """
    names = list(result.param_names)
    C = result.correlation() if len(names) else np.zeros((0, 0))
    k = len(names)
    fig = _new((max(4.5, 0.62 * k + 2.2), max(3.8, 0.55 * k + 1.6)))
    ax = fig.add_subplot()
    if k == 0 or np.asarray(result.covariance).size == 0:
        ax.text(0.5, 0.5, "the calibration holds no covariance matrix", ha="center", va="center", fontsize=11)
        ax.set_axis_off()
        return fig
    m = ax.imshow(C, cmap="RdBu_r", vmin=-1, vmax=1)
    fig.colorbar(m, ax=ax, label="correlation", shrink=0.85)
    ax.set_xticks(range(k), names, rotation=45, ha="right", fontsize=8)
    ax.set_yticks(range(k), names, fontsize=8)
    for i in range(k):
        for j in range(k):
            ax.text(j, i, f"{C[i, j]:.2f}", ha="center", va="center", fontsize=7,
                    color="white" if abs(C[i, j]) > 0.6 else "black")
    ax.set_title("Parameter correlations", fontsize=10)
    return fig


def compare_maps(comparison) -> Figure:
    """Two calibrations compared over the field of view: ray difference (deg) and in combined sigmas.

    Parameters
    ----------
    comparison : psdcal.report.compare.Comparison

    Returns
    -------
    Figure
    """
    c = comparison
    d = c.d_mm
    fig = _new((11.5, 4.9))
    s = c.summary()
    for k, (val, label, cmap) in enumerate(
        ((c.delta_deg, "ray difference [deg]", "viridis"), (c.n_sigma, "difference / combined sigma", "inferno"))
    ):
        ax = fig.add_subplot(1, 2, k + 1)
        v = np.where(np.isfinite(val), val, np.nan)
        vmax = np.nanmax(v) if np.any(np.isfinite(v)) else 1.0
        m = ax.pcolormesh(d[..., 0], d[..., 1], v, shading="gouraud", cmap=cmap, vmin=0, vmax=max(vmax, 1e-12))
        fig.colorbar(m, ax=ax, label=label, shrink=0.85)
        if k == 1 and np.isfinite(vmax) and vmax > 1:
            ax.contour(d[..., 0], d[..., 1], v, levels=[1, 2, 3], colors="w", linewidths=0.7)
        ax.set_aspect("equal")
        ax.set_xlabel("x on the sensor [mm]")
        ax.set_ylabel("y on the sensor [mm]")
    fig.axes[0].set_title(f"{c.names[0]} vs {c.names[1]}: max {s['max_deg']:.3g} deg, RMS {s['rms_deg']:.3g} deg",
                          fontsize=10)
    fig.axes[2].set_title(f"max {s['max_sigma']:.3g}, RMS {s['rms_sigma']:.3g} combined sigma", fontsize=10)
    return fig


def all_figures(result, *, k: float = DEFAULT_K, n_cells: int = 6, region_mm=None, flags=None, points_mm=None) -> dict:
    """Every figure of the calibration report, by name (``{"residuals": Figure, ...}``)."""
    result = align_to_problem(result)
    if flags is None:
        flags = flag_outliers(result, k)
    return {
        "residuals": residuals(result, k=k, flags=flags, points_mm=points_mm),
        "residual_histogram": residual_histogram(result),
        "residuals_per_image": residuals_per_image(result, k=k, flags=flags, points_mm=points_mm),
        "per_image_rms": per_image_rms(result, k=k, flags=flags),
        "coverage": coverage(result, n_cells=n_cells, region_mm=region_mm, points_mm=points_mm),
        "distortion_field": distortion_field(result),
        "aoa_uncertainty": aoa_uncertainty(result),
        "correlation": correlation(result),
    }


__all__ = [
    "all_figures",
    "aoa_uncertainty",
    "compare_maps",
    "correlation",
    "coverage",
    "distortion_field",
    "per_image_rms",
    "residual_histogram",
    "residuals",
    "residuals_per_image",
]
