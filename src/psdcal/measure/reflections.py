"""A sensor whose ray disagrees with the others: a reflection, found and left out (docs/guide/positioning.md#reflections).

An infrared emitter seen off a wall or a shiny floor is the commonest real
fault of optical positioning.  A sensor that sees the reflection as well as
the emitter (a PSD gives the power-weighted centroid of all the light on it)
or only the reflection (a ghost) reports a ray that misses the emitter, while
the other sensors agree.  With ``k`` sensors the rays of one emitter at one
time carry ``2 k - 3`` degrees of freedom of redundancy; this module uses
them.

:func:`screen_rays`, for every (time step, emitter) of a batch:

1. triangulates with every ray (:func:`psdcal.measure.positioning.triangulate`);
2. ``k >= 3``: triangulates again without each sensor ``j`` in turn; the drop
   ``D_j = chi2_all - chi2_without_j`` is, for consistent Gaussian rays,
   chi-squared with 2 degrees of freedom (the outlier test of one 2-vector
   observation).  A sensor is *suspect* when ``D_j`` exceeds the upper
   ``alpha / k`` point of chi^2(2) (Bonferroni over the ``k`` sensors: the
   false-alarm rate of a whole row is at most ``alpha``) and the rays left
   are consistent (their chi2 below the upper ``alpha`` point of
   chi^2(2 (k - 1) - 3)).  Exactly one suspect: it is left out (flag
   ``left_out``) and the position is the triangulation without it.  Several
   suspects (the bias lies where the geometry cannot tell which sensor is
   wrong): flag ``ambiguous``, every ray kept.  The largest drop is above the
   threshold but no single removal makes the rest consistent: flag
   ``unresolved`` (more than one ray disagrees), every ray kept;
3. ``k == 2``: one disagreeing pair (chi2 above the upper ``alpha`` point of
   chi^2(1)) cannot say which ray is the reflection: flag ``ambiguous``,
   both kept, nothing chosen.

Flags are ``""`` (nothing found), ``left_out``, ``ambiguous``,
``unresolved``.  The default ``alpha`` is :data:`psdcal._consistency.ALPHA`
(0.1 % of rows flagged on correct data at most).
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from psdcal._consistency import ALPHA
from psdcal._stats import chi2_isf
from psdcal.measure.positioning import (
    Triangulation,
    apply_extra_variance,
    extra_ray_variance,
    pooled_check,
    triangulate,
)

#: Flags of :class:`RayScreen` (``""``: nothing found).
FLAGS = ("", "left_out", "ambiguous", "unresolved")


@dataclass(frozen=True)
class RayScreen:
    """The rays of a batch screened for one disagreeing sensor.

    Attributes
    ----------
    tri : Triangulation
        The positions: without the left-out sensor where one was left out,
        with every ray elsewhere.
    left_out : (...) int ndarray
        Index of the sensor left out, -1 where none.
    flag : (...) object ndarray of str
        One of :data:`FLAGS`.
    chi2_all : (...) ndarray
        chi2 of the triangulation with every ray.
    drop : (...) ndarray
        The largest chi2 drop ``D_j`` over the sensors where it was computed
        (rows of three sensors or more whose ``chi2_all`` exceeds the drop
        threshold; a drop never exceeds ``chi2_all``), NaN elsewhere.
    alpha : float
        Design false-alarm rate of a row's flag on consistent rays.
    """

    tri: Triangulation
    left_out: np.ndarray
    flag: np.ndarray
    chi2_all: np.ndarray
    drop: np.ndarray
    alpha: float


def _isf_table(alpha: float, k_max: int):
    """Thresholds indexed by the number of valid sensors m: drop (chi2(2), alpha/m), rest (chi2(2m-5), alpha), pair."""
    drop = np.full(k_max + 1, np.inf)
    rest = np.full(k_max + 1, np.inf)
    for m in range(3, k_max + 1):
        drop[m] = chi2_isf(alpha / m, 2)
        rest[m] = chi2_isf(alpha, 2 * (m - 1) - 3)
    return drop, rest, chi2_isf(alpha, 1)


def screen_rays(n, cov_n, R, t_mm, tri: Triangulation | None = None, *, alpha: float = ALPHA,
                **kw) -> RayScreen:
    """Triangulate, and find and leave out one sensor whose ray disagrees with the others.

    Parameters
    ----------
    n, cov_n, R, t_mm, **kw
        As :func:`psdcal.measure.positioning.triangulate`: rays ``(k, ..., 2)``
        (NaN where a sensor does not see the emitter), covariances
        ``(k, ..., 2, 2)``, poses ``(k, 3, 3)`` and ``(k, 3)`` mm, and its
        keyword arguments (``cov_pose``, ``calib``, ``inflate``).  With
        ``inflate`` (the default, as ``triangulate``) the batch's pooled rule
        is applied to the rays kept; give ``inflate=False`` to pool several
        batches afterwards (``locate --sensors``).
    tri : Triangulation, optional
        The triangulation with every ray when already computed (with
        ``inflate=False``).
    alpha : float
        Design false-alarm rate per row (Bonferroni-split over the sensors).

    Returns
    -------
    RayScreen
    """
    n = np.asarray(n, dtype=float)
    cov_n = np.asarray(cov_n, dtype=float)
    k = n.shape[0]
    inflate = bool(kw.pop("inflate", True))
    kw.pop("alpha", None)
    if tri is None:
        tri = triangulate(n, cov_n, R, t_mm, inflate=False, alpha=alpha, **kw)
    valid = np.all(np.isfinite(n), axis=-1) & np.all(np.isfinite(cov_n), axis=(-1, -2))  # (k, ...)
    m = valid.sum(0)
    batch = m.shape
    thr_drop, thr_rest, thr_pair = _isf_table(alpha, max(k, 3))
    chi2_all = np.asarray(tri.chi2, dtype=float)
    flag = np.full(batch, "", dtype=object)
    left = np.full(batch, -1, dtype=int)
    best = np.full(batch, np.nan)
    with np.errstate(invalid="ignore"):
        flag[(m == 2) & (chi2_all > thr_pair)] = "ambiguous"
    md = np.minimum(m, len(thr_drop) - 1)
    with np.errstate(invalid="ignore"):
        # a drop never exceeds chi2_all: only rows whose chi2_all passes the drop threshold are refitted
        many = (m >= 3) & (chi2_all > thr_drop[md])
    if k >= 3 and np.any(many):
        sub = many  # the refitted rows, flattened: (k, S, ...)
        ns_, cov_ = n[:, sub], cov_n[:, sub]
        kw_ = dict(kw)
        if kw_.get("calib") is not None:
            D, Sc, Ap = kw_["calib"]
            kw_["calib"] = (np.asarray(D)[:, sub], Sc, Ap)
        v_, md_, c_all = valid[:, sub], md[sub], chi2_all[sub]
        S = int(sub.sum())
        tris, drops = [], np.full((k, S), -np.inf)
        suspect = np.zeros((k, S), dtype=bool)
        for j in range(k):
            if not np.any(v_[j]):
                tris.append(None)
                continue
            nj = ns_.copy()
            nj[j] = np.nan
            tj = triangulate(nj, cov_, R, t_mm, inflate=False, alpha=alpha, **kw_)
            tris.append(tj)
            with np.errstate(invalid="ignore"):
                d = np.where(v_[j], c_all - tj.chi2, -np.inf)
                drops[j] = d
                suspect[j] = v_[j] & (d > thr_drop[md_]) & (tj.chi2 <= thr_rest[md_])
        dmax = drops.max(0)
        best[sub] = dmax
        trig = dmax > thr_drop[md_]
        ns = suspect.sum(0)
        one = trig & (ns == 1)
        f_ = np.full(S, "", dtype=object)
        f_[trig & (ns >= 2)] = "ambiguous"
        f_[trig & (ns == 0)] = "unresolved"
        f_[one] = "left_out"
        l_ = np.where(one, np.argmax(suspect, axis=0), -1)
        flag[sub] = f_
        left[sub] = l_
        tri = _merge(tri, tris, sub, l_)
    if inflate and tri.cov_p_stated_mm2 is not None:  # the batch's pooled rule, on the rays kept
        tri = replace(tri, cov_p_mm2=tri.cov_p_stated_mm2)
        dof = int(np.sum(tri.dof))
        check = pooled_check(float(np.nansum(tri.chi2)), dof, int(np.sum(tri.n_sensors >= 2)), alpha)
        tri = apply_extra_variance(tri, check, extra_ray_variance(tri, dof) if check.passed is False else 0.0)
    return RayScreen(tri=tri, left_out=left, flag=flag, chi2_all=chi2_all, drop=best, alpha=float(alpha))


def noise_scale(chi2, dof) -> float:
    """A robust factor on the stated ray covariances from rows' ``chi2`` and ``dof`` (>= 1).

    The median over the rows of ``chi2_i / m(dof_i)``, ``m(d)`` the median of
    chi^2(d): about 1 when the stated noise is right, the variance factor when
    every ray is noisier than stated by the same factor, and (a median) little
    moved by a minority of rows with a reflection.
    """
    from scipy.stats import chi2 as chi2_dist

    chi2 = np.asarray(chi2, dtype=float)
    dof = np.asarray(dof, dtype=float)
    use = np.isfinite(chi2) & (dof > 0)
    if not np.any(use):
        return 1.0
    return max(1.0, float(np.median(chi2[use] / chi2_dist.median(dof[use]))))


def screen_with_noise_scale(n, cov_n, R, t_mm, scale: float, *, alpha: float = ALPHA, **kw):
    """Screen again when the rays are noisier than stated: decide with ``scale * cov_n``, fit with ``cov_n``.

    When a file's rows are noisier than their stated covariances (its pooled
    test fails), a first screening measured the drops against too small a
    noise and left sensors out for noise alone.  This screens again with every
    ray's covariance multiplied by ``scale`` (:func:`noise_scale`, robust to a
    minority of reflections), so that the false-alarm rate is the stated one
    again, and returns the triangulation of the rays kept with the *stated*
    covariances and ``inflate=False``, for the caller's pooled rule.

    Returns
    -------
    screen : RayScreen
        The decisions (``left_out``, ``flag``) made with the scaled noise.
    tri : Triangulation
        The rays kept, stated covariances, not inflated.
    """
    kw.pop("inflate", None)
    cov_n = np.asarray(cov_n, dtype=float)
    n = np.array(n, dtype=float, copy=True)
    scr = screen_rays(n, cov_n * float(scale), R, t_mm, alpha=alpha, inflate=False, **kw)
    for j in range(n.shape[0]):
        n[j][scr.left_out == j] = np.nan
    return scr, triangulate(n, cov_n, R, t_mm, inflate=False, alpha=alpha, **kw)


#: Fields of :class:`Triangulation` whose leading axis is the sensor (the others lead with the batch).
_PER_SENSOR = ("residual_n", "ray_cov_n")


def _merge(tri: Triangulation, refits, sub, left) -> Triangulation:
    """``tri`` with the rows ``sub`` (a batch mask) whose ``left`` (index into the refitted rows) is ``j``
    taken from ``refits[j]`` (fitted on those rows only), field by field."""
    out = {}
    for f in fields(tri):
        v = getattr(tri, f.name)
        if not isinstance(v, np.ndarray):
            continue
        v = np.array(v, copy=True)
        per_sensor = f.name in _PER_SENSOR
        part = v[:, sub] if per_sensor else v[sub]
        for j, tj in enumerate(refits):
            sel = left == j
            w = None if tj is None else getattr(tj, f.name)
            if w is None or not np.any(sel):
                continue
            if per_sensor:
                part[:, sel] = w[:, sel]
            else:
                part[sel] = w[sel]
        if per_sensor:
            v[:, sub] = part
        else:
            v[sub] = part
        out[f.name] = v
    return replace(tri, **out)


def left_out_names(screen: RayScreen, names) -> np.ndarray:
    """The name of the sensor left out in each row ("" where none), object array of the batch's shape."""
    lut = np.array(list(names) + [""], dtype=object)
    return lut[np.where(screen.left_out >= 0, screen.left_out, len(lut) - 1)]


def reflection_warnings(left_names, flags, alpha: float = ALPHA) -> list[str]:
    """The warning lines of a screened batch: one per sensor left out, one for ambiguous and unresolved rows.

    Parameters
    ----------
    left_names : (M,) array of str
        :func:`left_out_names` of the rows written.
    flags : (M,) array of str
        :attr:`RayScreen.flag` of the same rows.
    """
    left_names = np.asarray(left_names, dtype=object)
    flags = np.asarray(flags, dtype=object)
    total = len(flags)
    out = []
    rate = f"{100 * alpha:g} %"
    for name in sorted({str(x) for x in left_names.tolist() if x}):
        c = int((left_names == name).sum())
        out.append(f"sensor {name} left out of {c} of {total} rows: its ray disagrees with the other sensors beyond "
                   f"the {rate} false-alarm rate while they agree (a reflection off a wall or the floor, or "
                   "that sensor's pose is off); column 'left_out'")
    amb = int((flags == "ambiguous").sum())
    if amb:
        out.append(f"{amb} of {total} rows have rays that disagree beyond the {rate} false-alarm rate but the "
                   "geometry cannot tell which sensor is wrong (with two sensors a reflection cannot be told from "
                   "the truth): every ray kept, nothing chosen; column 'reflection' = ambiguous")
    unr = int((flags == "unresolved").sum())
    if unr:
        out.append(f"{unr} of {total} rows have rays that disagree beyond the {rate} false-alarm rate and leaving "
                   "out any one sensor does not make the rest agree (more than one bad ray): every ray kept; "
                   "column 'reflection' = unresolved")
    return out


__all__ = ["FLAGS", "RayScreen", "left_out_names", "reflection_warnings", "noise_scale", "screen_rays", "screen_with_noise_scale"]
