#!/usr/bin/env python3
"""Statistical efficiency of the two calibration costs against the Cramér-Rao bound.

For each of the paper's lenses (docs/model.md#paper-simulation-setup) one pose set is fixed
(``simulate_set(lens, n_images, seed=...)``); every Monte Carlo trial adds
fresh Gaussian noise of ``sigma`` mm per coordinate to its noiseless impact
points and calibrates with the ``image`` cost and with the ``template`` cost
(model: one focal length, no skew, k1, k2, no tangential terms).

The Cramér-Rao bound of the global parameters is the top-left block of
``sigma^2 (J^T J)^-1``, ``J`` the Jacobian of the sensor-plane residuals
(``image`` cost) with respect to all parameters (poses included) at the
truth. The ``template`` cost is not the likelihood of the measurements: to
first order its estimate moves by ``-(J_T^T J_T)^-1 J_T^T D n`` for a noise
``n`` on the impact points, ``J_T`` its own Jacobian and ``D`` the derivative
of its residuals with respect to the measured points, so its predicted
covariance is the "sandwich" ``sigma^2 G G^T`` with
``G = (J_T^T J_T)^-1 J_T^T D``. Both predictions are printed beside the Monte
Carlo spread.

Columns of the table:

- ``MC std / sqrt(CRB)``: efficiency loss (1 = efficient), with the
  standard error ``1/sqrt(2N)`` of a sample standard deviation;
- ``MC std / efficient, paired``: the same with a control variate: the
  Monte Carlo std divided by the sample std of the first-order efficient
  estimates ``theta + (J^T J)^-1 J^T n`` of the *same* noise draws ``n``
  (whose exact covariance is the bound), which cancels most of the sampling
  error (about 1 % here);
- ``predicted``: ``sqrt(linearised variance) / sqrt(CRB)`` (1 for ``image``);
- ``reported / MC``: mean of the standard errors the calibration reports,
  divided by the Monte Carlo standard deviation;
- ``bias / s.e.``: ``(mean - truth) / (MC std / sqrt(N))``.

Usage::

    .venv/bin/python benchmarks/efficiency.py [--trials 400] [--images 12] [--noise-mm 0.002] [--jobs 2] [--markdown]
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path
import time

import numpy as np
sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/_table.py, also when imported by the tests
from _table import print_table  # noqa: E402

import psdcal
from psdcal.calibration._refine import Evaluator, Problem
from psdcal.calibration.core import calibrate
from psdcal.model.params import ModelSpec
from psdcal.study.simulate import simulate_set

PARAMS = ("f_mm", "cx_mm", "cy_mm", "k1")
COSTS = ("image", "template")
SPEC = ModelSpec(radial=2, tangential=False)


def _truth_state(sset, prob: Problem) -> np.ndarray:
    """The true state vector of ``prob`` (global parameters, then all poses)."""
    return prob.pack(sset.intrinsics, sset.distortion, np.ones(4), sset.rvecs, sset.tvecs_mm)


def _evaluator(sset, points_mm, cost: str):
    prob = Problem(sset.template_mm, np.asarray(points_mm, dtype=float), SPEC, cost=cost)
    return prob, Evaluator(prob, sset.intrinsics, sset.distortion, np.ones(4))


def crb(sset, sigma_mm: float) -> np.ndarray:
    """Cramér-Rao bound (n_global, n_global) of the global parameters at the truth.

    Parameters
    ----------
    sset : SimulatedSet
        Provides the truth and the noiseless impact points.
    sigma_mm : float
        Noise standard deviation per coordinate, mm.
    """
    prob, ev = _evaluator(sset, sset.ideal_points_mm, "image")
    J = ev.jacobian(_truth_state(sset, prob))
    cov = sigma_mm**2 * np.linalg.inv(J.T @ J)
    return cov[: prob.n_global, : prob.n_global]


def linearised_covariance(sset, sigma_mm: float, cost: str, h_mm: float = 1e-6) -> np.ndarray:
    """First-order covariance (n_global, n_global) of the estimate minimising ``cost``.

    ``sigma^2 G G^T`` with ``G = (J^T J)^-1 J^T D``, ``J`` the Jacobian of the
    cost's residuals in the state and ``D`` their derivative with respect to
    the measured points (central differences, step ``h_mm``; a residual of
    a point depends on that point only, so four evaluations give ``D``).
    For the ``image`` cost ``D`` is ``-I`` and this is the Cramér-Rao bound.
    """
    X0 = sset.ideal_points_mm
    prob, ev = _evaluator(sset, X0, cost)
    z = _truth_state(sset, prob)
    J = ev.jacobian(z)
    n_pts = J.shape[0] // 2
    D = np.zeros((n_pts, 2, 2))  # D[i, :, k] = d r_i / d d_i[k]
    for k in range(2):
        step = np.zeros(2)
        step[k] = h_mm
        r_plus = _evaluator(sset, X0 + step, cost)[1].residuals(z)
        r_minus = _evaluator(sset, X0 - step, cost)[1].residuals(z)
        D[:, :, k] = ((r_plus - r_minus) / (2 * h_mm)).reshape(n_pts, 2)
    Dfull = np.zeros((2 * n_pts, 2 * n_pts))
    for i in range(n_pts):
        Dfull[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = D[i]
    G = np.linalg.solve(J.T @ J, J.T @ Dfull)
    cov = sigma_mm**2 * G @ G.T
    return cov[: prob.n_global, : prob.n_global]


def efficient_gain(sset) -> np.ndarray:
    """(n_global, 2 n_points) first-order map from point noise to the efficient estimate.

    A noise ``n`` on the measured points (all valid, in ``points_mm.ravel()``
    order) moves the least-squares solution of the image cost by
    ``(J^T J)^-1 J^T n`` (the residual is model minus measured).
    """
    prob, ev = _evaluator(sset, sset.ideal_points_mm, "image")
    if not prob.valid.all():
        raise ValueError("efficient_gain needs every point of every image")
    J = ev.jacobian(_truth_state(sset, prob))
    return np.linalg.solve(J.T @ J, J.T)[: prob.n_global]


def _calibrate_chunk(args):
    """Worker: calibrate ``template`` with each noisy point set of ``points`` (n, M, 2)."""
    template, points, cost = args
    est = np.empty((len(points), len(PARAMS)))
    std = np.empty((len(points), len(PARAMS)))
    for i, pts in enumerate(points):
        res = calibrate(template, pts, cost=cost, radial=2, tangential=False)
        est[i] = [res.parameter(p) for p in PARAMS]
        std[i] = [res.std[p] for p in PARAMS]
    return est, std


def monte_carlo(sset, sigma_mm: float, n_trials: int, seed: int, costs=COSTS, jobs: int = 1) -> dict:
    """Calibrate ``n_trials`` noisy copies of one pose set with each cost (same draws for all).

    Returns
    -------
    dict cost -> {"est": (n, len(PARAMS)), "std": (n, len(PARAMS)), "seconds": float},
    and "noise" -> (n, M_images, M, 2) the draws.
    """
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, sigma_mm, (n_trials,) + sset.ideal_points_mm.shape)
    out = {"noise": noise}
    for cost in costs:
        t0 = time.perf_counter()
        chunks = np.array_split(sset.ideal_points_mm + noise, max(jobs, 1))
        args = [(sset.template_mm, c, cost) for c in chunks if len(c)]
        if jobs > 1:
            from concurrent.futures import ProcessPoolExecutor

            with ProcessPoolExecutor(max_workers=jobs) as pool:
                parts = list(pool.map(_calibrate_chunk, args))
        else:
            parts = [_calibrate_chunk(a) for a in args]
        out[cost] = {
            "est": np.concatenate([p[0] for p in parts]),
            "std": np.concatenate([p[1] for p in parts]),
            "seconds": time.perf_counter() - t0,
        }
    return out


def table(lens: str, n_images: int, sigma_mm: float, n_trials: int, seed: int, jobs: int = 1) -> list[dict]:
    """Rows of the efficiency table for one lens (one row per cost and parameter)."""
    sset = simulate_set(lens, n_images=n_images, noise_mm=0.0, seed=seed)
    names = Problem(sset.template_mm, sset.ideal_points_mm, SPEC).names
    idx = [names.index(p) for p in PARAMS]
    bound = np.sqrt(np.diag(crb(sset, sigma_mm)))[idx]
    mc = monte_carlo(sset, sigma_mm, n_trials, seed + 1000, jobs=jobs)
    truth = np.array([sset.intrinsics.f_mm, sset.intrinsics.cx_mm, sset.intrinsics.cy_mm, sset.distortion.k1])
    lin = truth + mc["noise"].reshape(n_trials, -1) @ efficient_gain(sset)[idx].T
    lin_std = lin.std(axis=0, ddof=1)
    rows = []
    for cost in COSTS:
        pred = np.sqrt(np.diag(linearised_covariance(sset, sigma_mm, cost)))[idx]
        est, std = mc[cost]["est"], mc[cost]["std"]
        s = est.std(axis=0, ddof=1)
        for j, p in enumerate(PARAMS):
            rows.append(
                {
                    "lens": lens,
                    "cost": cost,
                    "param": p,
                    "sqrt_crb": bound[j],
                    "mc_std": s[j],
                    "ratio": s[j] / bound[j],
                    "paired": s[j] / lin_std[j],
                    "predicted": pred[j] / bound[j],
                    "reported": std[:, j].mean() / s[j],
                    "bias_se": (est[:, j].mean() - truth[j]) / (s[j] / np.sqrt(n_trials)),
                    "ms_per_cal": 1e3 * mc[cost]["seconds"] / n_trials,
                }
            )
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=400)
    ap.add_argument("--images", type=int, default=12)
    ap.add_argument("--noise-mm", type=float, default=0.002)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--lenses", nargs="+", default=["lens1", "lens2"])
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    ap.add_argument("--markdown", action="store_true", help="print a Markdown table (for docs/benchmarks.md)")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = []
    for lens in a.lenses:
        rows += table(lens, a.images, a.noise_mm, a.trials, a.seed, a.jobs)
    se = 1 / np.sqrt(2 * a.trials)
    print(
        f"psdcal {psdcal.__version__}, Python {platform.python_version()}, numpy {np.__version__}; "
        f"{a.trials} trials, {a.images} images of 14 points, sigma = {a.noise_mm * 1e3:g} um, "
        f"model f, C, k1, k2; s.e. of MC std / sqrt(CRB) = {se:.3f}"
    )
    head = ("lens", "cost", "param", "sqrt(CRB)", "MC std", "MC std / sqrt(CRB)", "MC std / efficient, paired",
            "predicted", "reported / MC", "bias / s.e.")
    lines = []
    for r in rows:
        lines.append(
            (
                r["lens"],
                r["cost"],
                r["param"],
                f"{r['sqrt_crb']:.3g}",
                f"{r['mc_std']:.3g}",
                f"{r['ratio']:.3f}",
                f"{r['paired']:.3f}",
                f"{r['predicted']:.3f}",
                f"{r['reported']:.3f}",
                f"{r['bias_se']:+.2f}",
            )
        )
    print_table(head, lines, a.markdown)
    ms = {c: np.mean([r["ms_per_cal"] for r in rows if r["cost"] == c]) for c in COSTS}
    print(f"wall time per calibration ({a.jobs} worker(s)): image {ms['image']:.1f} ms, "
          f"template {ms['template']:.1f} ms; total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
