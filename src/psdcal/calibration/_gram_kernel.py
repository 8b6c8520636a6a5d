"""Block normal equations of a compact Jacobian, the long runs of a view summed in SIMD-friendly chunks.

:func:`gram_block_normal` returns what
:func:`psdcal.calibration._image_kernel.block_normal` returns (the blocks ``U``,
``W_v``, ``V_v`` of ``J^T J`` and the parts ``gg``, ``gp`` of ``J^T r``; the
numpy reference is :func:`psdcal.calibration._normal.block_normal_reference`),
and sums the same products. Only the order of the additions differs where a
view's run of consecutive observations has at least :data:`CHUNK_MIN_POINTS`
points (a chessboard, Zhang's 256 corners):

- the rows of the run are copied, :data:`CHUNK_POINTS` points at a time, into
  a column-major buffer (one row of the buffer per column of ``J``, the
  residuals in its last row), which stays in the first-level cache;
- each entry of the chunk's ``(m, m)`` lower triangle and of its ``J^T r`` is
  then one dot product of two contiguous rows of the buffer
  (:func:`_chunk_gram`, compiled with :func:`psdcal._jit.njit_sum`: the
  compiler splits each sum over SIMD lanes and accumulators, about four times
  fewer instructions than the row-by-row loop).

The chunked sums differ from the row-by-row ones at rounding level (relative
1e-16 of the sums of squares); shorter runs (the 14-point templates) take the
row-by-row loop of ``block_normal`` itself and give its bits exactly.
tests/test_gram_kernel.py compares both with the numpy reference.
"""
from __future__ import annotations

import numpy as np

from psdcal._jit import njit, njit_sum
from psdcal.calibration._image_kernel import add_view_block, mirror_blocks

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
def _run_rows(Jc, r, i0, i1, m, M, gl):
    """The sums of observations ``i0 .. i1 - 1`` row by row (``block_normal``'s loop, the same order)."""
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
    """Normal equations of a compact block Jacobian, kept in blocks (as ``_image_kernel.block_normal``).

    Parameters
    ----------
    Jc : (2N, ng + 6) compact Jacobian (:func:`~psdcal.calibration._image_kernel.image_model`),
    r : (2N,) residuals, img : (N,) int view of each observation, n_views : int

    Returns
    -------
    U : (ng, ng), W : (n_views, ng, 6), V : (n_views, 6, 6), gg : (ng,), gp : (n_views, 6)
        The blocks of ``J^T J`` and ``J^T r``; runs of :data:`CHUNK_MIN_POINTS` or more observations of
        one view summed in chunks (rounding-level differences), shorter ones row by row (the same bits
        as ``block_normal``).
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
