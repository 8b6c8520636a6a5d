"""Constant-velocity tracking (psdcal.measure.tracking, `locate --track`, `psdcal track`).

Trajectories drawn from the filter's own model (white acceleration of density
q, asynchronous measurement times per emitter, known measurement covariance):
the NEES of the state and the NIS of the innovations must average their
dimensions, and the tracked RMS error must be below the untracked by the
factor the filter's covariance predicts.
"""
from __future__ import annotations

import csv

import numpy as np
import pytest

from psdcal.errors import InputError
from psdcal.measure.tracking import TrackConfig, cv_matrices, track


def _simulate(rng, *, n_emitters=3, n=400, d=3, q=4e5, outliers=0):
    ts, ems, zs, Rs, truth = [], [], [], [], []
    for e in range(n_emitters):
        t = np.cumsum(rng.uniform(0.005, 0.03, n))  # asynchronous, irregular
        x = np.concatenate([rng.uniform(0, 3000, d), rng.normal(0, 300, d)])
        tp = t[0]
        for ti in t:
            F, Q = cv_matrices(ti - tp, d, q)
            x = F @ x + rng.multivariate_normal(np.zeros(2 * d), Q) if ti > tp else x
            tp = ti
            A = rng.normal(size=(d, d))
            R = A @ A.T * rng.uniform(0.5, 4.0) + 0.2 * np.eye(d)
            ts.append(ti)
            ems.append(f"e{e}")
            zs.append(x[:d] + rng.multivariate_normal(np.zeros(d), R))
            Rs.append(R)
            truth.append(x.copy())
    order = np.argsort(ts, kind="stable")
    z = np.array(zs)[order]
    truth = np.array(truth)[order]
    if outliers:
        idx = rng.choice(len(z), outliers, replace=False)
        z[idx] += rng.choice([-1, 1], (outliers, d)) * 200.0
    return np.array(ts)[order], np.array(ems, dtype=object)[order], z, np.array(Rs)[order], truth


def test_nees_nis_consistent():
    rng = np.random.default_rng(1)
    d, q = 3, 4e5
    t, em, z, R, truth = _simulate(rng, d=d, q=q)
    res = track(t, em, z, R, TrackConfig(q=q, init_sigma_v=600.0))
    keep = np.zeros(len(t), bool)
    for e in set(em):
        idx = np.flatnonzero(em == e)
        keep[idx[20:]] = True  # after the start-up
    err = np.concatenate([res.p, res.v], axis=1) - truth
    nees = np.einsum("ni,nij,nj->n", err, np.linalg.inv(res.cov), err)[keep]
    n = keep.sum()
    assert abs(nees.mean() - 2 * d) < 3 * np.sqrt(2 * 2 * d / n) * 2  # chi2(6): var 12; consecutive rows correlate (x2)
    nis = res.nis[keep & ~res.gated]
    assert abs(nis.mean() - d) < 3 * np.sqrt(2 * d / len(nis)) * 1.5
    assert res.gated.mean() < 0.01  # 0.1 % gate


def test_rms_lower_by_the_predicted_factor():
    rng = np.random.default_rng(2)
    d, q = 3, 1e5
    t, em, z, R, truth = _simulate(rng, d=d, q=q, n=500)
    res = track(t, em, z, R, TrackConfig(q=q, init_sigma_v=600.0))
    keep = np.zeros(len(t), bool)
    for e in set(em):
        keep[np.flatnonzero(em == e)[30:]] = True
    rms_raw = np.sqrt(np.mean(np.sum((z - truth[:, :d]) ** 2, -1)[keep]))
    rms_trk = np.sqrt(np.mean(np.sum((res.p - truth[:, :d]) ** 2, -1)[keep]))
    predicted = np.sqrt(np.mean(np.trace(res.cov[:, :d, :d], axis1=1, axis2=2)[keep])
                        / np.mean(np.trace(R, axis1=1, axis2=2)[keep]))
    assert rms_trk < 0.8 * rms_raw
    assert rms_trk / rms_raw == pytest.approx(predicted, rel=0.1)


def test_outliers_gated():
    rng = np.random.default_rng(3)
    t, em, z, R, truth = _simulate(rng, d=2, q=1e5, outliers=15)
    res = track(t, em, z, R, TrackConfig(q=1e5, init_sigma_v=600.0))
    bad = np.linalg.norm(z - truth[:, :2], axis=1) > 100
    assert res.gated[bad].mean() > 0.9
    assert res.gated[~bad].mean() < 0.01
    assert np.sqrt(np.mean(np.sum((res.p - truth[:, :2]) ** 2, -1)[~bad])) < 5.0


def test_time_going_back_is_an_error():
    with pytest.raises(InputError, match="time goes back"):
        track([0.0, 1.0, 0.5], ["a", "a", "a"], np.zeros((3, 2)), np.broadcast_to(np.eye(2), (3, 2, 2)))


def test_locate_track_cli(tmp_path):
    """A moving tag seen by two sensors: the tracked positions beat the window-by-window ones."""
    from psdcal.cli import main

    room = tmp_path / "room"
    assert main(["simulate-recording", "room", "--anchors", "0", "--moving", "circle", "--speed-mm-s", "300",
                 "--duration-s", "2", "--snr-db", "40", "--seed", "4", "-o", str(room)]) == 0
    out, trk = tmp_path / "xyz.csv", tmp_path / "track.csv"
    assert main(["locate", "--allow-no-covariance", "--sensors", str(room / "sensors.json"), "--rate-hz", "20000", "--carrier-hz", "1600",
                 "--emitter", "tag", "-o", str(out), "--track", str(trk), "--track-q", "2e5"]) == 0
    with open(trk) as fh:
        rows = list(csv.DictReader(fh))
    assert {"vX_mm_s", "sigma_X_mm", "sigma_vZ_mm_s", "nis", "gated"} <= set(rows[0])
    t = np.array([float(r["t_s"]) for r in rows])
    p = np.array([[float(r[c]) for c in ("X_mm", "Y_mm", "Z_mm")] for r in rows])
    with open(out) as fh:
        raw = np.array([[float(r[c]) for c in ("X_mm", "Y_mm", "Z_mm")] for r in csv.DictReader(fh)])
    from psdcal.study.recordings import Emitter

    e = Emitter("tag", "circle", (3000.0, 2000.0, 1000.0), radius_mm=600.0, speed_mm_s=300.0)
    tw = t[:, None] + (np.arange(200) - 99.5)[None] / 20000.0
    truth = e.position(tw).mean(axis=1)
    k = slice(20, None)
    err_trk = np.sqrt(np.mean(np.sum((p - truth) ** 2, -1)[k]))
    err_raw = np.sqrt(np.mean(np.sum((raw - truth) ** 2, -1)[k]))
    assert err_trk < 0.8 * err_raw
    # the tag's speed is recovered
    v = np.array([[float(r[c]) for c in ("vX_mm_s", "vY_mm_s")] for r in rows])
    assert np.median(np.hypot(v[k, 0], v[k, 1])) == pytest.approx(300.0, rel=0.1)


def test_track_time_multiplexed_angles(tmp_path):
    """One sensor, three emitters taking turns: each track is updated at its own times (every third
    segment); the fixed emitters' angular velocities are zero within their sigma, the angles' sigmas match
    their scatter."""
    from psdcal.cli import main

    room = tmp_path / "room"
    assert main(["simulate-recording", "room", "--sensors", "1", "--anchors", "2", "--moving", "line",
                 "--speed-mm-s", "300", "--mux", "tdm", "--duration-s", "2.4", "--snr-db", "45", "--seed", "3",
                 "-o", str(room)]) == 0
    out, trk = tmp_path / "ang.csv", tmp_path / "trk.csv"
    assert main(["locate", str(room / "s1.npy"), "--calib", str(room / "calib_truth.json"), "--allow-no-covariance", "--rate-hz", "20000",
                 "--carrier-hz", "1000", "--schedule", str(room / "schedule.csv"), "--window-s", "0.005",
                 "-o", str(out), "--track", str(trk), "--track-q", "0.5"]) == 0
    with open(trk) as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 120 and not any(r["gated"] == "1" for r in rows)
    for e in ("a1", "a2"):
        mine = [r for r in rows if r["emitter"] == e]
        t = np.array([float(r["t_s"]) for r in mine])
        np.testing.assert_allclose(np.diff(t), 0.06, atol=1e-9)
        v = np.array([[float(r["valpha_x_deg_s"]), float(r["valpha_y_deg_s"])] for r in mine])[10:]
        sv = np.array([[float(r["sigma_valpha_x_deg_s"]), float(r["sigma_valpha_y_deg_s"])] for r in mine])[10:]
        assert np.mean(np.abs(v) < 3 * sv) > 0.95
    with open(out) as fh:
        a1 = [r for r in csv.DictReader(fh) if r["emitter"] == "a1"]
    ax = np.array([float(r["alpha_x_deg"]) for r in a1])
    sx = np.array([float(r["sigma_alpha_x_deg"]) for r in a1])
    assert 0.6 < ax.std() / np.sqrt(np.mean(sx**2)) < 1.5


from hypothesis import given, settings, strategies as st  # noqa: E402


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), n_emitters=st.integers(1, 4))
def test_tracks_do_not_mix(seed, n_emitters):
    """Each emitter's track is the same whether its rows are filtered alone or interleaved with others'."""
    rng = np.random.default_rng(seed)
    t, em, z, R, _ = _simulate(rng, n_emitters=n_emitters, n=40, d=2, q=1e5)
    cfg = TrackConfig(q=1e5, init_sigma_v=600.0)
    all_ = track(t, em, z, R, cfg)
    for e in set(em):
        m = em == e
        alone = track(t[m], em[m], z[m], R[m], cfg)
        np.testing.assert_array_equal(alone.p, all_.p[m])
        np.testing.assert_array_equal(alone.cov, all_.cov[m])
        np.testing.assert_array_equal(alone.gated, all_.gated[m])
