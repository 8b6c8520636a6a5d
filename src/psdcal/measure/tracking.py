"""Tracking located emitters over time: a constant-velocity Kalman filter per emitter.

State of one emitter ``x = (p, v)`` (``d`` positions, or angles, and their
rates); between two of its measurements ``dt`` apart (emitters are updated
asynchronously: each at its own times, as with time multiplexing)

    x' = F x + w,   F = [[I, dt I], [0, I]],
    Q = q [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]]

(white acceleration of spectral density ``q``, units^2 / s^3), and a
measurement ``z = p + e`` with the covariance ``R`` that ``locate`` computes.
The update is the Kalman filter's (Joseph form for the covariance).

Gating: a measurement whose normalised innovation squared
``NIS = y^T S^-1 y`` exceeds the ``gate_p`` quantile of ``chi2(d)`` is not used
(the row says ``gated``); after ``max_gated`` such measurements in a row the
track restarts from the measurement (the emitter really moved).

Note: ``locate``'s sigma combines the signal noise with the calibration
covariance; the calibration part is the same error window after window and
does not average out, so a filter fed with it reports a covariance that
keeps that floor only approximately.  For consistent filtering of the noise,
give the noise sigma alone (``sigma_x_mm`` propagated), or accept a slightly
optimistic covariance at long times.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from psdcal.errors import InputError


@dataclass(frozen=True)
class TrackConfig:
    """Settings of the constant-velocity filter.

    Attributes
    ----------
    q : float
        Spectral density of the white acceleration, units^2 / s^3 (mm^2/s^3 for
        positions; deg^2/s^3 for angles).
    gate_p : float
        Probability of the chi2 gate (0.999: 0.1 % of good measurements gated).
    max_gated : int
        Consecutive gated measurements after which the track restarts.
    init_sigma_v : float
        1-sigma of the velocity at a track's start, units / s.
    """

    q: float = 1e6
    gate_p: float = 0.999
    max_gated: int = 5
    init_sigma_v: float = 2000.0

    def __post_init__(self):
        if not (self.q > 0 and math.isfinite(self.q)):
            raise InputError(f"the process noise q must be positive, got {self.q}", field="q")
        if not (0 < self.gate_p < 1):
            raise InputError(f"gate_p must be in (0, 1), got {self.gate_p}", field="gate_p")
        if self.max_gated < 1:
            raise InputError(f"max_gated must be at least 1, got {self.max_gated}", field="max_gated")


@dataclass(frozen=True)
class TrackResult:
    """Filtered states, one per measurement (in the input order).

    Attributes
    ----------
    t_s : (N,) ndarray
    emitter : (N,) object ndarray
    p : (N, d) ndarray
        Filtered position (or angle).
    v : (N, d) ndarray
        Filtered velocity, units / s.
    cov : (N, 2d, 2d) ndarray
        Covariance of ``(p, v)``.
    nis : (N,) ndarray
        Normalised innovation squared (NaN at a track's start).
    gated : (N,) bool ndarray
        The measurement was not used.
    restarted : (N,) bool ndarray
        A track (re)started at this measurement.
    """

    t_s: np.ndarray
    emitter: np.ndarray
    p: np.ndarray
    v: np.ndarray
    cov: np.ndarray
    nis: np.ndarray
    gated: np.ndarray
    restarted: np.ndarray

    @property
    def sigma_p(self) -> np.ndarray:
        d = self.p.shape[1]
        return np.sqrt(np.clip(np.diagonal(self.cov, axis1=-2, axis2=-1)[:, :d], 0, None))

    @property
    def sigma_v(self) -> np.ndarray:
        d = self.p.shape[1]
        return np.sqrt(np.clip(np.diagonal(self.cov, axis1=-2, axis2=-1)[:, d:], 0, None))


def cv_matrices(dt: float, d: int, q: float):
    """``F`` and ``Q`` (2d, 2d) of the constant-velocity model over ``dt`` seconds."""
    I = np.eye(d)
    F = np.block([[I, dt * I], [np.zeros((d, d)), I]])
    Q = q * np.block([[dt**3 / 3 * I, dt**2 / 2 * I], [dt**2 / 2 * I, dt * I]])
    return F, Q


def track(t_s, emitter, z, R, config: TrackConfig = TrackConfig()) -> TrackResult:
    """Filter measurements of several emitters (each its own constant-velocity track).

    Parameters
    ----------
    t_s : (N,) array_like
        Times, s (non-decreasing per emitter).
    emitter : (N,) sequence
        Emitter names (a track per name).
    z : (N, d) array_like
        Measured positions (or angles).
    R : (N, d, d) array_like
        Their covariances.
    config : TrackConfig

    Returns
    -------
    TrackResult
    """
    from scipy.stats import chi2

    t = np.asarray(t_s, dtype=float)
    z = np.asarray(z, dtype=float)
    R = np.asarray(R, dtype=float)
    em = np.asarray(emitter, dtype=object)
    N = len(t)
    if z.ndim != 2 or R.shape != (N, z.shape[1], z.shape[1]) or len(em) != N or z.shape[0] != N:
        raise InputError(f"shapes t {t.shape}, z {z.shape}, R {R.shape} do not match")
    d = z.shape[1]
    H = np.hstack([np.eye(d), np.zeros((d, d))])
    gate = float(chi2.ppf(config.gate_p, d))
    P_out = np.full((N, d), np.nan)
    V_out = np.full((N, d), np.nan)
    C_out = np.full((N, 2 * d, 2 * d), np.nan)
    nis = np.full(N, np.nan)
    gated = np.zeros(N, dtype=bool)
    restarted = np.zeros(N, dtype=bool)
    state: dict = {}
    I2 = np.eye(2 * d)
    for i in range(N):
        name = em[i]
        zi, Ri = z[i], R[i]
        if not (np.all(np.isfinite(zi)) and np.all(np.isfinite(Ri))):
            gated[i] = True
            continue
        st = state.get(name)
        if st is not None and t[i] < st[0]:
            raise InputError(f"time goes back for emitter {name!r} at t = {t[i]:.9g} s", field="t_s")
        if st is None:
            x = np.concatenate([zi, np.zeros(d)])
            P = np.zeros((2 * d, 2 * d))
            P[:d, :d] = Ri
            P[d:, d:] = config.init_sigma_v**2 * np.eye(d)
            state[name] = [t[i], x, P, 0]
            restarted[i] = True
        else:
            t0, x, P, n_gated = st
            F, Q = cv_matrices(t[i] - t0, d, config.q)
            x = F @ x
            P = F @ P @ F.T + Q
            y = zi - x[:d]
            S = P[:d, :d] + Ri
            Sinv = np.linalg.inv(S)
            nis[i] = float(y @ Sinv @ y)
            if nis[i] > gate:
                gated[i] = True
                n_gated += 1
                if n_gated >= config.max_gated:  # lost: restart on this measurement
                    x = np.concatenate([zi, np.zeros(d)])
                    P = np.zeros((2 * d, 2 * d))
                    P[:d, :d] = Ri
                    P[d:, d:] = config.init_sigma_v**2 * np.eye(d)
                    n_gated = 0
                    restarted[i] = True
            else:
                K = P @ H.T @ Sinv
                x = x + K @ y
                A = I2 - K @ H
                P = A @ P @ A.T + K @ Ri @ K.T  # Joseph form
                n_gated = 0
            state[name] = [t[i], x, 0.5 * (P + P.T), n_gated]
        _, x, P, _ = state[name]
        P_out[i], V_out[i], C_out[i] = x[:d], x[d:], P
    return TrackResult(t, em, P_out, V_out, C_out, nis, gated, restarted)


# --------------------------------------------------------------------------- CSV
_KINDS = (
    (("X_mm", "Y_mm", "Z_mm"), ("sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm"), "mm"),
    (("X_mm", "Y_mm"), ("sigma_X_mm", "sigma_Y_mm"), "mm"),
    (("alpha_x_deg", "alpha_y_deg"), ("sigma_alpha_x_deg", "sigma_alpha_y_deg"), "deg"),
)


def track_csv(in_path, out_path, *, q: float | None = None, gate_p: float = 0.999, max_gated: int = 5) -> dict:
    """Track the rows of a ``locate`` output CSV; write the filtered states.

    The tracked columns are ``X_mm,Y_mm,Z_mm`` (several sensors), else
    ``X_mm,Y_mm`` (a plane), else ``alpha_x_deg,alpha_y_deg``; the measurement
    covariance is diagonal from their ``sigma_`` columns.  Output columns::

        t_s,emitter,<cols>,<v cols>,<sigma cols>,<sigma v cols>,nis,gated

    with ``v`` columns named ``v<col>_s`` (e.g. ``vX_mm_s``).

    Parameters
    ----------
    q : float, optional
        Process noise (default 1e6 mm^2/s^3, or 10 deg^2/s^3 for angles).

    Returns
    -------
    dict with ``n_rows``, ``n_gated``, ``columns``, ``mean_nis``.
    """
    from pathlib import Path

    from psdcal._atomic import atomic_path

    path = Path(in_path)
    from psdcal.io import csv_rows

    rows = csv_rows(path, "locate output")
    if not rows:
        raise InputError("empty file", path=path)
    header = [h.strip() for h in rows[0]]
    for cols, sig, unit in _KINDS:
        if all(c in header for c in cols + sig):
            break
    else:
        raise InputError("no X_mm,Y_mm[,Z_mm] or alpha_x_deg,alpha_y_deg columns with their sigma_ columns",
                         path=path, line=1)
    for c in ("t_s", "emitter"):
        if c not in header:
            raise InputError(f"missing column '{c}'", path=path, line=1, field=c)
    body = [(k + 2, r) for k, r in enumerate(rows[1:]) if r and any(x.strip() for x in r)]

    def col(name):
        j = header.index(name)
        out = np.empty(len(body))
        for i, (lineno, r) in enumerate(body):
            try:
                out[i] = float(r[j])
            except (ValueError, IndexError):
                raise InputError(f"not a number: {r[j] if j < len(r) else ''!r}", path=path, line=lineno,
                                 field=name) from None
        return out

    t = col("t_s")
    em = np.array([r[header.index("emitter")] for _, r in body], dtype=object)
    z = np.stack([col(c) for c in cols], -1)
    s = np.stack([col(c) for c in sig], -1)
    Rm = np.einsum("ni,ij->nij", s**2, np.eye(len(cols)))
    if q is None:
        q = 1e6 if unit == "mm" else 10.0
    res = track(t, em, z, Rm, TrackConfig(q=q, gate_p=gate_p, max_gated=max_gated,
                                          init_sigma_v=2000.0 if unit == "mm" else 100.0))
    vcols = [f"v{c}_s" for c in cols]
    scols = [f"sigma_{c}" for c in cols]
    svcols = [f"sigma_v{c}_s" for c in cols]
    out_cols = ["t_s", "emitter", *cols, *vcols, *scols, *svcols, "nis", "gated"]
    sp, sv = res.sigma_p, res.sigma_v
    with atomic_path(out_path, suffix=".csv") as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as out:
            out.write(",".join(out_cols) + "\n")
            for i in range(len(t)):
                vals = [*res.p[i], *res.v[i], *sp[i], *sv[i]]
                nis = "" if not np.isfinite(res.nis[i]) else f"{res.nis[i]:.6g}"
                out.write(f"{t[i]:.10g},{em[i]}," + ",".join(f"{v:.10g}" for v in vals)
                          + f",{nis},{int(res.gated[i])}\n")
    fin = np.isfinite(res.nis) & ~res.gated
    return {"n_rows": len(t), "n_gated": int(res.gated.sum()), "columns": tuple(out_cols),
            "mean_nis": float(np.mean(res.nis[fin])) if fin.any() else math.nan, "dims": len(cols)}
