"""Levenberg-Marquardt refinement of intrinsics, distortion and all poses (Section 3.1).

Two costs (docs/model.md#refinement):

- ``image``: residual ``G(distort(project(P))) - d`` in mm on the sensor, the
  maximum-likelihood estimate when the noise is on the measured points
  (``G`` is the channel-gain readout map, identity unless gains are fitted);
- ``template``: the paper's Eq 29, residual ``backproject(undistort(d)) - P``
  in mm on the template plate.

Both come with analytic Jacobians assembled per point from the chain rule:
the pose columns of a point are non-zero only for its own image (the
block-sparse structure), and the distortion map's Jacobian follows from the
implicit function theorem (:func:`psdcal.model.distortion.distort_jacobians`).
The problem is solved by :func:`levenberg_marquardt` on the normal equations
with Marquardt's scaling (MINPACK's QR of the whole Jacobian is several times
slower for these sizes; scipy's ``least_squares`` remains available to
cross-check, see the tests).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psdcal.model.distortion import distort, distort_jacobians, undistort
from psdcal.model.params import DISTORTION_NAMES, Distortion, Intrinsics, ModelSpec
from psdcal.model.readout import LX_MM, LY_MM, gain_homography, gain_map

_INTR_COLS = {"f_mm": 0, "cx_mm": 1, "cy_mm": 2, "skew": 3, "fy_mm": 4}
_GAIN_IDX = {"g_x2": 1, "g_y1": 2, "g_y2": 3}


@dataclass(frozen=True)
class SolverOptions:
    """Settings of the LM solver.

    Attributes
    ----------
    ftol, xtol, gtol : float
        Tolerances of :func:`levenberg_marquardt`: relative reduction of the
        cost, relative scaled step, scaled gradient. A relative cost change of
        1e-12 puts the parameters within ~1e-5 standard errors of the optimum
        on noisy data; noiseless data converge quadratically to round-off.
    max_iterations : int
        Maximum number of Jacobian evaluations (LM iterations).
    """

    ftol: float = 1e-12
    xtol: float = 1e-12
    gtol: float = 1e-12
    max_iterations: int = 200


def rodrigues_batch(r, *, derivatives: bool = True):
    """Rotations R (n, 3, 3) and their derivatives dR (n, 3, 3, 3) (dR[:, k] = dR/dr_k).

    With ``derivatives=False`` dR is None.
    """
    r = np.asarray(r, dtype=float)
    n = r.shape[0]
    theta = np.linalg.norm(r, axis=1)
    K = np.zeros((n, 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -r[:, 2], r[:, 1]
    K[:, 1, 0], K[:, 1, 2] = r[:, 2], -r[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -r[:, 1], r[:, 0]
    small = theta < 1e-12
    th = np.where(small, 1.0, theta)
    A = np.where(small, 1.0, np.sin(th) / th)
    B = np.where(small, 0.5, (1 - np.cos(th)) / th**2)
    R = np.eye(3) + A[:, None, None] * K + B[:, None, None] * (K @ K)
    if not derivatives:
        return R, None
    IR = np.eye(3) - R
    dR = np.empty((n, 3, 3, 3))
    for k in range(3):
        w = np.cross(r, IR[:, :, k])
        W = np.zeros((n, 3, 3))
        W[:, 0, 1], W[:, 0, 2] = -w[:, 2], w[:, 1]
        W[:, 1, 0], W[:, 1, 2] = w[:, 2], -w[:, 0]
        W[:, 2, 0], W[:, 2, 1] = -w[:, 1], w[:, 0]
        dR[:, k] = ((r[:, k, None, None] * K + W) / th[:, None, None] ** 2) @ R
        if np.any(small):
            E = np.zeros((3, 3))
            e = np.eye(3)[k]
            E[0, 1], E[0, 2], E[1, 0], E[1, 2], E[2, 0], E[2, 1] = -e[2], e[1], e[2], -e[0], -e[1], e[0]
            dR[small, k] = E
    return R, dR


@dataclass(frozen=True)
class Problem:
    """A calibration problem in the solver's terms.

    Attributes
    ----------
    template_mm : (M, 2)
    points_mm : (n_images, M, 2), NaN where missing.
    spec : ModelSpec
    cost : "image" | "template"
    fixed_intrinsics, fixed_distortion, fixed_gains :
        Values of the parameters that are not free (and the start of the free ones).
    fixed : names of global parameters of ``spec`` held at their start value
        (``calibrate(fix=...)``); they leave the state vector.
    """

    template_mm: np.ndarray
    points_mm: np.ndarray
    spec: ModelSpec
    cost: str = "image"
    sensor_mm: tuple[float, float] = (LX_MM, LY_MM)
    fixed: tuple = ()
    valid: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "valid", np.all(np.isfinite(self.points_mm), axis=-1))

    @property
    def n_images(self) -> int:
        return self.points_mm.shape[0]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(n for n in self.spec.global_names if n not in self.fixed)

    @property
    def n_global(self) -> int:
        return len(self.names)

    # -- state vector ---------------------------------------------------------------
    def pack(self, intr: Intrinsics, dist: Distortion, gains, rvecs, tvecs) -> np.ndarray:
        vals = {**intr.to_dict(), **dist.to_dict()}
        if "fy_mm" in self.names and intr.fy_mm is None:
            vals["fy_mm"] = intr.f_mm
        g = np.asarray(gains, dtype=float) / float(gains[0])
        vals.update({"g_x2": g[1], "g_y1": g[2], "g_y2": g[3]})
        head = np.array([vals[n] for n in self.names], dtype=float)
        poses = np.concatenate([np.asarray(rvecs, float), np.asarray(tvecs, float)], axis=1).ravel()
        return np.concatenate([head, poses])

    def unpack(self, z, base_intr: Intrinsics, base_dist: Distortion, base_gains):
        vals = dict(zip(self.names, z[: self.n_global]))
        intr = Intrinsics(
            f_mm=float(vals.get("f_mm", base_intr.f_mm)),
            cx_mm=float(vals.get("cx_mm", base_intr.cx_mm)),
            cy_mm=float(vals.get("cy_mm", base_intr.cy_mm)),
            skew=float(vals.get("skew", base_intr.skew if self.spec.skew else 0.0)),
            fy_mm=float(vals["fy_mm"]) if "fy_mm" in vals else (base_intr.fy_mm if self.spec.aspect else None),
        )
        coef = base_dist.as_array().copy()
        for i, n in enumerate(DISTORTION_NAMES):
            if n in vals:
                coef[i] = vals[n]
        gains = np.asarray(base_gains, dtype=float).copy()
        for n, i in _GAIN_IDX.items():
            if n in vals:
                gains[i] = vals[n]
        poses = z[self.n_global :].reshape(self.n_images, 6)
        return intr, coef, gains, poses[:, :3], poses[:, 3:]


def _global_columns(names, d_dintr5, d_dcoef7, d_dgains4=None):
    """Assemble (N, 2, n_global) from per-parameter derivative stacks."""
    cols = []
    for n in names:
        if n in _INTR_COLS:
            cols.append(d_dintr5[..., _INTR_COLS[n]])
        elif n in _GAIN_IDX:
            cols.append(d_dgains4[..., _GAIN_IDX[n]])
        else:
            cols.append(d_dcoef7[..., DISTORTION_NAMES.index(n)])
    return np.stack(cols, axis=-1)


class Evaluator:
    """Residuals and Jacobian of a :class:`Problem` at a state vector (cached per state)."""

    def __init__(self, prob: Problem, base_intr: Intrinsics, base_dist: Distortion, base_gains):
        self.prob = prob
        self.base = (base_intr, base_dist, np.asarray(base_gains, dtype=float))
        self.img_idx, self.pt_idx = np.nonzero(prob.valid)
        self.d_meas = prob.points_mm[self.img_idx, self.pt_idx]
        self.P = prob.template_mm[self.pt_idx]
        self._key = None
        self._val = None
        self._rkey = self._rval = None
        self._dkey = self._dval = self._yval = None
        self._anchor = None
        self._kernel = self._tkernel = self._normal = None  # compiled image / template cost
        if prob.cost == "image" or not prob.spec.fit_gains:
            from psdcal import _jit

            if _jit.enabled():  # the compiled costs (psdcal.calibration._image_kernel); this class's numpy code is their reference
                from psdcal.calibration._image_kernel import global_map, image_model, normal_equations, template_model

                if prob.cost == "image":
                    self._kernel = image_model
                else:
                    self._tkernel = template_model
                self._normal = normal_equations
                self._gmap = global_map(prob.names)
                self._no_warm = np.full(self.d_meas.shape, np.nan)
                self._separate_fy = prob.spec.aspect
                skew = base_intr.skew if prob.spec.skew else 0.0
                self._theta0 = np.array([base_intr.f_mm, base_intr.cx_mm, base_intr.cy_mm, skew, base_intr.fy,
                                         *base_dist.as_array(), *np.asarray(base_gains, dtype=float)], dtype=float)
                if prob.spec.fit_gains:  # gain_homography is linear in the gains: its values at the unit vectors
                    self._gain_basis = np.stack([gain_homography(e, *prob.sensor_mm) for e in np.eye(4)])
                else:
                    self._gain_basis = np.zeros((0, 3, 3))

    def unpack(self, z):
        return self.prob.unpack(z, *self.base)

    def residuals(self, z):
        """Residuals only (the trial points of LM need no Jacobian)."""
        key = z.tobytes()
        if key == self._key:
            return self._val[0]
        if self.prob.cost == "image":
            r = (self.model_points(z) - self.d_meas).ravel()
        elif self._tkernel is not None:
            r = self._template_compiled(z, want_jac=False)[0]
        else:
            intr, coef, gains, rv, tv = self.unpack(z)
            x = undistort(self.d_meas, coef, intr.c)
            R = self._rotations(rv, derivatives=False)[0]
            Mm = np.concatenate([R[:, :, :2], tv[:, :, None]], axis=2)
            Hinv = np.linalg.inv(intr.matrix() @ Mm)
            q = np.einsum("nij,nj->ni", Hinv[self.img_idx], np.concatenate([x, np.ones((x.shape[0], 1))], axis=1))
            r = (q[:, :2] / q[:, 2:3] - self.P).ravel()
        return np.where(np.isfinite(r), r, 1e3)

    def evaluate(self, z):
        """Residuals and Jacobian at ``z`` (cached for the last state)."""
        key = z.tobytes()
        if key == self._key:
            return self._val
        if self._kernel is not None:
            d, J = self._compiled(z, key, want_jac=True)
            val = ((d - self.d_meas).ravel(), J)
        elif self._tkernel is not None:
            val = self._template_compiled(z, want_jac=True)
        elif self.prob.cost == "image":
            val = self._image(z)
        else:
            val = self._template(z)
        r, J = val
        bad = ~np.isfinite(r)
        if np.any(bad):
            r = np.where(bad, 1e3, r)
            J = np.where(bad[:, None], 0.0, J)
            J = np.nan_to_num(J)
            val = (r, J)
        self._key, self._val = key, val
        return val

    def jacobian(self, z):
        return self.evaluate(z)[1]

    def normal_equations(self, J, r):
        """``(J^T J, J^T r)``, from the block structure when the kernel is compiled."""
        if self._normal is not None:
            return self._normal(J, r, self.img_idx, self._gmap.size)
        return J.T @ J, J.T @ r

    def _theta(self, z):
        """The 16 global parameters of the compiled kernels (psdcal.calibration._image_kernel.GLOBAL_ORDER)."""
        theta = self._theta0.copy()
        theta[self._gmap] = z[: self._gmap.size]
        return theta

    def _poses(self, z):
        return z[self._gmap.size :].reshape(-1, 6)

    def _rotations(self, rv, derivatives: bool = True):
        """R, dR of all poses, cached for the last rotation vectors (dR only when asked)."""
        key = rv.tobytes()
        if self._rkey != key or (derivatives and self._rval[1] is None):
            self._rkey, self._rval = key, rodrigues_batch(rv, derivatives=derivatives)
        return self._rval

    # -- image-plane cost --------------------------------------------------------------
    def _ideal(self, z, derivatives: bool = True):
        """Ideal image points x (N, 2) of the template and what their Jacobians need."""
        intr, coef, gains, rv, tv = self.unpack(z)
        R, dR = self._rotations(rv, derivatives)
        ii = self.img_idx
        Pc = np.einsum("nij,nj->ni", R[ii][:, :, :2], self.P) + tv[ii]
        xn, yn = Pc[:, 0] / Pc[:, 2], Pc[:, 1] / Pc[:, 2]
        x = np.stack([intr.f_mm * xn + intr.skew * yn + intr.cx_mm, intr.fy * yn + intr.cy_mm], axis=1)
        return intr, coef, gains, dR, Pc, xn, yn, x

    def _solve_distort(self, key, x, coef, c):
        """d with undistort(d) = x by Newton, warm-started and cached per state.

        Starts from the solution at the last Jacobian evaluation (MINPACK
        evaluates Jacobians only at accepted points, so it is near), then from
        the measured points, then from the default start.
        """
        if self._dkey == key:
            return self._dval
        d = np.full(x.shape, np.nan)
        todo = np.arange(x.shape[0])
        starts = [st for st in (self._anchor, self.d_meas) if st is not None] + [None]
        for st in starts:
            res = distort(x[todo], coef, c, d0_mm=None if st is None else st[todo], keep_failed=True)
            d[todo] = res.d_mm
            todo = todo[~res.converged]
            if todo.size == 0:
                break
        self._dkey, self._dval = key, d
        return d

    def _compiled(self, z, key, want_jac):
        """Modelled points d (N, 2) (and the Jacobian) by the compiled kernel.

        The Newton inverse starts from the solution at this state when it is
        cached (a Jacobian at the point whose residuals were just taken),
        otherwise from that of the last Jacobian evaluation.
        """
        if self._dkey == key:
            warm = self._dval
        else:
            warm = self._anchor if self._anchor is not None else self._no_warm
        d, ok, y, J = self._kernel(
            self.P, self.img_idx, self._theta(z), self._separate_fy, self._poses(z), warm, self.d_meas,
            self._gmap, want_jac, 1e-13, 50, self._gain_basis,
        )
        self._dkey, self._dval, self._yval = key, d, y
        if want_jac:
            self._anchor = d
        return y, J

    def _template_compiled(self, z, want_jac):
        """Residuals (2N,) of the template cost and their Jacobian by the compiled kernel."""
        return self._tkernel(self.P, self.img_idx, self._theta(z), self._separate_fy, self._poses(z), self.d_meas,
                             self._gmap, want_jac)

    def model_points(self, z):
        """Modelled measured points (N, 2) of the valid observations, mm on the sensor."""
        if self._kernel is not None:
            key = z.tobytes()
            return self._yval if self._dkey == key else self._compiled(z, key, want_jac=False)[0]
        intr, coef, gains, dR, Pc, xn, yn, x = self._ideal(z, derivatives=False)
        d = self._solve_distort(z.tobytes(), x, coef, intr.c)
        if self.prob.spec.fit_gains:
            d = gain_map(d, gains, *self.prob.sensor_mm)
        return d

    def _image(self, z):
        prob = self.prob
        intr, coef, gains, dR, Pc, xn, yn, x = self._ideal(z)
        ii = self.img_idx
        P = self.P
        Z = Pc[:, 2]
        f, fy, s = intr.f_mm, intr.fy, intr.skew
        d = self._solve_distort(z.tobytes(), x, coef, intr.c)
        self._anchor = d
        dd_dx, dd_dc, dd_dcoef = distort_jacobians(d, coef, intr.c)
        N = d.shape[0]
        zero, one = np.zeros(N), np.ones(N)
        separate_fy = intr.fy_mm is not None
        # dx/d(f, cx, cy, skew, fy)  (Eq 4)
        dx_dintr = np.stack(
            [
                np.stack([xn, zero if separate_fy else yn], 1),
                np.stack([one, zero], 1),
                np.stack([zero, one], 1),
                np.stack([yn, zero], 1),
                np.stack([zero, yn if separate_fy else zero], 1),
            ],
            axis=-1,
        )
        dd_dintr = dd_dx @ dx_dintr
        dd_dintr[:, :, 1:3] += dd_dc
        if prob.spec.fit_gains:
            y, dy_dd, dy_dg = gain_map(d, gains, *prob.sensor_mm, jacobians=True)
        else:
            y, dy_dd, dy_dg = d, None, None
        iz = 1.0 / Z
        dx_dPc = np.empty((N, 2, 3))
        dx_dPc[:, 0, 0] = f * iz
        dx_dPc[:, 0, 1] = s * iz
        dx_dPc[:, 0, 2] = -(f * xn + s * yn) * iz
        dx_dPc[:, 1, 0] = 0.0
        dx_dPc[:, 1, 1] = fy * iz
        dx_dPc[:, 1, 2] = -fy * yn * iz
        dd_dPc = dd_dx @ dx_dPc
        dPc_dr = np.einsum("nkij,nj->nik", dR[ii][:, :, :, :2], P)
        dd_dr = dd_dPc @ dPc_dr
        G = _global_columns(prob.names, dd_dintr, dd_dcoef, dy_dg)
        if prob.spec.fit_gains:
            # chain through the readout map for everything upstream of d
            nongain = [k for k, n in enumerate(prob.names) if n not in _GAIN_IDX]
            G[:, :, nongain] = dy_dd @ G[:, :, nongain]
            dd_dr = dy_dd @ dd_dr
            dd_dPc = dy_dd @ dd_dPc
        r = (y - self.d_meas).ravel()
        J = self._assemble(G, dd_dr, dd_dPc)
        return r, J

    def _assemble(self, G, d_dr, d_dt):
        prob = self.prob
        N = G.shape[0]
        ng = prob.n_global
        J = np.zeros((N, 2, ng + 6 * prob.n_images))
        J[:, :, :ng] = G
        rows = np.arange(N)
        base = ng + 6 * self.img_idx
        for k in range(3):
            J[rows, :, base + k] = d_dr[:, :, k]
            J[rows, :, base + 3 + k] = d_dt[:, :, k]
        return J.reshape(2 * N, -1)

    # -- template-plane cost (Eq 29) ---------------------------------------------------
    def _template(self, z):
        prob = self.prob
        intr, coef, gains, rv, tv = self.unpack(z)
        R, dR = rodrigues_batch(rv)
        ii = self.img_idx
        x, _, dx_dc, dx_dcoef = undistort(self.d_meas, coef, intr.c, jacobians=True)
        N = x.shape[0]
        Mm = np.concatenate([R[:, :, :2], tv[:, :, None]], axis=2)  # (n, 3, 3) = [r1 r2 t]
        A = intr.matrix()
        Hinv = np.linalg.inv(A @ Mm)  # (n, 3, 3)
        Minv = np.linalg.inv(Mm)
        xt = np.concatenate([x, np.ones((N, 1))], axis=1)
        q = np.einsum("nij,nj->ni", Hinv[ii], xt)
        Phat = q[:, :2] / q[:, 2:3]
        r = (Phat - self.P).ravel()
        iq2 = 1.0 / q[:, 2]
        dP_dq = np.zeros((N, 2, 3))
        dP_dq[:, 0, 0] = iq2
        dP_dq[:, 1, 1] = iq2
        dP_dq[:, 0, 2] = -q[:, 0] * iq2 * iq2
        dP_dq[:, 1, 2] = -q[:, 1] * iq2 * iq2
        mq = np.einsum("nij,nj->ni", Mm[ii], q)  # M q, with A M q = x~
        zero = np.zeros(N)
        separate_fy = intr.fy_mm is not None
        # d(x~)/dtheta - dA/dtheta (M q), for theta in (f, cx, cy, skew, fy)
        v_f = np.stack([-mq[:, 0], zero if separate_fy else -mq[:, 1], zero], 1)
        v_cx = np.stack([dx_dc[:, 0, 0] - mq[:, 2], dx_dc[:, 1, 0], zero], 1)
        v_cy = np.stack([dx_dc[:, 0, 1], dx_dc[:, 1, 1] - mq[:, 2], zero], 1)
        v_s = np.stack([-mq[:, 1], zero, zero], 1)
        v_fy = np.stack([zero, -mq[:, 1] if separate_fy else zero, zero], 1)
        V = np.stack([v_f, v_cx, v_cy, v_s, v_fy], axis=-1)  # (N, 3, 5)
        Hi = Hinv[ii]
        dq_dintr = Hi @ V
        dxt_dcoef = np.concatenate([dx_dcoef, np.zeros((N, 1, 7))], axis=1)
        dq_dcoef = Hi @ dxt_dcoef
        G = _global_columns(prob.names, dP_dq @ dq_dintr, dP_dq @ dq_dcoef)
        # poses: dq = -M^-1 (dM q)
        Mi = Minv[ii]
        dMq_dr = np.einsum("nkij,nj->nik", dR[ii][:, :, :, :2], q[:, :2])  # (N, 3, 3)
        dq_dr = -Mi @ dMq_dr
        dq_dt = -Mi * q[:, 2, None, None]
        return r, self._assemble(G, dP_dq @ dq_dr, dP_dq @ dq_dt)


@dataclass(frozen=True)
class RefineResult:
    """Raw output of :func:`refine`."""

    z: np.ndarray
    intrinsics: Intrinsics
    coeffs: np.ndarray
    gains: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray
    covariance: np.ndarray  # (n_params, n_params) of the full state
    sigma2: float  # residual variance of the minimised cost, its unit^2
    cost_rms: float
    iterations: int
    converged: bool
    message: str
    jacobian: np.ndarray
    residuals: np.ndarray
    model_mm: np.ndarray | None = None  # (N, 2) modelled points of the valid observations (image cost)


def refine(prob: Problem, intr0: Intrinsics, dist0: Distortion, gains0, rvecs0, tvecs0, options: SolverOptions = SolverOptions()) -> RefineResult:
    """Minimise the chosen cost over the free intrinsics, distortion, gains and all poses.

    The covariance is ``sigma^2 (J^T J)^-1`` at the solution with
    ``sigma^2 = |r|^2 / (m - n)`` (m residuals, n parameters), in the units of
    the minimised cost.
    """
    ev = Evaluator(prob, intr0, dist0, gains0)
    z0 = prob.pack(intr0, dist0, gains0, rvecs0, tvecs0)
    m = 2 * len(ev.img_idx)
    n = z0.size
    if m < n:
        from psdcal.errors import DegenerateViewsError

        raise DegenerateViewsError(f"{m // 2} observed points give {m} equations for {n} unknowns: add images or points")
    with _single_threaded_blas():
        sol = levenberg_marquardt(ev.residuals, ev.jacobian, z0, options, normal=ev.normal_equations)
        r, J = ev.evaluate(sol.x)
        return _finish(prob, ev, sol, r, J, m, n, options)


def _single_threaded_blas():
    """Small dense problems run fastest on one BLAS thread (and do not fight
    other processes of a Monte Carlo run for cores)."""
    global _CONTROLLER
    try:
        if _CONTROLLER is None:
            from threadpoolctl import ThreadpoolController

            _CONTROLLER = ThreadpoolController()
        return _CONTROLLER.limit(limits=1, user_api="blas")
    except Exception:  # threadpoolctl missing or unable to introspect: run as is
        import contextlib

        return contextlib.nullcontext()


_CONTROLLER = None


@dataclass(frozen=True)
class LMResult:
    """Outcome of :func:`levenberg_marquardt`."""

    x: np.ndarray
    cost: float
    status: int  # > 0 converged (1 gradient, 2 step, 3 cost reduction, 4 zero residual), 0 limit reached
    message: str
    njev: int
    nfev: int


def levenberg_marquardt(fun, jac, x0, options: SolverOptions = SolverOptions(), normal=None) -> LMResult:
    """Levenberg-Marquardt on the normal equations with Marquardt's scaling.

    Minimises ``0.5 |fun(x)|^2``. Each iteration solves
    ``(J^T J + mu D) h = -J^T r`` by Cholesky, where ``D`` is the running
    maximum of ``diag(J^T J)`` (scale invariance, as in MINPACK); the damping
    ``mu`` follows Nielsen's rule (Madsen, Nielsen & Tingleff, *Methods for
    non-linear least squares problems*, 2004, Algorithm 3.16). The Jacobian
    is evaluated only at accepted points; trial points need residuals only.
    For the small calibration problems (tens to hundreds of unknowns) this is
    several times faster than MINPACK's QR of the full Jacobian.

    Stops with status 1 when ``max_j |(J^T r)_j| / (|J_j| |r|) <= gtol``
    (MINPACK's gradient test), 2 when the scaled step is below ``xtol``
    times the scaled state, 3 when the actual and predicted relative
    reductions of the cost are both below ``ftol``, 4 on a zero residual, and
    0 (not converged) when ``max_iterations`` Jacobians have been evaluated.

    ``normal(J, r)``, when given, returns ``(J^T J, J^T r)`` (e.g. exploiting
    the sparsity of J); by default they are dense products.
    """
    if normal is None:
        def normal(J, r):
            return J.T @ J, J.T @ r

    from scipy.linalg.lapack import dpotrf, dpotrs  # Cholesky straight from LAPACK: these systems are small

    x = np.asarray(x0, dtype=float).copy()
    r = fun(x)
    J = jac(x)
    nfev, njev = 1, 1
    F = 0.5 * float(r @ r)
    A, g = normal(J, r)
    D = np.maximum(np.diag(A).copy(), 1e-300)
    diag = np.arange(x.size) * (x.size + 1)  # flat indices of the diagonal
    mu = 1e-8  # start near Gauss-Newton, like MINPACK's large initial trust region: a damped
    # first step from a poor closed-form start (C off by mm, Lens 1) can walk into a local minimum
    nu = 2.0
    status, message = 0, "iteration limit reached"
    max_nfev = 4 * options.max_iterations + 10
    while njev <= options.max_iterations and nfev < max_nfev:
        if F == 0.0:
            status, message = 4, "zero residual"
            break
        colnorm = np.sqrt(np.maximum(A.flat[diag], 1e-300))
        if np.max(np.abs(g) / colnorm) <= options.gtol * np.sqrt(2 * F):
            status, message = 1, "gradient below gtol"
            break
        Ad = A.copy()
        Ad.flat[diag] += mu * D
        L, info = dpotrf(Ad, lower=1, clean=0, overwrite_a=1)
        if info != 0:  # not positive definite at this damping
            mu *= nu
            nu *= 2.0
            continue
        h, info = dpotrs(L, g, lower=1)
        h = -h
        sD = np.sqrt(D)
        if np.sqrt((sD * h) @ (sD * h)) <= options.xtol * (np.sqrt((sD * x) @ (sD * x)) + options.xtol):
            status, message = 2, "step below xtol"
            break
        x_new = x + h
        r_new = fun(x_new)
        nfev += 1
        F_new = 0.5 * float(r_new @ r_new)
        pred = 0.5 * float(h @ (mu * D * h - g))
        rho = (F - F_new) / pred if pred > 0 else -1.0
        if rho > 0 and np.isfinite(F_new):
            small = (F - F_new) <= options.ftol * F and pred <= options.ftol * F
            x, r, F = x_new, r_new, F_new
            J = jac(x)
            njev += 1
            A, g = normal(J, r)
            D = np.maximum(D, A.flat[diag])
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if small:
                status, message = 3, "relative cost reduction below ftol"
                break
        else:
            mu *= nu
            nu *= 2.0
            if not np.isfinite(mu) or mu > 1e200:
                status, message = 2, "no further progress possible (damping overflow)"
                break
    return LMResult(x=x, cost=F, status=status, message=message, njev=njev, nfev=nfev)


def _finish(prob, ev, sol, r, J, m, n, options):
    dof = max(m - n, 1)
    sigma2 = float(r @ r) / dof
    JtJ = ev.normal_equations(J, r)[0]
    try:
        cov = sigma2 * np.linalg.inv(JtJ)
    except np.linalg.LinAlgError:
        cov = sigma2 * np.linalg.pinv(JtJ)
    intr, coef, gains, rv, tv = ev.unpack(sol.x)
    iterations = int(sol.njev) if sol.njev is not None else int(sol.nfev)
    converged = bool(sol.status > 0) and bool(np.all(np.isfinite(sol.x))) and iterations <= options.max_iterations
    return RefineResult(
        z=sol.x,
        intrinsics=intr,
        coeffs=coef,
        gains=gains,
        rvecs=rv,
        tvecs=tv,
        covariance=cov,
        sigma2=sigma2,
        cost_rms=float(np.sqrt(np.mean(r**2)) * np.sqrt(2.0)),
        iterations=iterations,
        converged=converged,
        message=str(sol.message),
        jacobian=J,
        residuals=r,
        model_mm=ev.model_points(sol.x) if prob.cost == "image" else None,
    )
