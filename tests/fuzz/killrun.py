"""kill -9 of writing commands at random moments: outputs complete or absent, sets never mixed.

Each scenario runs a command once to completion (version A, the existing
outputs), then runs it again with other options and ``--force`` (version B)
in a subprocess killed with SIGKILL after a random delay. After the
recovery any later psdcal run does (:func:`psdcal._atomic.recover` of the
output folders), every output must be byte-identical to its A or B version,
all outputs of the set the same version (or all absent when there was no A),
and no temporary or journal left.
"""
from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

from psdcal._atomic import JOURNAL_PREFIX, TMP_PREFIX, recover

SCENARIOS = {
    "simulate": (["simulate", "--images", "5", "--seed", "1", "-o", "o"],
                 ["simulate", "--images", "7", "--seed", "2", "-o", "o"],
                 ["o/template.csv", "o/points.csv", "o/truth.json"]),
    "simulate-amplitudes": (["simulate", "--images", "4", "--seed", "3", "-o", "o"],
                            ["simulate", "--images", "6", "--seed", "4", "--amplitudes", "--snr-db", "50", "-o", "o"],
                            ["o/template.csv", "o/points.csv", "o/truth.json"]),
    "errormap": (["errormap", "--calib", "c.json", "--grid", "5", "-o", "m.png", "--csv", "m.csv"],
                 ["errormap", "--calib", "c.json", "--grid", "9", "-o", "m.png", "--csv", "m.csv"],
                 ["m.png", "m.csv"]),
    "compare": (["compare", "c.json", "c2.json", "--grid", "5", "-o", "d.png", "--json", "d.json"],
                ["compare", "c.json", "c2.json", "--grid", "9", "-o", "d.png", "--json", "d.json"],
                ["d.png", "d.json"]),
    "aoa": (["aoa", "p.csv", "--calib", "c.json", "-o", "a.csv"],
            ["aoa", "p.csv", "--calib", "c.json", "--distance-mm", "1000", "-o", "a.csv"],
            ["a.csv"]),
}


def prepare(root: Path) -> Path:
    """A folder with c.json (a calibration with covariance) and p.csv (points) every scenario reads."""
    from psdcal.cli import main

    src = root / "src"
    src.mkdir(parents=True, exist_ok=True)
    if not (src / "c.json").exists():
        assert main(["simulate", "--images", "5", "--seed", "1", "-o", str(src / "s")]) == 0
        assert main(["calibrate", str(src / "s/points.csv"), "-t", str(src / "s/template.csv"), "-o",
                     str(src / "c.json"), "-q"]) == 0
        shutil.copy(src / "s/points.csv", src / "p.csv")
        assert main(["calibrate", str(src / "s/points.csv"), "-t", str(src / "s/template.csv"), "-o",
                     str(src / "c2.json"), "-q", "--radial", "1"]) == 0
    return src


def _state(work: Path, outputs, ref_a, ref_b, fresh):
    """Per output, the set of versions its bytes match ({"absent"}, {"A"}, {"B"}, {"A", "B"} or {"other"})."""
    versions = []
    for o in outputs:
        p = work / o
        if not p.exists():
            versions.append({"absent"})
            continue
        b = p.read_bytes()
        match = {v for v, ref in (("A", ref_a[o]), ("B", ref_b[o])) if b == ref and not (fresh and v == "A")}
        versions.append(match or {"other"})
    return versions


def _leftovers(work: Path):
    return [str(p.relative_to(work)) for p in work.rglob("*") if p.name.startswith((TMP_PREFIX, JOURNAL_PREFIX))]


def run_kills(root, n_kills: int, scenarios=None, seed: int = 0, log=None) -> Counter:
    """Kill ``n_kills`` runs (spread over ``scenarios``); raise AssertionError on a mixed or broken set."""
    rng = random.Random(seed)
    root = Path(root)
    src = prepare(root)
    names = list(scenarios or SCENARIOS)
    refs, durations = {}, {}
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    for name in names:
        a, b, outputs = SCENARIOS[name]
        ra, rb = root / f"ref-{name}-a", root / f"ref-{name}-b"
        for d, argv in ((ra, a), (rb, b)):
            shutil.copytree(src, d, dirs_exist_ok=True)
            # the references run as the killed runs do (a fresh CLI process): the bytes of a number can depend on
            # the kernel path a process takes (compiled or numpy reference, equal to ~1e-15)
            subprocess.run([sys.executable, "-m", "psdcal.cli", *argv, "--force"], cwd=d, env=env, check=True,
                           capture_output=True)
        refs[name] = ({o: (ra / o).read_bytes() for o in outputs}, {o: (rb / o).read_bytes() for o in outputs})
        d = root / f"time-{name}"
        shutil.copytree(src, d, dirs_exist_ok=True)
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "psdcal.cli", *b, "--force"], cwd=d, env=env, check=True,
                       capture_output=True)
        durations[name] = time.perf_counter() - t0
    outcomes = Counter()
    for k in range(n_kills):
        name = names[k % len(names)]
        a, b, outputs = SCENARIOS[name]
        ref_a, ref_b = refs[name]
        fresh = k % 3 == 2  # every third kill: no earlier outputs
        work = root / f"kill-{k}"
        shutil.copytree(src, work)
        if not fresh:
            subprocess.run([sys.executable, "-m", "psdcal.cli", *a, "--force"], cwd=work, env=env, check=True,
                           capture_output=True)
        delay = rng.uniform(0.3, 1.05) * durations[name]
        proc = subprocess.Popen([sys.executable, "-m", "psdcal.cli", *b, "--force"], cwd=work, env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        for d in {(work / o).parent for o in outputs}:
            recover(d)  # what the next psdcal run writing there does first
        v = _state(work, outputs, ref_a, ref_b, fresh)
        left = _leftovers(work)
        common = set.intersection(*v)
        kind = "MIXED" if not common or common == {"other"} else "/".join(sorted(common))
        outcomes[(name, "fresh" if fresh else "over-A", kind)] += 1
        if log:
            log(f"{name:20s} kill {k:3d} after {delay:.3f} s ({'fresh' if fresh else 'over A'}): {v}")
        assert {"other"} not in v, f"a broken output after kill {k} of {name}: {dict(zip(outputs, v))}"
        assert kind != "MIXED", f"mixed set after kill {k} of {name}: {dict(zip(outputs, v))}"
        assert not left, f"temporaries left after recovery: {left}"
        shutil.rmtree(work)
    return outcomes


HOOK = Path(__file__).with_name("killhook.py")


def _hooked(argv, cwd, env, at: int, log: Path):
    e = dict(env, PSDCAL_KILL_AT=str(at), PSDCAL_KILL_LOG=str(log))
    return subprocess.run([sys.executable, str(HOOK), *argv, "--force"], cwd=cwd, env=e, capture_output=True,
                          text=True)


def _events(log: Path):
    return [ln.split(" ", 2)[1:] for ln in log.read_text().splitlines()] if log.exists() else []


def run_kills_at_every_write(root, name: str, log=None, fresh_too: bool = True) -> Counter:
    """Kill scenario ``name`` at every write event in turn (see ``killhook.py``), over A (and fresh).

    A dry run lists the events (each output's staged write, then each rename
    of the commit: the journal, the outputs).  Then one run per event, over
    the A outputs and in a fresh folder, is killed exactly there; each must
    die of SIGKILL at that event (so the window was reached), and after the
    recovery every output is whole and all of one version, no temporary left.
    Returns the outcomes per (kill point, over-A/fresh, version).
    """
    root = Path(root)
    src = prepare(root)
    a, b, outputs = SCENARIOS[name]
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    ra, rb = root / f"det-ref-{name}-a", root / f"det-ref-{name}-b"
    for d, argv in ((ra, a), (rb, b)):
        shutil.copytree(src, d, dirs_exist_ok=True)
        proc = _hooked(argv, d, env, -1, root / f"det-{name}-{d.name}.log")
        assert proc.returncode == 0, proc.stderr
    ref_a, ref_b = ({o: (ra / o).read_bytes() for o in outputs}, {o: (rb / o).read_bytes() for o in outputs})
    events = _events(root / f"det-{name}-{rb.name}.log")
    written = [n for kind, n in events if kind == "written"]
    assert sorted(written) == sorted(Path(o).name for o in outputs), events  # every output through the writer
    outcomes = Counter()
    for fresh in (False, True) if fresh_too else (False,):
        for k, (kind, target) in enumerate(events):
            work = root / f"det-{name}-{k}-{'fresh' if fresh else 'over'}"
            shutil.copytree(src, work)
            if not fresh:  # the A outputs, as a completed run A left them
                for o in outputs:
                    (work / o).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(ra / o, work / o)
            klog = work.parent / (work.name + ".log")
            proc = _hooked(b, work, env, k, klog)
            assert proc.returncode == -signal.SIGKILL, (name, k, kind, target, proc.returncode, proc.stderr[-500:])
            assert _events(klog)[-1] == [kind, target], (name, k, _events(klog))  # killed exactly there
            for d in {(work / o).parent for o in outputs}:
                recover(d)
            v = _state(work, outputs, ref_a, ref_b, fresh)
            common = set.intersection(*v)
            version = "MIXED" if not common or common == {"other"} else "/".join(sorted(common))
            where = f"{name}: killed at event {k} ({kind} {target}, {'fresh' if fresh else 'over A'})"
            if log:
                log(f"{where}: {v}")
            assert {"other"} not in v, f"a broken output, {where}: {dict(zip(outputs, v))}"
            assert version != "MIXED", f"mixed set, {where}: {dict(zip(outputs, v))}"
            assert not _leftovers(work), f"temporaries left, {where}: {_leftovers(work)}"
            outcomes[(f"{kind} {target}", "fresh" if fresh else "over-A", version)] += 1
            shutil.rmtree(work)
    return outcomes
