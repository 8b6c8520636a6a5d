"""A rigid tag's six-degree-of-freedom pose over time (docs/guide/selfcal.md#the-tags-pose).

A tag is a rigid body carrying several emitters at known places (its *body
frame*, mm). Seen by one sensor or several with known poses, its pose at each
time step ``t`` is ``Pw = Q_t B + p_t`` (``Q_t`` body -> world, ``p_t`` the
body origin in the world, mm): the weighted least-squares fit of the directions
of its emitters, with the covariance of ``(phi, p)`` (``Q = exp([phi]) Q_hat``,
a small rotation in the world frame, rad; ``p`` in mm) from the angle noise
and, when the sensors file gives them, the sensors' pose covariances.

A planar tag seen by one sensor from afar has two poses that explain its
directions almost equally well (the mirror tilt); both are fitted and the step
is flagged ``ambiguous`` when the other one also agrees with the noise.

An error shared by all the directions one sensor gives at one step (one
timing or sweep error, correlated photodiodes) is tested separately
(:func:`common_mode_test`, the check ``tag_pose_common_mode``) and, when
found, added to the covariance: the pose fit hides most of it, so the
ratio inflation alone would not cover it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from psdcal._consistency import ALPHA, Check, chi2_check, inflate
from psdcal.errors import DegenerateViewsError, InputError
from psdcal.measure._rigid import (
    exp_so3,
    sum_by,
    tag_gauss_newton,
    weak_perspective,
    whiteners,
)
from psdcal.measure.angles_table import AnglesTable
from psdcal.measure.positioning import pose_vectors
from psdcal.model.projection import R_from_r, r_from_R_batch


@dataclass(frozen=True)
class Tag:
    """A rigid tag: emitter names and their positions in the body frame, mm (k, 3)."""

    names: tuple
    body_mm: np.ndarray

    def index(self, name) -> int:
        return self.names.index(name)


def read_tag(path) -> Tag:
    """Read a tag file ``emitter,X_mm,Y_mm,Z_mm`` (or ``X_m,Y_m,Z_m``): the emitters in the tag's body frame.

    At least three emitters, not all on one line (a line does not fix the
    rotation about it); names unique.
    """
    from psdcal.io import _read_rows

    path, rows = _read_rows(path)
    hline, header = rows[0]
    if "emitter" not in header:
        raise InputError("missing column 'emitter' (header: emitter,X_mm,Y_mm,Z_mm)", path=path, line=hline,
                         field="emitter")
    unit = next((u for u, f in (("mm", 1.0), ("m", 1000.0)) if all(f"{a}_{u}" in header for a in "XYZ")), None)
    if unit is None:
        raise InputError("missing columns X_mm,Y_mm,Z_mm (or X_m,Y_m,Z_m)", path=path, line=hline, field="X_mm")
    f = 1.0 if unit == "mm" else 1000.0
    names, pts = [], []
    for ln, row in rows[1:]:
        if len(row) != len(header):
            raise InputError(f"expected {len(header)} fields, found {len(row)}", path=path, line=ln)
        nm = row[header.index("emitter")]
        if not nm:
            raise InputError("empty emitter name", path=path, line=ln, field="emitter")
        if nm in names:
            raise InputError(f"repeated emitter {nm!r}", path=path, line=ln, field="emitter")
        v = []
        for a in "XYZ":
            col = f"{a}_{unit}"
            text = row[header.index(col)]
            try:
                x = float(text)
            except ValueError:
                raise InputError(f"not a number: {text!r}", path=path, line=ln, field=col) from None
            if not math.isfinite(x):
                raise InputError("not a finite number", path=path, line=ln, field=col)
            v.append(x * f)
        names.append(nm)
        pts.append(v)
    B = np.array(pts, dtype=float).reshape(-1, 3)
    if len(names) < 3:
        raise InputError(f"a tag needs at least 3 emitters, found {len(names)}", path=path)
    s = np.linalg.svd(B - B.mean(0), compute_uv=False)
    if s[1] < 1e-6 * max(s[0], 1e-300):
        raise InputError("the tag's emitters lie on one line: they do not fix its rotation", path=path)
    return Tag(tuple(names), B)


@dataclass(frozen=True)
class KnownSensor:
    """A sensor with a known pose ``Pc = R (Pw - c)``; ``cov`` (6, 6) over ``(omega_rad, c_mm)`` or None."""

    name: str
    R: np.ndarray
    c_mm: np.ndarray
    cov: np.ndarray | None = None


def omega_t_to_omega_c(R, c):
    """``d(omega, c) / d(omega, t)`` (6, 6) for ``t = -R c`` (the inverse of PoseResult's ``_to_omega_t``)."""
    from psdcal.model.projection import skew3

    T = np.zeros((6, 6))
    T[:3, :3] = np.eye(3)
    T[3:, :3] = R.T @ skew3(R @ c)
    T[3:, 3:] = -R.T
    return T


def load_sensor_poses(path) -> list[KnownSensor]:
    """The poses of a sensors file (``locate --sensors``, ``pose --into``, ``selfcal -o``); no calibration needed.

    Reads ``name``, ``rvec``, ``tvec_mm`` and the optional ``pose_covariance``
    (over ``omega, t``) of each entry.
    """
    from psdcal.io import read_json
    from psdcal.measure.pose import POSE_COV_NAMES

    path = Path(path)
    data = read_json(path, "sensors file")
    if isinstance(data, dict):
        data = data.get("sensors")
    if not isinstance(data, list) or not data:
        raise InputError("expected a list of sensors (or {\"sensors\": [...]})", path=path, field="sensors")
    out, seen = [], set()
    for i, item in enumerate(data):
        where = f"sensors[{i}]"
        if not isinstance(item, dict):
            raise InputError("each sensor must be an object", path=path, field=where)
        name = str(item.get("name", f"s{i + 1}"))
        if name in seen:
            raise InputError(f"repeated sensor name {name!r}", path=path, field=f"{where}.name")
        seen.add(name)
        vec = pose_vectors(item, path, where)
        R = R_from_r(vec["rvec"])
        c = -R.T @ vec["tvec_mm"]
        cov = None
        pc = item.get("pose_covariance")
        if pc is not None:
            try:
                ok = list(pc.get("names", [])) == list(POSE_COV_NAMES)
                m = np.asarray(pc.get("matrix"), dtype=float)
            except (AttributeError, TypeError, ValueError):
                ok, m = False, np.zeros(0)
            if not ok or m.shape != (6, 6) or not np.all(np.isfinite(m)):
                raise InputError(f"'pose_covariance' must have names {list(POSE_COV_NAMES)} and a 6x6 matrix",
                                 path=path, field=f"{where}.pose_covariance")
            T = omega_t_to_omega_c(R, c)
            cov = T @ (0.5 * (m + m.T)) @ T.T
        out.append(KnownSensor(name, R, c, cov))
    return out


def load_joint_covariance(path, sensors: list[KnownSensor]):
    """The sensors file's ``selfcal.joint_pose_covariance`` over ``(omega, c)`` of ``sensors`` (6K, 6K), or None.

    None when the file has none or it names other sensors; the sensors'
    correlations through the shared tag are then left out.
    """
    from psdcal.io import read_json

    data = read_json(path, "sensors file")
    jc = data.get("selfcal", {}).get("joint_pose_covariance") if isinstance(data, dict) else None
    if not isinstance(jc, dict):
        return None
    names = list(jc.get("sensors") or [])
    if sorted(names) != sorted(s.name for s in sensors) or len(names) != len(sensors):
        return None
    try:
        M = np.asarray(jc.get("matrix"), dtype=float)
    except (TypeError, ValueError):
        M = np.zeros(0)
    K = len(names)
    if M.shape != (6 * K, 6 * K) or not np.all(np.isfinite(M)):
        raise InputError(f"'selfcal.joint_pose_covariance.matrix' must be {6 * K} x {6 * K} finite numbers",
                         path=path, field="selfcal.joint_pose_covariance")
    by = {s.name: s for s in sensors}
    order = [names.index(s.name) for s in sensors]
    idx = np.concatenate([np.arange(6 * i, 6 * i + 6) for i in order])
    M = M[np.ix_(idx, idx)]
    T = np.zeros((6 * K, 6 * K))
    for j, s in enumerate(sensors):
        T[6 * j:6 * j + 6, 6 * j:6 * j + 6] = omega_t_to_omega_c(by[s.name].R, by[s.name].c_mm)
    return T @ (0.5 * (M + M.T)) @ T.T


@dataclass(frozen=True)
class TagPoses:
    """The tag's pose at each time step.

    Attributes
    ----------
    t_s : (T,) ndarray
    rvec : (T, 3) ndarray
        Rotation vector of ``Q`` (body -> world), rad.
    p_mm : (T, 3) ndarray
        The body origin in the world, mm.
    cov : (T, 6, 6) ndarray
        Covariance of ``(phi_rad, p_mm)``, ``Q = exp([phi]) Q_hat`` (after any inflation).
    chi2, dof : (T,) ndarrays
        Each step's weighted residual and its degrees of freedom ``2 m - 6``.
    n_obs, n_sensors : (T,) int ndarrays
    ambiguous : (T,) bool ndarray
        The mirror pose also agrees with the noise (one sensor, planar tag).
    check : Check
        chi2 of all steps against their total dof.
    warnings : tuple of str
    common_mode : Check or None
        ``tag_pose_common_mode``: whether each sensor's directions of one step
        share an error (see :func:`common_mode_test`); None when not tested.
    common_mode_sigma_rad : float
        The estimated standard deviation of that shared error (rad, in the
        direction coordinates), added to the covariance when the check fails
        (0 otherwise).
    """

    t_s: np.ndarray
    rvec: np.ndarray
    p_mm: np.ndarray
    cov: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    n_obs: np.ndarray
    n_sensors: np.ndarray
    ambiguous: np.ndarray
    check: Check
    warnings: tuple = field(default=())
    common_mode: Check | None = None
    common_mode_sigma_rad: float = 0.0

    @property
    def checks(self) -> tuple:
        """All the checks of the fit (``tag_pose_chi2``, then ``tag_pose_common_mode`` when tested)."""
        return (self.check,) if self.common_mode is None else (self.check, self.common_mode)

    @property
    def sigma_p_mm(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diagonal(self.cov, axis1=1, axis2=2)[:, 3:], 0, None))

    @property
    def sigma_rotation_deg(self) -> np.ndarray:
        return np.degrees(np.sqrt(np.clip(np.diagonal(self.cov, axis1=1, axis2=2)[:, :3], 0, None)))

    def columns(self) -> dict:
        """The CSV columns of ``psdcal tag-pose`` (name -> (T,) array)."""
        sp, sr = self.sigma_p_mm, self.sigma_rotation_deg
        return {"t_s": self.t_s, "X_mm": self.p_mm[:, 0], "Y_mm": self.p_mm[:, 1], "Z_mm": self.p_mm[:, 2],
                "rx_rad": self.rvec[:, 0], "ry_rad": self.rvec[:, 1], "rz_rad": self.rvec[:, 2],
                "sigma_X_mm": sp[:, 0], "sigma_Y_mm": sp[:, 1], "sigma_Z_mm": sp[:, 2],
                "sigma_rot_x_deg": sr[:, 0], "sigma_rot_y_deg": sr[:, 1], "sigma_rot_z_deg": sr[:, 2],
                "chi2": self.chi2, "dof": self.dof, "n_sensors": self.n_sensors,
                "ambiguous": self.ambiguous.astype(int)}


def observation_indices(table: AnglesTable, tag: Tag, sensor_names):
    """Rows of ``table`` on the tag's emitters and known sensors -> (rows, k, e, step index, step times)."""
    sidx = {s: i for i, s in enumerate(sensor_names)}
    eidx = {e: i for i, e in enumerate(tag.names)}
    rows = np.flatnonzero([s in sidx and e in eidx for s, e in zip(table.sensor, table.emitter)])
    k = np.array([sidx[s] for s in table.sensor[rows]], dtype=int)
    e = np.array([eidx[x] for x in table.emitter[rows]], dtype=int)
    times, t = np.unique(table.t_s[rows], return_inverse=True)
    return rows, k, e, t, times


def single_sensor_starts(n, L, e, t, T, B):
    """Every step's tag pose in one sensor's camera frame: both mirror starts refined, the best kept.

    ``n, L, e, t``: that sensor's observations (directions, whiteners, emitter and step indices).
    Returns ``Q, p (camera frame), cost, cost_other, ok`` (ok: the step had >= 3 emitters).
    """
    Q = np.tile(np.eye(3), (T, 1, 1))
    p = np.zeros((T, 3))
    p[:, 2] = 1.0
    cost = np.full(T, np.inf)
    alt = np.full(T, np.inf)
    ok = np.zeros(T, bool)
    E = len(B)
    pattern = np.zeros((T, E), bool)
    pattern[t, e] = True
    nn = np.zeros((T, E, 2))
    nn[t, e] = n
    for pat in np.unique(pattern[pattern.sum(1) >= 3], axis=0):
        steps = np.flatnonzero((pattern == pat).all(1))
        cand = []
        sel = np.isin(t, steps)
        remap = -np.ones(T, int)
        remap[steps] = np.arange(len(steps))
        for Q0, p0 in weak_perspective(nn[np.ix_(steps, np.flatnonzero(pat))], B[pat]):
            Qr, pr, c, _ = tag_gauss_newton(np.eye(3)[None], np.zeros((1, 3)), Q0, p0, B,
                                            np.zeros(sel.sum(), int), remap[t[sel]], e[sel], n[sel], L[sel],
                                            len(steps))
            cand.append((Qr, pr, c))
        costs = np.stack([c for _, _, c in cand])
        best = np.argmin(costs, axis=0)
        Q[steps] = np.stack([c[0] for c in cand])[best, np.arange(len(steps))]
        p[steps] = np.stack([c[1] for c in cand])[best, np.arange(len(steps))]
        cost[steps] = costs[best, np.arange(len(steps))]
        alt[steps] = costs[1 - best, np.arange(len(steps))] if len(cand) == 2 else np.inf
        ok[steps] = True
    return Q, p, cost, alt, ok


def tag_poses(table: AnglesTable, tag: Tag, sensors: list[KnownSensor], *, alpha: float = ALPHA,
              cov_joint=None, common_mode: bool = True) -> TagPoses:
    """The tag's pose at every time step from the directions of its emitters (one or several known sensors).

    The covariance is the angle noise's (inflated when the check fails) plus
    the sensors' pose uncertainty carried through the fit: each sensor's own
    ``cov``, or ``cov_joint`` (6K, 6K) over every sensor's ``(omega, c)`` in
    the order of ``sensors``, with the correlations between sensors (the
    self-calibration's ``cov_full``: its sensors are correlated through the
    shared tag).

    With ``common_mode`` (default), :func:`common_mode_test` checks whether
    the directions one sensor gives at one step share an error (the
    ``tag_pose_common_mode`` check); when they do, the covariance gets that
    error's part (its variance estimated from the data) and the ratio
    inflation comes from the rest of the residuals only.

    Rows of other emitters or unknown sensors are left out (a warning counts
    them). A step needs one sensor that sees at least three of the tag's
    emitters (for the start); steps without are left out.

    Raises
    ------
    DegenerateViewsError
        No step can be solved.
    """
    from psdcal._stats import chi2_sf

    names = [s.name for s in sensors]
    rows, k, e, t, times = observation_indices(table, tag, names)
    warnings = []
    if len(rows) < len(table):
        warnings.append(f"{len(table) - len(rows)} of {len(table)} rows are not of the tag's emitters "
                        "or of a sensor in the sensors file: left out")
    if len(rows) == 0:
        raise DegenerateViewsError("no observation of the tag's emitters by the sensors of the sensors file")
    T = len(times)
    B = tag.body_mm
    n = table.n[rows]
    L = whiteners(table.cov_n[rows])
    Rs = np.stack([s.R for s in sensors])
    cs = np.stack([s.c_mm for s in sensors])
    Q, p, cost, other, H, good, counts = fit_steps(Rs, cs, B, k, e, t, n, L, T)
    same = other == cost  # the mirror start fell back onto the same pose
    nobs = np.bincount(t, minlength=T)
    dof = 2 * nobs - 6
    solvable = good & np.isfinite(cost) & determined(H)
    if not solvable.any():
        raise DegenerateViewsError("no time step has a sensor that sees at least three of the tag's emitters")
    if (~solvable).any():
        warnings.append(f"{int((~solvable).sum())} of {T} time steps left out (no sensor sees three of the "
                        "tag's emitters there, or the pose is not determined)")
    with np.errstate(invalid="ignore"):
        p_other = np.array([chi2_sf(float(o), float(d)) if d > 0 and np.isfinite(o) else 0.0
                            for o, d in zip(other, dof)])
    ambiguous = (~same) & (p_other >= alpha)
    cov = np.full((T, 6, 6), np.nan)
    cov[solvable] = np.linalg.inv(H[solvable])
    chk = chi2_check(float(cost[solvable].sum()), float(dof[solvable].sum()), name="tag_pose_chi2",
                     what=f"the directions of the tag's emitters at {int(solvable.sum())} steps", alpha=alpha,
                     advice="the angle sigmas are too small, the tag file is wrong, or an emitter is reflected")
    K = len(sensors)
    jac = None
    cm, cm_sigma = None, 0.0
    if common_mode:
        jac = _jacobians(Rs, cs, Q, p, B, k, t, e, n, L)
        cmr = common_mode_test(jac[0], jac[2], L, k, t, solvable, K, alpha=alpha)
        cm = cmr.check
        if cm.passed is False:
            rest = chi2_check(cmr.rest_chi2, cmr.rest_dof, alpha=alpha)
            old = inflate(cov[solvable], chk)
            cov[solvable] = inflate(cov[solvable], rest) + cmr.var_rad2 * cmr.G[solvable]
            cm = _with_effect(cm, old[:, 3:, 3:], cov[solvable][:, 3:, 3:], cmr, rest, chk)
            msg = chk.message.split("; covariance inflated")[0]
            if chk.passed is False:
                msg += (f"; covariance inflated x{float(rest.inflation):.4g} by the residuals outside the shared "
                        "error (tag_pose_common_mode)")
            chk = replace(chk, inflation=rest.inflation, message=msg)
            cm_sigma = math.sqrt(cmr.var_rad2)
        else:
            cov = inflate(cov, chk)
    else:
        cov = inflate(cov, chk)
    if cov_joint is not None:
        CJ = np.asarray(cov_joint, dtype=float)
        if CJ.shape != (6 * K, 6 * K):
            raise InputError(f"cov_joint must be {6 * K} x {6 * K} (6 per sensor), got {CJ.shape}",
                             field="cov_joint")
    elif any(s.cov is not None for s in sensors):
        CJ = np.zeros((6 * K, 6 * K))
        for j, s_ in enumerate(sensors):
            if s_.cov is not None:
                CJ[6 * j:6 * j + 6, 6 * j:6 * j + 6] = s_.cov
    else:
        CJ = None
    if CJ is not None:  # d(tag) = -H^-1 G d(sensors): the sensors' part, not inflated again
        _, Js, Jt, _ = jac if jac is not None else _jacobians(Rs, cs, Q, p, B, k, t, e, n, L)
        G = sum_by(t * K + k, np.swapaxes(Jt, 1, 2) @ Js, T * K).reshape(T, K, 6, 6)
        G = np.swapaxes(G, 1, 2).reshape(T, 6, 6 * K)
        Hi = np.zeros((T, 6, 6))
        Hi[solvable] = np.linalg.inv(H[solvable])
        A = Hi @ G
        cov[solvable] = cov[solvable] + (A @ CJ @ np.swapaxes(A, 1, 2))[solvable]
    if chk.passed is False:
        warnings.append(chk.line())
    if cm is not None and cm.passed is False:
        warnings.append(cm.line())
    s = solvable
    return TagPoses(times[s], r_from_R_batch(Q[s]), p[s], cov[s], cost[s], dof[s], nobs[s],
                    (counts[s] > 0).sum(1), ambiguous[s], chk, tuple(warnings), cm, cm_sigma)


@dataclass(frozen=True)
class CommonModeTest:
    """What :func:`common_mode_test` found.

    Attributes
    ----------
    check : Check
        ``tag_pose_common_mode``: F test of the residuals along the shared
        shifts against the rest (statistic F, ``dof`` its numerator's).
    var_rad2 : float
        Estimated variance of the shared error, rad^2 (>= 0), in each of the
        two direction coordinates of each sensor at each step.
    G : (T, 6, 6) ndarray
        Per unit of that variance, the covariance it gives each step's
        ``(phi, p)`` (zero at the steps not tested).
    rest_chi2, rest_dof : float
        chi2 of the residuals outside the shared shifts, and its dof.
    """

    check: Check
    var_rad2: float
    G: np.ndarray = field(repr=False)
    rest_chi2: float
    rest_dof: float


def common_mode_test(r, Jt, L, k, t, steps, K: int, *, alpha: float = ALPHA) -> CommonModeTest:
    """Do the directions that one sensor gives at one step share an error?

    Model: on top of the stated independent noise, every sensor's directions
    at one step are shifted together by ``(d1, d2)``, each ~ N(0, tau^2)
    (rad, in the direction coordinates ``n``): one flash, sweep or clock
    error for all the emitters a sensor sees at once, or the photodiodes'
    correlated noise. The pose fit takes up most of such a shift (three of a
    step's ``2 x sensors`` shifts look like a translation), so it barely shows
    in each step's chi2 and is not covered by the ratio inflation; the rest,
    e.g. the rays of two sensors that no longer cross, shows.

    At each step the whitened residuals are split into their part along the
    shared shifts the fit leaves visible (``V``, orthonormal, inside the
    residual space) and the rest. With independent noise only, the two sums of
    squares over all steps are ``s chi2(d_cm)`` and ``s chi2(d_rest)`` with
    the same unknown scale ``s``, so ``F = (q_cm / d_cm) / (q_rest / d_rest)``
    follows ``F(d_cm, d_rest)`` whatever ``s`` is (the design false-alarm
    rate ``alpha`` holds even when the stated sigmas are off by a factor).
    ``tau^2`` is the moment estimate ``(q_cm - s d_cm) / sum |M U|^2``.

    Parameters
    ----------
    r : (N, 2) ndarray
        Whitened residuals at the solution.
    Jt : (N, 2, 6) ndarray
        Their Jacobians by each step's tag update.
    L : (N, 2, 2) ndarray
        The whiteners (``L C L^T = I``) of the observations.
    k, t : (N,) int ndarrays
        Sensor and step index of each observation.
    steps : (T,) bool ndarray
        The steps to use (solved ones).
    K : int
        Number of sensors.
    """
    from psdcal._stats import f_isf, f_sf

    T = len(steps)
    G = np.zeros((T, 6, 6))
    idx = np.flatnonzero(steps[t])
    order = idx[np.argsort(t[idx], kind="stable")]
    tt = t[order]
    m_of = np.bincount(tt, minlength=T)
    first = np.searchsorted(tt, np.arange(T))
    q_cm = d_cm = q_all = d_all = w2 = 0.0
    for m in np.unique(m_of[steps]):
        if m < 3:
            continue
        st = np.flatnonzero(steps & (m_of == m))
        rows = order[first[st][:, None] + np.arange(m)]  # (S, m)
        S = len(st)
        A = Jt[rows].reshape(S, 2 * m, 6)
        rr = r[rows].reshape(S, 2 * m)
        U = np.zeros((S, m, 2, K, 2))
        U[np.arange(S)[:, None], np.arange(m)[None, :], :, k[rows], :] = L[rows]
        U = U.reshape(S, 2 * m, 2 * K)
        At = np.swapaxes(A, 1, 2)
        Hi = np.linalg.inv(At @ A)
        Bm = Hi @ (At @ U)  # (S, 6, 2K): each shared shift's effect on the step's pose
        W = U - A @ Bm  # what the fit leaves of it in the residuals
        u, sv, _ = np.linalg.svd(W, full_matrices=False)
        keep = sv > 1e-9 * np.maximum(sv[:, :1], 1e-300)
        proj = np.einsum("sni,sn->si", u, rr)
        q_cm += float(np.sum(proj ** 2 * keep))
        d_cm += float(keep.sum())
        q_all += float(np.sum(rr ** 2))
        d_all += float(S * (2 * m - 6))
        w2 += float(np.sum(W ** 2))
        G[st] = Bm @ np.swapaxes(Bm, 1, 2)
    q_rest, d_rest = q_all - q_cm, d_all - d_cm
    name = "tag_pose_common_mode"
    what = "the directions each sensor gives at one step"
    if not (d_cm > 0 and d_rest > 0 and q_rest > 0 and w2 > 0):
        chk = Check(name, None, None, None, alpha, None, f"{what}: too few residuals to test a shared error",
                    dof=float(d_cm), inflation=1.0)
        return CommonModeTest(chk, 0.0, G, q_rest, d_rest)
    s = q_rest / d_rest
    F = (q_cm / d_cm) / s
    pv = f_sf(F, d_cm, d_rest)
    thr = f_isf(alpha, d_cm, d_rest)
    var = max((q_cm - s * d_cm) / w2, 0.0)
    if pv >= alpha:
        chk = Check(name, F, thr, pv, alpha, True,
                    f"{what} show no shared error (F {F:.3g} for {d_cm:g}, {d_rest:g} dof, p = {pv:.2g})",
                    dof=float(d_cm), effect_sigma=0.0, inflation=1.0)
        return CommonModeTest(chk, 0.0, G, q_rest, d_rest)
    chk = Check(name, F, thr, pv, alpha, False,
                f"{what} share an error of {1e6 * math.sqrt(var):.3g} urad (F {F:.3g} for {d_cm:g}, "
                f"{d_rest:g} dof, p = {pv:.2g})",
                advice="one timing, flash or sweep error for all of a sensor's emitters at once, or their "
                       "correlated noise: give the sweeps' time offsets if the angles come from sweeps",
                dof=float(d_cm), inflation=1.0)
    return CommonModeTest(chk, var, G, q_rest, d_rest)


def _with_effect(cm: Check, old, new, cmr: CommonModeTest, rest: Check, total: Check) -> Check:
    """The failed common-mode check with its effect on the positions: how far one real sigma reaches
    beyond the sigma stated without the shared error (median over steps, largest direction), and the
    positions' covariance growth (median ratio of traces) as ``inflation``."""
    ok = np.all(np.isfinite(old), axis=(1, 2)) & np.all(np.isfinite(new), axis=(1, 2))
    if not ok.any():
        return cm
    Lo = np.linalg.cholesky(old[ok])
    Li = np.linalg.inv(Lo)
    lam = np.linalg.eigvalsh(Li @ new[ok] @ np.swapaxes(Li, 1, 2))[:, -1]
    eff = float(np.median(np.sqrt(np.maximum(lam, 0)))) - 1.0
    ratio = float(np.median(np.trace(new[ok], axis1=1, axis2=2) / np.trace(old[ok], axis1=1, axis2=2)))
    msg = (cm.message + f"; added to the covariance (position sigmas x{math.sqrt(ratio):.3g}, up to "
           f"x{1 + eff:.3g} in the worst direction, median over steps), the rest of the residuals inflate it "
           f"x{float(rest.inflation):.4g} instead of the total's x{float(total.inflation):.4g}")
    return replace(cm, message=msg, effect_sigma=eff, inflation=ratio)


def determined(H, max_cond: float = 1e14):
    """Where the 6x6 information blocks ``H`` (T, 6, 6) are finite and invertible (condition < ``max_cond``)."""
    ok = np.all(np.isfinite(H), axis=(1, 2))
    out = np.zeros(len(H), bool)
    if ok.any():
        out[ok] = np.linalg.cond(H[ok]) < max_cond
    return out


def fit_steps(Rs, cs, B, k, e, t, n, L, T, starts=None):
    """Every step's tag pose with the sensors ``Rs, cs`` fixed: starts from the sensor seeing the most emitters,
    both mirror branches refined with all sensors, the better kept.

    ``starts``: each sensor's :func:`single_sensor_starts` ``(Q, p, ok)`` when already known.
    Returns ``Q, p, cost, cost_other (the other branch), H = J^T J (T, 6, 6), good (T,) bool, counts (T, K)``.
    """
    K = len(Rs)
    counts = np.zeros((T, K), int)
    np.add.at(counts, (t, k), 1)
    if starts is None:
        starts = []
        for j in range(K):
            m = k == j
            Qc, pc, _, _, ok = single_sensor_starts(n[m], L[m], e[m], t[m], T, B)
            starts.append((Qc, pc, ok))
    oks = np.stack([s[2] for s in starts], 1)
    best = np.argmax(np.where(oks, counts, -1), axis=1)
    good = oks[np.arange(T), best]
    Q = np.tile(np.eye(3), (T, 1, 1))
    p = np.full((T, 3), np.nan)
    cost = np.full(T, np.inf)
    other = np.full(T, np.inf)
    H = np.full((T, 6, 6), np.nan)
    if not good.any():
        return Q, p, cost, other, H, good, counts
    g = np.flatnonzero(good)
    sel = good[t]
    remap = -np.ones(T, int)
    remap[g] = np.arange(len(g))
    kk, ee, tt, nn, LL = k[sel], e[sel], remap[t[sel]], n[sel], L[sel]
    Qw = np.zeros((len(g), 3, 3))
    pw = np.zeros((len(g), 3))
    for j in range(K):
        m = best[g] == j
        Qw[m] = Rs[j].T @ starts[j][0][g[m]]
        pw[m] = starts[j][1][g[m]] @ Rs[j] + cs[j]
    Qa, pa, ca, Ha = tag_gauss_newton(Rs, cs, Qw, pw, B, kk, tt, ee, nn, LL, len(g))
    los = pw - cs[best[g]]
    los /= np.maximum(np.linalg.norm(los, axis=1, keepdims=True), 1e-300)
    Qm = _mirror_rotation(Qw, los, B)
    pm = pw + np.einsum("tij,j->ti", Qw, B.mean(0)) - np.einsum("tij,j->ti", Qm, B.mean(0))
    Qb, pb, cb, Hb = tag_gauss_newton(Rs, cs, Qm, pm, B, kk, tt, ee, nn, LL, len(g))
    use_b = cb < ca
    Q[g] = np.where(use_b[:, None, None], Qb, Qa)
    p[g] = np.where(use_b[:, None], pb, pa)
    cost[g] = np.where(use_b, cb, ca)
    oth = np.where(use_b, ca, cb)
    same = np.linalg.norm(r_from_R_batch(Qa @ np.swapaxes(Qb, 1, 2)), axis=1) < 1e-6
    other[g] = np.where(same, cost[g], oth)
    H[g] = np.where(use_b[:, None, None], Hb, Ha)
    return Q, p, cost, other, H, good, counts


def _mirror_rotation(Q, los, B):
    """The tag turned so that its plane's tilt about the line of sight is mirrored (the other PnP branch)."""
    normal = np.linalg.svd(B - B.mean(0))[2][2]  # the plane's normal (the thinnest direction of a 3D tag)
    nw = np.einsum("tij,j->ti", Q, normal)  # the plane's normal in the world
    # reflect the normal about the line of sight: n' = 2 (n.l) l - n; rotate Q by the turn taking n to n'
    n2 = 2 * np.einsum("ti,ti->t", nw, los)[:, None] * los - nw
    ax = np.cross(nw, n2)
    sn = np.linalg.norm(ax, axis=1)
    ang = np.arctan2(sn, np.einsum("ti,ti->t", nw, n2))
    w = np.where(sn[:, None] > 1e-12, ax / np.where(sn > 1e-12, sn, 1.0)[:, None], 0.0) * ang[:, None]
    return exp_so3(w) @ Q


def _jacobians(Rs, cs, Q, p, B, k, t, e, n, L):
    from psdcal.measure._rigid import residuals_and_jacobians

    return residuals_and_jacobians(Rs, cs, Q, p, B, k, t, e, n, L)


def write_tag_poses(path, res: TagPoses) -> None:
    """``psdcal tag-pose``'s CSV (columns of :meth:`TagPoses.columns`)."""
    from psdcal._atomic import write_text_atomic

    cols = res.columns()
    names = list(cols)
    lines = [",".join(names)]
    for i in range(len(res.t_s)):
        cells = []
        for nm in names:
            v = cols[nm][i]
            cells.append(str(int(v)) if nm in ("dof", "n_sensors", "ambiguous") else f"{float(v):.10g}")
        lines.append(",".join(cells))
    write_text_atomic(path, "\n".join(lines) + "\n")


__all__ = ["CommonModeTest", "KnownSensor", "Tag", "TagPoses", "common_mode_test", "load_sensor_poses", "read_tag", "single_sensor_starts", "tag_poses",
           "write_tag_poses"]
