#!/usr/bin/env python3
"""Run the benchmarks and write their tables into the docs.

``python3 tasks.py bench`` runs every benchmark of the registry below (each in its own process,
with the arguments its documented numbers were measured with, and ``--markdown``), prints its
output as it comes, and then rewrites every generated region of README.md and docs/ whose
benchmark succeeded: the table, with the command, the date, the machine (CPU model, cores,
load) and the library versions under it (see ``benchmarks/_docgen.py``). A benchmark that fails
leaves its regions as they were; the exit status is then non-zero. A table that a benchmark says it
skipped (``<!-- table: ID skipped: REASON -->``: a real-data study without the shared data folder beside the repository) leaves
its region as it was, with a note, and is no failure.

Usage::

    python3 tasks.py bench                      # every benchmark at full size; writes the docs
    python3 tasks.py bench locate aoa           # only these (a substring of the file name)
    python3 tasks.py bench --quick              # small sizes, a smoke run: prints, writes nothing
    python3 tasks.py bench --quick --write-docs # ... and writes the docs (marked "quick mode")
    python3 tasks.py bench --no-write-docs      # full size, print only
    python3 tasks.py bench --check              # run nothing: check the docs' regions against the registry
    python3 tasks.py bench --list               # the registry: scripts, tables, arguments
    python3 tasks.py bench opencv -- --sets 5   # arguments after -- replace the registry's (docs not written
                                                #   unless --write-docs; the caption records them)

The docs are written atomically: every page is written (through a temporary file and a rename)
only after all the selected benchmarks have run.
"""
from __future__ import annotations

import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import _docgen  # noqa: E402


@dataclass(frozen=True)
class Bench:
    """One benchmark script: its arguments (full size and quick) and the ids of the tables it prints."""

    full: tuple[str, ...] = ()
    quick: tuple[str, ...] = ()
    tables: tuple[str, ...] = ("1",)
    #: full-size duration on the 2-core development machine, s (for --list): measured for bench_pose, efficiency and
    #: the studies (at load 3-5 and on one process: an idle machine takes less, about half for those given two
    #: processes); bench_startup, bench_opencv and bench_default bounded
    #: by the interval between their captions' start times in the run of 2026-11-26 (load about 1); bench_scaling
    #: scaled from its measured 480 s at --repeats 9 (its scipy reference, 1-9 s a call, is most of it); estimated
    #: from the quick run for the others
    about_s: int = 60


#: Every script ``python3 tasks.py bench`` runs. A generated region of the docs names one of these
#: tables (``tests/test_bench_docs.py`` checks it, and that every table here has a region).
REGISTRY: dict[str, Bench] = {
    # (median of 5 calls, the project's rule elsewhere; 9 took 480 s, mostly the scipy reference's 9 calls a row)
    "bench_scaling": Bench(("--repeats", "5"), ("--quick", "--repeats", "1", "--scipy-max-views", "0"),
                           ("1", "2", "3"), 380),
    "bench_default": Bench((), ("--repeats", "2", "--cli-repeats", "1"), ("1", "2"), 90),
    "bench_linear": Bench((), ("--repeats", "20"), ("1",), 20),
    "bench_startup": Bench(("--repeats", "5", "--clone"), ("--repeats", "1"), ("1", "2", "3"), 150),
    "bench_aoa": Bench(("--runs", "5"), ("--points", "100000", "--runs", "1"), ("1",), 60),
    "bench_locate": Bench(("--seconds", "60", "--repeats", "15"), ("--seconds", "2", "--repeats", "1"), ("1",), 120),
    # (its start-up table compiles every kernel three times in fresh caches: minutes; not in --quick)
    "bench_opencv": Bench(("--sets", "20", "--repeats", "3"), ("--sets", "2", "--repeats", "1", "--no-startup"),
                          ("1", "2"), 150),
    "bench_montecarlo": Bench(("--trials", "30"), ("--trials", "3"), ("1",), 60),
    "bench_signalchain": Bench((), ("--points", "500"), ("1",), 20),
    "bench_verdict": Bench((), ("--sets", "2", "--repeats", "1"), ("1",), 20),
    "bench_live": Bench(("--seconds", "3"), ("--seconds", "1"), ("1",), 10),
    "bench_live_multi": Bench(("--seconds", "10", "--repeat", "3"), ("--seconds", "2", "--repeat", "1"), ("1",), 60),
    "bench_pose": Bench((), ("--right", "6", "--wrong", "2", "--repeats", "5"), ("1", "2", "3", "4"), 90),
    "bench_dashboard": Bench(("--reps", "3", "--seconds", "10"), ("--reps", "1", "--seconds", "2"), ("1", "2"), 120),
    "efficiency": Bench((), ("--trials", "20"), ("1",), 60),
    # the accuracy studies (false alarms, detections, NEES, errors against the truth): their figures in the docs
    # (the studies that can use both cores do: their tables are the same for any number of processes)
    "study_verdict": Bench(("--correct", "1000", "--faults", "100", "--advice", "30", "--jobs", "2"), ("--quick",),
                           ("correct", "faults", "real", "advice"), 110),
    "study_minima": Bench(("--fits", "1000", "--jobs", "2"), ("--quick",), ("1",), 50),
    "capture_study": Bench((), ("--quick",), ("views", "sweep"), 50),
    "export_fit": Bench((), ("--quick",), ("1",), 5),
    "study_selfcal": Bench(("--rooms", "300"), ("--quick",),
                           ("sim", "sim_check", "timing", "tag_rooms", "lighthouse", "shared_error", "coverage"), 50),
    "study_tracking": Bench(("--scenes", "200"), ("--quick",), ("sim", "lighthouse"), 45),
    "study_consistency_rows": Bench(("--files", "20000"), ("--quick",), ("rates", "lighthouse"), 20),
    "study_reflections": Bench(("--rooms", "400"), ("--quick",), ("strong", "weak", "weak_other"), 60),
    "study_tdm_carrier": Bench(("--records", "400"), ("--quick",), ("1",), 15),
    "study_channel_sums": Bench(("--runs", "3000"), ("--quick",), ("1",), 5),
    "study_angles_lighthouse": Bench((), ("--quick",), ("1",), 10),
    "study_signal_noise": Bench(("--records", "4000"), ("--quick",), ("1", "2"), 40),
    "zhang_real": Bench((), ("--quick",), ("1",), 5),
    "reproduce_paper": Bench(("--trials", "200", "--gain-trials", "25", "--workers", "2"), ("--quick",),
                             ("tables34", "remedies", "table1", "table2", "table7", "table8", "figure9"), 200),
}


def _usage_error(msg: str) -> int:
    print(msg, file=sys.stderr)
    return 2


def run_one(script: str, args: list[str]) -> tuple[int, str, float]:
    """Run ``benchmarks/SCRIPT.py ARGS --markdown``, echoing its output; (exit status, stdout, seconds)."""
    cmd = [sys.executable, str(HERE / f"{script}.py"), *args, "--markdown"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=HERE.parent, stdout=subprocess.PIPE, text=True, bufsize=1)
    out = []
    assert proc.stdout is not None
    for line in proc.stdout:
        print(line, end="", flush=True)
        out.append(line)
    rc = proc.wait()
    return rc, "".join(out), time.perf_counter() - t0


def check_docs(root: Path | None = None) -> list[str]:
    """Problems of the docs' generated regions against the registry, one line each (empty: all good)."""
    root = _docgen.ROOT if root is None else root
    problems, seen = [], set()
    for page in _docgen.doc_pages(root):
        text = page.read_text(encoding="utf-8")
        rel = page.relative_to(root)
        problems += [f"{rel}: {p}" for p in _docgen.marker_problems(text)]
        for name, body in _docgen.regions(text):
            script, tid = name.split("/", 1)
            if not body.strip():
                problems.append(f"{rel}: region {name!r} is empty: run python3 tasks.py bench {script}")
            if script not in REGISTRY:
                problems.append(f"{rel}: region {name!r}: no benchmark {script!r} in benchmarks/run_all.py's REGISTRY")
            elif tid not in REGISTRY[script].tables:
                problems.append(f"{rel}: region {name!r}: {script} prints no table {tid!r} "
                                f"(its tables: {', '.join(REGISTRY[script].tables)})")
            seen.add(name)
    for script, bench in REGISTRY.items():
        if not (HERE / f"{script}.py").exists():
            problems.append(f"REGISTRY names benchmarks/{script}.py, which does not exist")
        for tid in bench.tables:
            if f"{script}/{tid}" not in seen:
                problems.append(f"table {script}/{tid} has no generated region in README.md or docs/")
    return problems


def main(argv: list[str]) -> int:
    """Run the selected benchmarks and write the docs; 0 when all succeed, 1 when one fails, 2 on bad usage."""
    split = argv.index("--") if "--" in argv else len(argv)
    names, passthrough = argv[:split], argv[split + 1:]
    flags = {"--quick", "--write-docs", "--no-write-docs", "--check", "--list", "-h", "--help"}
    options = [n for n in names if n.startswith("-")]
    unknown = [o for o in options if o not in flags]
    if unknown:
        return _usage_error(f"options {unknown} must follow '--' (run_all.py [--quick] [--write-docs|--no-write-docs] "
                            "[NAME ...] -- ARGS)")
    if "-h" in options or "--help" in options:
        print(__doc__)
        return 0
    if "--write-docs" in options and "--no-write-docs" in options:
        return _usage_error("--write-docs and --no-write-docs exclude each other")
    if "--list" in options:
        for script, b in REGISTRY.items():
            print(f"{script}.py  tables {', '.join(b.tables)}  full: {' '.join(b.full) or '(defaults)'}  "
                  f"quick: {' '.join(b.quick)}  about {b.about_s} s")
        timing = sum(b.about_s for s, b in REGISTRY.items() if s.startswith("bench_") or s == "efficiency")
        total = sum(b.about_s for b in REGISTRY.values())
        print(f"full run: about {total / 60:.0f} min (timing benchmarks {timing / 60:.0f} min, "
              f"accuracy studies {(total - timing) / 60:.0f} min)")
        return 0
    if "--check" in options:
        problems = check_docs()
        for p in problems:
            print(p, file=sys.stderr)
        print("docs' generated regions: " + ("ok" if not problems else f"{len(problems)} problem(s)"))
        return 1 if problems else 0
    quick = "--quick" in options
    write = "--write-docs" in options or (not quick and not passthrough and "--no-write-docs" not in options)
    names = [n for n in names if not n.startswith("-")]
    scripts = list(REGISTRY)
    if names:
        unmatched = [n for n in names if not any(n in s for s in scripts)]
        if unmatched:
            return _usage_error(f"no benchmark matches {unmatched}; have {scripts}")
        scripts = [s for s in scripts if any(n in s for n in names)]

    env = _docgen.environment(_docgen.ROOT)
    tables: dict[str, str] = {}
    captions: dict[str, str] = {}
    failed, durations = [], {}
    for script in scripts:
        bench = REGISTRY[script]
        args = list(passthrough) if passthrough else list(bench.quick if quick else bench.full)
        print(f"=== {script}.py {' '.join(args)} ===", flush=True)
        at_start = {**env, **_docgen.load_and_date()}  # the load and date as this benchmark starts
        rc, out, seconds = run_one(script, args)
        durations[script] = seconds
        status = "ok" if rc == 0 else f"FAILED (exit {rc})"
        if rc == 0:
            try:
                got = _docgen.parse_tables(out)
            except ValueError as exc:
                got, status, rc = {}, f"FAILED ({exc})", 1
            skipped = _docgen.skipped_tables(out) if rc == 0 else {}
            for t, why in skipped.items():
                print(f"note: {script}.py skipped table {t} ({why}): its region is left as it was")
            missing = [t for t in bench.tables if t not in got and t not in skipped]
            if rc == 0 and missing and (passthrough or quick):  # other arguments may leave a table out
                print(f"note: {script}.py printed no table {', '.join(missing)}")
            elif rc == 0 and missing:
                status, rc = f"FAILED (printed no table {', '.join(missing)}; REGISTRY expects {bench.tables})", 1
            if rc == 0:
                tables.update({f"{script}/{t}": got[t] for t in bench.tables if t in got})
                captions[script] = _docgen.caption_line(script, args, at_start, quick)
        print(f"=== {script}.py: {status} in {seconds:.1f} s ===\n", flush=True)
        if rc != 0:
            failed.append(script)

    if write and tables:
        pages = {}
        for page in _docgen.doc_pages(_docgen.ROOT):
            text = page.read_text(encoding="utf-8")
            new, done = _docgen.replace_regions(text, tables, captions)
            if new != text:
                pages[page] = (new, done)
        for page, (new, done) in pages.items():  # all pages computed first, then each written by one rename
            _docgen.write_atomically(page, new)
            print(f"wrote {len(done)} table(s) into {page.relative_to(_docgen.ROOT)}")
        if not pages:
            print("no generated region changed")
    elif tables:
        print("docs not written (--write-docs to write them)")
    total = sum(durations.values())
    print(f"{len(scripts) - len(failed)} of {len(scripts)} benchmark(s) passed in {total:.0f} s "
          f"({', '.join(f'{s} {t:.0f} s' for s, t in durations.items())})")
    if failed:
        print(f"{len(failed)} benchmark(s) failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
