"""Block normal equations of a compact Jacobian, the long runs of a view summed in SIMD-friendly chunks.

:func:`gram_block_normal` returns the blocks ``U``, ``W_v``, ``V_v`` of ``J^T J`` and the
parts ``gg``, ``gp`` of ``J^T r`` of a compact block Jacobian (the numpy reference is
:func:`psdcal.calibration._normal.block_normal_reference`). Each run of consecutive
observations of one view is summed into one local ``(m, m)`` block, then added to ``U``,
``W_v``, ``V_v`` (:func:`add_view_block`): the inner loop touches a small array that stays in
cache instead of the view's blocks in the big arrays. A run shorter than
:data:`CHUNK_MIN_POINTS` (the 14-point templates) is summed row by row, the two rows of an
observation at once (:func:`_run_rows`); a longer one (a chessboard, Zhang's 256 corners) in
chunks:

- the rows of the run are copied, :data:`CHUNK_POINTS` points at a time, into
  a column-major buffer (one row of the buffer per column of ``J``, the
  residuals in its last row), which stays in the first-level cache;
- each entry of the chunk's ``(m, m)`` lower triangle and of its ``J^T r`` is
  then one dot product of two contiguous rows of the buffer
  (:func:`_chunk_gram`, compiled with :func:`psdcal._jit.njit_sum`: the
  compiler splits each sum over SIMD lanes and accumulators, about four times
  fewer instructions than the row-by-row loop).

The chunked sums differ from the row-by-row ones at rounding level (relative
1e-16 of the sums of squares). tests/test_gram_kernel.py compares both with the numpy reference.
"""
from __future__ import annotations

import numpy as np

from psdcal._jit import njit, njit_sum

#: A view's run of consecutive observations this long or longer is summed in chunks (shorter: row by row).
CHUNK_MIN_POINTS = 64
#: Observations (two rows each) per chunk: the buffer of a chunk (ng + 7 rows of 2 CHUNK_POINTS values,
#: 15 KB for ng = 8) stays in the first-level cache.
CHUNK_POINTS = 64


@njit_sum
def _chunk_gram(B, L, m, M, gl):
    """Add the Gram matrix of the chunk ``B[:m, :L]`` to the lower triangle of ``M`` (m, m) and its products
    with the residuals ``B[m, :L]`` to ``gl`` (m,): the sums of one chunk, in any order.

    Row ``a`` of the chunk is multiplied with four rows ``b .. b + 3`` in one pass (five loads for four
    products instead of eight)."""
    for a in range(m):
        b = 0
        while b + 3 <= a:
            t0 = t1 = t2 = t3 = 0.0
            for k in range(L):
                x = B[a, k]
                t0 += x * B[b, k]
                t1 += x * B[b + 1, k]
                t2 += x * B[b + 2, k]
                t3 += x * B[b + 3, k]
            M[a, b] += t0
            M[a, b + 1] += t1
            M[a, b + 2] += t2
            M[a, b + 3] += t3
            b += 4
        while b <= a:
            t = 0.0
            for k in range(L):
                t += B[a, k] * B[b, k]
            M[a, b] += t
            b += 1
        s = 0.0
        for k in range(L):
            s += B[a, k] * B[m, k]
        gl[a] += s


@njit
def add_view_block(M, gl, v, ng, U, W, V, gg, gp):
    """Add one view's run sums to the blocks: ``M`` (m, m) lower triangle of its ``J^T J`` and ``gl`` (m,) its
    ``J^T r`` (m = ng + 6) into ``U`` (lower triangle), ``W[v]``, ``V[v]`` (lower triangle), ``gg`` and ``gp[v]``."""
    for a in range(ng):
        gg[a] += gl[a]
        for b in range(a + 1):
            U[a, b] += M[a, b]
    for a in range(6):
        gp[v, a] += gl[ng + a]
        for b in range(ng):
            W[v, b, a] += M[ng + a, b]
        for b in range(a + 1):
            V[v, a, b] += M[ng + a, ng + b]


@njit
def mirror_blocks(U, V):
    """Fill the upper triangles of ``U`` (ng, ng) and of each ``V[v]`` (6, 6) from their lower ones, in place."""
    ng = U.shape[0]
    for a in range(ng):
        for b in range(a):
            U[b, a] = U[a, b]
    for v in range(V.shape[0]):
        for a in range(6):
            for b in range(a):
                V[v, b, a] = V[v, a, b]


@njit
def _run_rows(Jc, r, i0, i1, m, M, gl):
    """The sums of observations ``i0 .. i1 - 1`` row by row, the two rows of an observation at once."""
    for i in range(i0, i1):
        r0 = r[2 * i]
        r1 = r[2 * i + 1]
        for a in range(m):
            a0 = Jc[2 * i, a]
            a1 = Jc[2 * i + 1, a]
            gl[a] += a0 * r0 + a1 * r1
            for b in range(a + 1):
                M[a, b] += a0 * Jc[2 * i, b] + a1 * Jc[2 * i + 1, b]


@njit
def _run_chunked(Jc, r, i0, i1, m, M, gl, B):
    """The sums of observations ``i0 .. i1 - 1`` in chunks of :data:`CHUNK_POINTS` (buffer ``B`` (m + 1, 2 CHUNK_POINTS))."""
    i = i0
    while i < i1:
        n = min(CHUNK_POINTS, i1 - i)
        L = 2 * n
        row0 = 2 * i
        for k in range(L):  # transpose the chunk: one contiguous row per column of J, the residuals last
            for a in range(m):
                B[a, k] = Jc[row0 + k, a]
            B[m, k] = r[row0 + k]
        _chunk_gram(B, L, m, M, gl)
        i += n


@njit
def gram_block_normal(Jc, r, img, n_views):
    """Normal equations of a compact block Jacobian, kept in blocks.

    Parameters
    ----------
    Jc : (2N, ng + 6) compact Jacobian (:func:`~psdcal.calibration._image_kernel.image_model`),
    r : (2N,) residuals, img : (N,) int view of each observation, n_views : int

    Returns
    -------
    U : (ng, ng), W : (n_views, ng, 6), V : (n_views, 6, 6), gg : (ng,), gp : (n_views, 6)
        The blocks of ``J^T J`` and ``J^T r``; runs of :data:`CHUNK_MIN_POINTS` or more observations of
        one view summed in chunks (rounding-level differences from the row-by-row sums), shorter ones
        row by row.

    Cost O(N (ng + 6)^2): each observation touches its own view's blocks only.
    """
    m = Jc.shape[1]
    ng = m - 6
    U = np.zeros((ng, ng))
    W = np.zeros((n_views, ng, 6))
    V = np.zeros((n_views, 6, 6))
    gg = np.zeros(ng)
    gp = np.zeros((n_views, 6))
    M = np.empty((m, m))
    gl = np.empty(m)
    B = np.empty((m + 1, 2 * CHUNK_POINTS))
    N = img.shape[0]
    i = 0
    while i < N:
        v = img[i]
        j = i
        while j < N and img[j] == v:
            j += 1
        M[:, :] = 0.0
        gl[:] = 0.0
        if j - i >= CHUNK_MIN_POINTS:
            _run_chunked(Jc, r, i, j, m, M, gl, B)
        else:
            _run_rows(Jc, r, i, j, m, M, gl)
        add_view_block(M, gl, v, ng, U, W, V, gg, gp)
        i = j
    mirror_blocks(U, V)
    return U, W, V, gg, gp
