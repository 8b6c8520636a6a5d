"""The calibration verdict's linear algebra: the fit linearised at its solution, and what a suspect effect moves.

The verdict (:mod:`psdcal.calibration.verdict`) tests the residuals of a
converged fit against alternatives (a smooth field over the sensor, the
terms the model leaves out, one view or one LED on its own) and states how
much each alternative would move what the user uses: the global parameters
and the angles of arrival over the field of view, in units of their own
standard errors. Both come from the Jacobian at the solution:

- the residuals ``e`` (measured minus modelled, mm) and the projector
  ``I - P`` off the Jacobian's columns (poses view by view, then the global
  parameters);
- the profiled global Jacobian ``Gt`` (the global columns with each view's
  pose columns projected out, natural units: f in mm, k1 in mm^-2, ...) and
  ``Ninv = (Gt^T Gt)^-1``, so that the covariance of the global parameters is
  ``s^2 Ninv`` with ``s^2 = e^T e / dof``;
- :func:`~psdcal.calibration._verdict_fields.field_shift`: the linearised refit with extra columns ``B`` (a
  systematic field, the left-out terms): coefficients ``c`` from the
  residuals, and the shift ``-Ninv Gt^T B c`` of the global parameters;
- :func:`group_shift`: the linearised refit without a group of rows (a view,
  an LED): ``-(N - Gt_S^T Gt_S)^-1 Gt_S^T e_S`` (the influence of the group);
- :func:`angle_effect`: the shift of the angles of arrival on a grid over the
  points' extent, against their standard errors from the covariance.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from psdcal import _jit, _stats
from psdcal.calibration._verdict_blocks import (  # noqa: F401 (their names, importable from here)
    CHOLQR_MAX_COND,
    CHOLQR_ONE_PASS_COND,
    FIELD_DEGREE,
    POSE,
    Blocks,
    FieldParts,
    _bmm,
    _cholqr2,
    _compiled_bases,
    _compiled_products,
    field_basis,
    field_parts,
    normal_bases,
)
#: Grid of sensor points (per axis) over the points' extent on which the angles' shifts are evaluated.
ANGLE_GRID = 7
#: Parameters whose shift counts as an effect on their own (the distortion coefficients act through the angles).
KEY_PARAMETERS = ("f_mm", "fy_mm", "cx_mm", "cy_mm")


def _read_only(a: np.ndarray) -> np.ndarray:
    """``a``, marked read-only (a value memoised for several checks must not be changed by one of them)."""
    a.flags.writeable = False
    return a


@dataclass(frozen=True)
class Linear:
    """The fit linearised at its solution (see the module docstring)."""

    e: np.ndarray  # (m,) residuals meas - model, (x, y) per valid point, projected off the Jacobian
    perp: object  # B (m, k) -> (I - P) B, P the projector on the Jacobian's columns
    h: np.ndarray  # (m,) leverages
    pts: np.ndarray  # (N, 2) modelled points of the valid observations, mm
    img: np.ndarray  # (N,) image index
    led: np.ndarray  # (N,) template point index
    n: int  # rank of the Jacobian
    extra_names: tuple = ()  # terms the model leaves out
    extra: np.ndarray | None = None  # (m, len(extra_names)) their Jacobian columns at the solution
    names: tuple = ()  # the free global parameters of Gt
    g: np.ndarray | None = None  # (m, ng) global Jacobian (natural units)
    perp_pose: object = None  # B -> B projected off each view's pose columns
    held: dict | None = None  # fixed / prior-held parameters: name -> (data-only shift from the fit's value, its std)
    pgram: object = None  # B (m, k) -> ((I - P) B)^T ((I - P) B) without forming (I - P) B (None: through perp)
    blocks: Blocks | None = None  # the per-view Gram matrices and the projector from them (None: from QR)

    def gram_perp(self, B, btb=None) -> np.ndarray:
        """(k, k) the Gram matrix of ``(I - P) B``: ``B^T B`` (``btb`` when given) less its part on the Jacobian's
        span."""
        if self.pgram is not None:
            if isinstance(B, FieldParts):  # the fields' projected Gram matrix, once per linearisation (F-test, shift)
                if btb is None or btb is B.gram():
                    return B.memo("pgram", self, lambda: _read_only(self.pgram(B, btb)))
                return self.pgram(B, btb)
            return self.pgram(np.asarray(B, dtype=float), btb)
        Bp = self.perp(B.dense() if isinstance(B, FieldParts) else np.asarray(B, dtype=float))
        return Bp.T @ Bp

    @cached_property
    def extra_gram(self) -> tuple[np.ndarray, np.ndarray]:
        """(``extra^T extra``, the Gram matrix of ``(I - P) extra``): the left-out terms' test and their single
        tests share them."""
        if self.blocks is not None:
            return self.blocks.extra[:2]
        btb = self.extra.T @ self.extra
        return btb, self.gram_perp(self.extra, btb)

    @cached_property
    def extra_te(self) -> np.ndarray:
        """(len(extra_names),) ``extra^T e`` (the left-out terms' test and their single tests share it)."""
        return self.extra.T @ self.e

    @cached_property
    def gt(self) -> np.ndarray | None:
        """(m, ng) the profiled global Jacobian (each view's pose columns projected out), natural units."""
        if self.g is None:
            return None
        return self.blocks.gt() if self.blocks is not None else self.perp_pose(self.g)

    @cached_property
    def gtg(self) -> np.ndarray | None:
        """(ng, ng) ``Gt^T Gt`` (from the per-view Gram matrices when there are)."""
        if self.g is None:
            return None
        return self.blocks.gtg if self.blocks is not None else self.gt.T @ self.gt

    @cached_property
    def ninv(self) -> np.ndarray | None:
        """(ng, ng) ``(Gt^T Gt)^-1``."""
        return None if self.g is None else _pinv_sym(self.gtg)

    def gt_t(self, B) -> np.ndarray:
        """(ng, k) ``Gt^T B`` for B (m, k) or :class:`FieldParts`."""
        if self.blocks is not None:
            return self.blocks.extra[2] if B is self.extra else self.blocks.gt_t(B)
        return B.coords(self.gt) if isinstance(B, FieldParts) else self.gt.T @ B

    @property
    def dof(self) -> int:
        return int(self.e.size - self.n)

    @property
    def s2(self) -> float:
        return float(self.e @ self.e) / max(self.dof, 1)


def linearise(result, exclude=None) -> Linear:
    """The fit of ``result`` linearised at its solution (``exclude`` (n_images, M) bool: observations left out)."""
    from psdcal.calibration._verdict_jacobian import rich_jacobian
    from psdcal.calibration.checks import align_to_problem

    res = align_to_problem(result)
    p = res.problem
    spec = res.model
    opts = p.get("options", {}) if isinstance(p, dict) else {}
    fixed = tuple(n for n in (opts.get("fix") or {}) if n in spec.global_names)
    prior_names = tuple(n for q in (opts.get("priors") or []) for n in q.get("names", []) if n in spec.global_names)
    # the richer model (the terms this one leaves out at 0): its Jacobian holds this model's columns and theirs, the
    # free global columns, the left-out terms', the fixed ones, then each row's own view's six pose columns
    rj = rich_jacobian(res, fixed)
    r, X, img, led, d_meas, n_img = rj.r, rj.X, rj.img, rj.led, rj.d_meas, rj.n_img
    free, extra_names = list(rj.free), list(rj.extra)
    g, ne, nf = len(free), len(extra_names), len(fixed)
    dense = rj.dense and exclude is None
    if exclude is not None:
        keep_pt = ~np.asarray(exclude, dtype=bool)[img, led]
        rows = np.repeat(keep_pt, 2)
        r, X = r[rows], X[rows]
        img, led, d_meas = img[keep_pt], led[keep_pt], d_meas[keep_pt]
    e_raw = -r
    row_img = np.repeat(img, 2)
    blocks = normal_bases(X, g, ne, row_img, n_img, pose_last=True, dense=dense or None) \
        if r.size // 2 > NORMAL_BASES_MIN_POINTS else None
    if blocks is None and exclude is None:  # the QR path's products on the column-major columns they have always
        X = np.asfortranarray(X)  # had (a fancy index's copy): BLAS sums in the same order, the same numbers
    G, extra, Gh, Jpose = X[:, :g], X[:, g:g + ne], X[:, g + ne:g + ne + nf], X[:, g + ne + nf:]
    if blocks is not None:
        perp, h, rank, perp_pose, pgram = blocks.perp, blocks.h, blocks.rank, blocks.perp_pose, blocks.pgram
    else:
        perp, h, rank, perp_pose, pgram = projector(G, Jpose, row_img, n_img, gram=True)
    e = perp(e_raw[:, None])[:, 0]  # the solver stops within its tolerance of the stationary point
    held = _held(free, fixed, prior_names, G, Gh, perp_pose(G), perp_pose, e_raw, e, rank) if (fixed or prior_names) \
        else None
    # the modelled points (noise-free up to the fitted parameters): fields evaluated at the measured ones would carry
    # the noise's own gradient into the test and correlate with it
    return Linear(e, perp, h, d_meas + r.reshape(-1, 2), img, led, rank, tuple(extra_names), extra,
                  tuple(free), G, perp_pose, held, pgram, blocks)


#: Up to this condition number of the scaled matrix :func:`_pinv_sym` takes the compiled loop (its result and
#: LAPACK's then differ by ``eps cond``, rounding); beyond it (and with a dropped direction) numpy's code.
PINV_COMPILED_MAX_COND = 1e6


def _pinv_sym(N) -> np.ndarray:
    """Pseudo-inverse of a symmetric positive semi-definite matrix, scaled for conditioning.

    ``np.linalg.pinv(Ns, rcond=1e-12, hermitian=True)`` of the scaled matrix written out (its eigenvalues below
    1e-12 of the largest in magnitude dropped), without its checks and wrappers; with the compiled kernels, in one
    compiled loop where the scaled matrix is conditioned better than :data:`PINV_COMPILED_MAX_COND`
    (:func:`psdcal.calibration._verdict_kernel.pinv_sym`: the eigenproblem by Jacobi rotations, equal to rounding,
    tested)."""
    if N.shape[0] and _jit.use_compiled(0):
        from psdcal.calibration._verdict_kernel import pinv_sym

        out = np.empty(N.shape)
        if pinv_sym(np.ascontiguousarray(N, dtype=float), out, PINV_COMPILED_MAX_COND):
            return out
    d = np.sqrt(np.maximum(np.diag(N), 1e-300))
    dd = d[:, None] * d[None, :]
    lam, U = np.linalg.eigh(N / dd)
    a = np.abs(lam)
    big = a > 1e-12 * (a.max() if a.size else 0.0)
    inv = np.divide(1.0, lam, out=np.zeros_like(lam), where=big)
    return (U * inv) @ U.T / dd


def _held(free, fixed, prior_names, G, Gh, gt, perp_pose, e_raw, e, rank):
    """What the data alone say about the held parameters: name -> (shift from the fit's value, its std).

    Fixed parameters: the linearised free fit (their columns added); parameters under a prior: the fit without
    the prior rows (the data-only estimate around the MAP one, whose residuals the prior pulls off stationarity).
    """
    out = {}
    dof = max(e.size - rank - len(fixed), 1)
    if fixed:
        gall = np.concatenate([gt, perp_pose(Gh)], axis=1)
        ninv_all = _pinv_sym(gall.T @ gall)
        shift = ninv_all @ (gall.T @ e_raw)
        fit = gall @ shift
        r_free = e_raw - fit
        s2 = float(r_free @ r_free) / dof
        for k, n in enumerate(fixed):
            j = len(free) + k
            out[n] = (float(shift[j]), float(np.sqrt(max(s2 * ninv_all[j, j], 0.0))))
    if prior_names:
        ninv = _pinv_sym(gt.T @ gt)
        shift = ninv @ (gt.T @ e_raw)
        s2 = float(e @ e) / max(e.size - rank, 1)
        for n in prior_names:
            if n in free:
                j = free.index(n)
                out[n] = (float(shift[j]), float(np.sqrt(max(s2 * ninv[j, j], 0.0))))
    return out


def projector(G, Jpose, row_img, n_img, gram: bool = False):
    """The projector off the Jacobian's columns, from its block structure.

    The pose columns of a view touch only that view's rows: a batched QR of the
    (rows x 6) blocks projects them out view by view; then a QR of the global
    columns so projected. ``Jpose`` is (m, 6): each row's own view's pose
    columns (the compact form). Returns ``(perp, leverages, rank, perp_pose)``
    where ``perp(B)`` is ``(I - P) B`` for B (m, k) and ``perp_pose(B)`` projects
    off the pose columns only; with ``gram``, also ``pgram(B)``, the Gram matrix
    ``((I - P) B)^T (I - P) B`` from ``B^T B`` and B's coordinates on the
    orthonormal bases (no (m, k) projected copy of B).
    """
    m = row_img.size
    counts = np.bincount(row_img, minlength=n_img)
    nr = int(counts.max()) if m else 0
    # rows in view order, every view with as many rows: the blocks are a reshape (no scatter, no gather)
    dense = m > 0 and bool(np.all(counts == nr)) and bool(np.all(row_img[1:] >= row_img[:-1]))
    if dense:
        pos = None
        blocks = np.ascontiguousarray(Jpose).reshape(n_img, nr, 6)
        if m // 2 <= COMPILED_PROJECTOR_MAX_POINTS and _jit.use_compiled(m // 2):
            pre = _compiled_bases(blocks, G)
            if pre is not None:
                return _compiled_products(pre, nr, gram)
    else:
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        pos = np.arange(m) - starts[row_img]
        blocks = np.zeros((n_img, nr, 6))
        blocks[row_img, pos] = Jpose
    Qb = _cholqr2(blocks)
    if Qb is not None:  # every view's pose columns well conditioned: all six count
        rank = 6 * n_img
    else:
        blocks = blocks / np.maximum(np.linalg.norm(blocks, axis=1, keepdims=True), 1e-300)
        Qb, Rb = np.linalg.qr(blocks)
        dq = np.abs(np.diagonal(Rb, axis1=1, axis2=2))
        rank = int(np.sum(dq > 1e-10 * max(float(dq.max()), 1e-300)))
    Qrows = Qb.reshape(m, 6) if dense else Qb[row_img, pos]  # (m, 6): each row's part of its view's basis

    Qbt = np.ascontiguousarray(Qb.transpose(0, 2, 1))

    def to_blocks(B):
        if dense:
            return B.reshape(n_img, nr, B.shape[1])
        Bb = np.zeros((n_img, nr, B.shape[1]))
        Bb[row_img, pos] = B
        return Bb

    def perp_pose(B):
        B = np.asarray(B, dtype=float)
        # each view's part of B minus its projection on the view's pose basis (batched matrix products:
        # no (rows, 6, k) temporary)
        PB = _bmm(Qb, np.matmul(Qbt, to_blocks(B)))
        return B - (PB.reshape(m, B.shape[1]) if dense else PB[row_img, pos])

    Gn = G / np.maximum(np.sqrt(np.maximum(np.einsum("ij,ij->j", G, G), 0.0)), 1e-300)
    Gp = perp_pose(Gn)
    if Gp.shape[1]:
        Qg = _cholqr2(Gp, unit_columns=False)  # Gp's columns: unit ones less their part on the poses
        if Qg is None:
            Qg, Rg = np.linalg.qr(Gp)
            dg = np.abs(np.diag(Rg))
            keep = dg > 1e-8 * max(float(dg.max()), 1e-300)
            if not keep.all():
                U, sv, _ = np.linalg.svd(Gp, full_matrices=False)
                Qg = U[:, sv > 1e-8 * sv[0]]
    else:
        Qg = np.zeros((m, 0))
    rank += Qg.shape[1]

    def perp(B):
        Bp = perp_pose(np.asarray(B, dtype=float))
        return Bp - Qg @ (Qg.T @ Bp)

    h = np.einsum("ij,ij->i", Qrows, Qrows) + np.einsum("ij,ij->i", Qg, Qg)
    if not gram:
        return perp, h, rank, perp_pose

    def pgram(B, btb=None):
        # P = (pose bases, view by view) + Qg Qg^T with Qg orthogonal to the pose columns: B^T P B is the sum of the
        # squares of B's coordinates on both
        if isinstance(B, FieldParts):
            if not dense:
                B = B.dense()
            else:
                cb = B.coords_blocks(Qbt)
                cg = B.coords(Qg)
                return (B.gram() if btb is None else btb) - cb.T @ cb - cg.T @ cg
        cb = np.matmul(Qbt, to_blocks(B)).reshape(-1, B.shape[1])
        cg = Qg.T @ B
        return (B.T @ B if btb is None else btb) - cb.T @ cb - cg.T @ cg

    return perp, h, rank, perp_pose, pgram


#: Above this many points (two rows each) the projector comes from each view's Gram matrix
#: (:func:`~psdcal.calibration._verdict_blocks.normal_bases`) where the blocks are well conditioned; up to it from
#: the compiled QR (:func:`_compiled_bases`), whose loops cost as little on few rows. linearise on 5 x 64 points:
#: 0.43 ms from the Gram matrices, 0.49 ms compiled; 5 x 100: 0.50 and 0.62 ms; 12 x 14 and 20 x 14: equal within
#: the noise (one run, process CPU time, the fastest of 300 calls, a loaded 2-core machine).
NORMAL_BASES_MIN_POINTS = 300
#: Up to this many points (two rows each) the projector comes from the compiled kernels (:func:`_compiled_bases`,
#: :func:`_compiled_products`: loops, where a numpy call's overhead dominates); above it from numpy, whose BLAS
#: products of the tall blocks are faster there. The verdict on 12 x 14 points: 1.8 ms compiled, 2.1 ms numpy;
#: 6 x 14: 1.7 and 2.0 ms; 5 x 64: 2.0 and 2.2 ms; Zhang's 5 x 256: 4.2 and 4.0 ms (one run, process CPU time,
#: the fastest of 150 calls).
COMPILED_PROJECTOR_MAX_POINTS = 500


def group_shift(lin: Linear, rows) -> np.ndarray:
    """The linearised shift of the global parameters (ng,) when the residual rows ``rows`` (bool (m,)) are left out."""
    b = lin.blocks
    if b is not None:  # Gt^T Gt from the per-view Gram matrices and the rows of Gt = Qg Rg
        v, nr = b.Q.shape[:2]
        counts = np.count_nonzero(np.asarray(rows).reshape(v, nr), axis=1)
        k = int(np.argmax(counts))
        if counts[k] == nr and counts.sum() == nr:  # one whole view: Gt_k^T Gt_k is its Schur complement
            gte = b.Rg.T @ (b.Q[k, :, POSE:].T @ lin.e[k * nr:(k + 1) * nr])
            return -_pinv_sym(lin.gtg - b.gtg_view[k]) @ gte
        gs = b.qg[rows] @ b.Rg
    else:
        gs = lin.gt[rows]
    Nm = lin.gtg - gs.T @ gs
    return -_pinv_sym(Nm) @ (gs.T @ lin.e[rows])


def view_shift(lin: Linear, k: int) -> np.ndarray:
    """:func:`group_shift` of all the rows of view ``k`` (from the per-view Gram matrices without finding the view
    in a row mask where there are: the same arithmetic)."""
    b = lin.blocks
    if b is not None:  # the views' rows in order, nr each
        nr = b.Q.shape[1]
        gte = b.Rg.T @ (b.Q[k, :, POSE:].T @ lin.e[k * nr:(k + 1) * nr])
        return -_pinv_sym(lin.gtg - b.gtg_view[k]) @ gte
    return group_shift(lin, np.repeat(lin.img == k, 2))


def group_f(lin: Linear, groups, n_groups, ssr, dof):
    """Per-group F statistics of the residual variance against the other groups', and the p-value of the
    largest (``pv`` is NaN for the other groups)."""
    if _jit.use_compiled(groups.size):  # the same operations in one loop (equal to the last bit, tested)
        from psdcal.calibration import _verdict_kernel as vk

        F, d_g, d_r, usable, worst = vk.group_f(np.ascontiguousarray(groups), lin.h, lin.e, int(n_groups),
                                                float(ssr), float(dof))
        pv = np.full(n_groups, np.nan)
        pv[worst] = _stats.f_sf(F[worst], d_g[worst], d_r[worst]) if usable[worst] else 1.0
        return F, pv
    q = lin.e.reshape(-1, 2)
    # per point: the sums of its two coordinates written out (numpy's reductions over a last axis of 2 are slow)
    om = 1.0 - lin.h
    lev = np.bincount(groups, weights=om[0::2] + om[1::2], minlength=n_groups)
    sq = np.bincount(groups, weights=q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1], minlength=n_groups)
    usable = (lev >= 0.5) & (dof - lev >= 0.5)
    d_g = np.where(usable, lev, 1.0)
    d_r = np.where(usable, dof - lev, 1.0)
    F = np.where(usable, (sq / d_g) / (np.maximum(ssr - sq, 1e-300) / d_r), np.nan)
    # the checks test the worst group only (largest F): its p-value is the one computed (the others are NaN)
    worst = int(np.argmax(np.where(np.isfinite(F), F, -np.inf)))
    pv = np.full(n_groups, np.nan)
    pv[worst] = _stats.f_sf(F[worst], d_g[worst], d_r[worst]) if usable[worst] else 1.0
    return F, pv


# -- consequences -------------------------------------------------------------------------
def _angles(values: dict, result, d_mm) -> np.ndarray:
    """Angles of arrival (K, 2) rad of sensor points ``d_mm`` (K, 2) under parameter ``values`` (name -> value)."""
    from psdcal.model.distortion import undistort
    from psdcal.model.params import Distortion, Intrinsics

    intr = result.intrinsics
    fy = values.get("fy_mm", intr.fy_mm)
    I2 = Intrinsics(f_mm=values.get("f_mm", intr.f_mm), cx_mm=values.get("cx_mm", intr.cx_mm),
                    cy_mm=values.get("cy_mm", intr.cy_mm), skew=values.get("skew", intr.skew), fy_mm=fy)
    dist = Distortion(**{**result.distortion.to_dict(), **{k: v for k, v in values.items() if k in
                                                             result.distortion.to_dict()}})
    x = undistort(d_mm, dist, I2.c)
    # the ray of the ideal point (inverse of x = f X/Z + skew Y/Z + cx, y = fy Y/Z + cy)
    ty = (x[:, 1] - I2.cy_mm) / I2.fy
    tx = (x[:, 0] - I2.cx_mm - I2.skew * ty) / I2.f_mm
    return np.stack([np.arctan(tx), np.arctan(ty)], axis=1)


def angle_grid(lin: Linear) -> np.ndarray:
    """(K, 2) sensor points on a grid over the observed points' extent, mm."""
    x, y = lin.pts[:, 0], lin.pts[:, 1]  # (numpy reduces a column view much faster than (N, 2) along axis 0)
    x0, x1, y0, y1 = x.min(), x.max(), y.min(), y.max()
    g = _UNIT_GRID
    out = np.empty((ANGLE_GRID, ANGLE_GRID, 2))
    # np.meshgrid's order, raveled: x runs fastest
    out[:, :, 0] = x0 + g * (x1 - x0)
    out[:, :, 1] = (y0 + g * (y1 - y0))[:, None]
    return out.reshape(ANGLE_GRID * ANGLE_GRID, 2)


_UNIT_GRID = np.linspace(0.0, 1.0, ANGLE_GRID)


@dataclass(frozen=True)
class Consequences:
    """The angles' sensitivities on the grid: ``A`` (2K, n) d(angle)/d(parameter) for ``names``,
    ``D`` (K, 2, 2) d(angle)/d(sensor point), ``sd`` (2K,) the angles' standard errors, ``cov`` (ng, ng) the
    free parameters' covariance, ``grid`` (K, 2)."""

    names: tuple
    A: np.ndarray
    D: np.ndarray
    sd: np.ndarray
    cov: np.ndarray
    grid: np.ndarray


def consequences(lin: Linear, result, cov=None) -> Consequences:
    """The angles' sensitivities (analytic: one :func:`~psdcal.model.distortion.undistort` with its Jacobians) and
    standard errors over the field of view.

    ``cov`` is the covariance of ``lin.names`` (default ``s^2 Ninv``); the extra
    terms' sensitivities are included (``names`` = free parameters then extra terms).
    :func:`consequences_reference` is the same by finite differences.
    """
    grid = angle_grid(lin)
    names = tuple(lin.names) + tuple(lin.extra_names)
    cov = lin.s2 * lin.ninv if cov is None else np.asarray(cov, dtype=float)
    A, D = angle_jacobians(result, grid, names)
    Af = A[:, : len(lin.names)]
    sd = np.sqrt(np.maximum(np.einsum("ij,ij->i", Af @ cov, Af), 0.0))  # diag(Af cov Af^T)
    return Consequences(names, A, D, sd, cov, grid)


def angle_jacobians(result, d_mm, names) -> tuple[np.ndarray, np.ndarray]:
    """d(angles)/d(parameters) (2K, len(names)), rows (x0, y0, x1, ...), and d(angles)/d(sensor point) (K, 2, 2)
    of the angles of :func:`_angles` at the sensor points ``d_mm`` (K, 2); a name that is no intrinsic or
    distortion parameter (a gain) has a zero column. ``f_mm`` moves ``fy`` too when the model has no ``fy_mm``."""
    from psdcal.model.distortion import undistort
    from psdcal.model.params import DISTORTION_NAMES

    d_mm = np.ascontiguousarray(d_mm, dtype=float)
    if d_mm.ndim == 2 and _jit.use_compiled(d_mm.shape[0]):  # the same arithmetic in loops (tested equal)
        from psdcal.calibration import _rules_kernel

        return _rules_kernel.angle_jacobians(result, d_mm, names)
    intr = result.intrinsics
    f, fy, sk = float(intr.f_mm), float(intr.fy), float(intr.skew)
    c = np.array([intr.cx_mm, intr.cy_mm], dtype=float)
    x, dx_dd, dx_dc, dx_dcoef = undistort(d_mm, result.distortion, c, jacobians=True)
    ty = (x[:, 1] - c[1]) / fy
    tx = (x[:, 0] - c[0] - sk * ty) / f
    wx = 1.0 / (1.0 + tx * tx)  # d arctan(t) / dt
    wy = 1.0 / (1.0 + ty * ty)

    K = x.shape[0]
    n = len(names)
    # every parameter's column at once: the chain rule of the angles through x (tx = (x0 - cx - skew ty) / f,
    # ty = (x1 - cy) / fy) with each parameter's derivatives of x, C, skew, f and fy (zero where it has none), the
    # same arithmetic as one column at a time
    dx0 = np.zeros((K, n))
    dx1 = np.zeros((K, n))
    dcx, dcy, dsk, df, dfy = (np.zeros(n) for _ in range(5))
    for k, nm in enumerate(names):
        if nm == "f_mm":
            df[k] = 1.0
            dfy[k] = 1.0 if intr.fy_mm is None else 0.0
        elif nm == "fy_mm":
            dfy[k] = 1.0
        elif nm == "cx_mm":
            dx0[:, k], dx1[:, k], dcx[k] = dx_dc[:, 0, 0], dx_dc[:, 1, 0], 1.0
        elif nm == "cy_mm":
            dx0[:, k], dx1[:, k], dcy[k] = dx_dc[:, 0, 1], dx_dc[:, 1, 1], 1.0
        elif nm == "skew":
            dsk[k] = 1.0
        elif nm in DISTORTION_NAMES:
            j = DISTORTION_NAMES.index(nm)
            dx0[:, k], dx1[:, k] = dx_dcoef[:, 0, j], dx_dcoef[:, 1, j]
    A3 = np.empty((K, 2, n))
    tyc, txc = ty[:, None], tx[:, None]
    dty = (dx1 - dcy - tyc * dfy) / fy
    A3[:, 0, :] = wx[:, None] * ((dx0 - dcx - dsk * tyc - sk * dty - txc * df) / f)
    A3[:, 1, :] = wy[:, None] * dty
    D = np.empty((K, 2, 2))
    dty = dx_dd[:, 1, :] / fy  # d(angle)/d(sensor point j): the chain above with dx = dx_dd[:, :, j] alone
    D[:, 0, :] = wx[:, None] * ((dx_dd[:, 0, :] - sk * dty) / f)
    D[:, 1, :] = wy[:, None] * dty
    A = A3.reshape(2 * K, len(names))
    return A, D


def consequences_reference(lin: Linear, result, cov=None) -> Consequences:
    """:func:`consequences` by finite differences (its reference, tested equal to it; the same arguments)."""
    grid = angle_grid(lin)
    names = tuple(lin.names) + tuple(lin.extra_names)
    vals = {**result.intrinsics.to_dict(), **result.distortion.to_dict()}
    if "fy_mm" not in vals:
        vals["fy_mm"] = result.intrinsics.fy
    cov = lin.s2 * lin.ninv if cov is None else np.asarray(cov, dtype=float)
    sdp = np.sqrt(np.maximum(np.diag(cov), 0.0))
    a0 = _angles({}, result, grid).ravel()
    A = np.zeros((a0.size, len(names)))
    for k, n in enumerate(names):
        if n not in vals:  # gains: the angles of impact points do not depend on them
            continue
        # one-sided steps of a hundredth of a standard error: the angles are linear in the parameters to far better
        # than the precision an effect is quoted to
        step = sdp[k] * 1e-2 if k < len(sdp) and sdp[k] > 0 else 1e-6 * max(abs(vals[n]), 1e-3)
        A[:, k] = (_angles({n: vals[n] + step}, result, grid).ravel() - a0) / step
    D = np.zeros((grid.shape[0], 2, 2))
    h = 1e-4
    b0 = a0.reshape(-1, 2)
    for j in range(2):
        dg = np.zeros(2)
        dg[j] = h
        D[:, :, j] = (_angles({}, result, grid + dg) - b0) / h
    Af = A[:, : len(lin.names)]
    sd = np.sqrt(np.maximum(np.einsum("ij,ij->i", Af @ cov, Af), 0.0))  # diag(Af cov Af^T)
    return Consequences(names, A, D, sd, cov, grid)


@dataclass(frozen=True)
class Effect:
    """How much an alternative moves the result: ``sigma`` the largest shift of a key parameter or an angle over
    the field of view in its own standard errors, ``what`` which, ``angle_rad`` the largest angle shift (rad),
    ``angle_sigma`` the largest angle shift in sigmas, ``params`` name -> shift in sigmas."""

    sigma: float
    what: str
    angle_rad: float
    angle_sigma: float
    params: dict

    def words(self) -> str:
        """The effect in words ("moves f_mm by 0.3 sigma, the angles by at most 0.4 sigma (12 urad)")."""
        key = {k: v for k, v in self.params.items() if k in KEY_PARAMETERS}
        worst = max(key, key=key.get) if key else None
        parts = []
        if worst is not None:
            parts.append(f"{worst} by {_sig(key[worst])}")
        a = self.angle_rad
        size = (f"{a * 1e3:.3g} mrad" if a < 1.0 else "more than 1 rad") if a >= 1e-3 else f"{a * 1e6:.3g} urad"
        parts.append(f"the angles by at most {_sig(self.angle_sigma)} ({size})")
        return "moves " + ", ".join(parts)


def _sig(x: float) -> str:
    return f"{x:.2g} sigma" if x < 1e3 else "more than 1000 sigma"


def effect(cons: Consequences, dtheta, *, dextra=None, field_at_grid=None) -> Effect:
    """The effect of a parameter shift ``dtheta`` (free parameters), with the extra terms' values ``dextra`` and
    an additive field on the sensor ``field_at_grid`` (K, 2) mm removed from the measured points."""
    n_free = len(dtheta)
    full = np.zeros(len(cons.names))
    full[:n_free] = dtheta
    if dextra is not None:
        full[n_free:] = dextra
    if _jit.use_compiled(cons.sd.size // 2):  # the same sums in one loop (tested against the code below)
        from psdcal.calibration import _fields_kernel as fk

        f = _NO_FIELD if field_at_grid is None else np.ascontiguousarray(field_at_grid, dtype=float)
        ang_sig, ang_rad, sdp = fk.angle_shifts(cons.A, full, cons.D, f, cons.sd, cons.cov)
        sdp = sdp.tolist()
    else:
        ang_sig, ang_rad, sdp = _angle_shifts(cons, full, field_at_grid)
    dth = np.abs(np.asarray(dtheta, dtype=float)).tolist()
    params = {n: dth[k] / sdp[k] for k, n in enumerate(cons.names[:n_free]) if sdp[k] > 0}
    key = {k: v for k, v in params.items() if k in KEY_PARAMETERS}
    what, sig = "the angles", ang_sig
    if key:
        kmax = max(key, key=key.get)
        if key[kmax] > sig:
            what, sig = kmax, key[kmax]
    return Effect(float(sig), what, ang_rad, ang_sig, params)


_NO_FIELD = np.zeros((0, 2))


def _angle_shifts(cons: Consequences, full, field_at_grid):
    """(the largest angle shift in its standard errors, the largest angle shift (rad), the parameters' standard
    errors as a list) of the parameter shift ``full`` (all of ``cons.names``) and the field ``field_at_grid``."""
    sdp = np.sqrt(np.maximum(np.diag(cons.cov), 0.0)).tolist()
    da = cons.A @ full
    if field_at_grid is not None:  # D (K, 2, 2) times the field (K, 2), the sum over its two components written out
        f = np.asarray(field_at_grid, dtype=float)
        D = cons.D
        da = da - (D[:, :, 0] * f[:, 0:1] + D[:, :, 1] * f[:, 1:2]).ravel()
    sd = cons.sd
    ok = sd > 0
    if ok.all():
        z = np.abs(da) / sd
    else:
        z = np.abs(da[ok]) / sd[ok] if ok.any() else np.zeros(1)
    ang_sig = float(np.max(z)) if z.size else 0.0
    ang_rad = float(np.max(np.abs(da))) if da.size else 0.0
    return ang_sig, ang_rad, sdp
