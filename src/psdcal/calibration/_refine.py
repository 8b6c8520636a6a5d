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
(:mod:`._normal`: dense, or block-sparse through the Schur complement of the poses)
with Marquardt's scaling (MINPACK's QR of the whole Jacobian is several times
slower for these sizes; scipy's ``least_squares`` remains available to
cross-check, see the tests).
"""
from __future__ import annotations

import contextlib
import functools
import math
import threading
from dataclasses import dataclass, field

import numpy as np

from psdcal import _jit
from psdcal._cache import cached_attribute
from psdcal.calibration._lm import LMResult, SolverOptions, levenberg_marquardt  # noqa: F401 (re-exported)
from psdcal.calibration._normal import BlockNormal, block_normal_reference, compact_from_dense
from psdcal.model.distortion import distort, distort_jacobians, undistort
from psdcal.model.params import DISTORTION_NAMES, Distortion, Intrinsics, ModelSpec
from psdcal.model.readout import LX_MM, LY_MM, gain_homography, gain_map

_INTR_COLS = {"f_mm": 0, "cx_mm": 1, "cy_mm": 2, "skew": 3, "fy_mm": 4}
_GAIN_IDX = {"g_x2": 1, "g_y1": 2, "g_y2": 3}


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
        p = np.asarray(self.points_mm)  # both coordinates finite (written out: a reduction over a last axis of 2 is slow)
        object.__setattr__(self, "valid", np.isfinite(p[..., 0]) & np.isfinite(p[..., 1]))

    @property
    def n_images(self) -> int:
        return self.points_mm.shape[0]

    @cached_attribute
    def names(self) -> tuple[str, ...]:
        return tuple(n for n in self.spec.global_names if n not in self.fixed)

    @cached_attribute
    def n_global(self) -> int:
        return len(self.names)

    # -- state vector ---------------------------------------------------------------
    def pack(self, intr: Intrinsics, dist: Distortion, gains, rvecs, tvecs) -> np.ndarray:
        g = np.asarray(gains, dtype=float) / float(gains[0])  # (no dicts, no concatenations: packed per refinement)
        head = [intr.fy if n == "fy_mm" else getattr(intr, n) if n in _INTR_COLS
                else g[_GAIN_IDX[n]] if n in _GAIN_IDX else getattr(dist, n) for n in self.names]
        rv = np.asarray(rvecs, dtype=float)
        z = np.empty(len(head) + 6 * rv.shape[0])
        z[:len(head)] = head
        poses = z[len(head):].reshape(rv.shape[0], 6)  # (a view of z)
        poses[:, :3], poses[:, 3:] = rv, tvecs
        return z

    def unpack(self, z, base_intr: Intrinsics, base_dist: Distortion, base_gains):
        zg = z[: self.n_global].tolist()  # (positions from _unpack_slots: no dict of the names per call)
        i_f, i_cx, i_cy, i_skew, i_fy = self._unpack_slots[0]
        intr = Intrinsics(
            f_mm=float(zg[i_f] if i_f >= 0 else base_intr.f_mm),
            cx_mm=float(zg[i_cx] if i_cx >= 0 else base_intr.cx_mm),
            cy_mm=float(zg[i_cy] if i_cy >= 0 else base_intr.cy_mm),
            skew=float(zg[i_skew] if i_skew >= 0 else (base_intr.skew if self.spec.skew else 0.0)),
            fy_mm=float(zg[i_fy]) if i_fy >= 0 else (base_intr.fy_mm if self.spec.aspect else None),
        )
        coef = base_dist.as_array()  # a new array
        gains = np.array(base_gains, dtype=float)  # a copy
        for i, k in self._unpack_slots[1]:
            if i < 0:
                gains[-i] = zg[k]
            else:
                coef[i] = zg[k]
        poses = z[self.n_global :].reshape(self.n_images, 6)
        return intr, coef, gains, poses[:, :3], poses[:, 3:]

    @cached_attribute
    def _unpack_slots(self) -> tuple:
        """Where :meth:`unpack` finds each free parameter in the state vector: the positions of ``f_mm``,
        ``cx_mm``, ``cy_mm``, ``skew``, ``fy_mm`` (-1: not free) and ``(i, position)`` of each of
        :attr:`_free_slots`."""
        pos = {n: k for k, n in enumerate(self.names)}
        return (tuple(pos.get(n, -1) for n in ("f_mm", "cx_mm", "cy_mm", "skew", "fy_mm")),
                tuple((i, pos[n]) for i, n in self._free_slots))

    @cached_attribute
    def _free_slots(self) -> tuple:
        """``(i, name)`` of the free distortion terms (``i``: index in DISTORTION_NAMES) and gains (``-i``: index
        in the four gains, 1-3)."""
        free = set(self.names)
        return (tuple((i, n) for i, n in enumerate(DISTORTION_NAMES) if n in free)
                + tuple((-i, n) for n, i in _GAIN_IDX.items() if n in free))

    @cached_attribute
    def kernel_constants(self) -> tuple:
        """What the compiled kernels take of this problem: ``gmap`` for :attr:`names`
        (psdcal.calibration._image_kernel.global_map), an all-NaN warm start (N, 2) (none) and the gain basis
        ((4, 3, 3) when the gains are fitted: gain_homography is linear in the gains, these are its values at
        the unit vectors; else (0, 3, 3)). Do not modify them."""
        from psdcal.calibration._image_kernel import global_map

        if self.spec.fit_gains:
            basis = np.stack([gain_homography(e, *self.sensor_mm) for e in np.eye(4)])
        else:
            basis = np.zeros((0, 3, 3))
        return global_map(self.names), np.full(self.observations[2].shape, np.nan), basis

    @cached_attribute
    def observations(self) -> tuple:
        """``(img_idx, pt_idx, d_meas, P)``: view (N,) and template point (N,) of each valid observation, its
        measured point (N, 2) and template point (N, 2), mm (computed once per problem; do not modify)."""
        if not self.valid.all():
            img_idx, pt_idx = np.nonzero(self.valid)
            return img_idx, pt_idx, self.points_mm[img_idx, pt_idx], self.template_mm[pt_idx]
        n, M = self.valid.shape  # every point seen: np.nonzero's arrays (columns of one (N, 2) array) without a search
        idx = np.empty((n, M, 2), dtype=np.intp)  # (filled by broadcasting: no repeat / tile temporaries)
        idx[:, :, 0] = np.arange(n)[:, None]
        idx[:, :, 1] = np.arange(M)
        P = np.empty((n, M, 2))
        P[:] = self.template_mm
        idx = idx.reshape(n * M, 2)
        return idx[:, 0], idx[:, 1], self.points_mm.reshape(n * M, 2).copy(), P.reshape(n * M, 2)


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


@functools.cache
def _compiled_costs() -> tuple:
    """The compiled image cost, normal equations, template cost and block normal equations (imported once)."""
    from psdcal.calibration import _gram_kernel, _image_kernel as ik
    return ik.image_model, ik.normal_equations, ik.template_model, _gram_kernel.gram_block_normal


def kernel_theta(intr: Intrinsics, dist: Distortion, gains, skew: bool) -> np.ndarray:
    """(16,) the compiled image cost's global parameters in the order of
    :data:`~psdcal.calibration._image_kernel.GLOBAL_ORDER`: f, cx, cy (mm), skew (0 unless the model has it),
    fy (mm), k1, k2, k3, p1, p2, l1, l2 and the four channel gains ``gains`` (4,)."""
    return np.array((intr.f_mm, intr.cx_mm, intr.cy_mm, intr.skew if skew else 0.0, intr.fy,
                     dist.k1, dist.k2, dist.k3, dist.p1, dist.p2, dist.l1, dist.l2,
                     *np.asarray(gains, dtype=float).tolist()), dtype=float)


class Evaluator:
    """Residuals and Jacobian of a :class:`Problem` at a state vector (cached per state)."""

    def __init__(self, prob: Problem, base_intr: Intrinsics, base_dist: Distortion, base_gains):
        self.prob = prob
        self.base = (base_intr, base_dist, np.asarray(base_gains, dtype=float))
        self.img_idx, self.pt_idx, self.d_meas, self.P = prob.observations
        self._key = None
        self._val = None
        self._rkey = self._rval = None
        self._dkey = self._dval = self._yval = None
        self._anchor = None
        self._kernel = self._tkernel = self._normal = None  # compiled image / template cost
        self._blocks = None  # compiled block normal equations
        self._ckey = self._cval = None
        #: with the compiled image cost, evaluate the Jacobian with the residuals of every trial point
        #: (set by :func:`refine`): most LM steps are accepted, and the Jacobian at an accepted point then
        #: costs nothing more than its residuals did, instead of a second pass over the points
        self.trial_jacobians = False
        if prob.cost == "image" or not prob.spec.fit_gains:
            if _jit.use_compiled(len(self.img_idx)):  # the compiled costs (psdcal.calibration._image_kernel); this class's numpy code is their reference
                image_model, normal_equations, template_model, gram_block_normal = _compiled_costs()
                if prob.cost == "image":
                    self._kernel = image_model
                else:
                    self._tkernel = template_model
                self._normal = normal_equations
                self._blocks = gram_block_normal  # (the compiled LM loop's: long runs in chunks)
                self._gmap, self._no_warm, self._gain_basis = prob.kernel_constants
                self._separate_fy = prob.spec.aspect
                self._theta0 = kernel_theta(base_intr, base_dist, self.base[2], prob.spec.skew)

    def unpack(self, z):
        return self.prob.unpack(z, *self.base)

    def residuals(self, z):
        """Residuals only (the trial points of LM need no Jacobian)."""
        key = z.tobytes()
        if key == self._key:
            return self._val[0]
        if self.trial_jacobians and self._kernel is not None:
            return self.evaluate_compact(z)[0]
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
        if self._kernel is not None or self._tkernel is not None:
            r, Jc = self.evaluate_compact(z)
            from psdcal.calibration._image_kernel import expand_compact

            val = (r, expand_compact(Jc, self.img_idx, self.prob.n_images))
            self._key, self._val = key, val
            return val
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

    def evaluate_compact(self, z):
        """Residuals (2N,) and the Jacobian in compact block form (2N, n_global + 6) at ``z``.

        Row ``2i`` / ``2i+1`` holds the global columns, then the six (r, t)
        columns of observation i's own view (``self.img_idx[i]``); memory and
        work are linear in the number of observations, not in views x observations.
        """
        key = z.tobytes()
        if key == self._ckey:
            return self._cval
        if self._kernel is not None:
            d, Jc = self._compiled(z, key, want_jac=True)
            r = (d - self.d_meas).ravel()
        elif self._tkernel is not None:
            r, Jc = self._template_compiled(z, want_jac=True)
        else:  # numpy reference: the dense Jacobian's non-zero blocks
            r, J = self.evaluate(z)
            Jc = compact_from_dense(J, self.img_idx, self.prob.n_global)
        bad = ~np.isfinite(r)
        if np.any(bad):
            r = np.where(bad, 1e3, r)
            Jc = np.nan_to_num(np.where(bad[:, None], 0.0, Jc))
        self._ckey, self._cval = key, (r, Jc)
        return r, Jc

    def jacobian_compact(self, z):
        """The compact block Jacobian (2N, n_global + 6) at ``z`` (see :meth:`evaluate_compact`)."""
        Jc = self.evaluate_compact(z)[1]
        if self.trial_jacobians and self._kernel is not None and self._dkey == z.tobytes():
            # LM asks for the Jacobian at accepted points only: the next Newton inverses start from here
            self._anchor = self._dval
        return Jc

    def block_system(self, Jc, r):
        """The normal equations ``J^T J``, ``J^T r`` of a compact Jacobian as a :class:`BlockNormal`."""
        n = self.prob.n_images
        if self._blocks is not None:
            U, W, V, gg, gp = self._blocks(Jc, r, self.img_idx, n)
        else:
            U, W, V, gg, gp = block_normal_reference(Jc, r, self.img_idx, n)
        return BlockNormal(U, W, V, gg, gp, compiled=self._blocks is not None)

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
        if want_jac and not self.trial_jacobians:  # with trial Jacobians: only at accepted points (jacobian_compact)
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
    covariance_global: np.ndarray  # (n_global, n_global) of the intrinsics, distortion, gains
    pose_covariance: np.ndarray  # (n_images, 6, 6) of each view's (r, t)
    cross_covariance: np.ndarray  # (n_images, n_global, 6) global-pose blocks
    sigma2: float  # residual variance of the minimised cost, its unit^2
    cost_rms: float
    iterations: int
    converged: bool
    message: str
    jacobian_compact: np.ndarray  # (2N, n_global + 6), see Evaluator.evaluate_compact
    img_idx: np.ndarray  # (N,) view of each valid observation
    residuals: np.ndarray
    model_mm: np.ndarray | None = None  # (N, 2) modelled points of the valid observations (image cost)

    @property
    def covariance(self) -> np.ndarray:
        """(n_params, n_params) covariance of the full state, assembled from the blocks
        (memory quadratic in the number of views: prefer the blocks)."""
        ng = self.covariance_global.shape[0]
        n = self.pose_covariance.shape[0]
        C = np.zeros((ng + 6 * n, ng + 6 * n))
        C[:ng, :ng] = self.covariance_global
        X = np.concatenate(list(self.cross_covariance), axis=1) if n else np.zeros((ng, 0))  # (ng, 6n)
        # pose-pose blocks of different views: Y_i S^-1 Y_j^T = X_i^T Cg^-1 X_j
        C[ng:, ng:] = X.T @ np.linalg.pinv(self.covariance_global) @ X
        C[:ng, ng:] = X
        C[ng:, :ng] = X.T
        for v in range(n):
            sl = slice(ng + 6 * v, ng + 6 * v + 6)
            C[sl, sl] = self.pose_covariance[v]
        return C

    @property
    def jacobian(self) -> np.ndarray:
        """The dense Jacobian (2N, n_params) at the solution (memory quadratic in views)."""
        from psdcal.calibration._image_kernel import expand_compact

        return expand_compact(self.jacobian_compact, self.img_idx, self.pose_covariance.shape[0])


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
    ev.trial_jacobians = True
    with _single_threaded_blas():
        if (ev._kernel is not None or ev._tkernel is not None) and COMPILED_LOOP:
            sol = _lm_compiled(ev, z0, options)
        else:
            sol = levenberg_marquardt(ev.residuals, ev.jacobian_compact, z0, options, normal=ev.block_system)
        r, Jc = ev.evaluate_compact(sol.x)
        return _finish(prob, ev, sol, r, Jc, m, n, options, system=sol.system)


#: Run the LM iterations of the image and template costs in one compiled call (:mod:`psdcal.calibration._lm_kernel`)
#: when their kernels are compiled; False: the Python loop :func:`levenberg_marquardt` (the reference) always.
COMPILED_LOOP = True


def _lm_compiled(ev, z0, options) -> "LMResult":
    """:func:`levenberg_marquardt` on ``ev``'s compiled image or template cost in one call; ``ev`` is left
    caching the solution's residuals, Jacobian and (image cost) model points, as after the Python loop."""
    from psdcal.calibration._lm_kernel import MESSAGES, lm_image

    x, F, status, njev, nfev, r, Jc, d, y, cov_ok, Cg, Cp, Cx = lm_image(
        ev.P, ev.img_idx, ev._theta0, ev._separate_fy, ev._gmap, ev._gain_basis, ev.d_meas,
        np.ascontiguousarray(z0, dtype=float), ev.prob.n_images, float(options.ftol), float(options.xtol),
        float(options.gtol), int(options.max_iterations), 1e-13, 50, ev._kernel is None)
    key = x.tobytes()
    ev._ckey, ev._cval = key, (r, Jc)
    if ev._kernel is not None:  # the image cost's model points (the template cost has none)
        ev._dkey, ev._dval, ev._yval = key, d, y
        ev._anchor = d
    # the kernel's schur_covariance of the solution's normal equations (else _finish forms them and inverts)
    system = _Solved((Cg, Cp, Cx)) if cov_ok else None
    return LMResult(x=x, cost=float(F), status=2 if status == 5 else int(status),
                    message=MESSAGES[int(status)], njev=int(njev), nfev=int(nfev), system=system)


@contextlib.contextmanager
def _single_threaded_blas(needed: bool = True):
    """Small dense problems run fastest on one BLAS thread (and do not fight
    other processes of a Monte Carlo run for cores).

    Nested uses (a refinement inside a calibration) cost nothing: only the
    outermost one of a thread asks threadpoolctl (some 6-50 us per call, even
    when the limit is already set). ``needed=False`` (a problem too small for
    any BLAS call to use threads) skips threadpoolctl for the whole block, and
    so does a process whose BLAS was started with one thread
    (:func:`assume_one_blas_thread`)."""
    depth = getattr(_DEPTH, "n", 0)
    _DEPTH.n = depth + 1
    try:
        if depth or not needed or _ONE_BLAS_THREAD:
            yield
        else:
            with _blas_limit():
                yield
    finally:
        _DEPTH.n = depth


_DEPTH = threading.local()  # .n: how many _single_threaded_blas contexts this thread has open
#: True once :func:`assume_one_blas_thread` said the BLAS runs on one thread for the whole process.
_ONE_BLAS_THREAD = False


def assume_one_blas_thread() -> None:
    """Declare that this process's BLAS was started with one thread (its thread-count variables set to 1
    before numpy was first imported, as a fresh ``psdcal calibrate`` does): :func:`_single_threaded_blas` then
    does not load threadpoolctl, whose first use (importing it, finding the loaded libraries) costs a
    one-shot command more than any limit it could set."""
    global _ONE_BLAS_THREAD
    _ONE_BLAS_THREAD = True


def _blas_limit():
    """threadpoolctl's one-thread BLAS limit (a null context when threadpoolctl cannot provide one)."""
    global _CONTROLLER
    try:
        if _CONTROLLER is None:
            from threadpoolctl import ThreadpoolController

            _CONTROLLER = ThreadpoolController()
        return _CONTROLLER.limit(limits=1, user_api="blas")
    except Exception:  # threadpoolctl missing or unable to introspect: run as is
        return contextlib.nullcontext()


_CONTROLLER = None


class _Solved:
    """The normal equations at a compiled LM's solution, represented by their inverse's blocks (computed with
    them in the same call): what :func:`_finish` asks of a :class:`BlockNormal`."""

    def __init__(self, blocks):
        self._blocks = blocks

    def covariance_blocks(self):
        return self._blocks


def _finish(prob, ev, sol, r, Jc, m, n, options, system=None):
    dof = max(m - n, 1)
    sigma2 = float(r @ r) / dof
    # the solver's last normal equations are those at the solution (it forms them at accepted points only)
    sysm = system if isinstance(system, (BlockNormal, _Solved)) else ev.block_system(Jc, r)
    Cg, Cp, Cx = sysm.covariance_blocks()
    intr, coef, gains, rv, tv = ev.unpack(sol.x)
    iterations = int(sol.njev) if sol.njev is not None else int(sol.nfev)
    converged = bool(sol.status > 0) and bool(np.isfinite(sol.x).all()) and iterations <= options.max_iterations
    return RefineResult(
        z=sol.x, intrinsics=intr, coeffs=coef, gains=gains, rvecs=rv, tvecs=tv,
        covariance_global=sigma2 * Cg, pose_covariance=sigma2 * Cp, cross_covariance=sigma2 * Cx, sigma2=sigma2,
        cost_rms=math.sqrt(float(np.add.reduce(r * r)) / r.size) * math.sqrt(2.0),  # np.mean's sum, then the rms
        iterations=iterations,
        converged=converged,
        message=str(sol.message),
        jacobian_compact=Jc,
        img_idx=ev.img_idx,
        residuals=r,
        model_mm=ev.model_points(sol.x) if prob.cost == "image" else None,
    )
