"""Numbers that hold: every timing figure of README.md and docs/ is written by ``python3 tasks.py bench``.

Fast (no benchmark runs): the docs' generated regions against the registry of
``benchmarks/run_all.py``, a scan of the pages for hand-written timing figures outside those
regions, and the writing machinery itself on a fake benchmark in a temporary tree.
"""
from __future__ import annotations

import re
import textwrap
from pathlib import Path

import pytest
from _bench import load_benchmark

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"


def _load(name):
    return load_benchmark(name, "_benchdocs_")


@pytest.fixture(scope="module")
def run_all():
    return _load("run_all")


@pytest.fixture(scope="module")
def docgen(run_all):
    return run_all._docgen


def test_every_region_names_a_registered_table_and_every_table_has_a_region(run_all):
    assert run_all.check_docs() == []


def test_every_benchmark_script_is_registered(run_all):
    scripts = {p.stem for p in BENCH.glob("bench_*.py")}
    assert scripts - set(run_all.REGISTRY) == set(), "a bench_*.py that tasks.py bench would not run"
    for name, bench in run_all.REGISTRY.items():
        src = (BENCH / f"{name}.py").read_text(encoding="utf-8")
        assert '"--markdown"' in src, f"{name}.py takes no --markdown"
        assert bench.tables and bench.quick is not None


#: Timing figures a person would write by hand (a number with a throughput or time-ratio unit).
TIMING_FIGURES = [
    r"\d\s*x real time",
    r"\d[\d.,]*\s*(?:[kM]\s*)?(?:points|spots|calibrations|redraws)/s\b",
    r"\d[\d.,]*\s*M points",
    r"\d[\d.]*\s*x\s+(?:OpenCV|`?calibrateCamera`?|mrcal|an OpenCV script|the (?:bare|fit|old))",
    r"\d[\d.]*\s*(?:ms|s|us|µs|ns)\s+(?:of CPU|per (?:call|point|spot|trial|calibration|process))",
    r"\d[\d.]*\s*(?:ms|us|µs|ns) per (?:point|spot|call)",
    r"\bin \d+\.\d+\s*ms\b",
    r"\btakes? (?:about )?\d[\d.]*\s*(?:ms|s|min)\b",
    r"\btook (?:about )?\d[\d.]*\s*(?:ms|s|min)\b",
    r"\d[\d.]*\s*(?:ms|s|min)\**\s+(?:wall|CPU)\b",
    r"\d[\d.]*\s*(?:ms|s|min) on (?:this|the|a|\d)[ -]",
    r"\bmedian time \d",
]
#: A table whose header names a time or a rate is a measurement table (it must be generated).
TIME_HEADER = re.compile(r"\bms\b|\bseconds\b|\bs/|real time|/s\b|per second|\bµs\b|\bus/", re.I)


def _prose(text: str, docgen) -> str:
    """The page without generated regions, fenced code blocks and HTML comments (code prints its own times)."""
    text = docgen.outside_regions(text)
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"<!--.*?-->", "", text, flags=re.S)


def test_no_hand_written_timing_figures_outside_the_generated_regions(docgen):
    found = []
    for page in docgen.doc_pages(ROOT):
        prose = _prose(page.read_text(encoding="utf-8"), docgen)
        rel = page.relative_to(ROOT)
        for pat in TIMING_FIGURES:
            for m in re.finditer(pat, prose):
                line = prose[: m.start()].count("\n") + 1
                found.append(f"{rel}: {m.group(0)!r} (prose line {line})")
        for m in re.finditer(r"^\|(.+)\|\n\|[-:| ]+\|$", prose, re.M):  # a table's header and separator
            if TIME_HEADER.search(m.group(1)):
                found.append(f"{rel}: a hand-written table with a time column: {m.group(1).strip()!r}")
    assert found == [], "\n".join(found)


def test_the_scan_finds_the_figures_that_did_not_reproduce(docgen):
    # the test above is only as good as its patterns: the examples must be caught
    for figure in ("918-1279x real time", "29 M points/s", "5 x 14 in 0.50 ms", "0.07-0.36x OpenCV",
                   "about 10,000 spots/s", "One fit takes about 30 ms", "1.38 s of CPU", "**1.9 min** wall (200 s CPU)",
                   "25 s on this 2-core machine", "median time 0.30 s per room"):
        assert any(re.search(p, figure) for p in TIMING_FIGURES), figure
    table = "| command | seconds | ratio |\n|---|---|---|\n| a | 1 | 2 |\n"
    assert TIME_HEADER.search(re.match(r"^\|(.+)\|\n", table).group(1))
    # ... but not the same figures inside a generated region
    page = "<!-- bench:bench_locate/1 begin -->\n| x real time |\n|---|\n| 918x real time |\n<!-- bench:bench_locate/1 end -->\n"
    prose = _prose(page, docgen)
    assert not any(re.search(p, prose) for p in TIMING_FIGURES) and not TIME_HEADER.search(prose.replace("bench:", ""))


def test_tables_are_parsed_by_explicit_id_or_by_order(docgen):
    out = textwrap.dedent("""\
        some text
        | a | b |
        |---|---|
        | 1 | 2 |

        <!-- table: speed -->
        | c |
        |---|
        | 3 |
        title line
        | d |
        |---|
        | 4 |
        """)
    t = docgen.parse_tables(out)
    assert list(t) == ["1", "speed", "2"]
    assert t["speed"] == "| c |\n|---|\n| 3 |\n"
    assert t["2"].endswith("| 4 |\n")
    with pytest.raises(ValueError):
        docgen.parse_tables("<!-- table: x -->\n| a |\n|---|\n\n<!-- table: x -->\n| b |\n|---|\n")
    # an id line that a text line separates from the table names nothing
    assert list(docgen.parse_tables("<!-- table: x -->\ntext\n| a |\n|---|\n")) == ["1"]


def test_unbalanced_or_nested_markers_are_reported(docgen):
    assert docgen.marker_problems("<!-- bench:a/1 begin -->\nx\n<!-- bench:a/1 end -->\n") == []
    assert docgen.marker_problems("<!-- bench:a/1 begin -->\nx\n") != []
    assert docgen.marker_problems("<!-- bench:a/1 begin -->\n<!-- bench:b/1 end -->\n") != []


FAKE_OK = '''
import sys
if "--markdown" not in sys.argv:
    sys.exit(3)
print("bench output; args", sys.argv[1:-1])
print("<!-- table: main -->")
print("| what | ms |")
print("|---|---|")
print("| thing | %s |" % sys.argv[1])
print()
print("| other |")
print("|---|")
print("| 7 |")
'''
FAKE_FAIL = 'import sys\nprint("| half |")\nsys.exit(1)\n'


def _fake_tree(tmp_path, docgen, monkeypatch, run_all):
    (tmp_path / "benchmarks").mkdir()
    (tmp_path / "benchmarks" / "bench_ok.py").write_text(FAKE_OK)
    (tmp_path / "benchmarks" / "bench_bad.py").write_text(FAKE_FAIL)
    (tmp_path / "docs" / "guide").mkdir(parents=True)
    readme = ("# title\n\ntext before\n\n<!-- bench:bench_ok/main begin -->\nold table\n<!-- bench:bench_ok/main end -->\n"
              "\nbetween\n<!-- bench:bench_bad/1 begin -->\nkept as it was\n<!-- bench:bench_bad/1 end -->\ntail\n")
    (tmp_path / "README.md").write_text(readme)
    page = "# p\n\n<!-- bench:bench_ok/1 begin -->\n<!-- bench:bench_ok/1 end -->\n\n<!-- bench:bench_ok/main begin -->\n<!-- bench:bench_ok/main end -->\n"
    (tmp_path / "docs" / "guide" / "p.md").write_text(page)
    monkeypatch.setattr(run_all, "HERE", tmp_path / "benchmarks")
    monkeypatch.setattr(docgen, "ROOT", tmp_path)
    monkeypatch.setattr(run_all, "REGISTRY", {
        "bench_ok": run_all.Bench(full=("42",), quick=("1",), tables=("main", "1")),
        "bench_bad": run_all.Bench(full=(), quick=(), tables=("1",)),
    })
    return readme, page


def test_bench_writes_its_tables_with_the_machine_and_leaves_everything_else(tmp_path, monkeypatch, run_all, docgen,
                                                                              capsys):
    readme, page = _fake_tree(tmp_path, docgen, monkeypatch, run_all)
    assert [p for p in run_all.check_docs(tmp_path) if "is empty" not in p] == []
    assert "p.md: region 'bench_ok/1' is empty" in "\n".join(run_all.check_docs(tmp_path))
    assert run_all.main([]) == 1  # bench_bad failed: its region is kept, the others are written
    out = capsys.readouterr()
    assert "bench_bad" in out.err and "wrote" in out.out
    new = (tmp_path / "README.md").read_text()
    assert new.startswith("# title\n\ntext before\n\n<!-- bench:bench_ok/main begin -->\n")
    assert "| thing | 42 |" in new and "old table" not in new
    assert "<!-- bench:bench_bad/1 begin -->\nkept as it was\n<!-- bench:bench_bad/1 end -->\ntail\n" in new
    cap = re.search(r"<small>Generated by `python3 tasks.py bench` \(`benchmarks/bench_ok.py 42`\) on "
                    r"(\d{4}-\d\d-\d\d \d\d:\d\d UTC); (.+), (\d+) cores, load ([\d. ]+|unknown) \(1, 5, 15 min\); Python ([\d.]+), "
                    r"numpy (\S+), scipy (\S+), numba (\S+), OpenCV (.+?); psdcal (.+)\.</small>", new)
    assert cap, new
    assert "quick mode" not in new
    p = (tmp_path / "docs" / "guide" / "p.md").read_text()
    assert "| 7 |" in p and "| thing | 42 |" in p  # both tables, each in its own region
    assert docgen.outside_regions(p) == docgen.outside_regions(page)
    assert docgen.outside_regions(new) == docgen.outside_regions(readme)
    # the page checks out (bench_bad's region is old but not empty), and a second run rewrites the same
    # regions in place (no growth)
    assert run_all.check_docs(tmp_path) == []
    assert run_all.main(["ok"]) == 0
    again = (tmp_path / "README.md").read_text()
    assert again.count("| thing | 42 |") == 1 and len(again.splitlines()) == len(new.splitlines())
    assert not list(tmp_path.rglob("*.tmp"))  # written by rename, no temporary left


def test_quick_mode_writes_only_when_asked_and_says_so(tmp_path, monkeypatch, run_all, docgen, capsys):
    readme, _ = _fake_tree(tmp_path, docgen, monkeypatch, run_all)
    assert run_all.main(["--quick", "ok"]) == 0
    assert (tmp_path / "README.md").read_text() == readme
    assert "docs not written" in capsys.readouterr().out
    assert run_all.main(["--quick", "--write-docs", "ok"]) == 0
    new = (tmp_path / "README.md").read_text()
    assert "| thing | 1 |" in new and "quick mode" in new
    # arguments after -- replace the registry's and write nothing unless asked
    assert run_all.main(["ok", "--", "5"]) == 0
    assert (tmp_path / "README.md").read_text() == new


def test_check_reports_unknown_tables_and_tables_without_a_region(tmp_path, monkeypatch, run_all, docgen):
    _fake_tree(tmp_path, docgen, monkeypatch, run_all)
    (tmp_path / "docs" / "guide" / "q.md").write_text(
        "<!-- bench:bench_ok/9 begin -->\n<!-- bench:bench_ok/9 end -->\n"
        "<!-- bench:bench_gone/1 begin -->\n<!-- bench:bench_gone/1 end -->\n<!-- bench:bench_ok/1 begin -->\n")
    problems = "\n".join(run_all.check_docs(tmp_path))
    assert "bench_ok/9" in problems and "prints no table '9'" in problems
    assert "bench_gone" in problems
    assert "not part of a begin/end pair" in problems
    monkeypatch.setattr(run_all, "REGISTRY", {**run_all.REGISTRY, "bench_new": run_all.Bench(tables=("1",))})
    problems = "\n".join(run_all.check_docs(tmp_path))
    assert "bench_new/1 has no generated region" in problems and "bench_new.py, which does not exist" in problems


def test_bad_usage_is_exit_2(run_all, capsys):
    assert run_all.main(["--sets", "1"]) == 2
    assert run_all.main(["--write-docs", "--no-write-docs"]) == 2
    assert run_all.main(["no-such-bench"]) == 2
    assert "no benchmark matches" in capsys.readouterr().err
