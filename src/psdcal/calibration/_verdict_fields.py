"""The verdict's field tests: the nested F-test of extra columns on the residuals and the linearised refit with them.

On the fit linearised at its solution (:class:`~psdcal.calibration._verdict_linear.Linear`):

- :func:`f_test` / :func:`explained`: the residuals' sum of squares along the
  span of extra columns ``B`` (a smooth field over the sensor, the terms the
  model leaves out) once the Jacobian's span is projected out, and its F-test;
  from the Gram matrices of ``B`` and of ``(I - P) B`` and from ``B^T e``
  (small eigenproblems, never a tall factorisation);
- :func:`field_shift`: the linearised refit with those columns: their
  coefficients and the shift of the global parameters;
- :func:`terms_test`: the test of the terms the model leaves out (together and
  one by one);
- :func:`structure_fields`, :func:`structure_test`: the ``structure`` check's fields and test.

The small-matrix steps run compiled where numba is available
(:mod:`psdcal.calibration._fields_kernel`); the numpy code here is their
reference.
"""
from __future__ import annotations

import math

import numpy as np

from psdcal import _jit, _stats
from psdcal.calibration._verdict_blocks import FieldParts, field_parts
from psdcal.calibration._verdict_linear import Linear, linearise


def _sym_eig_desc(K):
    """Eigenvalues (descending, clipped at 0) and eigenvectors (columns) of the symmetric matrix ``K``."""
    lam, V = np.linalg.eigh(K)
    return np.maximum(lam[::-1], 0.0), V[:, ::-1]


def _span_basis(Kn) -> np.ndarray:
    """M (k, r) such that ``Bn M`` is an orthonormal basis of span(Bn), from ``Kn = Bn^T Bn`` (unit columns): the
    directions of an eigenvalue below 1e-12 of the largest dropped. ``L^-T`` of the Cholesky factor ``L`` where no
    direction is (the smallest eigenvalue is at least ``1 / ||L^-1||_F^2``, the largest at most the trace), else from
    the eigenproblem."""
    try:
        Li = np.linalg.inv(np.linalg.cholesky(Kn))
    except np.linalg.LinAlgError:
        Li = None
    if Li is not None and np.all(np.isfinite(Li)) and 1.0 / float(np.sum(Li * Li)) > 1e-12 * float(np.trace(Kn)):
        return Li.T
    lam0, V0 = _sym_eig_desc(Kn)
    keep = lam0 > 1e-12 * max(float(lam0[0]), 1e-300)
    return V0[:, keep] / np.sqrt(lam0[keep])


def _bte(lin: Linear, B) -> np.ndarray:
    """(k,) ``B^T e`` (memoised on :class:`FieldParts`: the F-test and the shift share it)."""
    if B is lin.extra:
        return lin.extra_te
    if not isinstance(B, FieldParts):
        return B.T @ lin.e
    return B.memo("bte", lin, lambda: B.t_dot(lin.e))


def _basis(lin: Linear, B, weights: bool = True):
    """The residuals' coordinates ``ute`` on an orthonormal basis U of span((I - P) B) (the fields the parameters do
    not absorb), and the map from them to coefficients of B's columns: ``c = W ute``.

    U is that of the singular value decomposition ``(I - P) B = U S V^T`` (the
    directions with a singular value below 1e-2 of the largest dropped), found
    from the Gram matrix ``V S^2 V^T`` (:meth:`Linear.gram_perp`): ``U^T e =
    S^-1 V^T B^T e`` as ``e`` is itself projected off the Jacobian. U is never
    formed (small eigenproblems instead of a tall SVD). Without ``weights``, W is None (the test needs ute only).
    """
    parts = isinstance(B, FieldParts)
    if B is lin.extra:
        btb, K = lin.extra_gram
    else:
        btb = B.gram() if parts else B.T @ B
        K = lin.gram_perp(B, btb)
    if _jit.use_compiled(lin.e.size // 2):  # the same steps in one kernel (tested against the code below)
        from psdcal.calibration import _fields_kernel as fk

        ok, ute, W = fk.field_coords(btb, K, _bte(lin, B), weights)
        if ok:
            return ute, (W if weights else None)
    scale = np.maximum(np.sqrt(np.maximum(np.diag(btb), 0.0)), 1e-300)
    K = K / np.outer(scale, scale)  # that of B's columns scaled to norm 1
    nb = np.sqrt(np.maximum(np.diag(K), 0.0))
    use = nb > 1e-4  # fields the model's parameters absorb (to 1e-4) test nothing
    if not use.any():
        return np.zeros(0), (np.zeros((B.shape[1], 0)) if weights else None)
    lam, V = _sym_eig_desc(K[np.ix_(use, use)])
    s = np.sqrt(lam)
    keep = s > 1e-2 * s[0]
    s, V = s[keep], V[:, keep]
    bte = _bte(lin, B)
    ute = (V.T @ (bte[use] / scale[use])) / s
    if not weights:
        return ute, None
    W = np.zeros((B.shape[1], s.size))
    W[use] = (V / s) / scale[use, None]
    return ute, W


def explained(lin: Linear, B) -> tuple[float, int]:
    """Sum of squares of the residuals along span(B) minus the Jacobian's span, and its dimension."""
    ute, _ = _basis(lin, B, weights=False)
    if ute.size == 0:
        return 0.0, 0
    return float(ute @ ute), int(ute.size)


def f_test(lin: Linear, B) -> tuple[float, float, int, float]:
    """(F, p, dim, explained sum of squares) of the nested test of the fields ``B`` (m, k) on the residuals;
    (nan, 1, 0, 0) when none is testable."""
    expl, p_dim = explained(lin, B)
    dof = lin.dof
    if p_dim == 0 or dof - p_dim <= 0:
        return float("nan"), 1.0, 0, 0.0
    ssr = float(lin.e @ lin.e)
    F = (expl / p_dim) / max((ssr - expl) / (dof - p_dim), 1e-300)
    return float(F), float(_stats.f_sf(F, p_dim, dof - p_dim)), int(p_dim), float(expl)


def field_shift(lin: Linear, B, *, min_visible: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The linearised refit with the extra columns ``B`` (m, k): (their coefficients c (k,), the shift of the
    global parameters (ng,)), both in natural units (B's columns are d(model)/d(coefficient)).

    ``min_visible`` > 0 keeps only the combinations of B's columns whose part
    off the Jacobian's span is at least that fraction of their norm: a field
    the parameters absorb almost wholly is seen only through its small visible
    part, and extrapolating that part to the whole field multiplies the noise
    (a generic field has no model linking the two parts; a model term has).
    """
    parts = isinstance(B, FieldParts)
    if not parts:
        B = np.asarray(B, dtype=float)
    if lin.g is None or B.shape[1] == 0:
        return np.zeros(B.shape[1]), np.zeros(len(lin.names))

    def gt_b(c):  # Gt^T B c (the fields' parts give Gt^T B without the dense fields)
        return lin.gt_t(B) @ c

    if min_visible <= 0:
        ute, W = _basis(lin, B)
        if ute.size == 0:
            return np.zeros(B.shape[1]), np.zeros(len(lin.names))
        c = W @ ute
        return c, -lin.ninv @ gt_b(c)
    # an orthonormal basis Qb = Bn M of span(B) (from B's Gram matrix), then the singular values s of (I - P) Qb
    # (the visible fraction of each combination) from its Gram matrix M^T K M: no tall factorisation. Bn is B with
    # columns scaled to norm 1: its Gram matrices are B's scaled (one Gram of B serves the F-test and this).
    btb = B.gram() if parts else B.T @ B
    if _jit.use_compiled(lin.e.size // 2):  # the same steps in one kernel (tested against the code below)
        from psdcal.calibration import _fields_kernel as fk

        ok, c = fk.visible_fit(btb, lin.gram_perp(B, btb), _bte(lin, B), float(min_visible))
        if ok:
            return c, -lin.ninv @ gt_b(c)
    scale = np.maximum(np.sqrt(np.maximum(np.diag(btb), 0.0)), 1e-300)
    ss = np.outer(scale, scale)
    M = _span_basis(btb / ss)
    lam, V = _sym_eig_desc(M.T @ (lin.gram_perp(B, btb) / ss) @ M)
    s = np.sqrt(np.minimum(lam, 1.0))
    use = s > min_visible
    if not use.any():
        return np.zeros(B.shape[1]), np.zeros(len(lin.names))
    bte = _bte(lin, B) / scale  # Bn^T e
    ute = (V[:, use].T @ (M.T @ bte)) / s[use]  # the residuals on (I - P) Qb's left singular vectors
    a = M @ (V[:, use] @ (ute / s[use]))  # coefficients on Bn
    c = a / scale
    return c, -lin.ninv @ gt_b(c)



def terms_test(lin: Linear):
    """(F, p, dim, most significant term) of the nested-model test of the left-out terms, None without any."""
    if lin.extra is None or lin.extra.shape[1] == 0:
        return None
    dof = lin.dof
    ssr = float(lin.e @ lin.e)
    F, p, p_dim, _ = f_test(lin, lin.extra)
    if p_dim == 0:
        return None
    # each term alone too (one degree of freedom: more power for a single missing term); Bonferroni over all tests
    btb, K = lin.extra_gram
    # per column (Python floats: a handful of terms), the norm, the norm of the projected unit column, and
    # ((I - P) Bn)^T e for the unit column Bn (e is itself projected)
    diag_b, diag_k, te = np.diag(btb).tolist(), np.diag(K).tolist(), lin.extra_te.tolist()
    cand = []  # (F, name) of each testable term alone
    for k, name in enumerate(lin.extra_names):
        norm = max(math.sqrt(max(diag_b[k], 0.0)), 1e-300)
        nb = math.sqrt(max(diag_k[k], 0.0)) / norm
        if nb > 1e-4:  # as in explained(): a column the model absorbs tests nothing
            ek = ((te[k] / norm) / nb) ** 2
            cand.append((ek / max((ssr - ek) / (dof - 1), 1e-300), name))
    # the p-value of one degree of freedom falls as F grows: the smallest (all that the decision and the message
    # use) is the largest F's, unless another F ties it or it underflows to 0 (then the tuples' order decides)
    top = max((F for F, _ in cand), default=0.0)
    single = [(float(_stats.f_sf(F, 1, dof - 1)), F, name) for F, name in cand if F == top]
    if len(single) > 1 or (single and single[0][0] == 0.0):
        single = [(float(_stats.f_sf(F, 1, dof - 1)), F, name) for F, name in cand]
    n_tests = 1 + len(cand)
    if single and min(single)[0] < p:
        pk, Fk, _ = min(single)
        return float(Fk), float(min(1.0, n_tests * pk)), 1, min(single)[2]
    best = min(single)[2] if single else lin.extra_names[0]
    return float(F), float(min(1.0, n_tests * p)), p_dim, best



def structure_test(result, exclude=None) -> tuple[float, float]:
    """(F, p-value) of the verdict's structure check on ``result``'s residuals, ``exclude`` (n_images, M)
    observations left out (the same function the verdict calls: :func:`structure_fields`)."""
    lin = linearise(result, exclude)
    F, p, _, _ = f_test(lin, structure_fields(lin, result))
    return F, p


def structure_fields(lin: Linear, result, *, parts: bool = False):
    """The structure check's fields (m, p) at the modelled points (``parts``: as :class:`FieldParts`)."""
    fp = field_parts(lin.pts, result.intrinsics.c, np.asarray(result.sensor_mm, float) / 2)
    return fp if parts else fp.dense()
