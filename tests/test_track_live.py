"""The live track (`locate --sensors ... --track` on live input): written row by row, equal to `psdcal track`.

The rows are drawn here (two emitters on constant-velocity paths with white noise, an outlier, an invalid
row, a gap); the reference is :func:`psdcal.measure.tracking.track_csv` on the located file.
"""
from __future__ import annotations

import numpy as np
import pytest

from psdcal.cli import main
from psdcal.errors import InputError
from psdcal.measure.locate import MULTI_COLUMNS
from psdcal.measure.locate import _write_rows
from psdcal.measure.track_live import LiveTrackWriter
from psdcal.measure.tracking import track_csv


def _rows(seed=3, n=400, dt=0.01):
    """Located rows (MULTI_COLUMNS) of two emitters every ``dt`` s: A with an outlier, an invalid row and a gap."""
    rng = np.random.default_rng(seed)
    cols = {c: [] for c in MULTI_COLUMNS}
    sig = np.array([0.5, 0.7, 1.2])
    for k in range(n):
        t = k * dt
        for name, p0, v in (("A", np.array([100.0, 200.0, 300.0]), np.array([50.0, -20.0, 5.0])),
                            ("B", np.array([-400.0, 50.0, 900.0]), np.array([-10.0, 30.0, 0.0]))):
            if name == "A" and 150 <= k < 210:  # A unseen for 0.6 s: a gap (10 x 0.01 s)
                continue
            p = p0 + v * t + sig * rng.standard_normal(3)
            if name == "A" and k == 80:
                p = p + 40.0  # an outlier: gated
            if name == "B" and k == 120:
                p = np.full(3, np.nan)  # not located: invalid
            row = dict(t_s=t, emitter=name, X_mm=p[0], Y_mm=p[1], Z_mm=p[2], sigma_X_mm=sig[0],
                       sigma_Y_mm=sig[1], sigma_Z_mm=sig[2], n_sensors=3, chi2=1.0, dof=3, flagged=0,
                       left_out=-1, reflection="")
            for c in MULTI_COLUMNS:
                cols[c].append(row[c])
    out = {c: np.array(v, dtype=object if c in ("emitter", "reflection") else float) for c, v in cols.items()}
    for c in ("n_sensors", "dof", "flagged", "left_out"):
        out[c] = out[c].astype(np.int64)
    return out


def _batches(cols, sizes):
    n, i, k = len(cols["t_s"]), 0, 0
    while i < n:
        j = min(n, i + sizes[k % len(sizes)])
        yield {c: v[i:j] for c, v in cols.items()}
        i, k = j, k + 1


@pytest.mark.parametrize("max_gap_s", [None, 0.3])
def test_live_track_equals_track_of_the_located_file(tmp_path, max_gap_s):
    cols = _rows()
    located = tmp_path / "located.csv"
    with open(located, "w", encoding="utf-8", newline="") as fh:
        fh.write(",".join(MULTI_COLUMNS) + "\n")
        _write_rows(fh, cols, MULTI_COLUMNS)
    want = track_csv(located, tmp_path / "batch.csv", max_gap_s=max_gap_s)
    w = LiveTrackWriter(tmp_path / "live.csv", MULTI_COLUMNS, max_gap_s=max_gap_s)
    for b in _batches(cols, [1, 7, 64, 3]):
        w.add(b)
    got = w.close()
    assert (tmp_path / "live.csv").read_bytes() == (tmp_path / "batch.csv").read_bytes()
    st = [ln.rsplit(",", 1)[1] for ln in (tmp_path / "live.csv").read_text().splitlines()[1:]]
    assert {"start", "ok", "gated", "gap", "invalid"} <= set(st)  # every case the rows were drawn to show
    for k in ("n_rows", "n_used", "n_gated", "n_invalid", "n_restarts", "n_gap", "n_jump", "n_tested", "columns",
              "mean_nis", "mean_nis_used", "q", "q_factor", "max_gap_s", "checks", "warnings"):
        assert got[k] == want[k], k


def test_rows_are_written_as_they_come(tmp_path):
    cols = _rows(n=50)
    w = LiveTrackWriter(tmp_path / "live.csv", MULTI_COLUMNS)
    seen = []
    for b in _batches(cols, [10]):
        w.add(b)
        seen.append(len((tmp_path / "live.csv").read_text().splitlines()) - 1)  # before close: on disk already
    w.close()
    assert seen == list(np.cumsum([len(b["t_s"]) for b in _batches(cols, [10])]))


def test_failed_checks_give_the_q_advice(tmp_path):
    """A q far too large for these constant-velocity paths: the NIS check fails (innovations smaller than
    stated), and the advice is the one track_csv gives on the file."""
    cols = _rows(n=300)
    located = tmp_path / "located.csv"
    with open(located, "w", encoding="utf-8", newline="") as fh:
        fh.write(",".join(MULTI_COLUMNS) + "\n")
        _write_rows(fh, cols, MULTI_COLUMNS)
    want = track_csv(located, tmp_path / "batch.csv", q=1e8)
    w = LiveTrackWriter(tmp_path / "live.csv", MULTI_COLUMNS, q=1e8)
    w.add(cols)
    got = w.close()
    assert want["q_factor"] is not None and any(x.startswith("track_nis") for x in want["warnings"])
    assert got["warnings"] == want["warnings"] and got["q_factor"] == want["q_factor"]


def test_refusals(tmp_path):
    with pytest.raises(InputError, match="--track-q auto needs the whole run"):
        LiveTrackWriter(tmp_path / "t.csv", MULTI_COLUMNS, q="auto")
    with pytest.raises(InputError, match="no X_mm"):
        LiveTrackWriter(tmp_path / "t.csv", ("t_s", "emitter", "chi2"))


def test_cli_replay_with_track_equals_psdcal_track(tmp_path, capsys):
    """`locate --sensors --replay ... --track`: the live track equals `psdcal track` on the located rows."""
    rate = 20_000.0
    assert main(["simulate-recording", "room", "--sensors", "3", "--anchors", "2", "--moving", "none",
                 "--duration-s", "0.6", "--rate-hz", str(rate), "-o", str(tmp_path / "room")]) == 0
    sensors = tmp_path / "room" / "sensors.json"
    files = [f"file:{tmp_path / 'room' / f's{i}.f64'}" for i in (1, 2, 3)]
    for i in (1, 2, 3):
        np.ascontiguousarray(np.load(tmp_path / "room" / f"s{i}.npy"), dtype="<f8").tofile(tmp_path / "room" / f"s{i}.f64")
    args = ["locate", *files, "--sensors", str(sensors), "--rate-hz", str(rate), "--allow-no-covariance",
            "--carrier-hz", "1000", "--carrier-hz", "1150", "-o", str(tmp_path / "rows.csv"),
            "--track", str(tmp_path / "live_track.csv"), "--track-q", "1e4"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "tracked rows to" in out
    assert main(["track", str(tmp_path / "rows.csv"), "-o", str(tmp_path / "track.csv"), "--q", "1e4"]) == 0
    assert (tmp_path / "live_track.csv").read_bytes() == (tmp_path / "track.csv").read_bytes()
