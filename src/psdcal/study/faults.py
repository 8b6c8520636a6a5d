"""Synthetic calibration sets with and without planted faults (issue "never silently wrong").

Used by the verdict's false-alarm / detection study (``benchmarks/study_verdict.py``)
and by the tests: irregular 14-LED templates (points scattered in a
200 x 180 mm plate, not on rows, so the line-straightness step finds no
line), the paper's two lenses, random views, Gaussian noise, and the faults
a user actually meets: raw amplitudes through unequal channel gains fitted
without ``--fit-gains``, two template LEDs swapped, one view mislabelled,
points written in metres, a model without k2 on Lens 2.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from psdcal.study.simulate import LENSES, SimulatedSet, simulate_set

#: Kinds of planted fault :func:`faulty_set` can make.
FAULTS = ("none", "gains", "swap", "mislabel", "metres", "no_k2")


def irregular_template(rng, n_points: int = 14, size_mm=(200.0, 180.0), min_spacing_mm: float = 25.0) -> np.ndarray:
    """(n_points, 2) LED positions drawn uniformly in a ``size_mm`` plate, mm, at least ``min_spacing_mm`` apart.

    No three points are (numerically) collinear, so the line-straightness
    step has no line to use: the case where the closed form meets distorted
    points with no preliminary correction.
    """
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    half = np.asarray(size_mm, dtype=float) / 2
    pts: list = []
    while len(pts) < n_points:
        p = rng.uniform(-half, half)
        if all(np.hypot(*(p - q)) >= min_spacing_mm for q in pts):
            pts.append(p)
    return np.array(pts)


@dataclass(frozen=True)
class Case:
    """One synthetic calibration case.

    Attributes
    ----------
    set : SimulatedSet, the clean geometry and its truth.
    points_mm : (n_images, M, 2) what the user hands to ``calibrate`` (fault included).
    template_mm : (M, 2) the template the user hands in (fault included).
    fault : one of :data:`FAULTS`.
    model : dict of ``calibrate`` keyword arguments (radial, tangential, ...).
    bad_image : index of the mislabelled view (or None).
    noise_mm : standard deviation of the noise per coordinate, mm.
    """

    set: SimulatedSet
    points_mm: np.ndarray
    template_mm: np.ndarray
    fault: str
    model: dict
    bad_image: int | None = None
    noise_mm: float = 0.0
    amplitudes: np.ndarray | None = None  # (n_images, M, 4) raw amplitudes, V (fault "gains")

    def write(self, directory) -> tuple:
        """Write ``template.csv`` and ``points.csv`` (amplitudes when the case has them) into ``directory``; their paths."""
        from pathlib import Path

        from psdcal.io import write_amplitudes, write_points, write_template

        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        ids = list(range(len(self.template_mm)))
        write_template(d / "template.csv", ids, self.template_mm)
        imgs = list(range(self.points_mm.shape[0]))
        if self.amplitudes is not None:
            write_amplitudes(d / "points.csv", imgs, ids, self.amplitudes)
        else:
            write_points(d / "points.csv", imgs, ids, self.points_mm)
        return d / "template.csv", d / "points.csv"


def random_case(seed: int, *, fault: str = "none", lens: str | None = None, n_images: int | None = None,
                noise_mm: float | None = None, model: dict | None = None) -> Case:
    """A random case (irregular template, lens, 6-15 views, 0.2-10 um noise), with ``fault`` planted.

    Everything not given is drawn from ``seed``. ``model`` defaults to the
    true model of the lens (radial 1 for Lens 1, 2 for Lens 2, no tangential);
    for ``fault="no_k2"`` the lens is Lens 2 and the model has radial 1.
    """
    if fault not in FAULTS:
        raise ValueError(f"fault must be one of {FAULTS}")
    rng = np.random.default_rng(seed)
    if fault == "no_k2":
        lens = "lens2"
    lens = lens or ("lens1", "lens2")[int(rng.integers(2))]
    n_images = n_images or int(rng.integers(6, 16))
    if noise_mm is None:
        noise_mm = float(np.exp(rng.uniform(np.log(0.2e-3), np.log(10e-3))))
    T = irregular_template(rng)
    s = simulate_set(lens, n_images=n_images, noise_mm=noise_mm, seed=rng, template_mm=T, max_tilt_deg=30.0)
    if model is None:
        model = {"radial": 1 if lens == "lens1" else 2, "tangential": False}
    model = dict(model)
    X = s.points_mm.copy()
    Tu = T.copy()
    bad = None
    amps = None
    if fault == "gains":
        from psdcal.study.gain_sim import simulate_amplitudes
        from psdcal.model.readout import impact_point

        snr = float(rng.uniform(40.0, 60.0))
        amps, _, _ = simulate_amplitudes(s.ideal_points_mm, snr_db=snr, r_tol=0.01, c_tol=0.15, seed=rng)
        X = impact_point(amps)
        noise_mm = float(np.nanstd(impact_point(simulate_amplitudes(s.ideal_points_mm, snr_db=snr, seed=1)[0]) - s.ideal_points_mm))
    elif fault == "swap":
        i, j = rng.choice(len(T), 2, replace=False)
        Tu[[i, j]] = Tu[[j, i]]
    elif fault == "mislabel":
        # two LEDs merged by the demodulator: one label lost, the following ones shifted by one
        bad = int(rng.integers(n_images))
        k = int(rng.integers(len(T) - 4))
        X[bad, k:-1] = X[bad, k + 1:].copy()
        X[bad, -1] = np.nan
    elif fault == "metres":
        X = X / 1000.0
        Tu = Tu / 1000.0  # a consistently metric user: both files in metres
    elif fault == "no_k2":
        model["radial"] = 1
    return Case(s, X, Tu, fault, model, bad, float(noise_mm), amps)


def true_start_cost(case: Case, result) -> float:
    """Image-cost RMS reached by refining ``result``'s model from the truth (the global minimum's cost).

    A fit whose cost exceeds this (beyond round-off) stopped in a local minimum.
    """
    from psdcal.calibration._refine import Problem, SolverOptions, refine

    s = case.set
    prob = Problem(np.asarray(case.template_mm, float), np.asarray(case.points_mm, float), result.model,
                   cost="image", sensor_mm=tuple(result.sensor_mm))
    from psdcal.model.params import Distortion

    free = set(result.model.distortion_names)
    dist0 = Distortion(**{n: v for n, v in s.distortion.to_dict().items() if n in free})
    intr0 = s.intrinsics
    if result.model.aspect:
        intr0 = replace(intr0, fy_mm=intr0.f_mm)
    ref = refine(prob, intr0, dist0, np.ones(4), s.rvecs, s.tvecs_mm, SolverOptions())
    return float(ref.cost_rms) if ref.converged else float("inf")


def lens_truth(lens: str):
    """(Intrinsics, Distortion) of a lens preset."""
    return LENSES[lens]


def single_start_fit(case: Case):
    """The fit the pre-multistart ``calibrate`` made: one refinement from the closed form (a forced start).

    On irregular templates with Lens 1 it stops in a wrong minimum about one
    time in three; :func:`wrong_minimum` keeps those.
    """
    from psdcal.calibration._refine import Problem, SolverOptions, refine
    from psdcal.calibration.core import _make_result, initial_estimate, linear_starts  # noqa: F401
    from psdcal.model.params import ModelSpec

    m = case.model
    spec = ModelSpec(radial=m.get("radial", 2), tangential=m.get("tangential", True))
    T, X = np.asarray(case.template_mm, float), np.asarray(case.points_mm, float)
    st = initial_estimate(T, X, radial_terms=spec.radial)
    prob = Problem(T, X, spec, cost="image")
    ref = refine(prob, st.intrinsics, st.distortion(spec.radial), np.ones(4), st.rvecs, st.tvecs_mm, SolverOptions())
    ids = tuple(range(X.shape[0]))
    return _make_result(prob, ref, st, ids, tuple(range(T.shape[0])), spec, "image", np.ones(4), True, True, SolverOptions())


def wrong_minimum(seed: int, *, min_ratio: float = 1.001, max_tries: int = 200):
    """(case, result): a Lens 1 case whose single-start fit stopped in a wrong minimum (cost above the global one).

    Cases are drawn from seeds ``seed * max_tries + k``; the first whose
    single-start cost exceeds ``min_ratio`` times the cost refined from the
    truth is returned.
    """
    for k in range(max_tries):
        case = random_case(seed * max_tries + k, lens="lens1", model={"radial": 1 + k % 2, "tangential": False})
        try:
            res = single_start_fit(case)
        except Exception:  # noqa: BLE001 -- a start that fails is not the fault studied here
            continue
        if not res.converged:
            continue
        best = true_start_cost(case, res)
        if res.cost_rms > min_ratio * best:
            return case, res
    raise RuntimeError("no wrong minimum found")


#: Faults planted on a real data set by :func:`plant_fault`.
REAL_FAULTS = ("swap", "reversed", "metres", "fix_f")


def mirror_partner(template_mm) -> np.ndarray | None:
    """Index of each template point's mirror image across the template's vertical centre line (None when the
    template has no such symmetry)."""
    T = np.asarray(template_mm, dtype=float)
    xm = T[:, 0].min() + T[:, 0].max()
    M = np.stack([xm - T[:, 0], T[:, 1]], axis=1)
    d = np.linalg.norm(M[:, None, :] - T[None, :, :], axis=-1)
    j = np.argmin(d, axis=1)
    tol = 1e-6 * max(float(np.ptp(T)), 1.0)
    return j if np.all(d[np.arange(len(T)), j] <= tol) else None


def plant_fault(template_mm, points_mm, fault: str, *, f_mm: float | None = None, view: int = 0):
    """A real set with one planted fault: ``(template_mm, points_mm, calibrate kwargs, what)``.

    ``swap``: two neighbouring LEDs near the template's middle swap labels in
    every view (their template rows exchanged); ``reversed``: one view's labels
    mirrored left-right (each point labelled as its mirror partner: a row
    listed in reverse; reversing the whole order of a symmetric grid is a
    180 deg turn of the board, a valid view); ``metres``: the points in metres
    (divided by 1000); ``fix_f``: f fixed 5 % above ``f_mm`` (the clean fit's).
    """
    T = np.array(template_mm, dtype=float)
    X = np.array(points_mm, dtype=float)
    if fault == "swap":
        c = T.mean(axis=0)
        a = int(np.argmin(np.linalg.norm(T - c, axis=1)))
        d = np.linalg.norm(T - T[a], axis=1)
        d[a] = np.inf
        b = int(np.argmin(d))
        T[[a, b]] = T[[b, a]]
        return T, X, {}, f"template LEDs {a} and {b} swapped"
    if fault == "reversed":
        j = mirror_partner(T)
        if j is None:
            raise ValueError("the template has no left-right mirror symmetry")
        X[view] = X[view][j]
        return T, X, {}, f"view {view}'s labels mirrored"
    if fault == "metres":
        return T, X / 1000.0, {}, "points in metres"
    if fault == "fix_f":
        if f_mm is None:
            raise ValueError("fix_f needs the clean fit's f_mm")
        return T, X, {"fix": {"f_mm": 1.05 * float(f_mm)}}, f"f fixed at {1.05 * f_mm:.4g} mm (5 % off)"
    raise ValueError(f"unknown fault {fault!r} (one of {', '.join(REAL_FAULTS)})")
