"""The normal equations of the refinement: dense, or block-sparse with a Schur complement (Section 3.1).

The pose columns of a point are non-zero only for its own view, so ``J^T J`` has a dense global block
``U`` (intrinsics, distortion, gains), one 6 x 6 block ``V_i`` per view and their couplings ``W_i``:

- :class:`DenseNormal`: ``J^T J`` and ``J^T r`` as they are (few views);
- :class:`BlockNormal`: ``(U, W, V)`` solved through the Schur complement of the pose blocks, with the
  compiled kernels of :mod:`._gram_kernel` and :mod:`._schur_kernel` and the numpy references here
  (:func:`block_normal_reference`, :func:`schur_solve_reference`, :func:`schur_covariance_reference`).

:func:`psdcal.calibration._lm.levenberg_marquardt` solves either.
"""
from __future__ import annotations

import numpy as np


def compact_from_dense(J, img, ng):
    """Compact block form (2N, ng + 6) of a dense Jacobian (2N, ng + 6 n) whose pose entries of
    observation i lie only in the six columns of its view ``img[i]`` (numpy)."""
    rows = np.arange(J.shape[0])
    cols = ng + 6 * np.repeat(img, 2)[:, None] + np.arange(6)[None, :]
    return np.concatenate([J[:, :ng], J[rows[:, None], cols]], axis=1)


def block_normal_reference(Jc, r, img, n_views):
    """Numpy reference of :func:`psdcal.calibration._gram_kernel.gram_block_normal`:
    ``(U, W, V, gg, gp)`` of a compact Jacobian."""
    ng = Jc.shape[1] - 6
    Jg = Jc[:, :ng]
    Jp = Jc[:, ng:].reshape(-1, 2, 6)
    rr = r.reshape(-1, 2)
    U = Jg.T @ Jg
    gg = Jg.T @ r
    Wi = np.einsum("nca,ncb->nab", Jg.reshape(-1, 2, ng), Jp)  # (N, ng, 6)
    Vi = np.einsum("nca,ncb->nab", Jp, Jp)
    gi = np.einsum("nca,nc->na", Jp, rr)
    W = np.zeros((n_views, ng, 6))
    V = np.zeros((n_views, 6, 6))
    gp = np.zeros((n_views, 6))
    np.add.at(W, img, Wi)
    np.add.at(V, img, Vi)
    np.add.at(gp, img, gi)
    return U, W, V, gg, gp


def schur_solve_reference(U, W, V, gg, gp, damp_g, damp_p):
    """Numpy reference of :func:`psdcal.calibration._schur_kernel.schur_solve` (batched LAPACK)."""
    n = V.shape[0]
    ng = U.shape[0]
    Vd = V + np.einsum("na,ab->nab", damp_p, np.eye(6))
    try:
        np.linalg.cholesky(Vd)
        Y = np.linalg.solve(Vd, np.swapaxes(W, 1, 2))  # (n, 6, ng)
        y = np.linalg.solve(Vd, gp[:, :, None])[:, :, 0]
        S = U + np.diag(damp_g) - np.einsum("nak,nkb->ab", W, Y)
        b = gg - np.einsum("nak,nk->a", W, y)
        np.linalg.cholesky(S)
        hg = np.linalg.solve(S, b)
    except np.linalg.LinAlgError:
        return False, np.zeros(ng), np.zeros((n, 6))
    hp = np.linalg.solve(Vd, (gp - np.einsum("nak,a->nk", W, hg))[:, :, None])[:, :, 0]
    return True, hg, hp


def schur_covariance_reference(U, W, V):
    """Numpy reference of :func:`psdcal.calibration._schur_kernel.schur_covariance`."""
    n = V.shape[0]
    ng = U.shape[0]
    try:
        np.linalg.cholesky(V)
        Vinv = np.linalg.inv(V)
        Y = Vinv @ np.swapaxes(W, 1, 2)
        S = U - np.einsum("nak,nkb->ab", W, Y)
        np.linalg.cholesky(S)
        Cg = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return False, np.zeros((ng, ng)), np.zeros((n, 6, 6)), np.zeros((n, ng, 6))
    Cx = -np.einsum("ab,nkb->nak", Cg, Y)
    Cp = Vinv - np.einsum("nka,nab->nkb", Y, Cx)
    return True, Cg, Cp, Cx


class DenseNormal:
    """Dense normal equations ``A h = g`` for :func:`levenberg_marquardt`.

    Attributes ``A`` (n, n) and ``g`` (n,) may be added to (priors, extra rows)
    before the solver uses them.
    """

    def __init__(self, A, g):
        self.A = A
        self.g = g

    def diagonal(self):
        return np.diag(self.A).copy()

    def solve(self, damp):
        """``(A + diag(damp))^-1 g``, or None when the matrix is not positive definite."""
        Ad = self.A.copy()
        Ad.flat[:: Ad.shape[0] + 1] += damp
        try:
            L = np.linalg.cholesky(Ad)
        except np.linalg.LinAlgError:
            return None
        return _cho_solve_dense(L, self.g)

    def inverse(self):
        """``A^-1`` (pseudo-inverse when singular)."""
        try:
            return np.linalg.inv(self.A)
        except np.linalg.LinAlgError:
            return np.linalg.pinv(self.A)


def _cho_solve_dense(L, b):
    """``(L L^T)^-1 b`` for a lower-triangular L (two triangular solves, numpy only)."""
    y = np.linalg.solve(L, b)
    return np.linalg.solve(L.T, y)


class BlockNormal:
    """Normal equations of a block-sparse calibration Jacobian, kept in blocks.

    ``A = [[U, W_1 .. W_n], [W_1^T .. W_n^T, diag(V_1 .. V_n)]]`` with the
    global block ``U`` (ng, ng), the couplings ``W`` (n, ng, 6) and the pose
    blocks ``V`` (n, 6, 6); ``g = (gg, gp.ravel())``. Steps and covariances
    eliminate the poses through the Schur complement (the reduced system of
    the global parameters), so memory and work grow linearly with the number
    of views. Extra residual rows acting on the global parameters only
    (priors) add to ``U`` and ``gg``.
    """

    def __init__(self, U, W, V, gg, gp, compiled: bool = True):
        self.U, self.W, self.V, self.gg, self.gp = U, W, V, gg, gp
        self.compiled = compiled

    @property
    def n_global(self) -> int:
        return self.U.shape[0]

    @property
    def g(self):
        return np.concatenate([self.gg, self.gp.ravel()])

    def diagonal(self):
        return np.concatenate([np.diag(self.U), np.einsum("naa->na", self.V).ravel()])

    def solve(self, damp):
        """``(A + diag(damp))^-1 g`` by the Schur complement, or None when not positive definite."""
        ng = self.n_global
        dg, dp = damp[:ng], damp[ng:].reshape(-1, 6)
        if self.compiled:
            from psdcal.calibration._schur_kernel import schur_solve

            ok, hg, hp = schur_solve(self.U, self.W, self.V, self.gg, self.gp, dg, dp)
        else:
            ok, hg, hp = schur_solve_reference(self.U, self.W, self.V, self.gg, self.gp, dg, dp)
        if not ok:
            return None
        return np.concatenate([hg, hp.ravel()])

    def covariance_blocks(self):
        """Blocks of ``A^-1``: global (ng, ng), pose (n, 6, 6), global-pose (n, ng, 6).

        When A is singular (an unidentifiable direction) the blocks come from
        the pseudo-inverse of the dense A (rare; memory quadratic in views).
        """
        if self.compiled:
            from psdcal.calibration._schur_kernel import schur_covariance

            ok, Cg, Cp, Cx = schur_covariance(self.U, self.W, self.V)
        else:
            ok, Cg, Cp, Cx = schur_covariance_reference(self.U, self.W, self.V)
        if ok and np.all(np.isfinite(Cg)):
            return Cg, Cp, Cx
        ng, n = self.n_global, self.V.shape[0]
        C = np.linalg.pinv(self.dense())
        Cg = C[:ng, :ng]
        Cp = np.stack([C[ng + 6 * v : ng + 6 * v + 6, ng + 6 * v : ng + 6 * v + 6] for v in range(n)]) if n else np.zeros((0, 6, 6))
        Cx = np.stack([C[:ng, ng + 6 * v : ng + 6 * v + 6] for v in range(n)]) if n else np.zeros((0, ng, 6))
        return Cg, Cp, Cx

    def dense(self):
        """The dense ``A`` (for tests and small problems)."""
        ng, n = self.n_global, self.V.shape[0]
        A = np.zeros((ng + 6 * n, ng + 6 * n))
        A[:ng, :ng] = self.U
        for v in range(n):
            sl = slice(ng + 6 * v, ng + 6 * v + 6)
            A[:ng, sl] = self.W[v]
            A[sl, :ng] = self.W[v].T
            A[sl, sl] = self.V[v]
        return A


def _as_system(val):
    """A :class:`DenseNormal` / :class:`BlockNormal` from what a ``normal`` callback returned."""
    if isinstance(val, tuple):
        return DenseNormal(*val)
    return val
