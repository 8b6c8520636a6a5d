"""The fit's starting values: the linear stage and the choice among its starts (the paper's Section 3.1-3.2).

- :func:`initial_estimate`: line-straightness distortion (:mod:`._straightness`), a homography per view
  (:mod:`._homography`), closed-form intrinsics and poses (:mod:`._closed_form`);
- :func:`linear_starts` / :func:`focal_from_homographies` / :func:`template_hint`: several starts and the
  template diagnosis the verdict quotes;
- :func:`subsample_views`, the multistart and staged refinements that pick the start the full fit refines.

The front door that uses them is :func:`psdcal.calibration.core.calibrate`; every name here is also
reachable from :mod:`psdcal.calibration.core`.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import math
import functools
from dataclasses import dataclass, replace

import numpy as np

from psdcal.calibration._closed_form import intrinsics_from_homographies, poses_from_homographies
from psdcal.calibration._homography import homographies
from psdcal.calibration._refine import Problem, SolverOptions, refine
from psdcal.calibration._straightness import estimate_radial, find_lines
from psdcal.calibration.result import _ALL_INTR, MISFIT_FRACTION  # noqa: F401 (their names here: core's)
from psdcal.model.distortion import undistort
from psdcal.errors import DegenerateViewsError, InputError
from psdcal.model.params import DISTORTION_NAMES, Distortion, Intrinsics, ModelSpec

if TYPE_CHECKING:
    from psdcal.calibration.core import CalibrationResult

COSTS = ("image", "template")
#: The line-straightness step uses at most this many template lines (the longest):
#: a dense grid (Zhang's 256 corners) has hundreds, mostly short diagonals.
MAX_STRAIGHTNESS_LINES = 40
#: ... and at most this many points of each line (spread along it, both ends kept): the curvature of a
#: line is fixed by a few of its points, and a 16-point chessboard row costs twice 8 for no better start.
MAX_LINE_POINTS = 8


@dataclass(frozen=True)
class InitialEstimate:
    """What the linear stages produce (the start of the refinement; the paper's Tables 1-2).

    Attributes
    ----------
    preliminary_k : (2,) k1, k2 of the line-straightness step (zeros when skipped).
    n_lines : int, number of (image, line) groups the step used.
    homographies : (n_images, 3, 3)
    intrinsics : Intrinsics from the closed form.
    rvecs, tvecs_mm : (n_images, 3) poses from the homographies.
    points_per_view : int or None, the homographies were fitted to the spread subset of each view's points
        (:func:`subsample_views`, about this many points a view); None: to every point.
    """

    preliminary_k: np.ndarray
    n_lines: int
    homographies: np.ndarray
    intrinsics: Intrinsics
    rvecs: np.ndarray
    tvecs_mm: np.ndarray
    points_per_view: int | None = None

    def distortion(self, radial: int) -> Distortion:
        """The preliminary k1, k2 as a start for a model with ``radial`` lens terms."""
        return Distortion(k1=float(self.preliminary_k[0]) if radial >= 1 else 0.0,
                          k2=float(self.preliminary_k[1]) if radial >= 2 else 0.0)


def _check_inputs(template_mm, points_mm, image_ids, min_images):
    try:
        T = np.asarray(template_mm, dtype=float)
        X = np.asarray(points_mm, dtype=float)
    except (ValueError, TypeError) as exc:  # ragged nested lists, non-numbers
        raise InputError(f"template_mm and points_mm must be numeric arrays of shape (M, 2) and "
                         f"(n_images, M, 2): {exc}") from None
    if T.ndim != 2 or T.shape[1] != 2:
        raise InputError(f"template_mm must have shape (M, 2), got {T.shape}")
    if X.ndim != 3 or X.shape[2] != 2 or X.shape[1] != T.shape[0]:
        raise InputError(f"points_mm must have shape (n_images, {T.shape[0]}, 2), got {X.shape}")
    if not np.isfinite(T).all():
        raise InputError("template_mm contains NaN or infinite values")
    # a point is missing only when both coordinates are NaN (nothing to look at when all are finite)
    if not np.isfinite(X).all():
        nan = np.isnan(X)
        if np.any(nan.any(-1) & ~nan.all(-1)) or np.any(np.isinf(X)):
            raise InputError("points_mm: a point must be either two finite coordinates or two NaN (missing)")
    ids = list(range(X.shape[0])) if image_ids is None else list(image_ids)
    if len(ids) != X.shape[0]:
        raise InputError(f"image_ids has {len(ids)} entries for {X.shape[0]} images")
    if X.shape[0] < min_images:
        raise DegenerateViewsError(f"{X.shape[0]} images; calibration needs at least {min_images}")
    return T, X, ids


def initial_estimate(
    template_mm,
    points_mm,
    *,
    preliminary: bool = True,
    normalize: bool = True,
    radial_terms: int = 2,
    skew: bool = False,
    aspect: bool = False,
    image_ids=None,
    dlt_points=None,
) -> InitialEstimate:
    """The first, linear stage of the calibration (Sections 3.1-3.3).

    Parameters
    ----------
    template_mm : (M, 2)
    points_mm : (n_images, M, 2), NaN where missing.
    preliminary : apply the line-straightness distortion estimate first.
    normalize : Hartley-normalise the DLT.
    radial_terms : how many of k1, k2 the preliminary step estimates (0-2).
    dlt_points : (n_images, M, 2), optional
        The points the homographies (and so the closed form) are fitted to: a spread subset of
        ``points_mm`` (:func:`subsample_views`, NaN elsewhere); the preliminary step and the checks use
        ``points_mm``. Default: ``points_mm`` itself.
    """
    T, X, ids = _check_inputs(template_mm, points_mm, image_ids, 3 if (skew or aspect) else 2)
    Xd = X if dlt_points is None else np.asarray(dlt_points, dtype=float)
    k = np.zeros(2)
    n_lines = 0
    c0 = np.zeros(2)
    if preliminary and radial_terms > 0:
        lines = _straightness_lines(T)
        if lines:
            st = estimate_radial(X, lines, c_mm=c0, n_terms=min(2, radial_terms))
            k[: st.k.size] = st.k
            n_lines = st.n_lines
    coef = np.zeros(7)
    coef[:2] = k
    if n_lines:
        from psdcal import _jit

        if _jit.use_compiled(X.shape[0] * X.shape[1]):
            from psdcal.calibration._image_kernel import undistort_points

            Xc = undistort_points(Xd, coef, c0)  # undistort's arithmetic, compiled (tests/test_lm_kernel.py)
        else:
            Xc = undistort(Xd, coef, c0)
    else:
        Xc = Xd
    Hs = homographies(T, Xc, normalize=normalize, labels=[f"image {i}" for i in ids])
    intr = intrinsics_from_homographies(Hs, skew=skew, aspect=aspect)
    extent = _extent(X)
    if not (intr.f_mm < 1e3 * extent and np.hypot(intr.cx_mm, intr.cy_mm) < 10 * extent):
        raise DegenerateViewsError(
            f"the views do not determine the intrinsics (closed form gives f = {intr.f_mm:.3g} mm, "
            f"C = ({intr.cx_mm:.3g}, {intr.cy_mm:.3g}) mm): tilt the template differently between views"
        )
    return InitialEstimate(k, n_lines, Hs, intr, *poses_from_homographies(Hs, intr),
                           points_per_view=None if dlt_points is None else SUBSAMPLE_POINTS)


def _extent(X) -> float:
    """Twice the largest |coordinate| of the finite points (1.0 when there is none), mm: a scale of the sensor."""
    m = float(np.fmax.reduce(np.abs(X), axis=None)) if X.size else math.nan  # fmax skips NaN (missing points)
    return 2.0 * m if math.isfinite(m) else 1.0


def _straightness_lines(T) -> list:
    """The template lines of the straightness step, thinned (:func:`_thin_lines`); cached per template (read-only
    index arrays, shared by the calls)."""
    return list(_lines_of(*_template_key(T), MAX_STRAIGHTNESS_LINES, MAX_LINE_POINTS))


def _template_key(T) -> tuple:
    """``(shape, bytes)`` of a float template: a hashable key for the per-template caches."""
    T = np.ascontiguousarray(T, dtype=float)
    return T.shape, T.tobytes()


def _template_of(shape, data) -> np.ndarray:
    """The template of a :func:`_template_key` (read-only)."""
    return np.frombuffer(data, dtype=float).reshape(shape)


@functools.lru_cache(maxsize=8)
def _lines_of(shape, data, max_lines, max_points) -> tuple:
    T = _template_of(shape, data)
    out = tuple(np.array(ln) for ln in _thin_lines(T, find_lines(T, max_lines=max_lines), max_points))
    for ln in out:
        ln.flags.writeable = False
    return out


def _thin_lines(T, lines, k: int) -> list:
    """The lines with at most ``k`` indices each, spread evenly along the line (both ends kept), sorted.

    All lines at once: each line's direction is the principal axis of its
    points (2 x 2 scatter in closed form), its points are ordered along it
    and ``k`` of them taken at evenly spaced ranks.
    """
    lines = [np.asarray(ln) for ln in lines]
    if not lines or max(ln.size for ln in lines) <= k:
        return lines
    n = np.array([ln.size for ln in lines])
    start = np.concatenate([[0], np.cumsum(n)[:-1]])
    idx = np.concatenate(lines)
    owner = np.repeat(np.arange(len(lines)), n)
    P = T[idx]
    P = P - (np.add.reduceat(P, start, axis=0) / n[:, None])[owner]
    sxx, sxy, syy = (np.add.reduceat(P[:, 0] * P[:, 0], start), np.add.reduceat(P[:, 0] * P[:, 1], start),
                     np.add.reduceat(P[:, 1] * P[:, 1], start))
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)[owner]
    order = np.lexsort((P[:, 0] * np.cos(theta) + P[:, 1] * np.sin(theta), owner))  # by line, then along it
    out = []
    for j, ln in enumerate(lines):
        if ln.size <= k:
            out.append(ln)
            continue
        along = idx[order[start[j]: start[j] + n[j]]]
        out.append(np.sort(along[np.round(np.linspace(0, n[j] - 1, k)).astype(int)]))
    return out




#: Points per view on which the starts of the refinement are compared when a view has more than twice as
#: many (:func:`subsample_views`); the final refinement always takes every point.
SUBSAMPLE_POINTS = 32


def subsample_views(T, X, k: int = SUBSAMPLE_POINTS):
    """``X`` with all but about ``k`` spread points of each view set to NaN; None when no view has more than ``2 k``.

    The points are chosen once on the template: the one nearest the centre of
    each cell of a ``g x g`` grid over the plate, ``g = ceil(sqrt(k))``, so they
    cover the whole plate, corners included (where distortion shows most). A
    view that keeps fewer than ``k / 2`` of them (a partly seen template)
    keeps all its points.

    Parameters
    ----------
    T : (M, 2) template points, mm
    X : (n_images, M, 2) measured points, mm, NaN where missing
    """
    T = np.asarray(T, dtype=float)
    if T.shape[0] <= 2 * k:
        return None
    X = np.asarray(X, dtype=float)
    valid = np.isfinite(X[..., 0]) & np.isfinite(X[..., 1])  # (n_images, M)
    mask = _subsample_mask(*_template_key(T), k)
    if valid.all():  # every view sees every point (a chessboard): the same subset of each
        if int(np.count_nonzero(mask)) < k // 2:  # (as below: every view keeps all its points)
            return X.copy()
        return np.where(mask[:, None], X, np.nan)
    n_valid = valid.sum(axis=1)
    if not np.any(n_valid > 2 * k):
        return None
    keep = valid & mask[None, :]
    few = (keep.sum(axis=1) < k // 2) | (n_valid <= 2 * k)
    keep[few] = valid[few]
    return np.where(keep[..., None], X, np.nan)


@functools.lru_cache(maxsize=8)
def _subsample_mask(shape, data, k) -> np.ndarray:
    """(M,) bool, read-only: the template points :func:`subsample_views` keeps (cached per template)."""
    T = _template_of(shape, data)
    # one point per cell of a g x g grid over the plate (the one nearest the cell's centre)
    g = int(np.ceil(np.sqrt(k)))
    lo, hi = T.min(axis=0), T.max(axis=0)
    size = np.where(hi > lo, (hi - lo) / g, 1.0)
    cell = np.minimum(((T - lo) / size).astype(np.int64), g - 1)
    off = np.sum(((T - lo) / size - cell - 0.5) ** 2, axis=1)
    key = cell[:, 0] * g + cell[:, 1]
    order = np.lexsort((off, key))
    first = np.ones(order.size, dtype=bool)
    first[1:] = key[order[1:]] != key[order[:-1]]
    chosen = np.zeros(T.shape[0], dtype=bool)
    chosen[order[first]] = True
    chosen.flags.writeable = False
    return chosen


#: LM iterations a further start runs before it is compared with the best solution so far
#: (:func:`_refine_starts`).
PROBE_ITERATIONS = 3


def _fc(intr) -> np.ndarray:
    """(f, cx, cy) of an Intrinsics, mm."""
    return np.array([intr.f_mm, intr.cx_mm, intr.cy_mm])


def _gap(a, b) -> float:
    """Distance between two (f, cx, cy) in the valley's terms: C in mm plus f in 1 % steps of 0.1 mm."""
    return float(np.hypot(np.hypot(a[1] - b[1], a[2] - b[2]), 10.0 * (a[0] - b[0]) / abs(b[0])))


def _same_basin(start, probe, solution) -> bool:
    """Whether a probe heads into a solution's valley: within 0.05 mm of it, or half-way there."""
    g = _gap(probe, solution)
    return g < 0.05 or g < 0.5 * _gap(start, solution)


def _refine_starts(pfirst, first, cands, g0, solver):
    """Refine every start; ``[(label, RefineResult, ok)]``.

    The first start is refined to convergence. Each further start first runs
    :data:`PROBE_ITERATIONS` iterations: when it is then in the valley of a
    solution already found (:func:`_same_basin`) it can only end there and
    stops; otherwise it is refined to convergence from where it is. So the
    usual case (every start in one valley) costs a few iterations per start,
    and a start in another valley gets its full refinement.
    """
    tried = []
    probe = _probe_solver(solver)
    seen = []  # (start (f, C), solution (f, C)) of the converged refinements
    for label, i0, d0, rv, tv in cands:
        if first.aspect and i0.fy_mm is None:
            i0 = replace(i0, fy_mm=i0.f_mm)
        if not (first.aspect or first.skew):
            i0 = replace(i0, fy_mm=None, skew=0.0)
        d0 = _restrict(d0, first)
        x0 = _fc(i0)
        if any(_gap(x0, a) < 0.02 for a, _ in seen):
            continue  # the same start as one already refined
        try:
            if seen:
                r = refine(pfirst, i0, d0, g0, rv, tv, probe)
                if r.converged or any(_same_basin(x0, _fc(r.intrinsics), b) for _, b in seen):
                    tried.append((label, r, False))  # a probe: never chosen over the converged solution of its valley
                    continue
                i0, d0, g0r, rv, tv = r.intrinsics, Distortion.from_array(r.coeffs), r.gains, r.rvecs, r.tvecs
            else:
                g0r = g0
            r = refine(pfirst, i0, d0, g0r, rv, tv, solver)
        except (np.linalg.LinAlgError, FloatingPointError, ValueError):  # a start that breaks the solver is not a candidate
            continue
        ok = bool(r.converged and np.isfinite(r.cost_rms) and r.intrinsics.f_mm > 0 and (r.tvecs[:, 2] > 0).all())
        tried.append((label, r, ok))
        if ok:
            seen.append((x0, _fc(r.intrinsics)))
    # A probe or an unconverged refinement below the best converged cost is in a lower valley (a converged
    # solution is a local minimum: points of its own valley cost more): refine it on, from where it stopped.
    for _ in range(2):
        best = min((t[1].cost_rms for t in tried if t[2]), default=np.inf)
        lower = [t for t in tried if not t[2] and np.isfinite(t[1].cost_rms) and t[1].cost_rms < best * (1 - 1e-6)]
        if not lower:
            break
        label, r0, _ = min(lower, key=lambda t: t[1].cost_rms)
        try:
            r = refine(pfirst, r0.intrinsics, Distortion.from_array(r0.coeffs), r0.gains, r0.rvecs, r0.tvecs,
                       replace(solver, max_iterations=2 * solver.max_iterations))
        except (np.linalg.LinAlgError, FloatingPointError, ValueError):
            break
        ok = bool(r.converged and np.isfinite(r.cost_rms) and r.intrinsics.f_mm > 0 and (r.tvecs[:, 2] > 0).all())
        tried = [t for t in tried if t[1] is not r0] + [(label + "+", r, ok)]
        if not ok and not r.cost_rms < r0.cost_rms:
            break
    return tried


#: Focal lengths (mm) tried when neither the closed form nor any single view gives one.
F_GRID_MM = (4.0, 8.0, 16.0, 32.0, 64.0)


def focal_from_homographies(Hs, c_mm=(0.0, 0.0)) -> np.ndarray:
    """Focal length (n,) of each view with the optical centre known, mm (NaN where the view does not fix it).

    With ``C`` known, ``H' = T(-C) H`` is ``diag(f, f, 1) [r1 r2 t]`` up to
    scale, and the orthonormality of ``r1, r2`` (Zhang's Eq 22 with the
    principal point fixed) gives two estimates of ``f^2`` per view::

        f^2 = -(h11 h12 + h21 h22) / (h31 h32)
        f^2 = -(h11^2 + h21^2 - h12^2 - h22^2) / (h31^2 - h32^2)

    combined by least squares in ``1/f^2``. A view parallel to the sensor
    (``h31 = h32 = 0``) does not fix ``f``; neither does a solution with
    ``f^2 <= 0`` (noise, distortion): both give NaN, never an error.
    """
    Hs = np.asarray(Hs, dtype=float).reshape(-1, 3, 3)
    from psdcal import _jit

    if _jit.use_compiled(Hs.shape[0]):  # one compiled call; the numpy lines below are its reference
        from psdcal.calibration._homography import linear_kernels

        return linear_kernels().focal_from_homographies_kernel(np.ascontiguousarray(Hs), float(c_mm[0]), float(c_mm[1]))
    Tc = np.array([[1.0, 0.0, -c_mm[0]], [0.0, 1.0, -c_mm[1]], [0.0, 0.0, 1.0]])
    G = Tc @ Hs
    G = G / np.linalg.norm(G[:, :, :2], axis=(1, 2))[:, None, None]
    h1, h2 = G[:, :, 0], G[:, :, 1]
    a = np.stack([h1[:, 0] * h2[:, 0] + h1[:, 1] * h2[:, 1],
                  h1[:, 0] ** 2 + h1[:, 1] ** 2 - h2[:, 0] ** 2 - h2[:, 1] ** 2], axis=1)
    b = np.stack([h1[:, 2] * h2[:, 2], h1[:, 2] ** 2 - h2[:, 2] ** 2], axis=1)
    den = np.sum(a * a, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(den > 0, -np.sum(a * b, axis=1) / np.where(den > 0, den, 1.0), np.nan)  # 1/f^2: a w + b = 0
        return np.where(np.isfinite(w) & (w > 0), 1.0 / np.sqrt(np.where(w > 0, w, 1.0)), np.nan)


def _restrict(dist: Distortion, spec: ModelSpec) -> Distortion:
    """``dist`` with the terms that ``spec`` does not estimate set to zero."""
    free = set(spec.distortion_names)
    return Distortion(**{n: v for n, v in dist.to_dict().items() if n in free})


def template_hint(T, X, Hs, point_ids=None) -> str:
    """A message naming template LEDs that no view's homography fits ("" when none stands out).

    Each view's residuals from its homography (lens distortion makes them
    smooth in the image, different from view to view) are divided by that
    view's median; an LED whose median over the views is far above the other
    LEDs' is off in every view: a wrong template coordinate, or a permutation
    of the LED order (two LEDs swapped, a row listed in reverse). When
    swapping the two worst LEDs makes the homographies fit, say so.
    """
    from psdcal.calibration._homography import apply_homography

    T = np.asarray(T, dtype=float)
    ids = list(range(len(T))) if point_ids is None else list(point_ids)

    def per_led(Tm):
        Hm = homographies(Tm, X, normalize=True)
        res = np.stack([np.hypot(*(apply_homography(H, Tm) - x).T) for H, x in zip(Hm, X)])  # (n_images, M)
        res = res / np.maximum(np.nanmedian(res, axis=1, keepdims=True), 1e-300)
        return np.nanmedian(res, axis=0), float(np.nansum(res ** 2))

    try:
        led, total = per_led(T)
    except (DegenerateViewsError, np.linalg.LinAlgError):
        return ""
    order = [int(k) for k in np.argsort(-led)[:8]]

    def misfit(Tm):
        Hm = homographies(Tm, X, normalize=True)
        return sum(float(np.nansum(np.sum((apply_homography(H, Tm) - x) ** 2, axis=-1))) for H, x in zip(Hm, X))

    try:
        base = misfit(T)
        # a row listed in reverse: each line of >= 3 template points reversed
        best_row = (base, None)
        for line in find_lines(T, max_lines=MAX_STRAIGHTNESS_LINES):
            idx = np.asarray(line, dtype=int)
            T2 = T.copy()
            T2[idx] = T[idx[::-1]]
            m2 = misfit(T2)
            if m2 < best_row[0]:
                best_row = (m2, idx)
        # swapped LEDs: up to three swaps among the least consistent LEDs, the best one each time
        cur, swaps, best = T.copy(), [], base
        for _ in range(3):
            step = (best, None)
            for i in range(len(order)):
                for j in range(i + 1, len(order)):
                    T2 = cur.copy()
                    T2[[order[i], order[j]]] = T2[[order[j], order[i]]]
                    m2 = misfit(T2)
                    if m2 < step[0]:
                        step = (m2, (order[i], order[j]))
            if step[1] is None or step[0] > 0.5 * best:
                break
            a, b = step[1]
            cur[[a, b]] = cur[[b, a]]
            swaps.append(step[1])
            best = step[0]
            if best < base / 1e3:
                break
    except (DegenerateViewsError, np.linalg.LinAlgError):
        best, swaps, best_row = np.inf, [], (np.inf, None)
        base = np.inf
    if best_row[1] is not None and best_row[0] < base / 10 and best_row[0] <= best:
        row = ", ".join(str(ids[k]) for k in best_row[1])
        return (f"a template permutation fits: the row of LEDs {row} looks listed in reverse (check the LED order "
                "in the template), not the views")
    if swaps and best < base / 10:
        pairs = " and ".join(f"LEDs {ids[a]} and {ids[b]}" for a, b in swaps)
        return (f"a template permutation fits: {pairs} look swapped (check the LED order in the "
                "template: swapped LEDs or a row listed in reverse), not the views")
    if led[order[0]] > 4.0 * np.median(led):
        a, b = order[0], order[1]
        return (f"template LEDs {ids[a]} and {ids[b]} are off the projective fit in every view: check the template "
                "(LED order: swapped LEDs or a row listed in reverse; coordinates), not the views")
    return ""


def linear_starts(T, X, *, preliminary=True, normalize=True, radial=2, skew=False, aspect=False, general=False,
                  f_guess_mm=None, image_ids=None, point_ids=None, dlt_points=None):
    """Starts of the refinement from the linear stages, the first that fail being replaced by ones that cannot.

    Returns ``(primary, starts)``: ``primary`` is the :class:`InitialEstimate`
    recorded in the result's stages (the closed form when it works, else the
    first fallback); ``starts`` is a list of ``(label, Intrinsics,
    Distortion, rvecs, tvecs_mm)``:

    - ``closed-form``: Zhang's closed form after the line-straightness step
      (the general one, sqrt(fx fy) and C at the electrical centre, with
      ``general`` for raw readouts through unequal gains);
    - ``closed-form-raw``: the same without the preliminary step, when the
      closed form after that step fails (without lines in the template the
      step does nothing and the closed form is this one); when both work the
      raw one is the worse start of the same method (distorted points bias
      its f by several %) and is not tried;
    - ``centre``: C at the electrical centre and the median of the focal
      lengths each homography gives with that C (:func:`focal_from_homographies`):
      the closed form's C is unreliable on distorted points without lines
      (irregular templates), where it lands in another valley of the cost;
    - ``f-guess``: C at the electrical centre and ``f_guess_mm``;
    - ``f-grid``: C at the electrical centre and each of :data:`F_GRID_MM`,
      only when nothing above gave a start.

    ``dlt_points``: the spread subset of ``X`` (:func:`subsample_views`) the
    homographies are fitted to (:func:`initial_estimate`); default every point.

    Raises DegenerateViewsError only when the views are degenerate in fact:
    collinear template points (no homography) or no view tilted enough to
    fix a focal length, and no ``f_guess_mm``.
    """
    T = np.asarray(T, dtype=float)
    X = np.asarray(X, dtype=float)
    ids = list(range(X.shape[0])) if image_ids is None else list(image_ids)
    starts = []
    primary = None
    closed_error = None
    labels = [f"image {i}" for i in ids]
    try:
        est = initial_estimate(T, X, preliminary=preliminary, normalize=normalize, radial_terms=radial,
                               skew=skew or general, aspect=aspect or general, image_ids=ids, dlt_points=dlt_points)
    except DegenerateViewsError as exc:
        closed_error, est = exc, None
    Xd = X if dlt_points is None else np.asarray(dlt_points, dtype=float)
    ppv = None if dlt_points is None else SUBSAMPLE_POINTS
    # the views' homographies (after the preliminary step when it applied: the better start); raises on collinear
    # points, views that are degenerate in fact
    Hs_raw = est.homographies if est is not None else homographies(T, Xd, normalize=normalize, labels=labels)
    raw_too = False
    if est is None and preliminary and radial > 0:
        raw_too = True  # the closed form failed after the preliminary step: try it on the raw points
    for est_i, label in ((est, "closed-form"), (None if not raw_too else "raw", "closed-form-raw")):
        if est_i is None:
            continue
        if est_i == "raw":
            try:
                intr = intrinsics_from_homographies(Hs_raw, skew=skew or general, aspect=aspect or general)
            except DegenerateViewsError as exc:
                closed_error = exc
                continue
            est_i = InitialEstimate(np.zeros(2), 0, Hs_raw, intr, *poses_from_homographies(Hs_raw, intr),
                                    points_per_view=ppv)
        elif est_i.n_lines == 0:
            label = "closed-form-raw"
        if general:
            i_s = Intrinsics(f_mm=float(np.sqrt(est_i.intrinsics.f_mm * est_i.intrinsics.fy)))
            est_i = replace(est_i, intrinsics=i_s, rvecs=poses_from_homographies(est_i.homographies, i_s)[0],
                            tvecs_mm=poses_from_homographies(est_i.homographies, i_s)[1])
        if primary is None:
            primary = est_i
        starts.append((label, est_i.intrinsics, est_i.distortion(radial), est_i.rvecs, est_i.tvecs_mm))
    fs = focal_from_homographies(Hs_raw)
    fs = fs[np.isfinite(fs)]
    extent = _extent(X)
    fs = fs[fs < 1e3 * extent]
    zero = est.distortion(radial) if est is not None else Distortion()  # the preliminary k with its homographies
    fallback = []
    if fs.size:
        fs = np.sort(fs)  # their median (np.median's arithmetic, without its overhead on a few numbers)
        h = fs.size // 2
        fallback.append(("centre", float(fs[h]) if fs.size % 2 else float((fs[h - 1] + fs[h]) / 2.0)))
    if f_guess_mm is not None:
        fallback.append(("f-guess", float(f_guess_mm)))
    if not starts and not fallback:
        if closed_error is not None and fs.size == 0:
            hint = template_hint(T, X, Hs_raw, point_ids)
            if hint:
                raise DegenerateViewsError(f"no camera fits these views: {hint}")
            raise DegenerateViewsError(
                f"the views do not determine the intrinsics ({closed_error}; no single view fixes a focal length): "
                "tilt the template differently between views, or give a nominal focal length with --f-guess"
            )
        fallback += [("f-grid", f) for f in F_GRID_MM]
    for label, f in fallback:
        i0 = Intrinsics(f_mm=f)
        rv, tv = poses_from_homographies(Hs_raw, i0)
        starts.append((label, i0, zero, rv, tv))
        if primary is None:
            primary = InitialEstimate(np.zeros(2), 0, Hs_raw, i0, rv, tv, points_per_view=ppv)
    return primary, starts


def implausible(result: CalibrationResult) -> str:
    """Why a refined solution cannot be a real sensor ("" when it can).

    A focal length that is not positive and finite, or a template view that is
    not in front of the sensor (t_z <= 0), means the solver stopped in a
    meaningless stationary point, whatever its convergence test said.
    """
    intr = result.intrinsics
    dist = result.distortion
    values = (intr.f_mm, intr.fy, intr.cx_mm, intr.cy_mm, intr.skew, *(getattr(dist, n) for n in DISTORTION_NAMES))
    if not all(math.isfinite(v) for v in values):
        return "non-finite parameters"
    if not (intr.f_mm > 0 and intr.fy > 0):
        return f"focal length {intr.f_mm:.3g} mm"
    if (result.problem or {}).get("kind") == "directions":  # the one pose is the stage's rotation and offsets
        return ""
    tz = np.asarray(result.tvecs_mm, dtype=float)[:, 2]
    if not all(math.isfinite(v) and v > 0 for v in tz.tolist()):  # (a few views: plain floats beat the ufuncs)
        i = int(np.argmin(np.nan_to_num(tz, nan=-np.inf)))
        return f"image {result.image_ids[i]} behind the sensor (t_z = {tz[i]:.3g} mm)"
    return ""


#: Offsets (in units of the sensor's size) of the optical-centre starts tried
#: when PSD terms are estimated (see :func:`_psd_multistart`).
PSD_CENTRE_STARTS = ((0.0, 0.0), (1, 1), (1, -1), (-1, 1), (-1, -1))
PSD_CENTRE_STEP = 1.0 / 12.0


def _psd_multistart(T, X, spec, sensor_mm, start, intr0, dist0, g0, rv0, tv0, solver):
    """Best image-cost fit over several starts of the optical centre (PSD terms free).

    With the PSD's own radial terms free, the cost has long valleys: to first
    order the data fix only k1 + l1, the decentring term k1 C and the
    principal point, and from the linear stage's centre (1-2 mm off for a
    long lens) the refinement can settle where k1 and l1 trade against C.
    Refining also from C at the electrical centre and at four points around
    it (+-Lx/12, +-Ly/12; poses from the homographies for each start) and
    keeping the lowest cost reached the truth on all of 60 simulated Lens 1
    and Lens 2 sets with the paper's l1, where the single start failed on
    most. Costs five more refinements, for this model only.
    """
    pimg = Problem(T, X, spec, cost="image", sensor_mm=tuple(sensor_mm))
    cands = [refine(pimg, intr0, dist0, g0, rv0, tv0, solver)]
    lin = start.distortion(spec.radial)
    for ox, oy in PSD_CENTRE_STARTS:
        i0 = replace(intr0, cx_mm=ox * PSD_CENTRE_STEP * sensor_mm[0], cy_mm=oy * PSD_CENTRE_STEP * sensor_mm[1])
        cands.append(refine(pimg, i0, lin, g0, *poses_from_homographies(start.homographies, i0), solver))
    ok = [c for c in cands if c.converged and np.isfinite(c.cost_rms)]
    return min(ok, key=lambda c: c.cost_rms) if ok else None


@functools.lru_cache(maxsize=16)
def _probe_solver(solver: SolverOptions) -> SolverOptions:
    """``solver`` limited to :data:`PROBE_ITERATIONS` iterations (a probe of a further start)."""
    return replace(solver, max_iterations=min(PROBE_ITERATIONS, solver.max_iterations))


@functools.lru_cache(maxsize=16)
def _stage_solver(solver: SolverOptions) -> SolverOptions:
    """Tolerances of a start stage: its solution only seeds the final refinement, which
    converges to the same optimum, so it stops at a relative cost change of 1e-7
    (the parameters are then within ~1e-3 standard errors of its optimum)."""
    return replace(solver, ftol=max(solver.ftol, 1e-7), xtol=max(solver.xtol, 1e-8))


@functools.lru_cache(maxsize=32)
def staged_start(spec: ModelSpec) -> ModelSpec | None:
    """The core model refined first when ``spec`` has terms beyond it (None otherwise); cached per spec (a
    frozen dataclass: the answer is the same object for equal specs)."""
    core = ModelSpec(radial=min(spec.radial, 2), tangential=False, psd_radial=0, skew=False, aspect=False, fit_gains=False)
    extra = spec.psd_radial > 0 or spec.skew or spec.aspect or spec.fit_gains or spec.radial > 2
    return core if extra else None


def _model_spec(radial, tangential, psd_radial, skew, aspect, fit_gains) -> ModelSpec:
    """``ModelSpec(...)`` of :func:`calibrate`'s switches, the same (validated) object for the same switches
    (the type of each switch is part of the key: ``radial=True`` is refused, never taken for ``radial=1``)."""
    try:
        return _model_spec_cached(radial, tangential, psd_radial, skew, aspect, fit_gains)
    except TypeError:  # an unhashable switch: ModelSpec says what is wrong with it
        return ModelSpec(radial=radial, tangential=tangential, psd_radial=psd_radial, skew=skew, aspect=aspect,
                         fit_gains=fit_gains)


@functools.lru_cache(maxsize=64, typed=True)
def _model_spec_cached(radial, tangential, psd_radial, skew, aspect, fit_gains) -> ModelSpec:
    return ModelSpec(radial=radial, tangential=tangential, psd_radial=psd_radial, skew=skew, aspect=aspect,
                     fit_gains=fit_gains)


def _compiled_fit(points_mm) -> bool:
    """Whether the fit of ``points_mm`` runs on the compiled kernels (psdcal._jit.use_compiled)."""
    from psdcal import _jit

    n = _n_points(points_mm)
    return _jit.use_compiled(int(n) if math.isfinite(n) else 0)


def _n_points(points_mm) -> float:
    """n_images x M of a points array (inf when it has no such shape: the checks report that)."""
    try:
        shape = np.shape(points_mm)
    except ValueError:  # ragged
        return math.inf
    return shape[0] * shape[1] if len(shape) >= 2 else math.inf
