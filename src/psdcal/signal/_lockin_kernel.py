"""Compiled window sums of the joint lock-in: one pass over each window's samples.

:meth:`psdcal.signal.stream.MultiCarrierLockin._fit` needs, per window of
``n`` samples and per channel, the least-squares coefficients
``coef = P x`` (``P`` the ``(2k + 1, n)`` projection table: ``sin, cos`` of
each carrier and the offset) and the sum of squares ``|x|^2`` (the residual
and the finiteness check).  numpy does that as one small matrix product per
window plus a strided reduction (two passes over the samples, and BLAS's
per-call overhead on a 3 x 1250 x 4 product).

:func:`window_sums` does it in one compiled loop per window: one pass over
the window's rows ``(n, 4)`` per group of up to five projection rows, each
row's four channels multiplied by one table value, and the sum of squares
accumulated in the first pass.  The sums are reassociated (``fastmath``
reassoc and contract only: no assumption about NaN or infinities, so a
non-finite sample still gives a non-finite sum), which lets the compiler
vectorise the loop along the samples (the rows are read flat, with unsigned
indices: see :func:`_window_sums`): the result differs from numpy's by
rounding (relative 1e-15 of ``|P| |x|``), which the tests bound
(``tests/test_locate_fastpath.py``).  The numpy code in
:mod:`psdcal.signal.stream` stays the reference.

numba is imported at the first call (:func:`window_sums` is lazy).
"""
from __future__ import annotations

import math

import numpy as np

#: fastmath flags of the kernel: reassociation (SIMD sums) and fused multiply-add only; never
#: ``nnan``/``ninf`` (a non-finite sample must still give a non-finite sum).
FASTMATH = frozenset({"reassoc", "contract"})


def padded_table(proj_t: np.ndarray) -> np.ndarray:
    """The projection table ``(J, n)`` padded with zero rows to the kernel's groups (5 rows, then 3)."""
    J, n = proj_t.shape
    n5, n3 = _groups(J)
    out = np.zeros((5 * n5 + 3 * n3, n))
    out[:J] = proj_t
    return out


def _groups(J: int) -> tuple[int, int]:
    """Passes of five and of three rows covering ``J`` rows: (J // 5, 0, 1 or 2 passes of three)."""
    n5, r = divmod(int(J), 5)
    return n5, (0 if r == 0 else (2 if r == 4 else 1))


def _window_sums(P, y, n, coef, xx):  # pragma: no cover - compiled
    """``coef[w] = P[:J] @ x[w n:(w + 1) n]`` (J, 4) and ``xx[w] = sum x^2`` (4,) for each window ``w``.

    ``P`` (5 n5 + 3 n3, n): the table padded by :func:`padded_table`; ``y`` (4 nw n,) the windows'
    rows ``x`` (nw n, 4) flattened (C order: sample ``t``'s channel ``c`` at ``4 t + c``); ``n``
    the window's samples as ``np.uint64``; ``coef`` (nw, J, 4), ``xx`` (nw, 4) written.  One pass
    over a window's rows per group of five (or three) table rows: each sample row's four channels
    are multiplied by one table value; the sums of squares are those of the first pass.

    The indices are unsigned and the rows flat on purpose: numba wraps a negative signed index
    (``x[i]`` is ``x[i + len]`` for ``i < 0``), and that select hides from LLVM that channel ``c``
    of sample ``t`` lies at a fixed stride from channel ``c`` of sample ``t + 1``.  With it hidden,
    the loop is vectorised along the samples with gathers (AVX-512 machines: 2.2 ns a row of four
    channels, slower than scalar code); with a provably affine address, with interleaved loads
    (about 1 ns a row for one carrier; the same sums to the bit).
    """
    four = np.uint64(4)
    nw = np.uint64(y.shape[0]) // (four * n)
    J = coef.shape[1]
    n5 = J // 5
    r = J - 5 * n5
    n3 = 0
    if r > 0:
        n3 = 1
    if r == 4:
        n3 = 2
    for w in range(nw):
        b = w * n * four
        first = True
        for g in range(n5):
            j = 5 * g
            q0 = P[j]
            q1 = P[j + 1]
            q2 = P[j + 2]
            q3 = P[j + 3]
            q4 = P[j + 4]
            s0 = s1 = s2 = s3 = 0.0
            a00 = a01 = a02 = a03 = 0.0
            a10 = a11 = a12 = a13 = 0.0
            a20 = a21 = a22 = a23 = 0.0
            a30 = a31 = a32 = a33 = 0.0
            a40 = a41 = a42 = a43 = 0.0
            for t in range(n):
                i = b + four * t  # (unsigned: see above)
                v0 = y[i]
                v1 = y[i + np.uint64(1)]
                v2 = y[i + np.uint64(2)]
                v3 = y[i + np.uint64(3)]
                p = q0[t]
                a00 += p * v0
                a01 += p * v1
                a02 += p * v2
                a03 += p * v3
                p = q1[t]
                a10 += p * v0
                a11 += p * v1
                a12 += p * v2
                a13 += p * v3
                p = q2[t]
                a20 += p * v0
                a21 += p * v1
                a22 += p * v2
                a23 += p * v3
                p = q3[t]
                a30 += p * v0
                a31 += p * v1
                a32 += p * v2
                a33 += p * v3
                p = q4[t]
                a40 += p * v0
                a41 += p * v1
                a42 += p * v2
                a43 += p * v3
                s0 += v0 * v0
                s1 += v1 * v1
                s2 += v2 * v2
                s3 += v3 * v3
            coef[w, j, 0], coef[w, j, 1], coef[w, j, 2], coef[w, j, 3] = a00, a01, a02, a03
            coef[w, j + 1, 0], coef[w, j + 1, 1], coef[w, j + 1, 2], coef[w, j + 1, 3] = a10, a11, a12, a13
            coef[w, j + 2, 0], coef[w, j + 2, 1], coef[w, j + 2, 2], coef[w, j + 2, 3] = a20, a21, a22, a23
            coef[w, j + 3, 0], coef[w, j + 3, 1], coef[w, j + 3, 2], coef[w, j + 3, 3] = a30, a31, a32, a33
            coef[w, j + 4, 0], coef[w, j + 4, 1], coef[w, j + 4, 2], coef[w, j + 4, 3] = a40, a41, a42, a43
            if first:  # the sums of squares of the first pass (every pass makes them: no second loop body)
                xx[w, 0], xx[w, 1], xx[w, 2], xx[w, 3] = s0, s1, s2, s3
                first = False
        for g in range(n3):
            j = 5 * n5 + 3 * g
            q0 = P[j]
            q1 = P[j + 1]
            q2 = P[j + 2]
            s0 = s1 = s2 = s3 = 0.0
            a00 = a01 = a02 = a03 = 0.0
            a10 = a11 = a12 = a13 = 0.0
            a20 = a21 = a22 = a23 = 0.0
            for t in range(n):
                i = b + four * t  # (unsigned: see above)
                v0 = y[i]
                v1 = y[i + np.uint64(1)]
                v2 = y[i + np.uint64(2)]
                v3 = y[i + np.uint64(3)]
                p = q0[t]
                a00 += p * v0
                a01 += p * v1
                a02 += p * v2
                a03 += p * v3
                p = q1[t]
                a10 += p * v0
                a11 += p * v1
                a12 += p * v2
                a13 += p * v3
                p = q2[t]
                a20 += p * v0
                a21 += p * v1
                a22 += p * v2
                a23 += p * v3
                s0 += v0 * v0
                s1 += v1 * v1
                s2 += v2 * v2
                s3 += v3 * v3
            coef[w, j, 0], coef[w, j, 1], coef[w, j, 2], coef[w, j, 3] = a00, a01, a02, a03
            if j + 1 < J:
                coef[w, j + 1, 0], coef[w, j + 1, 1], coef[w, j + 1, 2], coef[w, j + 1, 3] = a10, a11, a12, a13
            if j + 2 < J:
                coef[w, j + 2, 0], coef[w, j + 2, 1], coef[w, j + 2, 2], coef[w, j + 2, 3] = a20, a21, a22, a23
            if first:
                xx[w, 0], xx[w, 1], xx[w, 2], xx[w, 3] = s0, s1, s2, s3
                first = False


_compiled = None


def window_sums(P, x, n, coef, xx) -> None:
    """:func:`_window_sums` of the rows ``x`` (nw n, 4) (any strides: copied when not C-contiguous),
    compiled at the first call (numba imported then)."""
    global _compiled
    if _compiled is None:
        from psdcal import _jit

        # error_model "python": the kernel divides nothing, and numpy's error model (the project's
        # default) keeps LLVM from vectorising its loops (3x slower)
        _compiled = _jit._compile(_window_sums, fastmath=set(FASTMATH), error_model="python")
    _compiled(P, np.ascontiguousarray(x).reshape(-1), np.uint64(n), coef, xx)


def _window_stats(coef, xx, gram, gi, n, dof, floor2, var, amp, var_amp, zr, zi):  # pragma: no cover - compiled
    """The per-window arithmetic of ``MultiCarrierLockin._windows`` (its numpy code is the reference).

    ``coef`` (nw, 2k + 1, 4), ``xx`` (nw, 4): the window sums; ``gram`` (2k + 1, 2k + 1), ``gi`` (k, 2, 2);
    writes ``var`` (nw, 4) the residual noise variance (clipped at 0, floored at ``floor2 xx / n``),
    ``amp`` and ``var_amp`` (nw, k, 4) the amplitudes projected on the common phase and their variance,
    ``zr``, ``zi`` (nw, k) the sums of the four channels' in-phase and quadrature parts.
    """
    nw = coef.shape[0]
    J = coef.shape[1]
    k = (J - 1) // 2
    for w in range(nw):
        for c in range(4):
            f = 0.0
            for i in range(J):
                g = 0.0
                for j in range(J):
                    g += gram[i, j] * coef[w, j, c]
                f += coef[w, i, c] * g
            v = xx[w, c] - f
            if v < 0.0:
                v = 0.0
            v = v / dof
            fl = floor2 * xx[w, c] / n
            if v != v or fl != fl:
                v = np.nan
            elif fl > v:
                v = fl
            var[w, c] = v
        for m in range(k):
            a = coef[w, 2 * m, 0] + coef[w, 2 * m, 1] + coef[w, 2 * m, 2] + coef[w, 2 * m, 3]
            b = coef[w, 2 * m + 1, 0] + coef[w, 2 * m + 1, 1] + coef[w, 2 * m + 1, 2] + coef[w, 2 * m + 1, 3]
            zr[w, m] = a
            zi[w, m] = b
            mag = math.hypot(a, b)
            ur = 1.0
            ui = 0.0
            if mag > 0.0:
                ur = a / mag
                ui = b / mag
            quad = ur * ur * gi[m, 0, 0] + 2.0 * ur * ui * gi[m, 0, 1] + ui * ui * gi[m, 1, 1]
            for c in range(4):
                amp[w, m, c] = coef[w, 2 * m, c] * ur + coef[w, 2 * m + 1, c] * ui
                var_amp[w, m, c] = var[w, c] * quad


_stats_compiled = None


def window_stats(coef, xx, gram, gi, n, dof, floor2):
    """:func:`_window_stats` (compiled at the first call): returns ``(var, amp, var_amp, zr, zi)``."""
    global _stats_compiled
    if _stats_compiled is None:
        from psdcal import _jit

        _stats_compiled = _jit._compile(_window_stats)
    nw, J = coef.shape[0], coef.shape[1]
    k = (J - 1) // 2
    var = np.empty((nw, 4))
    amp = np.empty((nw, k, 4))
    var_amp = np.empty((nw, k, 4))
    zr = np.empty((nw, k))
    zi = np.empty((nw, k))
    _stats_compiled(np.ascontiguousarray(coef), np.ascontiguousarray(xx), gram, gi, float(n), float(max(dof, 1)),
                    float(floor2), var, amp, var_amp, zr, zi)
    return var, amp, var_amp, zr, zi
