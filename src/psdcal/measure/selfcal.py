"""A room that calibrates itself: every sensor's pose from a moving rigid tag (docs/guide/selfcal.md).

A tag with emitters at known places on one rigid body (:class:`psdcal.measure.tagpose.Tag`)
moves through the room; at each time step two or more sensors see some of
its emitters. The unknowns are each sensor's pose ``(R_k, c_k)``
(``Pc = R_k (Pw - c_k)``) and the tag's pose ``(Q_t, p_t)`` at every step
(``Pw = Q_t B + p_t``); the observations are the directions ``n`` of the
emitters (an :class:`psdcal.measure.angles_table.AnglesTable`). The tag's
geometry fixes the scale; the frame (6 degrees of freedom) is fixed by

- surveyed points (``survey``): emitters at known world positions also seen
  by the sensors; every sensor is then free; or, by default,
- the reference sensor: the world frame *is* its camera frame
  (``R = I``, ``c = 0``; psdcal's camera frame, ``x`` right, ``y`` down,
  ``z`` forward). The reference is the first sensor in sorted name order
  (or the one named), so the result does not depend on the order of the rows
  or of the sensors.

A known distance between two sensors' centres (``distances``) adds its own
residual (scale information on top of the tag's).

Solution
--------
1. Start (no guess needed): each sensor's view of the tag at each step by a
   scaled-orthographic solve in a camera turned towards the tag, both mirror
   branches of a planar tag refined (:func:`psdcal.measure.tagpose.single_sensor_starts`);
   the relative pose of two sensors by a trimmed Procrustes (Kabsch) fit of
   the tag's emitters in both cameras over the steps both see; sensors
   chained to the reference along the pairs with the most shared steps.
2. Maximum likelihood: Levenberg-Marquardt over all poses, the tag blocks
   eliminated by a Schur complement (they are independent given the sensors),
   so one iteration costs ``O(T)`` small 6x6 solves and one ``6K`` system.
3. Covariance of the sensor poses over ``(omega_k, c_k)`` (``R = exp([omega]) R_hat``,
   camera frame, rad; centre mm) in the chosen gauge: the inverse of the
   reduced (Schur) information matrix; ``chi2`` of the directions against
   ``2 N - 6 T - 6 K_free`` degrees of freedom through
   :func:`psdcal._consistency.chi2_check`, the covariance inflated when it fails.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psdcal._consistency import ALPHA, Check, chi2_check, inflate, verdict_of
from psdcal.errors import ConvergenceError, DegenerateViewsError, InputError
from psdcal.measure._rigid import (
    _mv,
    exp_so3,
    fixed_point_residuals,
    gram,
    kabsch,
    residuals_and_jacobians,
    sum_by,
    whiteners,
)
from psdcal.measure.angles_table import AnglesTable
from psdcal.measure.tagpose import Tag, determined, fit_steps, single_sensor_starts
from psdcal.model.projection import r_from_R_batch, skew3

TOL = 1e-10


@dataclass(frozen=True)
class SelfCalResult:
    """Sensor poses from a moving tag.

    Attributes
    ----------
    names : tuple of str
        Sensor names, sorted.
    R : (K, 3, 3) ndarray
        Rotations world -> camera.
    c_mm : (K, 3) ndarray
        Projection centres in the world, mm.
    cov : (K, 6, 6) ndarray
        Covariance of each sensor's ``(omega_rad, c_mm)`` (zero for the reference sensor).
    cov_full : (6K, 6K) ndarray
        The joint covariance (sensors correlate through the shared tag).
    gauge : str
        ``"reference"`` or ``"survey"``.
    reference : str or None
    tag_t_s, tag_rvec, tag_p_mm : ndarrays (T,), (T, 3), (T, 3)
        The tag's pose at each step used.
    chi2, dof : float
    check : Check
    n_steps, n_obs : int
    iterations : int
    warnings : tuple of str
    """

    names: tuple
    R: np.ndarray
    c_mm: np.ndarray
    cov: np.ndarray
    cov_full: np.ndarray = field(repr=False)
    gauge: str
    reference: str | None
    tag_t_s: np.ndarray = field(repr=False)
    tag_rvec: np.ndarray = field(repr=False)
    tag_p_mm: np.ndarray = field(repr=False)
    chi2: float
    dof: int
    check: Check
    n_steps: int
    n_obs: int
    iterations: int
    warnings: tuple = ()

    def index(self, name) -> int:
        return self.names.index(name)

    def rvec(self, k) -> np.ndarray:
        return r_from_R_batch(self.R[k][None])[0]

    def tvec_mm(self, k) -> np.ndarray:
        return -self.R[k] @ self.c_mm[k]

    def cov_omega_t(self, k) -> np.ndarray:
        """Covariance (6, 6) of sensor ``k`` over ``(omega_rad, t_mm)`` (the sensors file's ``pose_covariance``)."""
        T = np.zeros((6, 6))
        T[:3, :3] = np.eye(3)
        T[3:, :3] = skew3(self.R[k] @ self.c_mm[k])
        T[3:, 3:] = -self.R[k]
        return T @ self.cov[k] @ T.T

    def joint_cov_omega_t(self) -> np.ndarray:
        """The joint covariance (6K, 6K) over every sensor's ``(omega_rad, t_mm)``, in the order of ``names``."""
        K = len(self.names)
        T = np.zeros((6 * K, 6 * K))
        for k in range(K):
            T[6 * k:6 * k + 3, 6 * k:6 * k + 3] = np.eye(3)
            T[6 * k + 3:6 * k + 6, 6 * k:6 * k + 3] = skew3(self.R[k] @ self.c_mm[k])
            T[6 * k + 3:6 * k + 6, 6 * k + 3:6 * k + 6] = -self.R[k]
        return T @ self.cov_full @ T.T

    def nees(self, k, R_true, c_true_mm) -> float:
        """Normalised estimation error squared (6 dof) of sensor ``k`` against a true pose in this result's frame."""
        omega = r_from_R_batch((np.asarray(R_true) @ self.R[k].T)[None])[0]
        err = np.concatenate([omega, np.asarray(c_true_mm, dtype=float) - self.c_mm[k]])
        return float(err @ np.linalg.solve(self.cov[k], err))

    def sensors_entries(self, calibs: dict | None = None) -> list:
        """Entries of a sensors file (``locate --sensors``): name, [calib,] rvec, tvec_mm, pose_covariance, pose."""
        from psdcal.measure.pose import POSE_COV_NAMES

        out = []
        for k, nm in enumerate(self.names):
            d = {"name": nm}
            if calibs and nm in calibs:
                d["calib"] = calibs[nm]
            d["rvec"] = self.rvec(k).tolist()
            d["tvec_mm"] = self.tvec_mm(k).tolist()
            d["pose_covariance"] = {"names": list(POSE_COV_NAMES), "matrix": self.cov_omega_t(k).tolist()}
            sd = np.sqrt(np.clip(np.diag(self.cov[k]), 0, None))
            d["pose"] = {"center_w_mm": self.c_mm[k].tolist(), "sigma_center_mm": sd[3:].tolist(),
                         "sigma_rotation_deg": np.degrees(sd[:3]).tolist(),
                         "source": "selfcal", "fixed": bool(self.gauge == "reference" and nm == self.reference)}
            out.append(d)
        return out

    def summary(self) -> dict:
        """The run's summary for the sensors file's ``selfcal`` key."""
        return {"gauge": self.gauge, "reference": self.reference, "verdict": verdict_of([self.check]),
                "n_steps": self.n_steps, "n_obs": self.n_obs,
                "chi2": self.chi2, "dof": self.dof, "iterations": self.iterations,
                "checks": [self.check.to_dict()], "warnings": list(self.warnings),
                "joint_pose_covariance": {"sensors": list(self.names), "matrix": self.joint_cov_omega_t().tolist(),
                                          "names": "omega_x_rad, omega_y_rad, omega_z_rad, tx_mm, ty_mm, tz_mm "
                                                   "of each sensor in turn"},
                "frame": ("the reference sensor's camera frame (x right, y down, z forward), mm"
                          if self.gauge == "reference" else "the surveyed points' frame, mm")}


# --------------------------------------------------------------------------- start
def _robust_kabsch(A, B):
    """``R, t`` with ``B ~ R A + t``, refitted three times without the points beyond 3 robust sigmas."""
    keep = np.ones(len(A), bool)
    R, t = kabsch(A, B)
    for _ in range(3):
        d = np.linalg.norm(A @ R.T + t - B, axis=1)
        s = 1.4826 * np.median(d[keep]) + 1e-12
        new = d <= max(3.0 * s, 1e-9)
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
        R, t = kabsch(A[keep], B[keep])
    return R, t


def _start_sensors(K, ref, k, e, t, n, L, T, B):
    """Starting poses ``R (K, 3, 3), c (K, 3)`` of every sensor in the reference sensor's camera frame
    (and each sensor's own view of the tag at every step, :func:`single_sensor_starts`)."""
    pts, starts = [], []
    for j in range(K):
        m = k == j
        Qc, pc, cost, _, ok = single_sensor_starts(n[m], L[m], e[m], t[m], T, B)
        starts.append((Qc, pc, ok))
        P = np.einsum("tij,mj->tmi", Qc, B) + pc[:, None]  # every emitter in camera j at every step
        pts.append((P, ok & np.isfinite(cost)))
    links = {}
    for i in range(K):
        for j in range(K):
            if i < j:
                both = pts[i][1] & pts[j][1]
                if both.sum() >= 2:
                    A = pts[j][0][both].reshape(-1, 3)
                    Bp = pts[i][0][both].reshape(-1, 3)
                    R, tr = _robust_kabsch(A, Bp)  # camera j -> camera i
                    links[(i, j)] = (int(both.sum()), R, tr)
                    links[(j, i)] = (int(both.sum()), R.T, -R.T @ tr)
    # chain every sensor to the reference along the pairs with the most shared steps (a widest-path tree)
    to_ref = {ref: (np.eye(3), np.zeros(3))}  # camera j -> reference camera
    while len(to_ref) < K:
        best = None
        for (i, j), (cnt, R, tr) in links.items():
            if i in to_ref and j not in to_ref and (best is None or cnt > best[0]):
                best = (cnt, i, j, R, tr)
        if best is None:
            missing = sorted(set(range(K)) - set(to_ref))
            raise DegenerateViewsError(f"sensors {missing} share no time step (with 3 emitters seen by each) with "
                                       "the others: their poses cannot be related")
        _, i, j, R, tr = best
        Ri, ti = to_ref[i]
        to_ref[j] = (Ri @ R, Ri @ tr + ti)
    Rs = np.stack([to_ref[j][0].T for j in range(K)])  # world (= reference camera) -> camera j
    cs = np.stack([to_ref[j][1] for j in range(K)])
    return Rs, cs, starts


def _triangulate(Rs, cs, ks, n):
    """Least-squares intersection (3,) of the rays ``n`` seen by sensors ``ks``."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for kk, nn in zip(ks, n):
        d = Rs[kk].T @ np.array([nn[0], nn[1], 1.0])
        d /= np.linalg.norm(d)
        M = np.eye(3) - np.outer(d, d)
        A += M
        b += M @ cs[kk]
    return np.linalg.solve(A, b)


# --------------------------------------------------------------------------- solve
def self_calibrate(table: AnglesTable, tag: Tag, *, reference: str | None = None, survey=None,
                   distances=(), alpha: float = ALPHA, max_iterations: int = 200) -> SelfCalResult:
    """Every sensor's pose from a moving rigid tag (module docstring).

    Parameters
    ----------
    table : AnglesTable
        Observations; a time step is one value of ``t_s`` (resample sensors
        that do not sample together with :func:`psdcal.measure.angles_table.align_to_sensor`).
        Rows of emitters neither on the tag nor surveyed are left out.
    tag : Tag
    reference : str, optional
        The sensor whose camera frame is the world (default: the first name
        in sorted order). Ignored with ``survey``.
    survey : (names, points_mm (k, 3)), optional
        Emitters at known world positions (not on the tag), seen by the
        sensors: they fix the frame; at least three, not on one line, each
        seen by two sensors.
    distances : sequence of (sensor_a, sensor_b, distance_mm, sigma_mm)
        Known distances between sensors' centres.
    alpha : float
        False-alarm rate of the chi2 check.

    Raises
    ------
    InputError
        Fewer than two sensors, an unknown reference or distance sensor.
    DegenerateViewsError
        Sensors that share no step, too few surveyed points, a singular
        information matrix (a path that does not fix the poses).
    ConvergenceError
        The solver did not converge.
    """
    names = tuple(table.sensors)
    K = len(names)
    if K < 2:
        raise InputError(f"self-calibration needs at least two sensors, the table has {K}", field="sensor")
    sidx = {s: i for i, s in enumerate(names)}
    if reference is None:
        reference = names[0]
    if reference not in sidx:
        raise InputError(f"reference sensor {reference!r} is not in the table (sensors: {', '.join(names)})",
                         field="reference")
    ref = sidx[reference]
    B = tag.body_mm
    eidx = {x: i for i, x in enumerate(tag.names)}
    on_tag = np.array([x in eidx for x in table.emitter], bool)
    # steps seen by at least two sensors
    tt = table.t_s[on_tag]
    ss = table.sensor[on_tag]
    pairs = sorted(set(zip(tt.tolist(), ss.tolist())))
    per_t = {}
    for a, _ in pairs:
        per_t[a] = per_t.get(a, 0) + 1
    multi = np.array([per_t[a] >= 2 for a in table.t_s[on_tag]], bool)
    rows = np.flatnonzero(on_tag)[multi]
    warnings = []
    if len(rows) == 0:
        raise DegenerateViewsError("no time step where two sensors see the tag")
    k = np.array([sidx[s] for s in table.sensor[rows]], int)
    e = np.array([eidx[x] for x in table.emitter[rows]], int)
    times, t = np.unique(table.t_s[rows], return_inverse=True)
    T = len(times)
    n = table.n[rows]
    L = whiteners(table.cov_n[rows])
    Rs, cs, starts = _start_sensors(K, ref, k, e, t, n, L, T, B)
    Q, p, cost, _, H, good, _ = fit_steps(Rs, cs, B, k, e, t, n, L, T, starts=starts)
    keep = good & np.isfinite(cost) & determined(H)
    if not keep.all():
        warnings.append(f"{int((~keep).sum())} of {T} steps left out (no sensor sees three of the tag's emitters "
                        "there, or the tag's pose is not determined)")
        sel = keep[t]
        remap = -np.ones(T, int)
        remap[keep] = np.arange(int(keep.sum()))
        k, e, n, L, t = k[sel], e[sel], n[sel], L[sel], remap[t[sel]]
        Q, p, times = Q[keep], p[keep], times[keep]
        T = len(times)
    if T < 2:
        raise DegenerateViewsError("fewer than two usable time steps")
    # surveyed points
    sv = None
    if survey is not None:
        snames, spts = survey
        spos = {nm: np.asarray(x, dtype=float) for nm, x in zip(snames, spts)}
        srow = np.flatnonzero([x in spos and x not in eidx and s in sidx for x, s in zip(table.emitter, table.sensor)])
        ks_ = np.array([sidx[s] for s in table.sensor[srow]], int)
        Ps = np.array([spos[x] for x in table.emitter[srow]]).reshape(-1, 3)
        ns_ = table.n[srow]
        Ls_ = whiteners(table.cov_n[srow]) if len(srow) else np.zeros((0, 2, 2))
        seen = {}
        for x, kk, nn in zip(table.emitter[srow], ks_, ns_):
            seen.setdefault(x, []).append((kk, nn))
        A_ref, B_w = [], []
        for x, obs in seen.items():
            if len({kk for kk, _ in obs}) >= 2:
                A_ref.append(_triangulate(Rs, cs, [kk for kk, _ in obs], np.array([nn for _, nn in obs])))
                B_w.append(spos[x])
        if len(A_ref) < 3 or np.linalg.svd(np.array(B_w) - np.mean(B_w, 0), compute_uv=False)[1] < 1e-6 * max(
                1.0, np.ptp(np.array(B_w))):
            raise DegenerateViewsError(f"{len(A_ref)} surveyed points are seen by two sensors; the frame needs at "
                                       "least three, not on one line (or leave out --survey to fix the frame on "
                                       "the reference sensor)")
        Rw, tw = kabsch(np.array(A_ref), np.array(B_w))  # reference frame -> survey frame
        Rs = Rs @ Rw.T
        cs = cs @ Rw.T + tw
        Q = Rw @ Q
        p = p @ Rw.T + tw
        sv = (ks_, Ps, ns_, Ls_)
    free = np.ones(6 * K, bool)
    if sv is None:
        free[6 * ref:6 * ref + 6] = False
    dist = []
    for a, b_, d_mm, s_mm in distances:
        for x in (a, b_):
            if x not in sidx:
                raise InputError(f"distance sensor {x!r} is not in the table (sensors: {', '.join(names)})",
                                 field="distance")
        if not (d_mm > 0 and s_mm > 0):
            raise InputError("a known distance and its sigma must be > 0 mm", field="distance")
        dist.append((sidx[a], sidx[b_], float(d_mm), float(s_mm)))

    def evaluate(Rs, cs, Q, p, jac=True):
        r, Js, Jt, z = residuals_and_jacobians(Rs, cs, Q, p, B, k, t, e, n, L, jac=jac)
        chi2 = float((r * r).sum())
        behind = bool(np.any(z <= 0))
        out = {"chi2": chi2, "behind": behind}
        if sv is not None and len(sv[0]):
            rs, Jsv, zs = fixed_point_residuals(Rs, cs, sv[1], sv[0], sv[2], sv[3], jac=jac)
            out["chi2"] += float((rs * rs).sum())
            out["behind"] |= bool(np.any(zs <= 0))
        for a, b_, d_mm, s_mm in dist:
            out["chi2"] += float(((np.linalg.norm(cs[a] - cs[b_]) - d_mm) / s_mm) ** 2)
        if not jac:
            return out
        U = sum_by(k, gram(Js), K)
        gA = sum_by(k, _mv(np.swapaxes(Js, 1, 2), r), K)
        if sv is not None and len(sv[0]):
            U += sum_by(sv[0], gram(Jsv), K)
            gA += sum_by(sv[0], _mv(np.swapaxes(Jsv, 1, 2), rs), K)
        Uf = np.zeros((6 * K, 6 * K))
        for j in range(K):
            Uf[6 * j:6 * j + 6, 6 * j:6 * j + 6] = U[j]
        gA = gA.reshape(-1)
        for a, b_, d_mm, s_mm in dist:
            dv = cs[a] - cs[b_]
            ln = np.linalg.norm(dv)
            rd = (ln - d_mm) / s_mm
            J = np.zeros(6 * K)
            J[6 * a + 3:6 * a + 6] = dv / ln / s_mm
            J[6 * b_ + 3:6 * b_ + 6] = -dv / ln / s_mm
            Uf += np.outer(J, J)
            gA += J * rd
        V = sum_by(t, gram(Jt), T)
        gB = sum_by(t, _mv(np.swapaxes(Jt, 1, 2), r), T)
        W = sum_by(t * K + k, gram(Js, Jt), T * K).reshape(T, K, 6, 6)
        out.update(U=Uf, gA=gA, V=V, gB=gB, W=W.reshape(T, 6 * K, 6))
        return out

    def reduced(ev, lam):
        V = ev["V"]
        dV = np.diagonal(V, axis1=1, axis2=2)
        Vd = V + lam * np.einsum("ti,ij->tij", dV, np.eye(6))
        Vinv = np.linalg.inv(Vd)
        Wf = ev["W"]
        WV = Wf @ Vinv
        S = ev["U"] + lam * np.diag(np.diag(ev["U"])) - np.tensordot(WV, Wf, axes=([0, 2], [0, 2]))
        b = -ev["gA"] + np.einsum("tij,tj->i", WV, ev["gB"])
        return S, b, Vinv, Wf

    lam = 1e-4
    ev = evaluate(Rs, cs, Q, p)
    it = 0
    converged = False
    for it in range(1, max_iterations + 1):
        S, b, Vinv, Wf = reduced(ev, lam)
        ds = np.zeros(6 * K)
        try:
            ds[free] = np.linalg.solve(S[np.ix_(free, free)], b[free])
        except np.linalg.LinAlgError:
            lam *= 10.0
            continue
        dt = -np.einsum("tij,tj->ti", Vinv, ev["gB"] + np.einsum("tji,j->ti", Wf, ds))
        d6 = ds.reshape(K, 6)
        Rn = exp_so3(d6[:, :3]) @ Rs
        cn = cs + d6[:, 3:]
        Qn = exp_so3(dt[:, :3]) @ Q
        pn = p + dt[:, 3:]
        trial = evaluate(Rn, cn, Qn, pn, jac=False)
        if not trial["behind"] and trial["chi2"] < ev["chi2"]:
            gain = ev["chi2"] - trial["chi2"]
            Rs, cs, Q, p = Rn, cn, Qn, pn
            ev = evaluate(Rs, cs, Q, p)
            lam = max(lam / 10.0, 1e-12)
            if gain <= TOL * max(ev["chi2"], 1.0):
                converged = True
                break
        else:
            lam *= 10.0
            if lam > 1e10:
                converged = True  # no step lowers the cost: at the minimum to round-off
                break
    if not converged:
        raise ConvergenceError(f"the self-calibration did not converge in {max_iterations} iterations")
    S, _, _, _ = reduced(ev, 0.0)
    Sf = S[np.ix_(free, free)]
    w = np.linalg.eigvalsh(Sf)
    if w[0] <= 1e-12 * w[-1]:
        raise DegenerateViewsError("the sensors' poses are not determined by these steps (the tag's path is too "
                                   "short or too straight, or the sensors see too few of its emitters)")
    cov_full = np.zeros((6 * K, 6 * K))
    cov_full[np.ix_(free, free)] = np.linalg.inv(Sf)
    n_res = 2 * len(k) + (2 * len(sv[0]) if sv is not None else 0) + len(dist)
    dof = int(n_res - 6 * T - int(free.sum()))
    chk = chi2_check(ev["chi2"], dof, name="selfcal_chi2",
                     what=f"the directions of the tag's emitters ({len(k)} observations at {T} steps)", alpha=alpha,
                     advice="the angle sigmas are too small, the tag file does not match the tag, the sensors do "
                            "not sample at the same time (resample them), or an emitter is reflected")
    cov_full = inflate(cov_full, chk)
    if chk.passed is False:
        warnings.append(chk.line())
    cov = np.stack([cov_full[6 * j:6 * j + 6, 6 * j:6 * j + 6] for j in range(K)])
    return SelfCalResult(names, Rs, cs, cov, cov_full, "survey" if sv is not None else "reference",
                         None if sv is not None else reference, times, r_from_R_batch(Q), p, ev["chi2"], dof, chk,
                         T, len(k), it, tuple(warnings))


def to_frame(res: SelfCalResult, R_wr, t_wr, scale: float = 1.0):
    """Sensor poses ``(R (K, 3, 3), c (K, 3))`` moved into another frame ``x_w = scale R_wr x_r + t_wr``."""
    Rs = res.R @ np.asarray(R_wr).T
    cs = scale * res.c_mm @ np.asarray(R_wr).T + np.asarray(t_wr)
    return Rs, cs


__all__ = ["SelfCalResult", "self_calibrate", "to_frame"]
