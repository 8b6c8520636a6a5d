"""The verdict's projector from each view's block Gram matrix, the Cholesky QR it replaces, and the smooth fields.

The fit's Jacobian at its solution has a block structure: each view's six
pose columns touch only that view's rows, the global columns (f, C, the
distortion, ...) touch every row. :func:`psdcal.calibration._verdict_linear.projector`
builds orthonormal bases of its columns by QR of the tall blocks (two
Cholesky-QR passes, :func:`_cholqr2`, or the compiled loops of
:mod:`psdcal.calibration._verdict_kernel`).

:func:`normal_bases` builds the same bases from each view's Gram matrix
``K_v = X_v^T X_v`` of ``X_v = [A_v | G_v | E_v]`` (pose, global and the
richer model's extra columns of view v's rows): a small eigenproblem of each
``A_v^T A_v`` gives the pose basis ``Qb_v = A_v Mb_v`` (the first Cholesky-QR
pass of :func:`_cholqr2`, unit columns), the Schur complement
``Gt_v^T Gt_v = G_v^T G_v - (Qb_v^T G_v)^T (Qb_v^T G_v)`` summed over the views
is the Gram matrix of the profiled global Jacobian ``Gt`` (the global columns
with each view's pose columns projected out), and its eigenproblem gives the
global basis ``Qg = Gt Mg``. The bases of view v are then one product
``[Qb_v | Qg_v] = [A_v | G_v] T_v`` with a small transform ``T_v``
(:func:`normal_transforms`); ``Gt^T Gt``, ``Gt = Qg Rg`` and the projected
Gram matrices of the extra columns come from the ``K_v`` with no tall
product. Only the one-pass regime is taken (every block conditioned better
than :data:`CHOLQR_ONE_PASS_COND`, where one Cholesky-QR pass is orthonormal
to 1e-10): otherwise :func:`normal_bases` returns None and the QR path runs.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from psdcal import _jit

#: Polynomial degree of the smooth residual field of the ``structure`` check.
FIELD_DEGREE = 3
#: The pose columns of each view (rotation vector, translation).
POSE = 6

#: Above this condition number of a set of columns, their orthonormal basis comes from a Householder QR instead of
#: :func:`_cholqr2` (whose first pass loses ``cond^2`` of the precision that its second pass restores).
CHOLQR_MAX_COND = 1e5
#: ... and below this one, one pass is orthonormal to 1e-10 (its loss, ``eps cond^2``): no second pass.
CHOLQR_ONE_PASS_COND = 1e3


def _cholqr2(A, unit_columns: bool = True):
    """An orthonormal basis (..., r, k) of the columns of ``A`` (..., r, k) (a stack of blocks or one matrix) by two
    passes of a Cholesky QR (matrix products: several times faster than a Householder QR of tall thin blocks);
    None when the columns of a block are conditioned worse than :data:`CHOLQR_MAX_COND` (or rank deficient), each
    column scaled to norm 1 (``unit_columns``) or as given (a column much shorter than the longest one then counts
    as absorbed, as in a QR's rank test)."""
    K = np.swapaxes(A, -1, -2) @ A
    d = np.sqrt(np.diagonal(K, axis1=-2, axis2=-1))  # the columns' norms
    if not np.all(d > 0) or not np.all(np.isfinite(d)):
        return None
    if not unit_columns:
        d = np.ones_like(d)
    dd = d[..., :, None] * d[..., None, :]
    lam, V = np.linalg.eigh(K / dd)
    if not np.all(lam[..., 0] > lam[..., -1] / CHOLQR_MAX_COND ** 2) or not np.all(np.isfinite(lam)):
        return None
    Q = _bmm(A, V / d[..., :, None] / np.sqrt(lam)[..., None, :])
    if np.all(lam[..., 0] > lam[..., -1] / CHOLQR_ONE_PASS_COND ** 2):
        return Q  # orthonormal to eps cond^2 < 1e-10 already
    L = np.linalg.cholesky(np.swapaxes(Q, -1, -2) @ Q)
    return _bmm(Q, np.swapaxes(np.linalg.inv(L), -1, -2))


def _compiled_bases(blocks, G):
    """The projector's orthonormal bases from the compiled kernels (:mod:`psdcal.calibration._verdict_kernel`) for the
    dense layout (the views' rows consecutive, as many each): (Qb (m, 6), Qg (m, g), leverages (m,), rank), None
    when a conditioning test sends the work to the numpy code."""
    from psdcal.calibration import _verdict_kernel as vk

    n_img, nr = blocks.shape[0], blocks.shape[1]
    ok, Qb, Qg, h = vk.bases(blocks.reshape(n_img * nr, 6), nr, np.ascontiguousarray(G, dtype=float),
                             float(CHOLQR_MAX_COND), float(CHOLQR_ONE_PASS_COND))
    return (Qb, Qg, h, 6 * n_img + Qg.shape[1]) if ok else None


def _compiled_products(pre, nr, gram):
    """:func:`psdcal.calibration._verdict_linear.projector`'s functions as compiled loops over the bases ``pre`` (:func:`_compiled_bases`); ``nr`` rows
    per view."""
    from psdcal.calibration import _verdict_kernel as vk

    Qb, Qg, h, rank = pre

    def perp_pose(B):
        return vk.perp_pose(Qb, nr, np.ascontiguousarray(B, dtype=float))

    def perp(B):
        return vk.perp(Qb, nr, Qg, np.ascontiguousarray(B, dtype=float))

    if not gram:
        return perp, h, rank, perp_pose

    def pgram(B, btb=None):
        if isinstance(B, FieldParts):
            btb = B.gram() if btb is None else btb
            B = B.dense()
        B = np.ascontiguousarray(B, dtype=float)
        btb = B.T @ B if btb is None else btb
        return vk.pgram(Qb, nr, Qg, B, np.ascontiguousarray(btb, dtype=float))

    return perp, h, rank, perp_pose, pgram


def _bmm(A, B) -> np.ndarray:
    """``A @ B`` for a stack of tall blocks ``A`` (v, r, k) and small ``B`` (v, k, l) (or one matrix ``A``): numpy 2's
    batched product is faster than one BLAS call per block (Zhang's 5 x 512 x 6 blocks: 7-44 us against 21-59 us,
    l = 1-22; 12 x 28 x 6: 2.5-8 us against 25-33 us) and equal to the last bit."""
    return np.matmul(A, B)


def field_basis(pts, c_mm, half_mm) -> np.ndarray:
    """(2N, p) smooth vector fields over the sensor at ``pts`` (N, 2), rows (x0, y0, x1, y1, ...)."""
    return field_parts(pts, c_mm, half_mm).dense()


class FieldParts:
    """The fields of :func:`field_basis` in parts: each monomial ``mono`` (N, p) as an x-field then a y-field
    (columns 2k, 2k + 1), then the dense columns ``R`` (2N, r). The products the verdict needs (``B^T B``,
    ``Q^T B``) come from the parts, without the (2N, 2p + r) matrix, whose columns are half zeros."""

    def __init__(self, mono, R, ext=None):
        self.mono = mono
        self.R = R
        self._ext_memo = ext  # (N, p + 4) the parts side by side (see _ext), when the caller has them
        self.shape = (R.shape[0], 2 * mono.shape[1] + R.shape[1])

    def memo(self, key: str, owner, make):
        """``make()``, computed once per ``owner`` (by identity: the linearisation or the projector that the value
        belongs to) and kept on these fields under ``key``: the checks that test the same fields share it."""
        hit = self.__dict__.get("_memo_" + key)
        if hit is not None and hit[0] is owner:
            return hit[1]
        value = make()
        self.__dict__["_memo_" + key] = (owner, value)
        return value

    def dense(self) -> np.ndarray:
        n, p = self.mono.shape
        out = np.zeros((n, 2, 2 * p))
        out[:, 0, 0::2] = self.mono  # x-fields
        out[:, 1, 1::2] = self.mono  # y-fields
        return np.concatenate([out.reshape(2 * n, 2 * p), self.R], axis=1)

    def _ext(self) -> np.ndarray:
        """(N, p + 4) each point's monomials and its rows of ``R`` side by side (x r^4, x r^6, y r^4, y r^6): the
        products below are one matrix product with it each (computed once)."""
        ext = self._ext_memo
        if ext is None:
            ext = np.concatenate([self.mono, self.R.reshape(-1, 4)], axis=1)
            self._ext_memo = ext
        return ext

    def coords(self, Q) -> np.ndarray:
        """``Q^T B`` (q, k) for ``Q`` (2N, q), rows in B's order."""
        Q = np.ascontiguousarray(Q, dtype=float)
        n, p = self.mono.shape
        q = Q.shape[1]
        # one product for all columns: Q's rows (x_i, y_i) side by side, (N, 2q); M[k, a q + j] = sum_i ext[i, k]
        # Q[2 i + a, j]; the monomials' reordered to [j, 2 k + a], R's the sum of its x and y rows' parts
        M = self._ext().T @ Q.reshape(n, 2 * q)
        out = np.empty((q, self.shape[1]))
        out[:, :2 * p].reshape(q, p, 2)[...] = M[:p].reshape(p, 2, q).transpose(2, 0, 1)
        out[:, 2 * p:] = (M[p:p + 2, :q] + M[p + 2:, q:]).T
        return out

    def t_dot(self, e) -> np.ndarray:
        """``B^T e`` (k,) for ``e`` (2N,) in B's row order (:meth:`coords` of one column)."""
        p = self.mono.shape[1]
        M = self._ext().T @ np.asarray(e, dtype=float).reshape(-1, 2)  # (p + 4, 2): with the x rows, the y rows
        out = np.empty(self.shape[1])
        out[:2 * p] = M[:p].ravel()
        out[2 * p:] = M[p:p + 2, 0] + M[p + 2:, 1]
        return out

    def coords_blocks(self, Qbt) -> np.ndarray:
        """``Q_v^T B_v`` of each view, stacked (v * s, k), for ``Qbt`` (v, s, rows) whose rows are B's, view by view
        (every view as many)."""
        v, s_, nr = Qbt.shape
        p = self.mono.shape[1]
        mb = self.mono.reshape(v, nr // 2, p)
        poly = np.stack([Qbt[:, :, 0::2] @ mb, Qbt[:, :, 1::2] @ mb], axis=3).reshape(v, s_, 2 * p)
        rad = np.matmul(Qbt, self.R.reshape(v, nr, -1))
        return np.concatenate([poly, rad], axis=2).reshape(v * s_, -1)

    def coords_views(self, Q) -> np.ndarray:
        """``Q_v^T B_v`` of each view (v, s, k) for ``Q`` (v, rows, s) whose rows are B's, view by view (every view
        as many): as :meth:`coords`, one product of each view's points' parts with its rows (x_i, y_i) side by
        side."""
        v, nr, s_ = Q.shape
        p = self.mono.shape[1]
        ext = self._ext()
        out = np.empty((v, s_, self.shape[1]))
        M = np.matmul(np.swapaxes(ext.reshape(v, nr // 2, p + 4), 1, 2), Q.reshape(v, nr // 2, 2 * s_))
        out[:, :, :2 * p].reshape(v, s_, p, 2)[...] = M[:, :p].reshape(v, p, 2, s_).transpose(0, 3, 1, 2)
        out[:, :, 2 * p:] = np.swapaxes(M[:, p:p + 2, :s_] + M[:, p + 2:, s_:], 1, 2)
        return out

    def field(self, c) -> np.ndarray:
        """(N, 2) the field ``B c`` at the points (x, y), for coefficients ``c`` (k,) of B's columns."""
        p = self.mono.shape[1]
        c = np.asarray(c, dtype=float)
        cm = np.zeros((p + 4, 2))  # the coefficients of the points' parts (see _ext) for the x and y components
        cm[:p, 0] = c[0:2 * p:2]
        cm[:p, 1] = c[1:2 * p:2]
        cm[p:p + 2, 0] = c[2 * p:]
        cm[p + 2:, 1] = c[2 * p:]
        return self._ext() @ cm

    def gram(self) -> np.ndarray:
        """``B^T B`` (k, k) (computed once: the parts are not changed after construction)."""
        if getattr(self, "_gram", None) is None:
            g = self._gram_of_parts()
            g.flags.writeable = False
            self._gram = g
        return self._gram

    def _gram_of_parts(self) -> np.ndarray:
        p = self.mono.shape[1]
        ext = self._ext()
        E = ext.T @ ext  # (p + 4, p + 4): the monomials' products, theirs with R's x and y rows, R's rows'
        G = np.zeros((self.shape[1],) * 2)
        mm = E[:p, :p]
        G[0:2 * p:2, 0:2 * p:2] = mm
        G[1:2 * p:2, 1:2 * p:2] = mm
        G[0:2 * p:2, 2 * p:] = E[:p, p:p + 2]
        G[1:2 * p:2, 2 * p:] = E[:p, p + 2:]
        G[2 * p:, :2 * p] = G[:2 * p, 2 * p:].T
        G[2 * p:, 2 * p:] = E[p:p + 2, p:p + 2] + E[p + 2:, p + 2:]
        return G


def field_parts(pts, c_mm, half_mm) -> FieldParts:
    """:func:`field_basis` in parts (:class:`FieldParts`)."""
    pts = np.asarray(pts, dtype=float)
    if pts.ndim == 2 and _jit.use_compiled(pts.shape[0]):  # the same products in one loop (tested equal)
        from psdcal.calibration._fields_kernel import field_parts_ext as kernel

        half = np.asarray(half_mm, dtype=float)
        if half.shape != (2,):  # a scalar: both axes
            half = np.broadcast_to(half, (2,)).copy()
        return FieldParts(*kernel(np.ascontiguousarray(pts), np.asarray(c_mm, dtype=float), half, FIELD_DEGREE))
    u = pts / half_mm
    n = pts.shape[0]
    # the monomials u^i v^j (i + j <= FIELD_DEGREE) from the powers of u and v, in the order i, then j
    pu = np.empty((n, FIELD_DEGREE + 1))
    pv = np.empty((n, FIELD_DEGREE + 1))
    pu[:, 0] = pv[:, 0] = 1.0
    for q in range(1, FIELD_DEGREE + 1):  # products, not pow
        np.multiply(pu[:, q - 1], u[:, 0], out=pu[:, q])
        np.multiply(pv[:, q - 1], u[:, 1], out=pv[:, q])
    ij = [(i, j) for i in range(FIELD_DEGREE + 1) for j in range(FIELD_DEGREE + 1 - i)]
    mono = pu[:, [i for i, _ in ij]] * pv[:, [j for _, j in ij]]  # (N, n_mono)
    d = (pts - np.asarray(c_mm)) / half_mm
    r2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]
    R = np.empty((n, 2, 2))
    R[:, :, 0] = d * (r2 * r2)[:, None]
    R[:, :, 1] = d * (r2 * r2 * r2)[:, None]
    return FieldParts(mono, R.reshape(2 * n, 2))




# -- the projector from each view's Gram matrix -------------------------------------------
def normal_transforms(K, n_global: int, one_pass_cond: float = CHOLQR_ONE_PASS_COND):
    """The bases' transforms from each view's Gram matrix (the numpy reference of
    :func:`psdcal.calibration._verdict_kernel.normal_transforms`).

    ``K`` (v, k, k): ``X_v^T X_v`` with ``X_v = [A_v (6 pose columns) | G_v (n_global) | ...]``. Returns
    ``(ok, T (v, 6 + g, 6 + g), Rg (g, g), gtg_view (v, g, g))``: ``[Qb_v | Qg_v] = [A_v | G_v] T_v`` are
    orthonormal bases of view v's pose columns and of the global columns with the poses projected out
    (``Gt``), ``Gt = Qg Rg``, and ``gtg_view[v] = Gt_v^T Gt_v`` (the Schur complement of ``A_v^T A_v``). ok is
    False (the other arrays meaningless) when a block is conditioned worse than ``one_pass_cond`` (one Cholesky
    QR pass would not be orthonormal to 1e-10) or has a zero column.
    """
    s, g = POSE, int(n_global)
    v = K.shape[0]
    fail = (False, np.zeros((v, s + g, s + g)), np.zeros((g, g)), np.zeros((v, g, g)))
    Kaa = K[:, :s, :s]
    d = np.sqrt(np.diagonal(Kaa, axis1=1, axis2=2))  # the pose columns' norms
    if not np.all(d > 0) or not np.all(np.isfinite(d)):
        return fail
    lam, V = np.linalg.eigh(Kaa / (d[:, :, None] * d[:, None, :]))
    if not np.all(np.isfinite(lam)) or not np.all(lam[:, 0] > lam[:, -1] / one_pass_cond ** 2):
        return fail
    Mb = V / d[:, :, None] / np.sqrt(lam)[:, None, :]  # Qb_v = A_v Mb_v, _cholqr2's first pass
    cb = np.swapaxes(Mb, 1, 2) @ K[:, :s, s:s + g]  # Qb_v^T G_v
    gtg_view = K[:, s:s + g, s:s + g] - np.swapaxes(cb, 1, 2) @ cb
    T = np.zeros((v, s + g, s + g))
    T[:, :s, :s] = Mb
    if g == 0:
        return True, T, np.zeros((0, 0)), gtg_view
    # the global columns scaled to norm 1 over all rows, projected off the poses: their Gram matrix, its
    # eigenproblem (_cholqr2 of the projected columns as they are: a column the poses mostly absorb is short)
    nrm = np.maximum(np.sqrt(np.maximum(np.diagonal(K[:, s:s + g, s:s + g], axis1=1, axis2=2).sum(axis=0), 0.0)),
                     1e-300)
    Kp = gtg_view.sum(axis=0) / np.outer(nrm, nrm)
    dp = np.sqrt(np.diag(Kp))
    if not np.all(dp > 0) or not np.all(np.isfinite(dp)):
        return fail
    lg, Vg = np.linalg.eigh(Kp)
    if not np.all(np.isfinite(lg)) or not lg[0] > lg[-1] / one_pass_cond ** 2:
        return fail
    Mg = Vg / nrm[:, None] / np.sqrt(lg)[None, :]  # Qg = Gt Mg (Gt in natural units)
    T[:, :s, s:] = -(Mb @ cb) @ Mg  # Gt_v = G_v - A_v Mb_v cb_v
    T[:, s:, s:] = Mg
    Rg = (np.sqrt(lg)[:, None] * Vg.T) * nrm[None, :]  # Mg^-1
    return True, T, Rg, gtg_view


def normal_bases(X, n_global: int, n_extra: int, row_img, n_img: int, *, pose_last: bool = False, dense=None):
    """The projector's bases from each view's Gram matrix (:class:`Blocks`), None when the rows are not in the
    dense layout (views in order, as many rows each) or a block fails the one-pass conditioning test
    (:func:`normal_transforms`): the caller then takes the QR path.

    ``X`` (m, k) C-contiguous: each row's own view's six pose columns, then the ``n_global`` global columns
    (natural units), then ``n_extra`` more columns whose projected Gram matrix is wanted (the richer model's),
    then any others (ignored); with ``pose_last`` the global, extra and other columns come first and the six pose
    columns last (the order of :func:`psdcal.calibration._verdict_jacobian.rich_jacobian`). ``row_img`` (m,) the
    view of each row; ``dense`` True when the caller knows the layout dense (not checked again).
    """
    m = row_img.size
    if m == 0 or m % n_img:
        return None
    nr = m // n_img
    if not dense and not (row_img[0] == 0 and bool(np.all(np.diff(row_img) >= 0))
                          and bool(np.all(np.bincount(row_img, minlength=n_img) == nr))):
        return None
    s, g = POSE, int(n_global)
    k = s + g + int(n_extra)
    if pose_last:  # each view's Gram matrix of all the columns, reordered (pose, global, extra)
        kx = X.shape[1]
        Xb = X.reshape(n_img, nr, kx)
        order = _pose_first_order(kx, g + int(n_extra))
        K = np.matmul(np.swapaxes(Xb, 1, 2), Xb)[:, order[:, None], order]
    else:
        Xb = X.reshape(n_img, nr, X.shape[1])[:, :, :k]
        K = np.matmul(np.swapaxes(Xb, 1, 2), Xb)  # (v, k, k) each view's Gram matrix
    if _jit.use_compiled(m // 2):
        from psdcal.calibration import _verdict_kernel as vk

        ok, T, Rg, gtg_view = vk.normal_transforms(K, g, float(CHOLQR_ONE_PASS_COND))
    else:
        ok, T, Rg, gtg_view = normal_transforms(K, g, CHOLQR_ONE_PASS_COND)
    if not ok:
        return None
    if pose_last:  # [Qb_v | Qg_v] = X_v T_v with T's rows at X's columns (zero at the extra and other ones)
        Tx = np.zeros((n_img, kx, s + g))
        Tx[:, kx - s:] = T[:, :s]
        Tx[:, :g] = T[:, s:]
        Q = np.matmul(Xb, Tx)
    else:
        Q = np.matmul(Xb[:, :, :s + g], T)  # (v, nr, 6 + g): [Qb_v | Qg_v]
    return Blocks(K, T, Rg, gtg_view, Q, g)


def _pose_first_order(kx: int, n_first: int) -> np.ndarray:
    """The columns of a pose-last layout (``kx`` columns, the six pose ones last) in the pose-first order: the
    six pose columns, then the first ``n_first`` (global, extra)."""
    return np.concatenate([np.arange(kx - POSE, kx), np.arange(n_first)])


@dataclass(frozen=True)
class Blocks:
    """The Jacobian's per-view Gram matrices and the projector built from them (:func:`normal_bases`).

    ``gram`` (v, k, k) each view's ``X_v^T X_v`` (pose, global, extra columns); ``T`` (v, 6 + g, 6 + g) the
    transforms ``[Qb_v | Qg_v] = [A_v | G_v] T_v``; ``Rg`` (g, g) with ``Gt = Qg Rg``; ``gtg_view`` (v, g, g)
    each view's ``Gt_v^T Gt_v``; ``Q`` (v, nr, 6 + g) the bases' rows view by view."""

    gram: np.ndarray
    T: np.ndarray
    Rg: np.ndarray
    gtg_view: np.ndarray
    Q: np.ndarray
    n_global: int

    @property
    def rank(self) -> int:
        return self.Q.shape[0] * POSE + self.n_global

    @cached_property
    def gtg(self) -> np.ndarray:
        """(g, g) ``Gt^T Gt`` (the Schur complement of the pose blocks in the Jacobian's Gram matrix)."""
        return self.gtg_view.sum(axis=0)

    @cached_property
    def h(self) -> np.ndarray:
        """(m,) the leverages: the squared rows of the bases."""
        Q = self.Q
        return ((Q * Q) @ np.ones(Q.shape[2])).reshape(-1)  # (einsum's loop is slower on these shapes)

    @cached_property
    def qg(self) -> np.ndarray:
        """(m, g) the global basis (contiguous)."""
        return np.ascontiguousarray(self.Q[:, :, POSE:]).reshape(-1, self.n_global)

    def gt(self) -> np.ndarray:
        """(m, g) the profiled global Jacobian ``Gt = Qg Rg``."""
        return self.qg @ self.Rg

    def coords(self, B) -> np.ndarray:
        """(v, 6 + g, k) each view's ``[Qb_v | Qg_v]^T B_v`` of B (m, k) or :class:`FieldParts` (memoised on the
        latter)."""
        if isinstance(B, FieldParts):
            return B.memo("block_coords", self, lambda: B.coords_views(self.Q))
        v, nr = self.Q.shape[:2]
        return np.matmul(np.swapaxes(self.Q, 1, 2), B.reshape(v, nr, B.shape[1]))

    def _split_coords(self, B):
        """:meth:`_split` of B's :meth:`coords` (memoised on a :class:`FieldParts`, whose projected Gram matrix and
        ``Gt^T B`` both need them)."""
        if isinstance(B, FieldParts):
            return B.memo("block_split", self, lambda: self._split(self.coords(B)))
        return self._split(self.coords(B))

    def _split(self, c):
        """Coordinates ``c`` (v, 6 + g, k) -> (the pose ones (v * 6, k), the global ones (g, k))."""
        return c[:, :POSE].reshape(-1, c.shape[2]), c[:, POSE:].sum(axis=0)

    def perp_pose(self, B) -> np.ndarray:
        """B (m, k) less its part on each view's pose basis."""
        B = np.asarray(B, dtype=float)
        v, nr = self.Q.shape[:2]
        Bb = B.reshape(v, nr, B.shape[1])
        Qb = self.Q[:, :, :POSE]
        return (Bb - np.matmul(Qb, np.matmul(np.swapaxes(Qb, 1, 2), Bb))).reshape(B.shape)

    def perp(self, B) -> np.ndarray:
        """``(I - P) B`` for B (m, k): less its part on the pose bases (view by view) and on ``Qg``."""
        B = np.asarray(B, dtype=float)
        v, nr = self.Q.shape[:2]
        Bb = B.reshape(v, nr, B.shape[1])
        c = np.matmul(np.swapaxes(self.Q, 1, 2), Bb)
        c[:, POSE:] = c[:, POSE:].sum(axis=0)  # Qg^T B: over all views
        return (Bb - np.matmul(self.Q, c)).reshape(B.shape)

    def pgram(self, B, btb=None) -> np.ndarray:
        """``((I - P) B)^T (I - P) B`` from ``B^T B`` (``btb`` when given) and B's coordinates on the bases."""
        if not isinstance(B, FieldParts):
            B = np.asarray(B, dtype=float)
        cb, cg = self._split_coords(B)
        if btb is None:
            btb = B.gram() if isinstance(B, FieldParts) else B.T @ B
        return btb - cb.T @ cb - cg.T @ cg

    def gt_t(self, B) -> np.ndarray:
        """(g, k) ``Gt^T B`` (= ``Rg^T Qg^T B``)."""
        return self.Rg.T @ self._split_coords(B)[1]

    @cached_property
    def extra(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(``E^T E``, the Gram matrix of ``(I - P) E``, ``Gt^T E``) of the extra columns E, from the Gram matrices
        alone."""
        s, g = POSE, self.n_global
        K = self.gram
        c = np.matmul(np.swapaxes(self.T, 1, 2), K[:, :s + g, s + g:])  # [Qb_v | Qg_v]^T E_v
        cb, cg = self._split(c)
        btb = K[:, s + g:, s + g:].sum(axis=0)
        return btb, btb - cb.T @ cb - cg.T @ cg, self.Rg.T @ cg
