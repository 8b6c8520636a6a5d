"""Electrical (gain) calibration of the four PSD channels, and what gains do to the geometry.

The readout through unequal channel gains is a homography
------------------------------------------------------------
With the current split of docs/model.md#psd-readout (``a = 2x/Lx``, ``b = 2y/Ly`` of the
true spot), the four photocurrents are affine in ``(a, b)``::

    I_x1 = (1 - a - b)/4,  I_x2 = (1 + a + b)/4,  I_y1 = (1 + a - b)/4,  I_y2 = (1 - a + b)/4

Each channel multiplies its current by a gain ``g_i``.  Write the four gains
through their mean and three contrasts::

    G     = ( g_x1 + g_x2 + g_y1 + g_y2) / 4
    d_x   = (-g_x1 + g_x2 + g_y1 - g_y2) / 4      (x-electrode imbalance)
    d_y   = (-g_x1 + g_x2 - g_y1 + g_y2) / 4      (y-electrode imbalance)
    d_xy  = ( g_x1 + g_x2 - g_y1 - g_y2) / 4      (x pair against y pair)

Then the sum and the two numerators of Eq 1-2 are (times 4)::

    S   = G    + d_x a  + d_y b
    N_x = d_x  + G a    + d_xy b
    N_y = d_y  + d_xy a + G b

all affine in ``(a, b)``, so the readout ``a' = N_x / S``, ``b' = N_y / S``
is the projective map with the *symmetric* matrix, on ``(a, b, 1)``::

    H_ab = [[G,    d_xy, d_x],
            [d_xy, G,    d_y],
            [d_x,  d_y,  G  ]]

A common factor of the gains scales ``H_ab`` and cancels: three degrees of
freedom, the ratios ``u_x = d_x/G``, ``u_y = d_y/G``, ``e = d_xy/G``
(:func:`gain_parts`).  To first order in them, on the sensor in mm:

* ``u_x, u_y`` shift every point by ``(Lx/2 u_x, Ly/2 u_y)`` -- this looks
  like a shift of the optical centre and is harmless when calibration and
  measurement share the electronics -- *and* tilt the plane projectively
  (bottom row ``(2 u_x/Lx, 2 u_y/Ly)``).  A small rotation ``w`` of the camera
  about its x/y axes gives the same bottom row with a shift ``f w``: the tilt
  part is what a calibration with a single ``f`` absorbs as a rotation of all
  poses plus a large shift of the optical centre (``~ f^2 2 u/L``: mm for the
  paper's Lens 1), the cause of the paper's Tables 5-6 spread of C;
* ``e`` is a stretch along the diagonals ``x = +-y`` (scale ``1 +- e``), which
  no single-``f``, zero-skew model can absorb; a general intrinsic matrix
  (fx, fy, skew) absorbs it up to a rotation about the optical axis.

Identifiability (:func:`identifiability`): with a pure pinhole, *any*
homography of the sensor plane followed by the pinhole is again a pinhole
(``H A = A' R``, RQ decomposition) with a rotated frame that the per-image
poses absorb.  With a general intrinsic matrix none of the three gain ratios
is identifiable.  With single ``f`` and zero skew, to first order the tilt
parts ``(u_x, u_y)`` trade against ``(cx, cy)``, ``f`` and a common rotation
of the poses under the constraint ``cx u_x ~ cy u_y`` (the diagonal of the
composite map must stay isotropic): the joint model
``gain_map(project(P))`` has a null space of dimension 1, and 2 when the
optical centre sits at the electrical centre with equal gains (then the
second direction is merely weak, in proportion to the offset of C), while
``e`` is identifiable.  Only the lens distortion, radially symmetric about C in the
*true* sensor plane, breaks this tie; the joint fit is then regular but its
``(u_x, u_y)`` direction is as weakly determined as the distortion is weak.

Electrical calibration (remedy (b))
-----------------------------------
Spots at known positions on the bare PSD (lens removed, e.g. a focused LED on
an x-y stage), read out through the electronics: the gains follow from a
homogeneous linear system (each spot gives ``S x' = Lx/2 N_x``,
``S y' = Ly/2 N_y``, linear in ``g``; :func:`gains_linear`) refined by
Levenberg-Marquardt through :func:`psdcal.model.readout.gain_map`
(:func:`calibrate_gains`).  Later raw amplitudes are corrected by
:func:`apply_gains` before Eq 1-2.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from psdcal._consistency import ALPHA, Check, chi2_check, inflate
from psdcal.errors import DegenerateViewsError, InputError
from psdcal.model.readout import LX_MM, LY_MM, _NUM_X, _NUM_Y, _SPLIT, gain_homography, gain_map

GAIN_NAMES = ("g_x2", "g_y1", "g_y2")


# ---------------------------------------------------------------------------
# The projective map and its parts
# ---------------------------------------------------------------------------


def relative_gains(gains) -> np.ndarray:
    """Gains divided by ``g_x1``, shape (4,) (only the ratios act on Eq 1-2)."""
    g = np.asarray(gains, dtype=float)
    if g.shape != (4,):
        raise InputError(f"gains must have shape (4,), got {g.shape}", field="gains")
    if not (np.all(np.isfinite(g)) and g[0] != 0):
        raise InputError("gains must be finite with g_x1 != 0", field="gains")
    return g / g[0]


@dataclass(frozen=True)
class GainParts:
    """Mean gain and the three dimensionless contrasts of the readout homography.

    Attributes
    ----------
    mean : float
        ``G``, the mean gain (cancels in Eq 1-2).
    u_x, u_y : float
        ``d_x / G``, ``d_y / G``: centre shift ``(Lx/2 u_x, Ly/2 u_y)`` mm plus
        a projective tilt; trade against C, f and the poses (not identifiable
        from a pinhole model alone).
    e : float
        ``d_xy / G``: stretch along the diagonals, identifiable in a joint fit.
    """

    mean: float
    u_x: float
    u_y: float
    e: float

    def shift_mm(self, lx_mm: float = LX_MM, ly_mm: float = LY_MM) -> np.ndarray:
        """First-order shift of the readout at the centre, (2,) mm."""
        return np.array([0.5 * lx_mm * self.u_x, 0.5 * ly_mm * self.u_y])


def gain_parts(gains) -> GainParts:
    """Decompose four channel gains into ``G, u_x, u_y, e`` (module docstring)."""
    g = np.asarray(gains, dtype=float)
    G = g.sum() / 4.0
    d_x = (-g[0] + g[1] + g[2] - g[3]) / 4.0
    d_y = (-g[0] + g[1] - g[2] + g[3]) / 4.0
    d_xy = (g[0] + g[1] - g[2] - g[3]) / 4.0
    return GainParts(float(G), float(d_x / G), float(d_y / G), float(d_xy / G))


def gains_from_parts(u_x: float, u_y: float, e: float, mean: float = 1.0) -> np.ndarray:
    """Channel gains ``(g_x1, g_x2, g_y1, g_y2)`` with the given contrasts (inverse of :func:`gain_parts`)."""
    G = float(mean)
    d = np.array([G, u_x * G, u_y * G, e * G])
    # rows: g_i = G + s_x d_x + s_y d_y + s_xy d_xy (the contrast matrix is orthogonal / 4)
    signs = np.array([[1, -1, -1, 1], [1, 1, 1, 1], [1, 1, -1, -1], [1, -1, 1, -1]], dtype=float)
    return signs @ d


def homography_ab(gains) -> np.ndarray:
    """The symmetric matrix ``H_ab`` (3, 3) of the readout on ``(a, b, 1)`` (module docstring)."""
    p = gain_parts(gains)
    G = p.mean
    return G * np.array([[1.0, p.e, p.u_x], [p.e, 1.0, p.u_y], [p.u_x, p.u_y, 1.0]])


def apply_homography(H, xy_mm) -> np.ndarray:
    """``[x', y', 1] ~ H [x, y, 1]`` for points (..., 2), mm."""
    xy = np.asarray(xy_mm, dtype=float)
    h = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1) @ np.asarray(H, float).T
    return h[..., :2] / h[..., 2:3]


# ---------------------------------------------------------------------------
# Correcting data with known gains
# ---------------------------------------------------------------------------


def apply_gains(amplitudes, gains) -> np.ndarray:
    """Raw channel amplitudes corrected for the channel gains.

    ``v_i / (g_i / g_x1)``: the amplitudes the channels would give with
    equal gains (up to the common factor ``g_x1``, which cancels in Eq 1-2).

    Parameters
    ----------
    amplitudes : (..., 4) array_like
        ``vx1, vx2, vy1, vy2``, V.
    gains : (4,) array_like
        Channel gains (absolute or relative).

    Returns
    -------
    (..., 4) ndarray, V.
    """
    a = np.asarray(amplitudes, dtype=float)
    if a.shape[-1:] != (4,):
        raise InputError(f"amplitudes must have shape (..., 4), got {a.shape}", field="amplitudes")
    return a / relative_gains(gains)


def correct_points(points_mm, gains, lx_mm: float = LX_MM, ly_mm: float = LY_MM) -> np.ndarray:
    """Impact points read out through ``gains`` mapped back to the equal-gain readout, (..., 2) mm.

    The inverse homography of :func:`psdcal.model.readout.gain_homography`; the same
    as :func:`apply_gains` on the amplitudes followed by Eq 1-2.
    """
    H = gain_homography(relative_gains(gains), lx_mm, ly_mm)
    return apply_homography(np.linalg.inv(H), points_mm)


# ---------------------------------------------------------------------------
# Electrical calibration (remedy (b))
# ---------------------------------------------------------------------------


def calibration_spots(n_per_side: int = 7, extent_mm: float = 3.5) -> np.ndarray:
    """A square grid of known spot positions for the electrical calibration, (n^2, 2) mm."""
    if n_per_side < 2:
        raise InputError("need at least 2 spots per side", field="n_per_side")
    s = np.linspace(-extent_mm, extent_mm, int(n_per_side))
    X, Y = np.meshgrid(s, s)
    return np.stack([X.ravel(), Y.ravel()], axis=1)


def gains_linear(spots_mm, measured_mm, lx_mm: float = LX_MM, ly_mm: float = LY_MM) -> np.ndarray:
    """Relative gains from spots at known positions, closed form (homogeneous least squares).

    Eq 1-2 through gains ``g``: ``x' S(g) = Lx/2 N_x(g)`` and
    ``y' S(g) = Ly/2 N_y(g)`` with ``S, N_x, N_y`` linear in ``g`` (the
    channel currents ``c_i`` of the known spot as coefficients).  Stacking
    both equations of all spots gives ``M g = 0``; ``g`` is the right singular
    vector of the smallest singular value (rows scaled to unit norm).

    Parameters
    ----------
    spots_mm : (n, 2) array_like
        Known true positions on the bare PSD, mm (n >= 2, not all on one line
        through the centre).
    measured_mm : (n, 2) array_like
        Their readout through the electronics (Eq 1-2), mm.

    Returns
    -------
    (4,) ndarray
        Relative gains, ``g_x1 = 1``.
    """
    p = np.asarray(spots_mm, dtype=float).reshape(-1, 2)
    m = np.asarray(measured_mm, dtype=float).reshape(-1, 2)
    ok = np.all(np.isfinite(p), 1) & np.all(np.isfinite(m), 1)
    p, m = p[ok], m[ok]
    if p.shape[0] < 2:
        raise DegenerateViewsError("electrical calibration needs at least 2 spots with a reading")
    a = 2.0 * p[:, 0] / lx_mm
    b = 2.0 * p[:, 1] / ly_mm
    cur = np.stack([np.ones_like(a), a, b], axis=1) @ _SPLIT.T  # (n, 4) currents per unit total
    rows_x = cur * (0.5 * lx_mm * _NUM_X - m[:, :1])  # x' sum_i c_i g_i = Lx/2 sum_i s_i c_i g_i
    rows_y = cur * (0.5 * ly_mm * _NUM_Y - m[:, 1:2])
    M = np.concatenate([rows_x, rows_y])
    M = M / np.maximum(np.linalg.norm(M, axis=1, keepdims=True), 1e-300)
    _, sv, vt = np.linalg.svd(M)
    if sv.size < 4 or sv[-2] < 1e-9 * sv[0]:
        raise DegenerateViewsError("the spots do not determine the gains: spread them over the PSD")
    g = vt[-1]
    return g / g[0]


@dataclass(frozen=True)
class GainCalibration:
    """Result of an electrical calibration (:func:`calibrate_gains`).

    Attributes
    ----------
    gains : (4,) ndarray
        Relative channel gains ``(1, g_x2, g_y1, g_y2)``.
    covariance : (3, 3) ndarray
        Covariance of ``g_x2, g_y1, g_y2`` from the Jacobian at the solution.
    std : (3,) ndarray
        Their standard errors.
    rms_mm : float
        RMS distance between measured and modelled spots, mm.
    n_spots : int
    iterations : int
    converged : bool
    message : str
    check : Check or None
        The chi-squared test of the residuals against the stated point noise
        (``noise_mm``; :func:`psdcal._consistency.chi2_check`).  Without a
        stated noise it is not applicable (``passed`` None) and the covariance
        uses the residual scatter (``chi2 / dof = 1`` by construction).
    """

    gains: np.ndarray
    covariance: np.ndarray
    std: np.ndarray
    rms_mm: float
    n_spots: int
    iterations: int
    converged: bool
    message: str
    check: Check | None = None

    def apply(self, amplitudes) -> np.ndarray:
        """Correct raw amplitudes (..., 4) with the fitted gains (:func:`apply_gains`)."""
        return apply_gains(amplitudes, self.gains)

    def correct_points(self, points_mm, lx_mm: float = LX_MM, ly_mm: float = LY_MM) -> np.ndarray:
        """Correct raw impact points (..., 2) mm with the fitted gains (:func:`correct_points`)."""
        return correct_points(points_mm, self.gains, lx_mm, ly_mm)

    def to_dict(self) -> dict:
        return {
            "gains": [float(v) for v in self.gains],
            "std": dict(zip(GAIN_NAMES, (float(v) for v in self.std))),
            "rms_mm": float(self.rms_mm),
            "n_spots": int(self.n_spots),
            "iterations": int(self.iterations),
            "converged": bool(self.converged),
            "checks": [] if self.check is None else [self.check.to_dict()],
        }


def calibrate_gains(spots_mm, measured_mm, lx_mm: float = LX_MM, ly_mm: float = LY_MM,
                    *, max_iterations: int = 50, noise_mm: float | None = None) -> GainCalibration:
    """Electrical calibration: relative channel gains from spots at known positions.

    Minimises ``sum |gain_map(p_k, g) - d_k|^2`` over ``g_x2, g_y1, g_y2``
    (``g_x1 = 1``) by Levenberg-Marquardt with the analytic Jacobian of
    :func:`psdcal.model.readout.gain_map`, started from :func:`gains_linear`.  The
    maximum-likelihood estimate when the readout noise is Gaussian on the
    points.

    Parameters
    ----------
    spots_mm : (n, 2) array_like
        Known spot positions on the bare PSD (lens removed), mm.
    measured_mm : (n, 2) array_like
        Impact points read out through the channels (Eq 1-2), mm; NaN rows
        are skipped.
    lx_mm, ly_mm : float
        PSD active lengths, mm.
    max_iterations : int
    noise_mm : float, optional
        The known noise of each measured coordinate, mm (1-sigma).  With it
        the residuals are tested (``chi2 = sum r^2 / noise^2`` against
        ``2 n - 3`` dof at 1e-3): the covariance is ``noise^2 (J^T J)^-1``
        when they agree and grows by ``chi2 / dof`` (the ratio rule) with a
        check that says so when they do not.  Without it the covariance is
        ``s^2 (J^T J)^-1`` with ``s^2`` the residual variance.

    Returns
    -------
    GainCalibration
    """
    p = np.asarray(spots_mm, dtype=float).reshape(-1, 2)
    m = np.asarray(measured_mm, dtype=float).reshape(-1, 2)
    if p.shape != m.shape:
        raise InputError(f"spots_mm {p.shape} and measured_mm {m.shape} differ in shape")
    ok = np.all(np.isfinite(p), 1) & np.all(np.isfinite(m), 1)
    p, m = p[ok], m[ok]
    g0 = gains_linear(p, m, lx_mm, ly_mm)

    def full(z):
        return np.concatenate([[1.0], z])

    def fun(z):
        return (gain_map(p, full(z), lx_mm, ly_mm) - m).ravel()

    def jac(z):
        _, _, dg = gain_map(p, full(z), lx_mm, ly_mm, jacobians=True)
        return dg[:, :, 1:].reshape(-1, 3)

    sol = least_squares(fun, g0[1:], jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                        max_nfev=4 * max_iterations)
    r = fun(sol.x)
    J = jac(sol.x)
    dof = max(r.size - 3, 1)
    sigma2 = float(r @ r) / dof
    what = f"the {p.shape[0]} spots' residuals"
    if noise_mm is None:
        check = Check("gains_chi2", None, None, None, ALPHA, None,
                      f"{what}: no noise stated, the covariance uses their scatter "
                      f"({math.sqrt(sigma2) * 1e3:.3g} um per coordinate)", dof=float(dof), inflation=1.0)
        cov = sigma2 * np.linalg.pinv(J.T @ J)
    else:
        if not (np.isfinite(noise_mm) and noise_mm > 0):
            raise InputError(f"the point noise must be a positive number of mm, got {noise_mm}", field="noise_mm")
        check = chi2_check(float(r @ r) / noise_mm**2, dof, name="gains_chi2", what=what,
                           advice="the readout noise is larger than stated, a spot position is wrong (units, "
                                  "x and y swapped), or the PSD is non-linear beyond the gain model")
        cov = inflate(noise_mm**2 * np.linalg.pinv(J.T @ J), check)
    return GainCalibration(
        gains=full(sol.x),
        covariance=cov,
        std=np.sqrt(np.clip(np.diag(cov), 0.0, None)),
        rms_mm=float(np.sqrt(np.mean(np.sum(r.reshape(-1, 2) ** 2, axis=1)))),
        n_spots=int(p.shape[0]),
        iterations=int(sol.njev) if sol.njev is not None else int(sol.nfev),
        converged=bool(sol.status > 0),
        message=str(sol.message),
        check=check,
    )



# ---------------------------------------------------------------------------
# Identifiability of the joint (gains + geometry) model
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Identifiability:
    """Local identifiability of the joint model's global parameters (:func:`identifiability`).

    Attributes
    ----------
    names : tuple of str
        Global parameters, in the order of the vectors below.
    singular_values : (n,) ndarray
        Of the pose-marginalised, column-normalised Jacobian (descending).
    null_vectors : (n, k) ndarray
        Right singular vectors whose singular value is below ``tol`` times the
        largest (columns), in the normalised parameters.
    relative_condition : float
        Smallest over largest singular value.
    std_per_unit_noise : dict
        Standard error of each parameter per mm of point noise (1 mm
        per coordinate), from the marginal information.
    """

    names: tuple
    singular_values: np.ndarray
    null_vectors: np.ndarray
    relative_condition: float
    std_per_unit_noise: dict

    @property
    def rank_deficiency(self) -> int:
        return int(self.null_vectors.shape[1])


def identifiability(template_mm, intrinsics, distortion, rvecs, tvecs_mm, gains=None, *,
                    radial: int = 2, aspect: bool = False, skew: bool = False,
                    lx_mm: float = LX_MM, ly_mm: float = LY_MM, tol: float = 1e-8) -> Identifiability:
    """Rank of the joint gains + geometry model at given views (image cost, Jacobian at the truth).

    Builds the Jacobian of ``gain_map(distort(project(P)))`` over the free
    global parameters (f, C, [skew, fy], k1..k_radial, g_x2, g_y1, g_y2) and
    all poses, eliminates the poses (Schur complement: the information left
    for the global parameters once every pose is fitted), normalises the
    columns and returns its singular values and near-null directions.

    Parameters
    ----------
    template_mm : (M, 2)
    intrinsics : Intrinsics
    distortion : Distortion
    rvecs, tvecs_mm : (n_images, 3)
    gains : (4,), default equal gains
    radial : int
        Lens radial terms fitted (0: pure pinhole).
    aspect, skew : bool
        General intrinsic matrix.
    tol : float
        Relative singular value below which a direction counts as null.

    Returns
    -------
    Identifiability
    """
    from psdcal.calibration._refine import Evaluator, Problem
    from psdcal.model.distortion import distort
    from psdcal.model.params import ModelSpec
    from psdcal.model.projection import project

    T = np.asarray(template_mm, dtype=float)
    g = np.ones(4) if gains is None else relative_gains(gains)
    x = np.stack([project(T, intrinsics, r, t) for r, t in zip(rvecs, tvecs_mm)])
    d = gain_map(distort(x, distortion, intrinsics.c).d_mm, g, lx_mm, ly_mm)
    spec = ModelSpec(radial=radial, tangential=False, psd_radial=0, skew=skew, aspect=aspect, fit_gains=True)
    prob = Problem(T, d, spec, cost="image", sensor_mm=(lx_mm, ly_mm))
    ev = Evaluator(prob, intrinsics, distortion, g)
    z = prob.pack(intrinsics, distortion, g, rvecs, tvecs_mm)
    J = ev.jacobian(z)
    ng = prob.n_global
    Jg, Jp = J[:, :ng], J[:, ng:]
    # marginalise the poses: project Jg onto the orthogonal complement of range(Jp)
    Q, _ = np.linalg.qr(Jp)
    Jr = Jg - Q @ (Q.T @ Jg)
    scale = np.linalg.norm(Jg, axis=0)
    scale[scale == 0] = 1.0
    _, sv, vt = np.linalg.svd(Jr / scale, full_matrices=False)
    null = vt[sv < tol * sv[0]].T
    info = Jr.T @ Jr
    cov = np.linalg.pinv(info, rcond=1e-14)
    std = {n: float(np.sqrt(max(cov[k, k], 0.0))) for k, n in enumerate(prob.names)}
    return Identifiability(tuple(prob.names), sv, null, float(sv[-1] / sv[0]), std)
