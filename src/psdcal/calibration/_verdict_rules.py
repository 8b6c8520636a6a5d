"""The calibration verdict's plausibility rules: what no correct calibration of a PSD + lens looks like.

No statistics here (false-alarm rate 0 by construction on a plausible
camera): the points' scale (metres given for millimetres), f in a lens'
range, C within a lens mount's tolerance of the electrical centre,
convergence to a camera, a one-to-one distortion over the sensor, how well
the data determine f and C (``determination``), and whether the data
contradict a fixed value or a prior (``held_values``, a z-test: its
false-alarm rate is :data:`psdcal.calibration.verdict.ALPHA`).
"""
from __future__ import annotations

import functools
import math

import numpy as np

from psdcal import _jit
from psdcal._consistency import Check

#: Focal lengths outside this range (mm) are not a PSD lens.
F_RANGE_MM = (1.0, 500.0)
#: Optical centre farther than this fraction of the sensor's half-size from the electrical centre: suspect.
C_FRACTION = 0.5
#: Points spanning less than these fractions of the sensor: suspect / wrong.
SPAN_SUSPECT, SPAN_WRONG = 0.1, 0.01
#: f determined worse than these relative standard errors: suspect / wrong (f undetermined).
F_REL_SUSPECT, F_REL_WRONG = 0.1, 0.3
#: The optical centre determined worse than this fraction of the sensor's half-size: suspect.
C_STD_SUSPECT = 0.25
#: Views whose template normals all lie within this angle (deg) of each other are alike: suspect.
VIEWS_ALIKE_DEG = 3.0


def _length(mm: float) -> str:
    return f"{mm * 1e3:.3g} um" if mm < 0.1 else f"{mm:.3g} mm"


def plausibility(result, lin, sensor, half) -> list:
    """The physical-plausibility checks: points' scale, f, C, convergence, a one-to-one distortion."""
    checks = []
    X = lin.pts
    span = float(np.max(np.ptp(X.T.copy(), axis=1))) if len(X) > 1 else 0.0  # (2, N) rows: fast reduction
    smax = float(np.max(sensor))
    frac = span / smax
    ok = frac >= SPAN_SUSPECT
    checks.append(Check(
        "scale", span, SPAN_SUSPECT * smax, None, 0.0, ok,
        f"the points span {_length(span)} of the {smax:g} mm sensor",
        "" if ok else (f"points span {_length(span)}: are they in metres? The points file is in mm"
                       if frac < SPAN_WRONG else "the views cover a small part of the sensor: bring the template closer"),
        severe=frac < SPAN_WRONG,
    ))
    f = result.intrinsics.f_mm
    ok = F_RANGE_MM[0] <= f <= F_RANGE_MM[1]
    checks.append(Check(
        "focal_length", f, None, None, 0.0, ok,
        f"f = {f:.4g} mm" + ("" if ok else f", outside {F_RANGE_MM[0]:g}-{F_RANGE_MM[1]:g} mm"),
        "" if ok else ("not a lens for a PSD: check the units of the points (mm) and the template" if frac < SPAN_SUSPECT
                       else "the fit collapsed to a focal length no lens has: the views or the template do not fit "
                            "a camera (see the other checks: a mislabelled view, a template permutation)"),
        severe=not ok,
    ))
    intr = result.intrinsics
    cx, cy = float(intr.cx_mm), float(intr.cy_mm)
    hx, hy = float(half[0]), float(half[1])
    rel = _max_nan(abs(cx) / hx, abs(cy) / hy)  # np.max(np.abs(c) / half) on floats
    ok = rel <= C_FRACTION
    checks.append(Check(
        "optical_centre", float(np.hypot(cx, cy)), C_FRACTION * _min_nan(hx, hy), None, 0.0, ok,
        f"C = ({cx:.3g}, {cy:.3g}) mm from the electrical centre",
        "" if ok else "farther from the electrical centre than a lens mount puts it: a wrong minimum or ignored "
                      "channel gains (raw amplitudes: --fit-gains)",
        severe=rel > 1.0,
    ))
    from psdcal.calibration.core import implausible

    why = implausible(result)
    conv = bool(result.converged) and not why
    checks.append(Check(
        "converged", float(result.iterations), None, None, 0.0, conv,
        f"the refinement {'converged' if result.converged else 'did NOT converge'} in {result.iterations} iterations"
        + (f", to a solution that is not a camera ({why})" if why else ""),
        "" if conv else "no minimum was reached: the data do not fit the model (see the other checks: a bad view, "
                        "a template permutation, ignored gains), or allow more iterations (--max-iterations)",
        severe=not conv,
    ))
    mono = _monotonic(result)
    checks.append(Check(
        "distortion_monotonic", None, None, None, 0.0, mono, "the distortion is one-to-one over the sensor" if mono else
        "the distortion folds the sensor (not one-to-one over it)",
        "" if mono else "too many distortion terms for the points' coverage, or a wrong minimum: fewer terms (--radial 1) "
                        "or views reaching the sensor's corners",
        severe=not mono,
    ))

    return checks


def template_side(result) -> Check | None:
    """Whether every view sees the template from the same side (None when no pose is finite).

    The LEDs face the sensor, so the template's normal points away from it
    in every view. A view seen from the other side fits exactly as well: its
    labels are mirrored left-right (a row listed in reverse, the x axis of that
    view's points flipped); the intrinsics do not change, its pose is a mirror
    image. All views from behind: the template's handedness is flipped (x or y
    negated, or X and Y swapped).
    """
    rv = np.asarray(result.rvecs, dtype=float)
    tv = np.asarray(result.tvecs_mm, dtype=float)
    if len(rv) < 1:
        return None
    if rv.shape == tv.shape == (len(rv), 3) and len(rv) <= _FEW_VIEWS:  # a few views: on floats, as below
        if not (np.isfinite(rv).all() and np.isfinite(tv).all()):
            return None
        rl, tl = rv.tolist(), tv.tolist()
        # the einsum's sum n . t in its order; the template is behind when -(n . t) > 0
        behind = [i for i, (r, t) in enumerate(zip(rl, tl)) if _front_dot(_normal(*r), t) < 0.0]
        n_views = len(rl)
    else:
        if not np.all(np.isfinite(rv)) or not np.all(np.isfinite(tv)):
            return None
        side = -np.einsum("ij,ij->i", _normals(rv), tv)
        behind = np.nonzero(side > 0)[0].tolist()
        n_views = len(side)
    ids = ", ".join(str(result.image_ids[i]) for i in behind)
    if len(behind) == 0:
        return Check("template_side", 0.0, None, None, 0.0, True, "every view sees the template from the front")
    if len(behind) == n_views:
        return Check("template_side", float(len(behind)), None, None, 0.0, False,
                     "every view sees the template from behind: the template's handedness is flipped (x or y negated, "
                     "or X and Y swapped); the intrinsics are unaffected, the poses are mirror images",
                     "check the template's axes: X to the right and Y down the LED rows as the sensor sees them",
                     effect_sigma=0.0)
    return Check("template_side", float(len(behind)), None, None, 0.0, False,
                 f"view(s) {ids} see the template from behind while the others see its front: their labels are "
                 "mirrored left-right; the intrinsics are unaffected, their poses are mirror images",
                 f"check the labels of view(s) {ids} (a row listed in reverse?)", effect_sigma=0.0)


_CORNER_SIGNS = np.array([[sx, sy] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)])
_CORNER_SIGN_PAIRS = tuple(tuple(r) for r in _CORNER_SIGNS.tolist())


def _farthest_corner(cx: float, cy: float, hx: float, hy: float) -> float:
    """The distance from C (cx, cy) to the sensor's farthest corner (half-size hx, hy), mm:
    ``np.max(np.hypot(*(_CORNER_SIGNS * half - c).T))`` with the four corners on floats (the same numbers)."""
    return functools.reduce(_max_nan, [float(np.hypot(sx * hx - cx, sy * hy - cy)) for sx, sy in _CORNER_SIGN_PAIRS])


def _max_nan(a: float, b: float) -> float:
    """``np.max`` of two floats: NaN when either is (and the second of two equal ones, as numpy's)."""
    return a if a > b or a != a else b


def _min_nan(a: float, b: float) -> float:
    """``np.min`` of two floats: NaN when either is (and the second of two equal ones, as numpy's)."""
    return a if a < b or a != a else b


@functools.lru_cache(maxsize=8)
def _rays(n_dir: int, n_r: int):
    """(n_dir, 2) unit directions and (n_r,) radii from 0.02 to 1 (read-only: shared by every call)."""
    ang = np.linspace(0, 2 * np.pi, n_dir, endpoint=False)
    dirs = np.stack([np.cos(ang), np.sin(ang)], 1)
    unit = np.linspace(0.02, 1.0, n_r)
    dirs.flags.writeable = unit.flags.writeable = False
    return dirs, unit


def _monotonic(result, n_dir: int = 16, n_r: int = 60) -> bool:
    """Whether the undistorted radius grows along rays from C out to the sensor's farthest corner."""
    from psdcal.model.distortion import undistort

    c = np.asarray(result.intrinsics.c, dtype=float)
    half = np.asarray(result.sensor_mm, dtype=float) / 2
    rmax = _farthest_corner(float(c[0]), float(c[1]), float(half[0]), float(half[1]))
    dirs, unit = _rays(n_dir, n_r)
    rad = unit * rmax
    if _jit.use_compiled(n_dir * n_r):  # the same test in one loop (its tests: the same answer as the code below)
        from psdcal.calibration._rules_kernel import monotonic
        from psdcal.model.distortion import _as_coeffs

        return bool(monotonic(np.ascontiguousarray(_as_coeffs(result.distortion), dtype=float), c, half * 1.0001, rad,
                              dirs))
    d = c + rad[None, :, None] * dirs[:, None, :]
    lim = half * 1.0001
    # the two coordinates written out: numpy's reductions over a last axis of length 2 are slow
    inside = (np.abs(d[..., 0]) <= lim[0]) & (np.abs(d[..., 1]) <= lim[1])
    x = undistort(d, result.distortion, c)
    proj = (x[..., 0] - c[0]) * dirs[:, None, 0] + (x[..., 1] - c[1]) * dirs[:, None, 1]
    step = np.diff(proj, axis=1)
    both = inside[:, 1:] & inside[:, :-1]
    return bool(np.all(np.isfinite(proj[inside])) and np.all(step[both] > 0))



def determination(result, cov, names, half) -> Check:
    """How well the data determine f and the optical centre: a result whose f is known to 51 % is not good.

    ``cov`` (n, n) is the covariance of the free parameters ``names``; f
    determined worse than :data:`F_REL_SUSPECT` (relative standard error) is
    suspect, worse than :data:`F_REL_WRONG` wrong (undetermined); C worse
    than :data:`C_STD_SUSPECT` of the sensor's half-size suspect.
    """
    # np.sqrt(np.maximum(diag, 0)) on floats (np.maximum keeps a NaN)
    sd = {n: math.sqrt(_max_nan(v, 0.0)) for n, v in zip(names, np.diag(np.asarray(cov, float)).tolist())} if len(
        names) else {}
    f = float(result.intrinsics.f_mm)
    parts, worst, severe = [], 0.0, False
    rel_f = sd["f_mm"] / abs(f) if "f_mm" in sd and f else None
    if rel_f is not None:
        parts.append(f"f = {f:.4g} +- {sd['f_mm']:.2g} mm ({100 * rel_f:.2g} %)")
        worst = rel_f / F_REL_SUSPECT
        severe = rel_f > F_REL_WRONG or not math.isfinite(rel_f)
    csd = max(sd.get("cx_mm", 0.0), sd.get("cy_mm", 0.0))
    if "cx_mm" in sd or "cy_mm" in sd:
        parts.append(f"C to +- {_length(csd)}")
        worst = max(worst, csd / (C_STD_SUSPECT * min(float(h) for h in half)))
    spread = _tilt_spread_deg(result)
    alike = spread is not None and spread < VIEWS_ALIKE_DEG
    ok = bool(worst <= 1.0) and not alike
    msg = ("the data determine " + ", ".join(parts)) if parts else "f and C are held (fixed or by priors)"
    if alike:
        msg += (f"; the views are all alike (their template normals within {spread:.2g} deg of each other): f and C "
                "rest on the distortion alone")
    if not ok:
        msg += (f": worse than {100 * F_REL_SUSPECT:g} % in f or {C_STD_SUSPECT:g} of the sensor's half-size in C"
                + ("; f is undetermined" if severe else ""))
    return Check(
        "determination", float(rel_f) if rel_f is not None else None, F_REL_SUSPECT, None, 0.0, ok, msg,
        "" if ok else "the views do not determine the camera: tilt the template by 10-40 deg in different directions "
                      "between views (views parallel to the sensor, or all alike, fix neither f nor C), or hold f with "
                      "--fix / --prior from the lens' data sheet",
        severe=severe,
    )


def _normals(rvecs) -> np.ndarray:
    """(n, 3) the template's normal (its z axis) in the sensor frame of each view: ``R(rvec) e_z`` (Rodrigues)."""
    r = np.asarray(rvecs, dtype=float).reshape(-1, 3)
    if len(r) <= _FEW_VIEWS:  # a few views: the same formula on floats (numpy's per-call cost dominates there)
        return np.array([_normal(*v) for v in r.tolist()], dtype=float).reshape(-1, 3)
    th = np.sqrt(r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1] + r[:, 2] * r[:, 2])
    k = r / np.where(th > 0, th, 1.0)[:, None]
    c, s = np.cos(th), np.sin(th)
    # e_z c + (k x e_z) s + k k_z (1 - c), with k x e_z = (k_y, -k_x, 0) written out
    kx, ky, kz = k[:, 0], k[:, 1], k[:, 2]
    omc = 1.0 - c
    return np.stack([ky * s + kx * kz * omc, -kx * s + ky * kz * omc, c + kz * kz * omc], axis=1)


#: Up to this many views :func:`_normals` evaluates its formula view by view on floats.
_FEW_VIEWS = 32


def _normal(x: float, y: float, z: float) -> tuple[float, float, float]:
    """:func:`_normals` of one rotation vector (x, y, z)."""
    th = math.sqrt(x * x + y * y + z * z)
    if th > 0:
        x, y, z = x / th, y / th, z / th
    c, s = math.cos(th), math.sin(th)
    omc = 1.0 - c
    return y * s + x * z * omc, -x * s + y * z * omc, c + z * z * omc


def _tilt_spread_deg(result) -> float | None:
    """The largest angle (deg) between two views' template normals (None with fewer than two finite poses)."""
    rv = np.asarray(result.rvecs, dtype=float)
    if rv.ndim == 2 and rv.shape[1] == 3 and len(rv) <= _FEW_VIEWS:  # a few views: the normals on floats
        rows = rv.tolist() if np.isfinite(rv).all() else [r for r in rv.tolist() if _all_finite((r,))]
        if len(rows) < 2:
            return None
        n = np.array([_normal(*r) for r in rows], dtype=float)
    else:
        rv = rv[np.all(np.isfinite(rv), axis=1)]
        if len(rv) < 2:
            return None
        n = _normals(rv)
    # the smallest cosine (np.clip's and np.degrees' arithmetic on the one float that matters)
    cmin = min(max(float((n @ n.T).min()), -1.0), 1.0)
    return math.degrees(math.acos(cmin))


def _all_finite(rows) -> bool:
    """Whether every float of the lists ``rows`` is finite."""
    return all(math.isfinite(v) for r in rows for v in r)


def _front_dot(n, t) -> float:
    """``n . t`` of two 3-vectors (floats) summed in the order of ``np.einsum("ij,ij->i")``."""
    return n[0] * t[0] + n[1] * t[1] + n[2] * t[2]


def held_values(result, lin, alpha: float) -> Check | None:
    """Whether the data contradict a fixed value or a prior (None when nothing is held).

    For each held parameter, the linearised data-only estimate (``lin.held``:
    the shift from the fit's value and its standard error) against the held
    value (fixed: exactly; prior: its mean and standard deviation), a z-test,
    Bonferroni over the held parameters.
    """
    held = lin.held or {}
    if not held:
        return None
    opts = result.problem.get("options", {}) if isinstance(result.problem, dict) else {}
    fix = opts.get("fix") or {}
    prior = {}
    for q in opts.get("priors") or []:
        for i, n in enumerate(q.get("names", [])):
            cov = q.get("covariance")
            v = cov[i][i] if cov is not None and cov[i] is not None else None
            prior[n] = (float(q["mean"][i]), math.sqrt(v) if v is not None and v >= 0 else math.inf)
    z = {}
    words = {}
    for n, (shift, sd) in held.items():
        value = result.parameter(n)
        data = value + shift
        if n in fix:
            mean, sp, kind = float(fix[n]), 0.0, "fixed at"
        elif n in prior and math.isfinite(prior[n][1]):
            mean, sp, kind = prior[n][0], prior[n][1], "prior"
        else:
            continue
        tot = math.hypot(sd, sp)
        z[n] = abs(data - mean) / tot if tot > 0 else (0.0 if data == mean else math.inf)
        words[n] = (f"{n} {kind} {mean:.6g}" + (f" +- {sp:.2g}" if sp else "")
                    + f": the data say {data:.6g} +- {sd:.2g} ({z[n]:.3g} sigma)")
    if not z:
        return None
    worst = max(z, key=z.get)
    from psdcal._stats import chi2_sf

    p = float(min(1.0, len(z) * chi2_sf(z[worst] ** 2, 1)))
    ok = p >= alpha
    return Check(
        "held_values", z[worst], None, p, alpha, ok,
        "; ".join(words[n] for n in sorted(z, key=z.get, reverse=True)),
        "" if ok else f"the data contradict the value held for {worst}: free it (drop --fix/--prior) or check the value",
        severe=not ok and z[worst] >= 5.0, dof=1.0, effect_sigma=z[worst],
    )
