"""Simulated four-channel recordings with known truth (``psdcal simulate-recording``).

Two kinds of recording are made, in any format the readers of
:mod:`psdcal.signal.recording` understand (``.npy``, ``.csv``, ``.h5``,
``.tdms``):

* **template views** for calibration (:func:`simulate_template_views`): the
  LEDs of the planar template, seen by one sensor in several poses, either
  switched on one at a time (time multiplexing, with a schedule) or all at
  once on separate carriers (frequency multiplexing);
* **a room** (:func:`simulate_room`): fixed or moving emitters seen by one or
  several sensors with known poses in the room.

Signal model (docs/model.md#snr-definition): channel ``i`` carries ``A_i sin(2 pi f t + phi)``
(plus a DC offset) and white Gaussian noise of the same sigma on every
channel, ``sigma = A_mean / sqrt(2) / 10^(SNR/20)`` with ``A_mean`` the mean
channel amplitude of an emitter at the centre of the sensor.  The channel
gains (``gains``) multiply the amplitudes of Eq 1-2 (an imbalance that a
calibration with ``--fit-gains`` estimates).

The small helpers (:func:`calib_dict`, :func:`spot_for_angles`,
:func:`amplitudes`, :func:`signals`) are the building blocks the tests use.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from psdcal.errors import InputError
from psdcal.measure._geometry import project_world, spot_for_normalised  # noqa: F401 (re-exported)
from psdcal.measure.sensor_model import SensorModel
from psdcal.model.readout import photocurrents

#: The paper's Lens 2 with the optical centre offset (docs/model.md#paper-simulation-setup), a little PSD distortion.
BASE = {
    "intrinsics": {"f_mm": 8.0, "cx_mm": 0.5, "cy_mm": -0.7, "skew": 0.0},
    "distortion": {"k1": 1e-2, "k2": 3e-5, "k3": 0.0, "p1": 0.0, "p2": 0.0, "l1": -1.3e-3, "l2": 0.0},
    "sensor": {"lx_mm": 9.0, "ly_mm": 9.0},
}
NAMES = ["f_mm", "cx_mm", "cy_mm", "k1", "k2", "l1"]
STD = [5e-3, 4e-3, 4e-3, 2e-5, 1e-6, 1e-5]

#: Recording formats and their file suffixes.
FORMATS = {"npy": ".npy", "csv": ".csv", "hdf5": ".h5", "tdms": ".tdms"}


# --------------------------------------------------------------------------- building blocks
def calib_dict(*, names=NAMES, std=STD, corr=0.3, skew=None, fy=None, gains=None, seed=0, base=None):
    """A calibration JSON dict with a random positive-definite correlated covariance.

    Parameters
    ----------
    names, std : sequences
        Parameters the covariance is over and their standard deviations.
    corr : float
        Base correlation between the parameters.
    skew, fy, gains : optional
        Add a skew, a separate ``fy_mm`` or relative gains (4,) and their variances.
    seed : int
    base : dict, optional
        Intrinsics/distortion/sensor dict to start from (default :data:`BASE`).
    """
    d = {k: dict(v) for k, v in (base or BASE).items()}
    names = list(names)
    std = list(std)
    if skew is not None:
        d["intrinsics"]["skew"] = skew
        names.append("skew")
        std.append(1e-3)
    if fy is not None:
        d["intrinsics"]["fy_mm"] = fy
        names.append("fy_mm")
        std.append(5e-3)
    if gains is not None:
        d["gains"] = list(gains)
        names += ["g_x2", "g_y1", "g_y2"]
        std += [2e-3, 2e-3, 2e-3]
    rng = np.random.default_rng(seed)
    m = len(names)
    c = np.eye(m) * (1 - corr) + corr * np.ones((m, m))
    q = np.linalg.qr(rng.standard_normal((m, m)))[0]
    # mix the correlation structure a little so it is not uniform
    c = 0.7 * c + 0.3 * (q @ np.diag(rng.uniform(0.5, 1.5, m)) @ q.T)
    dd = 1 / np.sqrt(np.diag(c))
    c = dd[:, None] * c * dd[None]
    s = np.asarray(std, dtype=float)
    d["covariance"] = {"names": names, "matrix": (s[:, None] * c * s[None]).tolist()}
    return d


def model(**kw) -> SensorModel:
    """:class:`SensorModel` of :func:`calib_dict` (same keywords)."""
    return SensorModel.from_dict(calib_dict(**kw))


def spot_for_angles(m: SensorModel, alpha_rad, *, strict: bool = True):
    """Measured impact point (..., 2), mm, of a beam arriving at ``alpha_rad`` (..., 2).

    ``n = tan(alpha)``, ``x = A n`` (Eq 4), ``d = distort(x)`` (Eq 7-16).
    With ``strict`` an unconverged distortion is an assertion error; without,
    those points are NaN.
    """
    return spot_for_normalised(m, np.tan(np.asarray(alpha_rad, dtype=float)), strict=strict)


def amplitudes(m: SensorModel, d_mm, total=1.0):
    """Channel amplitudes (..., 4) of a spot at d_mm (through the sensor's gains)."""
    return photocurrents(d_mm, total, m.lx_mm, m.ly_mm) * m.gains


def signals(rate_hz, n, emitters, *, t0_s=0.0, noise=0.0, offset=(0.1, 0.12, 0.09, 0.11), rng=None):
    """Four-channel samples (4, n).

    emitters: list of (amplitudes (4,) or (4, n), carrier_hz, phase_rad).
    """
    t = t0_s + np.arange(n) / rate_hz
    x = np.zeros((4, n)) + np.asarray(offset)[:, None]
    for amp, f, ph in emitters:
        amp = np.asarray(amp, dtype=float)
        if amp.ndim == 1:
            amp = amp[:, None]
        x += amp * np.sin(2 * np.pi * f * t + ph)[None]
    if noise:
        rng = rng or np.random.default_rng(0)
        x += noise * rng.standard_normal((4, n))
    return x


def noise_sigma(total: float, snr_db: float | None) -> float:
    """Channel noise sigma for an emitter of total amplitude ``total`` (docs/model.md#snr-definition).

    ``A_mean = total / 4`` (a spot at the sensor's centre), ``sigma = A_mean /
    sqrt(2) / 10^(SNR/20)``; 0 when ``snr_db`` is None.
    """
    if snr_db is None:
        return 0.0
    return float(total) / 4.0 / math.sqrt(2.0) / 10 ** (float(snr_db) / 20.0)


# --------------------------------------------------------------------------- writers
def write_recording(path, x, rate_hz: float, *, t0_s: float = 0.0) -> Path:
    """Write four-channel samples ``x`` (4, n) to ``path`` (format from the suffix), atomically.

    ``.npy``: an ``(n, 4)`` float64 array (no rate).  ``.csv``: header
    ``t_s,vx1,vx2,vy1,vy2``.  ``.h5``/``.hdf5``: datasets ``vx1..vy2`` and a
    file attribute ``rate_hz``.  ``.tdms``: group ``psd``, channels
    ``vx1..vy2`` with ``wf_increment`` and ``wf_start_offset``.
    """
    from psdcal._atomic import atomic_path
    from psdcal.model.readout import CHANNELS

    path = Path(path)
    x = np.asarray(x, dtype=float)
    suffix = path.suffix.lower()
    with atomic_path(path, suffix=suffix) as tmp:
        if suffix == ".npy":
            np.save(tmp, np.ascontiguousarray(x.T))
        elif suffix == ".csv":
            t = t0_s + np.arange(x.shape[1]) / rate_hz
            data = np.column_stack([t, x.T])
            np.savetxt(tmp, data, delimiter=",", header="t_s," + ",".join(CHANNELS), comments="", fmt="%.12g")
        elif suffix in (".h5", ".hdf5"):
            import h5py

            with h5py.File(tmp, "w") as f:
                f.attrs["rate_hz"] = float(rate_hz)
                f.attrs["t0_s"] = float(t0_s)
                for name, row in zip(CHANNELS, x):
                    f.create_dataset(name, data=row)
        elif suffix == ".tdms":
            from nptdms import ChannelObject, TdmsWriter

            props = {"wf_increment": 1.0 / float(rate_hz), "wf_start_offset": float(t0_s)}
            with TdmsWriter(str(tmp)) as w:
                w.write_segment([ChannelObject("psd", name, row, properties=props) for name, row in zip(CHANNELS, x)])
        else:
            raise InputError(f"unknown recording format {suffix!r}; use one of {sorted(FORMATS.values())}",
                             path=path)
    return path


# --------------------------------------------------------------------------- template views
@dataclass(frozen=True)
class TemplateViews:
    """Simulated template views: signals per view and the truth.

    Attributes
    ----------
    x : list of (4, n) ndarrays
        One recording per view.
    rate_hz : float
    carriers_hz : tuple of float
        One carrier (TDM) or one per LED (FDM).
    point_ids : list of str
    schedule : list of (emitter, t_start_s, t_end_s) or None
        TDM only (the same for every view).
    window_s : float
        Window to demodulate with (FDM: the whole recording).
    truth : dict
        Intrinsics, distortion, gains and poses (JSON-ready).
    """

    x: list
    rate_hz: float
    carriers_hz: tuple
    point_ids: list
    template_mm: np.ndarray
    schedule: list | None
    window_s: float
    truth: dict = field(repr=False)


def simulate_template_views(lens="lens2", *, n_views: int = 12, mux: str = "tdm", rate_hz: float = 50_000.0,
                            carrier_hz: float = 1000.0, carrier_step_hz: float = 100.0, on_s: float = 0.02,
                            gap_s: float = 0.004, snr_db: float | None = 60.0, gain_imbalance: float = 0.0,
                            psd_l1: float = 0.0, total: float = 1.0, seed: int = 0,
                            template_mm=None) -> TemplateViews:
    """Signals of the calibration template's LEDs seen in ``n_views`` poses.

    Parameters
    ----------
    lens : str or (Intrinsics, Distortion)
        A preset of :data:`psdcal.study.simulate.LENSES` or the truth.
    n_views : int
    mux : {"tdm", "fdm"}
        ``"tdm"``: one LED on at a time on ``carrier_hz`` for ``on_s``, then
        ``gap_s`` dark; ``"fdm"``: all LEDs at once, LED ``j`` on
        ``carrier_hz + j carrier_step_hz``, for ``on_s`` (one window).
    rate_hz : float
    snr_db : float or None
        docs/model.md#snr-definition (None: no noise).
    gain_imbalance : float
        Relative spread of the channel gains (drawn uniformly in
        ``1 +- gain_imbalance``, ``g_x1 = 1``).
    psd_l1 : float
        PSD radial coefficient added to the lens' distortion (mm^-2).
    total : float
        Total amplitude of an LED (arbitrary units).
    seed : int
    """
    from psdcal.study.simulate import simulate_set

    if mux not in ("tdm", "fdm"):
        raise InputError(f"unknown multiplexing {mux!r}; use 'tdm' or 'fdm'", field="mux")
    if not (rate_hz > 0 and on_s > 0 and gap_s >= 0):
        raise InputError("rate, on-time must be positive and the gap not negative", field="rate_hz")
    rng = np.random.default_rng(seed)
    s = simulate_set(lens, n_images=n_views, noise_mm=0.0, seed=rng, template_mm=template_mm, psd_l1=psd_l1)
    M = len(s.template_mm)
    gains = np.ones(4)
    if gain_imbalance > 0:
        gains[1:] = 1.0 + rng.uniform(-gain_imbalance, gain_imbalance, 3)
    m = SensorModel(intrinsics=s.intrinsics, distortion=s.distortion, gains=gains)
    amps = amplitudes(m, s.ideal_points_mm, total)  # (views, M, 4)
    sigma = noise_sigma(total, snr_db)
    ids = [str(j) for j in range(M)]
    xs = []
    if mux == "tdm":
        n_on = int(round(on_s * rate_hz))
        n_gap = int(round(gap_s * rate_hz))
        period = n_on + n_gap
        n = n_gap + M * period
        sched = [(ids[j], (n_gap + j * period) / rate_hz, (n_gap + j * period + n_on) / rate_hz) for j in range(M)]
        carriers = (float(carrier_hz),)
        for v in range(n_views):
            x = signals(rate_hz, n, [], noise=0.0)
            t = np.arange(n) / rate_hz
            for j in range(M):
                a0 = n_gap + j * period
                ph = rng.uniform(0, 2 * np.pi)
                x[:, a0:a0 + n_on] += amps[v, j][:, None] * np.sin(2 * np.pi * carrier_hz * t[a0:a0 + n_on] + ph)
            if sigma:
                x += sigma * rng.standard_normal(x.shape)
            xs.append(x)
        window_s = min(on_s / 4, 0.005)
    else:
        carriers = tuple(float(carrier_hz + j * carrier_step_hz) for j in range(M))
        if max(carriers) >= rate_hz / 2:
            raise InputError(f"carriers up to {max(carriers):g} Hz need a rate above {2 * max(carriers):g} Hz",
                             field="rate_hz")
        n = int(round(on_s * rate_hz))
        sched = None
        for v in range(n_views):
            em = [(amps[v, j], carriers[j], rng.uniform(0, 2 * np.pi)) for j in range(M)]
            xs.append(signals(rate_hz, n, em, noise=sigma, rng=rng))
        window_s = n / rate_hz
    truth = s.truth_dict()
    truth.update(gains=gains.tolist(), relative_gains=(gains / gains[0]).tolist(), snr_db=snr_db,
                 noise_sigma=sigma, mux=mux, rate_hz=rate_hz, carriers_hz=list(carriers), window_s=window_s,
                 total_amplitude=total, seed=seed, sensor={"lx_mm": m.lx_mm, "ly_mm": m.ly_mm})
    return TemplateViews(xs, float(rate_hz), carriers, ids, s.template_mm, sched, float(window_s), truth)


# --------------------------------------------------------------------------- rooms
def look_at(center_w_mm, target_w_mm, up=(0.0, 0.0, 1.0)):
    """Pose ``(rvec, tvec_mm)`` of a sensor at ``center_w_mm`` whose optical axis points at ``target_w_mm``.

    World -> camera: ``Pc = R Pw + t`` (the calibration's convention); the
    camera's y axis points as far "down" (against ``up``) as it can.
    """
    from psdcal.model.projection import r_from_R

    c = np.asarray(center_w_mm, dtype=float)
    z = np.asarray(target_w_mm, dtype=float) - c
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=float)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in the world
    return r_from_R(R), -R @ c


@dataclass(frozen=True)
class Emitter:
    """An emitter in the room.

    ``kind`` ``"static"``: at ``p0_mm``; ``"circle"``: on a horizontal circle
    of ``radius_mm`` about ``p0_mm`` at ``speed_mm_s``; ``"line"``: back and
    forth from ``p0_mm`` to ``p1_mm`` at ``speed_mm_s``.
    """

    name: str
    kind: str
    p0_mm: tuple
    p1_mm: tuple | None = None
    radius_mm: float = 0.0
    speed_mm_s: float = 0.0
    carrier_hz: float = 1000.0
    #: Times the emitter is lit, s: ``[t_on, t_off)``.
    lit_s: tuple = (0.0, math.inf)

    def position(self, t_s) -> np.ndarray:
        """World position (..., 3), mm, at times ``t_s`` (...)."""
        t = np.asarray(t_s, dtype=float)
        p0 = np.asarray(self.p0_mm, dtype=float)
        if self.kind == "static":
            return np.broadcast_to(p0, t.shape + (3,)).copy()
        if self.kind == "circle":
            w = self.speed_mm_s / self.radius_mm
            return p0 + self.radius_mm * np.stack([np.cos(w * t), np.sin(w * t), np.zeros_like(t)], axis=-1)
        if self.kind == "line":
            p1 = np.asarray(self.p1_mm, dtype=float)
            L = float(np.linalg.norm(p1 - p0))
            s = np.mod(self.speed_mm_s * t, 2 * L)
            u = np.where(s <= L, s, 2 * L - s) / L
            return p0 + u[..., None] * (p1 - p0)
        raise InputError(f"unknown emitter kind {self.kind!r}", field="kind")

    def to_dict(self) -> dict:
        return {"name": self.name, "kind": self.kind, "p0_mm": list(self.p0_mm),
                "p1_mm": None if self.p1_mm is None else list(self.p1_mm), "radius_mm": self.radius_mm,
                "speed_mm_s": self.speed_mm_s, "carrier_hz": self.carrier_hz,
                "lit_s": [self.lit_s[0], None if math.isinf(self.lit_s[1]) else self.lit_s[1]]}


@dataclass(frozen=True)
class RoomSensor:
    """A simulated sensor in the room: its true model and pose."""

    name: str
    model: SensorModel
    rvec: np.ndarray
    tvec_mm: np.ndarray


def room_sensors(n_sensors: int, room_mm, model_truth: SensorModel, *, target_mm=None,
                 height_frac: float = 0.9) -> list[RoomSensor]:
    """``n_sensors`` sensors near the ceiling on the walls of a ``room_mm`` box, looking at ``target_mm``.

    The room spans ``[0, X] x [0, Y] x [0, Z]`` (mm); the sensors sit at
    ``height_frac Z`` on a ring around the room's centre, evenly spaced.
    """
    X, Y, Z = (float(v) for v in room_mm)
    target = np.array([X / 2, Y / 2, 0.3 * Z]) if target_mm is None else np.asarray(target_mm, float)
    out = []
    for i in range(int(n_sensors)):
        a = 2 * np.pi * (i + 0.125) / max(int(n_sensors), 1)
        c = np.array([X / 2 + 0.45 * X * np.cos(a), Y / 2 + 0.45 * Y * np.sin(a), height_frac * Z])
        rvec, tvec = look_at(c, target)
        out.append(RoomSensor(f"s{i + 1}", model_truth, rvec, tvec))
    return out


@dataclass(frozen=True)
class RoomRecording:
    """Simulated recordings of a room.

    Attributes
    ----------
    x : list of (4, n) ndarrays, one per sensor
    rate_hz : float
    sensors : list of RoomSensor
    emitters : list of Emitter
    schedule : list of (emitter, t_start_s, t_end_s) or None (TDM)
    visible : (n_sensors, n_emitters) bool
        Whether the emitter stayed on the sensor all the time.
    truth : dict
    """

    x: list
    rate_hz: float
    sensors: list
    emitters: list
    schedule: list | None
    visible: np.ndarray
    truth: dict = field(repr=False)


def simulate_room(sensors, emitters, *, duration_s: float = 1.0, rate_hz: float = 20_000.0,
                  snr_db: float | None = 60.0, mux: str = "fdm", slot_s: float = 0.02, gap_s: float = 0.0,
                  total: float = 1.0, gain_imbalance: float = 0.0, seed: int = 0,
                  grid_s: float = 5e-4, reflections=()) -> RoomRecording:
    """Four-channel signals of ``emitters`` seen by ``sensors`` over ``duration_s``.

    Moving emitters: the amplitudes are computed on a grid of ``grid_s`` and
    interpolated linearly.  ``mux="fdm"``: every emitter on its own
    ``carrier_hz`` all the time; ``"tdm"``: the emitters take turns (slots of
    ``slot_s`` then ``gap_s`` dark) on the first emitter's carrier, and the
    schedule is returned.  An emitter off a sensor (behind it or outside its
    active area) gives that sensor no light.

    Parameters
    ----------
    sensors : list of RoomSensor
    emitters : list of Emitter
    gain_imbalance : float
        Each sensor's channel gains drawn in ``1 +- gain_imbalance`` (the
        sensor models keep their own gains otherwise).
    """
    if mux not in ("tdm", "fdm"):
        raise InputError(f"unknown multiplexing {mux!r}; use 'tdm' or 'fdm'", field="mux")
    rng = np.random.default_rng(seed)
    n = int(round(duration_s * rate_hz))
    t = np.arange(n) / rate_hz
    tg = np.arange(0.0, duration_s + 2 * grid_s, grid_s)
    sigma = noise_sigma(total, snr_db)
    sched = None
    on = np.ones((len(emitters), n), dtype=bool)
    if mux == "tdm":
        # whole samples per slot and per gap, so that a slot's first sample is never the previous one's
        n_slot = int(round(slot_s * rate_hz))
        n_period = n_slot + int(round(gap_s * rate_hz))
        if n_slot < 1:
            raise InputError(f"a {slot_s:g} s slot is shorter than one sample", field="slot_s")
        sched = []
        k = 0
        while (k * n_period + n_slot) <= n:
            sched.append((emitters[k % len(emitters)].name, k * n_period / rate_hz, (k * n_period + n_slot) / rate_hz))
            k += 1
        idx = np.arange(n) // n_period
        in_slot = (np.arange(n) - idx * n_period) < n_slot
        for j in range(len(emitters)):
            on[j] = in_slot & (idx % len(emitters) == j)
    for j, e in enumerate(emitters):
        k0 = int(round(e.lit_s[0] * rate_hz))
        k1 = n if math.isinf(e.lit_s[1]) else int(round(e.lit_s[1] * rate_hz))
        on[j, :k0] = False
        on[j, k1:] = False
    xs, vis, used_gains = [], np.zeros((len(sensors), len(emitters)), dtype=bool), []
    for si, s in enumerate(sensors):
        m = s.model
        if gain_imbalance > 0:
            g = np.ones(4)
            g[1:] = 1.0 + rng.uniform(-gain_imbalance, gain_imbalance, 3)
            m = SensorModel(intrinsics=m.intrinsics, distortion=m.distortion, gains=g, lx_mm=m.lx_mm, ly_mm=m.ly_mm)
        used_gains.append(m.gains.tolist())
        x = signals(rate_hz, n, [], noise=0.0)
        for j, e in enumerate(emitters):
            P = e.position(tg)
            nrm, z = project_world(P, s.rvec, s.tvec_mm)
            d = spot_for_normalised(m, np.where((z > 0)[:, None], nrm, np.nan))
            ok = np.all(np.isfinite(d), -1) & (np.abs(d[:, 0]) < m.lx_mm / 2) & (np.abs(d[:, 1]) < m.ly_mm / 2)
            vis[si, j] = bool(np.all(ok))
            a = amplitudes(m, np.where(ok[:, None], d, 0.0), total) * ok[:, None]
            for rf in reflections:  # image sources: their light adds on the PSD (centroid of the spots)
                if rf.applies(s.name, e.name):
                    a = a + _reflected_amplitudes(m, rf, P, s, total)
            amp = np.stack([np.interp(t, tg, a[:, c]) for c in range(4)])
            f = e.carrier_hz if mux == "fdm" else emitters[0].carrier_hz
            x += amp * on[j][None] * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))[None]
        if sigma:
            x += sigma * rng.standard_normal(x.shape)
        xs.append(x)
    truth = {
        "rate_hz": rate_hz, "duration_s": duration_s, "snr_db": snr_db, "noise_sigma": sigma, "mux": mux,
        "emitters": [e.to_dict() for e in emitters],
        "sensors": [{"name": s.name, "rvec": np.asarray(s.rvec).tolist(), "tvec_mm": np.asarray(s.tvec_mm).tolist(),
                     "gains": g} for s, g in zip(sensors, used_gains)],
        "visible": vis.tolist(), "seed": seed,
    }
    if reflections:
        truth["reflections"] = [rf.to_dict() for rf in reflections]
    return RoomRecording(xs, float(rate_hz), list(sensors), list(emitters), sched, vis, truth)


def _reflected_amplitudes(m: SensorModel, rf, P_mm, s, total: float) -> np.ndarray:
    """Channel amplitudes (n, 4) of the image of the points ``P_mm`` (n, 3) in reflector ``rf`` seen by sensor ``s``."""
    from psdcal.study.reflections import sensor_centre_mm

    w = rf.weight(P_mm, sensor_centre_mm(s.rvec, s.tvec_mm))
    nrm, z = project_world(rf.mirror(P_mm), s.rvec, s.tvec_mm)
    d = spot_for_normalised(m, np.where((z > 0)[:, None], nrm, np.nan))
    with np.errstate(invalid="ignore"):
        ok = np.all(np.isfinite(d), -1) & (np.abs(d[:, 0]) < m.lx_mm / 2) & (np.abs(d[:, 1]) < m.ly_mm / 2) & (w > 0)
    return amplitudes(m, np.where(ok[:, None], d, 0.0), total) * (w * ok)[:, None]


def _in_view(m: SensorModel, P_mm, rvec, tvec_mm, margin: float = 0.9) -> np.ndarray:
    """Whether world points (..., 3) fall on ``margin`` of the sensor's active area."""
    nrm, z = project_world(P_mm, rvec, tvec_mm)
    d = spot_for_normalised(m, np.where((z > 0)[..., None], nrm, np.nan))
    with np.errstate(invalid="ignore"):
        return (np.all(np.isfinite(d), -1) & (np.abs(d[..., 0]) < margin * m.lx_mm / 2)
                & (np.abs(d[..., 1]) < margin * m.ly_mm / 2))


def room_layout(model_truth: SensorModel, *, room_mm=(6000.0, 4000.0, 3000.0), n_sensors: int = 2,
                n_anchors: int = 5, moving: str | None = "circle", speed_mm_s: float = 500.0,
                radius_mm: float = 600.0, carrier_hz: float = 1000.0, carrier_step_hz: float = 150.0,
                seed: int = 0, max_tries: int = 20000, survey_s: float = 0.0, sensors=None,
                anchors_mm=None, anchor_names=None):
    """Sensors around a room and emitters every sensor sees.

    ``sensors`` (a list of :class:`RoomSensor`) replaces the default ring of
    ``n_sensors``; ``anchors_mm`` (k, 3) with ``anchor_names`` replaces the
    random fixed emitters.

    ``n_anchors`` fixed emitters ``a1, a2, ...`` at random positions (at
    least 0.3 m apart, between 0.2 m and 60 % of the room's height) on 80 %
    of every sensor's active area, and (``moving``) one emitter ``tag`` on a
    circle about the room's centre at 1 m, or on a line across it.  The
    carriers are ``carrier_hz + k carrier_step_hz`` in that order (the tag's
    four steps further: a moving emitter's changing amplitude leaks into
    nearby carriers).  With ``survey_s > 0`` the fixed emitters are lit during
    ``[0, survey_s)`` only and the tag afterwards only (a survey for
    ``psdcal pose``, then the tracking), so that neither disturbs the other.

    Returns
    -------
    sensors : list of RoomSensor
    emitters : list of Emitter
    """
    rng = np.random.default_rng(seed)
    room = np.asarray(room_mm, dtype=float)
    if sensors is None:
        sensors = room_sensors(n_sensors, room, model_truth)
    centre = np.array([room[0] / 2, room[1] / 2, 1000.0])
    anchors: list[np.ndarray] = [] if anchors_mm is None else [np.asarray(a, float) for a in anchors_mm]
    if anchors_mm is not None:
        n_anchors = len(anchors)
    tries = 0
    while len(anchors) < n_anchors:
        tries += 1
        if tries > max_tries:
            raise InputError(f"could not place {n_anchors} anchors in view of every sensor; use fewer",
                             field="anchors")
        p = np.array([rng.uniform(0.2, 0.8) * room[0], rng.uniform(0.2, 0.8) * room[1],
                      rng.uniform(200.0, 0.6 * room[2])])
        if anchors and min(np.linalg.norm(p - a) for a in anchors) < 300.0:
            continue
        if all(_in_view(s.model, p, s.rvec, s.tvec_mm, 0.8) for s in sensors):
            anchors.append(p)
    lit_a = (0.0, survey_s) if survey_s > 0 else (0.0, math.inf)
    lit_t = (survey_s, math.inf)
    names = list(anchor_names) if anchor_names is not None else [f"a{i + 1}" for i in range(len(anchors))]
    emitters = [Emitter(names[i], "static", tuple(p), carrier_hz=carrier_hz + i * carrier_step_hz, lit_s=lit_a)
                for i, p in enumerate(anchors)]
    f_tag = carrier_hz + (len(anchors) + 4) * carrier_step_hz  # apart: its changing amplitude leaks less
    if moving == "circle":
        emitters.append(Emitter("tag", "circle", tuple(centre), radius_mm=radius_mm, speed_mm_s=speed_mm_s,
                                carrier_hz=f_tag, lit_s=lit_t))
    elif moving == "line":
        a = centre - np.array([radius_mm, radius_mm / 2, 0.0])
        b = centre + np.array([radius_mm, radius_mm / 2, 300.0])
        emitters.append(Emitter("tag", "line", tuple(a), tuple(b), speed_mm_s=speed_mm_s, carrier_hz=f_tag,
                                lit_s=lit_t))
    elif moving is not None:
        raise InputError(f"unknown trajectory {moving!r}; use 'circle' or 'line'", field="moving")
    return sensors, emitters
