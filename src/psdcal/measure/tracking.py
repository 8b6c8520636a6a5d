"""Tracking located emitters over time: a constant-velocity Kalman filter per emitter.

State of one emitter ``x = (p, v)`` (``d`` positions, or angles, and their
rates); between two of its measurements ``dt`` apart (emitters are updated
asynchronously: each at its own times, as with time multiplexing)

    x' = F x + w,   F = [[I, dt I], [0, I]],
    Q = q [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]]

(white acceleration of spectral density ``q``, units^2 / s^3), and a
measurement ``z = p + e`` with the covariance ``R`` that ``locate`` computes.
The update is the Kalman filter's (Joseph form for the covariance).

What a row says (``TrackResult.status``)
----------------------------------------
``start``
    The emitter's first valid measurement: the track starts there (position
    and covariance of the measurement, velocity 0 +- ``init_sigma_v``).
``ok``
    The measurement passed the gate and updated the track.
``gated``
    Its normalised innovation squared ``NIS = y^T S^-1 y`` exceeds the
    ``gate_p`` quantile of ``chi2(d)``: it is not used, and the row holds *no
    position* (NaN state and sigmas): the filter's prediction is a guess, not
    a measurement of where the emitter was.
``gap``
    Re-acquired after a gap: the time since the track's last used measurement
    exceeds ``max_gap_s`` (default: ``gap_intervals`` = 10 times the emitter's
    median interval between measurements).  Over such a time the
    constant-velocity extrapolation is not trusted (a hand-held emitter stops
    or turns while unseen, and a prediction with the old velocity would gate
    every good measurement): the track restarts from this measurement, as at
    ``start``, and is not tested against the prediction (NIS empty).
``jump``
    ``max_gated`` consecutive gated measurements that fit *each other* (they
    form a second constant-velocity track, each inside its gate) replace the
    track: the emitter moved faster than ``q`` allows, or the measurements
    come from a consistent false place (a reflection).  Scattered outliers
    never do this: they stay ``gated``.
``invalid``
    A non-finite measurement or covariance: not used, no position.

``restart`` is True on ``gap`` and ``jump`` rows, and each one gives a
warning.

Checks (``TrackResult.checks``): with the right ``q`` and ``R`` the
innovations of a Kalman filter are independent and the sum of the NIS of the
``n`` used measurements is ``chi2(d n)`` (truncated at the gate: the sum is
rescaled by ``d / E[NIS | NIS < gate]``, 1.005 for d = 3);
:func:`psdcal._consistency.chi2_check` tests it two-sided at the design
false-alarm rate (too large: ``q`` or the sigmas too small; too small: ``q``
or the sigmas too large), and the number of runs of gated measurements is
tested against ``1 - gate_p`` per tested row (binomial; runs, because a valid
measurement gated leaves the track off, and the next ones are likely gated
too).  A failed check is a warning; :func:`estimate_q_factor` gives the factor on ``q`` that makes the
NIS's 99 % point right ("q looks 4x too small").

Note: ``locate``'s sigma combines the signal noise with the calibration
covariance; the calibration part is the same error window after window and
does not average out, so a filter fed with it reports a covariance that
keeps that floor only approximately.  For consistent filtering of the noise,
give the noise sigma alone (``sigma_x_mm`` propagated), or accept a slightly
optimistic covariance at long times.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np

from psdcal._consistency import ALPHA, Check, chi2_check
from psdcal._stats import chi2_isf, chi2_sf
from psdcal.errors import InputError

#: Row statuses (see the module docstring).
STATUSES = ("start", "ok", "gated", "gap", "jump", "invalid")


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
        Consecutive gated measurements, consistent with each other, after which
        the track restarts on them (a ``jump``).
    init_sigma_v : float
        1-sigma of the velocity at a track's start, units / s.
    max_gap_s : float or None
        A longer time without a used measurement is a gap: the track is
        re-acquired from the next measurement.  None: ``gap_intervals`` times
        the emitter's median interval between measurements.
    gap_intervals : float
        See ``max_gap_s``.
    """

    q: float = 1e6
    gate_p: float = 0.999
    max_gated: int = 5
    init_sigma_v: float = 2000.0
    max_gap_s: float | None = None
    gap_intervals: float = 10.0

    def __post_init__(self):
        if not (self.q > 0 and math.isfinite(self.q)):
            raise InputError(f"the process noise q must be positive, got {self.q}", field="q")
        if not (0 < self.gate_p < 1):
            raise InputError(f"gate_p must be in (0, 1), got {self.gate_p}", field="gate_p")
        if self.max_gated < 1:
            raise InputError(f"max_gated must be at least 1, got {self.max_gated}", field="max_gated")
        if not (self.init_sigma_v > 0 and math.isfinite(self.init_sigma_v)):
            raise InputError(f"init_sigma_v must be positive, got {self.init_sigma_v}", field="init_sigma_v")
        if self.max_gap_s is not None and not self.max_gap_s > 0:
            raise InputError(f"max_gap_s must be positive, got {self.max_gap_s}", field="max_gap_s")
        if not self.gap_intervals > 1:
            raise InputError(f"gap_intervals must be above 1, got {self.gap_intervals}", field="gap_intervals")


@dataclass(frozen=True)
class TrackResult:
    """Filtered states, one per measurement (in the input order).

    Attributes
    ----------
    t_s : (N,) ndarray
    emitter : (N,) object ndarray
    p : (N, d) ndarray
        Filtered position (or angle); NaN on ``gated`` and ``invalid`` rows (no
        measurement was used there: the prediction is not written as a position).
    v : (N, d) ndarray
        Filtered velocity, units / s (NaN where ``p`` is).
    cov : (N, 2d, 2d) ndarray
        Covariance of ``(p, v)`` (NaN where ``p`` is).
    nis : (N,) ndarray
        Normalised innovation squared against the track's prediction (NaN at
        ``start`` and ``gap`` rows, which are not tested, and ``invalid`` ones).
    gated : (N,) bool ndarray
        The measurement was not used by the track (``gated`` and ``invalid`` rows).
    restarted : (N,) bool ndarray
        A track (re)started at this measurement (``start``, ``gap``, ``jump``).
    status : (N,) object ndarray
        One of :data:`STATUSES` per row.
    restart : (N,) bool ndarray
        The track was re-acquired here (``gap`` or ``jump``): a warning each.
    restart_distance : (N,) ndarray
        On ``restart`` rows, how far the new position is from the abandoned
        track's prediction, units of ``p``; NaN elsewhere.
    checks : tuple of Check
        The NIS and gating checks (see the module docstring).
    warnings : tuple of str
        One line per restart (the first 10 per emitter, then a count) and per
        failed check.
    max_gap_s : dict
        The gap threshold used per emitter, s.
    """

    t_s: np.ndarray
    emitter: np.ndarray
    p: np.ndarray
    v: np.ndarray
    cov: np.ndarray
    nis: np.ndarray
    gated: np.ndarray
    restarted: np.ndarray
    status: np.ndarray | None = None
    restart: np.ndarray | None = None
    restart_distance: np.ndarray | None = None
    checks: tuple = ()
    warnings: tuple = ()
    max_gap_s: dict | None = None

    @property
    def sigma_p(self) -> np.ndarray:
        d = self.p.shape[1]
        return np.sqrt(np.clip(np.diagonal(self.cov, axis1=-2, axis2=-1)[:, :d], 0, None))

    @property
    def sigma_v(self) -> np.ndarray:
        d = self.p.shape[1]
        return np.sqrt(np.clip(np.diagonal(self.cov, axis1=-2, axis2=-1)[:, d:], 0, None))

    @property
    def used(self) -> np.ndarray:
        """(N,) bool: rows whose state comes from their measurement (not gated, not invalid)."""
        return np.isfinite(self.p).all(axis=1)


def cv_matrices(dt: float, d: int, q: float):
    """``F`` and ``Q`` (2d, 2d) of the constant-velocity model over ``dt`` seconds."""
    I = np.eye(d)
    F = np.block([[I, dt * I], [np.zeros((d, d)), I]])
    Q = q * np.block([[dt**3 / 3 * I, dt**2 / 2 * I], [dt**2 / 2 * I, dt * I]])
    return F, Q


def _gap_thresholds(t, em, ok, config: TrackConfig) -> dict:
    out = {}
    for name in dict.fromkeys(em[ok].tolist()):
        if config.max_gap_s is not None:
            out[name] = float(config.max_gap_s)
            continue
        dts = np.diff(t[ok & (em == name)])
        dts = dts[dts > 0]
        out[name] = float(config.gap_intervals * np.median(dts)) if dts.size else math.inf
    return out


@functools.cache
def _blocks(d: int):
    """Constant (2d, 2d) blocks: ``F = I + dt J``, ``Q = q (dt^3/3 A + dt^2/2 B + dt C)``."""
    Z, I = np.zeros((d, d)), np.eye(d)
    return (np.block([[Z, I], [Z, Z]]), np.block([[I, Z], [Z, Z]]), np.block([[Z, I], [I, Z]]),
            np.block([[Z, Z], [Z, I]]))


class _Track:
    """One constant-velocity track: time of its last used measurement, state, covariance."""

    __slots__ = ("P", "n", "t", "x")

    def __init__(self, t, z, R, sigma_v):
        d = len(z)
        self.t, self.n = t, 1
        self.x = np.concatenate([z, np.zeros(d)])
        self.P = np.zeros((2 * d, 2 * d))
        self.P[:d, :d] = R
        self.P[d:, d:] = sigma_v**2 * np.eye(d)

    def predict(self, t, q):
        """``F x`` and ``F P F^T + Q`` over ``t - self.t`` (:func:`cv_matrices`, from constant blocks)."""
        J, A, B, C = _blocks(len(self.x) // 2)
        dt = t - self.t
        F = np.eye(len(self.x)) + dt * J
        return F @ self.x, F @ self.P @ F.T + (q * dt**3 / 3) * A + (q * dt**2 / 2) * B + (q * dt) * C

    @staticmethod
    def innovation(x, P, z, R):
        d = len(z)
        y = z - x[:d]
        Sinv = np.linalg.inv(P[:d, :d] + R)
        return y, Sinv, float(y @ Sinv @ y)

    def update(self, t, x, P, y, Sinv, R):
        d = len(y)
        K = P[:, :d] @ Sinv
        A = np.eye(2 * d)
        A[:, :d] -= K
        P = A @ P @ A.T + K @ R @ K.T  # Joseph form
        self.t, self.x, self.P, self.n = t, x + K @ y, 0.5 * (P + P.T), self.n + 1


#: The online filter's gap threshold uses the median of at most this many first intervals of an emitter.
ONLINE_INTERVALS = 1001


class Tracker:
    """The filter of :func:`track`, one finite measurement at a time (rows as they come, e.g. live input).

    Parameters
    ----------
    config : TrackConfig
    d : int
        Dimensions of a measurement.
    gaps_s : dict, optional
        Gap threshold (s) of each emitter (:func:`track` passes the whole file's). None: ``max_gap_s``, or
        ``gap_intervals`` times the median of the emitter's intervals seen so far (its first
        :data:`ONLINE_INTERVALS`; infinite before its second measurement): on evenly spaced rows the same
        threshold as the whole file's.
    """

    def __init__(self, config: TrackConfig, d: int, gaps_s: dict | None = None):
        self.config, self.d = config, d
        self.gate = chi2_isf(1.0 - config.gate_p, d)
        self._fixed = gaps_s
        self.tracks: dict = {}
        self.candidates: dict = {}
        self.last_t: dict = {}
        self._dts: dict = {}

    def gap_s(self, name) -> float:
        """The gap threshold of ``name`` now, s."""
        if self._fixed is not None:
            return self._fixed[name]
        if self.config.max_gap_s is not None:
            return float(self.config.max_gap_s)
        dts = self._dts.get(name)
        return float(self.config.gap_intervals * np.median(dts)) if dts else math.inf

    def gaps_s(self) -> dict:
        """Every emitter's gap threshold now (for the warnings)."""
        return {name: self.gap_s(name) for name in self.last_t}

    def step(self, ti: float, name, zi, Ri):
        """One finite measurement ``zi`` (d,) with covariance ``Ri`` (d, d) of emitter ``name`` at ``ti`` s.

        Returns ``(status, nis, dist, track)``: the row's word, its NIS (NaN when not tested), the restart's
        distance (NaN unless ``gap``/``jump``), and the track whose state the row reports (None when gated).
        """
        config, d = self.config, self.d
        nis = dist = math.nan
        prev = self.last_t.get(name)
        if prev is not None and ti < prev:
            raise InputError(f"time goes back for emitter {name!r} at t = {ti:.9g} s", field="t_s")
        gap = self.gap_s(name)
        if self._fixed is None and prev is not None and ti > prev:
            dts = self._dts.setdefault(name, [])
            if len(dts) < ONLINE_INTERVALS:
                dts.append(ti - prev)
        self.last_t[name] = ti
        trk = self.tracks.get(name)
        if trk is None:
            trk = self.tracks[name] = _Track(ti, zi, Ri, config.init_sigma_v)
            status = "start"
        elif ti - trk.t > gap:  # a gap: re-acquire from the measurement
            dist = float(np.linalg.norm(zi - (trk.x[:d] + (ti - trk.t) * trk.x[d:])))
            trk = self.tracks[name] = _Track(ti, zi, Ri, config.init_sigma_v)
            self.candidates.pop(name, None)
            status = "gap"
        else:
            x, P = trk.predict(ti, config.q)
            y, Sinv, nis = _Track.innovation(x, P, zi, Ri)
            if nis <= self.gate:
                trk.update(ti, x, P, y, Sinv, Ri)
                self.candidates.pop(name, None)
                status = "ok"
            else:
                status = "gated"
                cand = self.candidates.get(name)
                if cand is not None and ti - cand.t <= gap:
                    cx, cP = cand.predict(ti, config.q)
                    cy, cSinv, cnis = _Track.innovation(cx, cP, zi, Ri)
                    if cnis <= self.gate:
                        cand.update(ti, cx, cP, cy, cSinv, Ri)
                    else:
                        cand = None
                else:
                    cand = None
                if cand is None:
                    cand = self.candidates[name] = _Track(ti, zi, Ri, config.init_sigma_v)
                if cand.n >= config.max_gated:  # consistent, and not the track: jump to it
                    dist = float(np.linalg.norm(cand.x[:d] - x[:d]))
                    trk = self.tracks[name] = cand
                    del self.candidates[name]
                    status = "jump"
        return status, nis, dist, (None if status == "gated" else trk)


def track(t_s, emitter, z, R, config: TrackConfig = TrackConfig(), *, unit: str = "") -> TrackResult:
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
    unit : str
        Unit of ``z`` ("mm", "deg"), for the warnings.

    Returns
    -------
    TrackResult
        Gated and invalid rows hold NaN states; see the module docstring for
        the statuses, restarts and checks.
    """
    t = np.asarray(t_s, dtype=float)
    z = np.asarray(z, dtype=float)
    R = np.asarray(R, dtype=float)
    em = np.asarray(emitter, dtype=object)
    N = len(t)
    if z.ndim != 2 or R.shape != (N, z.shape[1], z.shape[1]) or len(em) != N or z.shape[0] != N:
        raise InputError(f"shapes t {t.shape}, z {z.shape}, R {R.shape} do not match")
    d = z.shape[1]
    finite = np.isfinite(z).all(1) & np.isfinite(R).all((1, 2)) & np.isfinite(t)
    gaps = _gap_thresholds(t, em, finite, config)
    P_out = np.full((N, d), np.nan)
    V_out = np.full((N, d), np.nan)
    C_out = np.full((N, 2 * d, 2 * d), np.nan)
    nis = np.full(N, np.nan)
    status = np.full(N, "invalid", dtype=object)
    dist = np.full(N, np.nan)
    filt = Tracker(config, d, gaps)
    for i in range(N):
        if not finite[i]:
            continue
        status[i], nis[i], dist[i], trk = filt.step(t[i], em[i], z[i], R[i])
        if trk is not None:
            P_out[i], V_out[i], C_out[i] = trk.x[:d], trk.x[d:], trk.P
    gated = (status == "gated") | (status == "invalid")
    restart = (status == "gap") | (status == "jump")
    restarted = restart | (status == "start")
    checks = nis_checks(nis, status, d, config.gate_p, emitter=em)
    warns = _restart_warnings(t, em, status, dist, gaps, unit) + [c.line() for c in checks if c.passed is False]
    return TrackResult(t, em, P_out, V_out, C_out, nis, gated, restarted, status, restart, dist,
                       tuple(checks), tuple(warns), gaps)


def _restart_warnings(t, em, status, dist, gaps, unit: str = "", per_emitter: int = 10) -> list:
    out = []
    u = f" {unit}" if unit else ""
    for name in dict.fromkeys(em.tolist()):
        idx = np.flatnonzero((em == name) & ((status == "gap") | (status == "jump")))
        for i in idx[:per_emitter]:
            if status[i] == "gap":
                out.append(f"{name}: track re-acquired at t = {t[i]:.6g} s after a gap longer than "
                           f"{gaps[name]:.3g} s (restart=1; {dist[i]:.4g}{u} from where the old velocity would "
                           f"have put it)")
            else:
                out.append(f"{name}: track jumped at t = {t[i]:.6g} s by {dist[i]:.4g}{u} to measurements that "
                           f"fit each other but not the track (restart=1): a reflection, or motion faster than "
                           f"q allows")
        if len(idx) > per_emitter:
            out.append(f"{name}: {len(idx) - per_emitter} more restarts (restart=1 rows)")
    return out


def nis_checks(nis, status, d: int, gate_p: float, alpha: float = ALPHA, emitter=None) -> list:
    """The NIS check (two-sided chi2 of the used rows) and the gating check (binomial).

    Parameters
    ----------
    nis : (N,) ndarray
        NIS per row (NaN where not tested).
    status : (N,) object ndarray
        Row statuses (:data:`STATUSES`).
    d : int
        Tracked coordinates per measurement.
    gate_p : float
        The gate probability used.
    alpha : float
        False-alarm rate of each check (each side of the NIS check: ``alpha / 2``).
    emitter : (N,) object ndarray, optional
        Emitter per row (the runs of gated rows are counted per emitter).

    Returns
    -------
    list of Check
        ``track_nis`` and ``track_gated`` (``passed`` None when nothing was tested).
    """
    used = (status == "ok") & np.isfinite(nis)
    n_used = int(used.sum())
    tested = np.isfinite(nis)
    n_tested, n_gated = int(tested.sum()), int((status == "gated").sum() + (status == "jump").sum())
    advice = ("q (the process noise) or the measurement sigmas are wrong: see the q factor in the summary, "
              "or rerun with --q auto")
    # the used rows passed the gate: their NIS is chi2(d) truncated at the gate, of mean m_t < d;
    # rescaled by d / m_t the sum is compared with chi2(d n) (a slightly conservative test)
    gate = chi2_isf(1.0 - gate_p, d)
    m_t = d * (1.0 - chi2_sf(gate, d + 2)) / (1.0 - chi2_sf(gate, d))
    s = float(np.sum(nis[used])) * d / m_t
    dof = d * n_used
    c = chi2_check(s, dof, name="track_nis", what=f"the innovations of {n_used} used measurements",
                   alpha=alpha / 2, inflate=False, advice=advice)
    if c.passed and 1.0 - chi2_sf(s, dof) < alpha / 2:
        p = 1.0 - chi2_sf(s, dof)
        c = Check("track_nis", s, None, p, alpha, False,
                  f"the innovations of {n_used} used measurements are smaller than the stated noise: "
                  f"NIS {s:.4g} for {dof} dof (p = {p:.2g}), mean {s / n_used:.3g} for {d}: q or the "
                  f"sigmas are too large", advice=advice, dof=float(dof),
                  effect_sigma=math.sqrt(s / dof) - 1.0, inflation=1.0)
    c = replace(c, false_alarm=alpha)
    checks = [c]
    if n_tested:
        from scipy.stats import binom

        # a valid measurement gated leaves the track where it was: the next ones are likely gated too, so
        # the gated rows come in runs; the runs ("episodes": a gated or jump row after a used one) start
        # independently, each tested row with probability 1 - gate_p
        episodes = 0
        for name in dict.fromkeys(emitter.tolist()) if emitter is not None else [None]:
            sel = tested if name is None else tested & (emitter == name)
            g = np.isin(status[sel], ("gated", "jump"))
            episodes += int(g[0]) + int(np.sum(g[1:] & ~g[:-1])) if g.size else 0
        rate = 1.0 - gate_p
        p = float(binom.sf(episodes - 1, n_tested, rate))
        ok = p >= alpha
        msg = (f"{n_gated} of {n_tested} tested measurements gated ({100 * n_gated / n_tested:.3g} %) in "
               f"{episodes} runs, {n_tested * rate:.3g} runs expected (p = {p:.2g})")
        checks.append(Check("track_gated", float(episodes), None, p, alpha, ok, msg,
                            advice="" if ok else "outliers (reflections), or q too small for the motion",
                            dof=float(n_tested)))
    else:
        checks.append(Check("track_gated", 0.0, None, None, alpha, None, "no measurement tested"))
    return checks


def estimate_q_factor(t_s, emitter, z, R, config: TrackConfig = TrackConfig(), *, quantile: float = 0.99,
                      lo: float = 1e-4, hi: float = 1e4, iters: int = 10) -> float:
    """The factor on ``config.q`` for which the NIS's ``quantile`` is chi2(d)'s.

    The statistic is the ``quantile`` (0.99) of the NIS over every tested row
    (gated ones included); the target is the same quantile of ``chi2(d)``.
    A tail quantile, because the tails decide what is gated: real motion is
    rarely white-noise acceleration (steady flight, then sharp turns), its
    innovations are heavier-tailed than chi2, and a q that makes the *mean*
    right then gates good measurements in every turn (on the Lighthouse
    flights, 3-5 % of them).  Up to ``1 - quantile`` of outliers do not move
    it.  Found by bisection on ``log(factor)`` in ``[lo, hi]`` (the NIS falls
    as q grows), each step a full filter run.  A result at ``lo`` or ``hi``
    means no q matches (the measurement sigmas are wrong).

    Returns
    -------
    float
        ``f``: "q looks ``f`` x too small" when ``f > 1``, ``1 / f`` x too large when ``f < 1``.
    """
    d = np.asarray(z).shape[1]
    target = chi2_isf(1.0 - quantile, d)

    def stat(f):
        r = track(t_s, emitter, z, R, replace(config, q=config.q * f))
        m = np.isfinite(r.nis)
        return float(np.quantile(r.nis[m], quantile)) if m.any() else math.nan

    a, b = math.log(lo), math.log(hi)
    if not stat(math.exp(a)) > target:
        return lo
    if stat(math.exp(b)) > target:
        return hi
    for _ in range(iters):
        m = 0.5 * (a + b)
        if stat(math.exp(m)) > target:
            a = m
        else:
            b = m
    return math.exp(0.5 * (a + b))


# --------------------------------------------------------------------------- CSV
_KINDS = (
    (("X_mm", "Y_mm", "Z_mm"), ("sigma_X_mm", "sigma_Y_mm", "sigma_Z_mm"), "mm"),
    (("X_mm", "Y_mm"), ("sigma_X_mm", "sigma_Y_mm"), "mm"),
    (("alpha_x_deg", "alpha_y_deg"), ("sigma_alpha_x_deg", "sigma_alpha_y_deg"), "deg"),
)


def _read_located(path):
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

    def col(name, empty_ok):
        j = header.index(name)
        out = np.empty(len(body))
        for i, (lineno, r) in enumerate(body):
            cell = r[j].strip() if j < len(r) else ""
            if empty_ok and cell == "":  # locate leaves a position it could not compute empty
                out[i] = math.nan
                continue
            try:
                out[i] = float(cell)
            except ValueError:
                raise InputError(f"not a number: {cell!r}", path=path, line=lineno, field=name) from None
        return out

    t = col("t_s", False)
    if not np.isfinite(t).all():
        k = int(np.flatnonzero(~np.isfinite(t))[0])
        raise InputError(f"not a finite time: {t[k]}", path=path, line=body[k][0], field="t_s")
    em = np.array([r[header.index("emitter")] for _, r in body], dtype=object)
    z = np.stack([col(c, True) for c in cols], -1)
    s = np.stack([col(c, True) for c in sig], -1)
    return t, em, z, s, cols, unit


#: Rows (the first ones) on which track_csv estimates the q factor.
_Q_ROWS = 20000


def _fmt(v) -> str:
    return f"{v:.10g}" if math.isfinite(v) else ""


def track_csv(in_path, out_path, *, q: float | str | None = None, gate_p: float = 0.999, max_gated: int = 5,
              max_gap_s: float | None = None) -> dict:
    """Track the rows of a ``locate`` output CSV; write the filtered states.

    The tracked columns are ``X_mm,Y_mm,Z_mm`` (several sensors), else
    ``X_mm,Y_mm`` (a plane), else ``alpha_x_deg,alpha_y_deg``; the measurement
    covariance is diagonal from their ``sigma_`` columns.  Output columns::

        t_s,emitter,<cols>,<v cols>,<sigma cols>,<sigma v cols>,nis,gated,restart,status

    with ``v`` columns named ``v<col>_s`` (e.g. ``vX_mm_s``).  On ``gated`` and
    ``invalid`` rows the state columns are empty (no position: the prediction
    is not a measurement); ``restart`` is 1 where the track was re-acquired
    (``gap``) or jumped (``jump``); ``status`` is the row's word (module docstring).

    Parameters
    ----------
    q : float or "auto", optional
        Process noise (default 1e6 mm^2/s^3, or 10 deg^2/s^3 for angles);
        ``"auto"``: the default times :func:`estimate_q_factor` (estimated on
        the first 20000 rows, as the factor given when a check fails).
    gate_p, max_gated, max_gap_s
        See :class:`TrackConfig`.

    Returns
    -------
    dict
        ``n_rows`` (every row), ``n_used``, ``n_gated``, ``n_invalid``,
        ``n_restarts`` (``n_gap`` + ``n_jump``), ``mean_nis`` (over every
        tested row, gated ones included), ``mean_nis_used``, ``n_tested``,
        ``q`` (used), ``q_factor`` (estimated when a check failed or q is
        "auto", else None), ``q_auto``, ``checks`` (list of dicts), ``warnings`` (list of str),
        ``columns``, ``dims``.
    """
    from pathlib import Path

    from psdcal._atomic import atomic_path

    path = Path(in_path)
    t, em, z, s, cols, unit = _read_located(path)
    Rm = np.einsum("ni,ij->nij", s**2, np.eye(len(cols)))
    auto = isinstance(q, str)
    if auto and q.strip().lower() != "auto":
        raise InputError(f"q must be a number or 'auto', got {q!r}", field="q")
    q0 = 1e6 if unit == "mm" else 10.0
    cfg = TrackConfig(q=q0 if (q is None or auto) else float(q), gate_p=gate_p, max_gated=max_gated,
                      init_sigma_v=2000.0 if unit == "mm" else 100.0, max_gap_s=max_gap_s)
    q_factor = None
    k = slice(0, _Q_ROWS)  # the q estimate reruns the filter ~12 times: on the first rows only
    if auto:
        q_factor = estimate_q_factor(t[k], em[k], z[k], Rm[k], cfg)
        cfg = replace(cfg, q=cfg.q * q_factor)
    res = track(t, em, z, Rm, cfg, unit=unit)
    failed = any(c.passed is False for c in res.checks)
    if not auto and failed:
        q_factor = estimate_q_factor(t[k], em[k], z[k], Rm[k], cfg)
    warnings = list(res.warnings) + track_warnings(res.checks, q_factor, cfg, unit, auto)
    out_cols = track_columns(cols)
    sp, sv = res.sigma_p, res.sigma_v
    with atomic_path(out_path, suffix=".csv") as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as out:
            out.write(",".join(out_cols) + "\n")
            for i in range(len(t)):
                out.write(track_line(t[i], em[i], res.p[i], res.v[i], sp[i], sv[i], res.nis[i], res.status[i]))
    return track_info(t, res.status, res.nis, int(res.used.sum()), out_cols, len(cols), cfg, q_factor, auto,
                      res.max_gap_s, res.checks, warnings)


def track_columns(cols) -> list:
    """The tracked file's columns for the measured columns ``cols`` (:func:`track_csv`)."""
    return ["t_s", "emitter", *cols, *[f"v{c}_s" for c in cols], *[f"sigma_{c}" for c in cols],
            *[f"sigma_v{c}_s" for c in cols], "nis", "gated", "restart", "status"]


def track_line(t: float, name, p, v, sigma_p, sigma_v, nis: float, status: str) -> str:
    """One row of the tracked file (:func:`track_columns`), with its newline; NaN states are empty."""
    vals = [*p, *v, *sigma_p, *sigma_v]
    gated = status in ("gated", "invalid")
    restart = status in ("gap", "jump")
    return (f"{t:.10g},{name}," + ",".join(_fmt(x) for x in vals)
            + f",{f'{nis:.6g}' if np.isfinite(nis) else ''},{int(gated)},{int(restart)},{status}\n")


def track_info(t, status, nis, n_used: int, out_cols, dims: int, cfg: TrackConfig, q_factor, auto: bool, gaps,
               checks, warnings) -> dict:
    """:func:`track_csv`'s returned summary from the rows' times, statuses and NIS."""
    st = np.asarray(status, dtype=object)
    nis = np.asarray(nis, dtype=float)
    tested = np.isfinite(nis)
    used = tested & (st == "ok")
    return {"n_rows": len(t), "n_used": n_used, "n_gated": int((st == "gated").sum()),
            "n_invalid": int((st == "invalid").sum()), "n_restarts": int(((st == "gap") | (st == "jump")).sum()),
            "n_gap": int((st == "gap").sum()), "n_jump": int((st == "jump").sum()), "n_tested": int(tested.sum()),
            "columns": tuple(out_cols), "dims": dims,
            "mean_nis": float(np.mean(nis[tested])) if tested.any() else math.nan,
            "mean_nis_used": float(np.mean(nis[used])) if used.any() else math.nan,
            "q": cfg.q, "q_factor": q_factor, "q_auto": auto, "max_gap_s": dict(gaps),
            "checks": [c.to_dict() for c in checks], "warnings": list(warnings)}


def track_warnings(checks, q_factor, cfg: TrackConfig, unit: str, auto: bool) -> list:
    """The advice that follows failed checks (``q_factor``: the factor on q estimated on the first rows, or None)."""
    failed = {c.name: c for c in checks if c.passed is False}
    out = []
    if not auto and failed and q_factor is not None:
        out.append(_q_advice(q_factor, cfg.q, unit))
    if "track_gated" in failed and "smaller than" in getattr(failed.get("track_nis"), "message", ""):
        out.append("the innovations are heavier-tailed than chi2 (mostly smaller than stated, yet more "
                   "gated): the motion is not white-noise acceleration (steady, then sharp turns); no q "
                   "fits both, a larger one gates fewer good measurements")
    elif auto and failed:
        out.append("with --q auto (the NIS's 99 % point matched) a check still fails: the innovations do not "
                   "follow chi2 for any q; the motion is not white-noise acceleration (steady, then sharp "
                   "turns), or the measurement sigmas are off")
    return out


def _q_advice(f: float, q: float, unit: str) -> str:
    u = "mm^2/s^3" if unit == "mm" else "deg^2/s^3"
    if f >= 1e4 or f <= 1e-4:
        return (f"no process noise q matches the innovations (tried q x1e-4 to x1e4): the measurement sigmas "
                f"are {'too small' if f > 1 else 'too large'}")
    size = f"{f:.2g}x too small" if f >= 1 else f"{1 / f:.2g}x too large"
    return (f"q looks {size} (the NIS's 99 % point is chi2's with q = {q * f:.3g} {u}; or the measurement "
            f"sigmas are off): rerun with --q {q * f:.3g} or --q auto")


def summary_line(info: dict, output) -> str:
    """The one-line summary of :func:`track_csv`'s result, counting every row."""
    q = f", q {info['q']:.3g}" + (f" (auto: x{info['q_factor']:.3g})" if info.get("q_auto") else "")
    return (f"wrote {info['n_rows']} tracked rows to {output} ({info['n_used']} positions, {info['n_gated']} gated, "
            f"{info['n_invalid']} invalid, {info['n_restarts']} restarts: {info['n_gap']} after gaps, "
            f"{info['n_jump']} jumps; mean NIS {info['mean_nis']:.3g} over all {info['n_tested']} tested rows, "
            f"{info['mean_nis_used']:.3g} over the used ones, for {info['dims']} dimensions{q})")
