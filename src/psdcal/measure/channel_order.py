"""The order of the four PSD channels: given (``--raw-order``) and checked on the data.

The documented order of the channels is ``vx1, vx2, vy1, vy2``
(:data:`DOCUMENTED_ORDER`).  A live stream carries no channel names: a frame
wired in another order (``vx1, vy1, vx2, vy2`` is the common mistake) is read
without complaint and gives wrong angles.  Two defences:

* :func:`psdcal.signal.live.parse_order` reads the order of the frame's channels as the user
  states it (``--raw-order vx1,vy1,vx2,vy2``) and returns the permutation that
  puts them in the documented order; anything that is not a permutation of
  the four names is refused.
* :class:`SumCheck` tests the data.  The PSD splits a spot's photocurrent
  over the four corner anodes as ``I (1 -+ a -+ b) / 4``
  (:func:`psdcal.model.readout.photocurrents`), so after the channel gains
  ``vx1 + vx2 = vy1 + vy2`` wherever the spot is.  The normalised
  difference ``D = (sx - sy) / (sx + sy)`` is therefore zero up to the noise
  in the right order, and in another order it is a coordinate of the spot:
  read as ``vx1, vy1, vx2, vy2`` the frame gives ``D = -2 y / Ly`` and the
  impact point's ``y`` reads 0, an error of exactly ``|D| Ly / 2`` mm.  The
  test is a chi-squared of ``D`` against its noise over every row
  (:func:`psdcal._consistency.chi2_check`, false-alarm rate :data:`ALPHA`);
  it warns when it fails **and** the disagreement beyond the noise is at
  least :data:`MIN_EFFECT_SIGMA` of a row's own sigma (the consequence: an
  error of that many sigmas of ``y``).  Wrong channel gains also make the
  sums differ (a constant ``D`` of about half the gain error): the warning
  names both causes.
"""
from __future__ import annotations

import math

import numpy as np

from psdcal._consistency import chi2_check

#: False-alarm rate of the sums check.
ALPHA = 1e-3
#: The sums must disagree by at least this many sigmas (RMS beyond the noise) to be reported.
MIN_EFFECT_SIGMA = 1.0


def gain_covariance(model) -> np.ndarray | None:
    """The (3, 3) covariance of ``g_x2, g_y1, g_y2`` in a SensorModel's covariance (zeros for a gain it
    does not name); None when it names none."""
    names = list(getattr(model, "names", ()))
    idx = [names.index(n) if n in names else -1 for n in ("g_x2", "g_y1", "g_y2")]
    if all(i < 0 for i in idx):
        return None
    cov = np.zeros((3, 3))
    for a, i in enumerate(idx):
        for b, j in enumerate(idx):
            if i >= 0 and j >= 0:
                cov[a, b] = model.covariance[i, j]
    return cov


class SumCheck:
    """Accumulates ``D = (sx - sy) / (sx + sy)`` of amplitude rows and tests it against zero.

    Parameters
    ----------
    gains : (4,) array_like
        Relative channel gains ``g_x1, g_x2, g_y1, g_y2`` (the signals are divided by them).
    ly_mm : float
        PSD active length in y (the error of the ``vx1, vy1, vx2, vy2`` wiring is ``|D| ly_mm / 2``).
    what : str
        The data in words, for the message (the recording's name).
    cov_gains : (3, 3) array_like, optional
        Covariance of ``g_x2, g_y1, g_y2`` (from the calibration or a gains file): a gain known to
        0.1 % moves ``D`` by about 0.05 % in every row alike, which is not a wrong order; the
        chi-squared is taken with the rows' covariance including it (a common error, not a
        per-row one).
    """

    def __init__(self, gains, ly_mm: float, what: str = "the recording", cov_gains=None):
        self.gains = np.asarray(gains, dtype=float)
        self.cov_gains = None if cov_gains is None else np.asarray(cov_gains, dtype=float)
        self.ly_mm = float(ly_mm)
        self.what = what
        self.n = 0
        self.s0 = 0.0  # sum D^2 / var(D)
        self.u = np.zeros(3)  # sum J^T D / var(D)
        self.m = np.zeros((3, 3))  # sum J^T J / var(D)
        self.sum_d2 = 0.0
        self.max_abs_d = 0.0

    @classmethod
    def for_model(cls, model, what: str) -> "SumCheck":
        """The check for a :class:`psdcal.measure.sensor_model.SensorModel` (its gains and their covariance)."""
        return cls(model.gains, model.ly_mm, what, gain_covariance(model))

    def add(self, a, var_a, *, compiled: bool = False) -> None:
        """Rows ``a`` (n, 4) of amplitudes ``vx1, vx2, vy1, vy2`` with their variances ``var_a`` (n, 4).

        ``compiled``: the sums by one compiled loop over the rows (:mod:`psdcal.measure._impact_kernel`;
        this numpy code is the reference, equal to rounding).
        """
        if compiled:
            from psdcal.measure._impact_kernel import channel_sum_rows

            acc = np.empty(16)
            channel_sum_rows(np.ascontiguousarray(np.asarray(a, dtype=float).reshape(-1, 4)),
                             np.ascontiguousarray(np.asarray(var_a, dtype=float).reshape(-1, 4)), self.gains, acc)
            if acc[0] == 0:
                return
            self.n += int(acc[0])
            self.s0 += float(acc[1])
            self.u += acc[2:5]
            self.m += acc[5:14].reshape(3, 3)
            self.sum_d2 += float(acc[14])
            self.max_abs_d = max(self.max_abs_d, float(acc[15]))
            return
        v = np.asarray(a, dtype=float).reshape(-1, 4) / self.gains
        var = np.asarray(var_a, dtype=float).reshape(-1, 4) / self.gains ** 2
        sx, sy = v[:, 0] + v[:, 1], v[:, 2] + v[:, 3]
        s = sx + sy
        with np.errstate(invalid="ignore", divide="ignore"):
            d = (sx - sy) / s
            var_d = 4.0 * (sy ** 2 * (var[:, 0] + var[:, 1]) + sx ** 2 * (var[:, 2] + var[:, 3])) / s ** 4
            # dD/d(g_x2, g_y1, g_y2) (v_i = a_i / g_i): the gains' error is common to every row
            dd_dv = np.stack([2 * sy, 2 * sy, -2 * sx, -2 * sx], axis=-1) / s[:, None] ** 2
            jac = (dd_dv * (-v / self.gains))[:, 1:]
            ok = (np.isfinite(d) & np.isfinite(var_d) & (var_d > 0) & (s > 0)
                  & np.all(np.isfinite(jac), axis=-1))
        if not np.any(ok):
            return
        d, var_d, jac = d[ok], var_d[ok], jac[ok]
        self.n += int(d.size)
        self.s0 += float(np.sum(d * d / var_d))
        self.u += jac.T @ (d / var_d)
        self.m += (jac / var_d[:, None]).T @ jac
        self.sum_d2 += float(np.sum(d * d))
        self.max_abs_d = max(self.max_abs_d, float(np.max(np.abs(d))))

    @property
    def chi2(self) -> float:
        """``D^T V^-1 D`` with ``V = diag(var D) + J C J^T``: the row noise and the gains' covariance ``C``,
        an error common to every row (Woodbury: ``s0 - u^T C (I + M C)^-1 u``)."""
        if self.cov_gains is None or not np.any(self.cov_gains):
            return self.s0
        c = self.cov_gains
        corr = float(self.u @ c @ np.linalg.solve(np.eye(3) + self.m @ c, self.u))
        return max(self.s0 - corr, 0.0)

    def check(self):
        """The :class:`psdcal._consistency.Check` of the rows so far (name ``channel_sums``), or None without rows."""
        if self.n == 0:
            return None
        return chi2_check(self.chi2, self.n, name="channel_sums",
                          what=f"the x and y channel sums of {self.what}", alpha=ALPHA, inflate=False,
                          advice="check the channel order (vx1,vx2,vy1,vy2; --raw-order for a live stream, "
                                 "--channels for a file) and the channel gains")

    def effect_sigma(self) -> float:
        """RMS disagreement of the sums beyond the noise, in the rows' own sigmas."""
        return math.sqrt(max(self.chi2 / self.n - 1.0, 0.0)) if self.n else 0.0

    def warning(self) -> str | None:
        """One line when the sums disagree beyond the noise and the consequence is at least
        :data:`MIN_EFFECT_SIGMA`; None otherwise."""
        # the effect first (one division): below MIN_EFFECT_SIGMA there is no warning whatever the test says,
        # and the test's threshold (an inverse chi-squared, some ms) is not computed
        if self.n == 0 or self.effect_sigma() < MIN_EFFECT_SIGMA:
            return None
        chk = self.check()
        if chk is None or chk.passed is not False:
            return None
        rms = math.sqrt(self.sum_d2 / self.n)
        return (f"{self.what}: the x and y channel sums differ by {100 * rms:.3g} % RMS (up to "
                f"{100 * self.max_abs_d:.3g} %; chi2 {self.chi2:.4g} for {self.n} rows, {self.effect_sigma():.3g} "
                f"sigma beyond the noise), where the PSD makes them equal: the channels are in another order than "
                f"vx1,vx2,vy1,vy2 (wired vx1,vy1,vx2,vy2, y reads 0: errors up to "
                f"{self.max_abs_d * self.ly_mm / 2:.3g} mm on the PSD) or the channel gains are wrong; "
                f"give --raw-order (live) or --channels (files)")
