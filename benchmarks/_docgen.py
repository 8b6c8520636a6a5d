"""Generated regions of the docs: the benchmarks' Markdown tables written into README.md and docs/.

A page holds a generated table between two markers::

    <!-- bench:bench_locate/1 begin -->
    ...written by ``python3 tasks.py bench``: the table, then one line with the command,
    the date, the machine and the library versions...
    <!-- bench:bench_locate/1 end -->

The name is ``SCRIPT/TABLE``: the benchmark's file name without ``.py`` and the table's id
in that script's ``--markdown`` output (``1``, ``2``, ... in the order printed, or the id a
``<!-- table: ID -->`` line printed just before the table gives it). Everything outside the
markers is left byte for byte as it was. This module imports nothing of psdcal, so that the
tests can check the pages without running a benchmark.
"""
from __future__ import annotations

import datetime as _dt
import os
import platform
import re
import subprocess
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: A generated region: its name, then its body (everything between the two markers).
REGION_RE = re.compile(
    r"^<!-- bench:(?P<name>[A-Za-z0-9_.-]+/[A-Za-z0-9_.-]+) begin -->\n(?P<body>.*?)^<!-- bench:(?P=name) end -->$",
    re.S | re.M,
)
#: Any marker (a line of its own), to find unbalanced or misspelt ones.
MARKER_RE = re.compile(r"^<!-- bench:(\S+) (begin|end) -->", re.M)
#: An explicit table id printed by a benchmark just before its table (``_table.print_table(table_id=...)``).
TABLE_ID_RE = re.compile(r"^<!-- table: ([A-Za-z0-9_.-]+) -->$")
#: A table a benchmark could not produce on this machine (a real-data study without the shared data folder beside the repository):
#: ``<!-- table: ID skipped: REASON -->``; its region is left as it was (``_table.print_skipped``).
SKIPPED_RE = re.compile(r"^<!-- table: ([A-Za-z0-9_.-]+) skipped: (.*) -->$")


def doc_pages(root: Path | None = None) -> list[Path]:
    """README.md and every Markdown page under docs/, sorted."""
    root = ROOT if root is None else root
    return [p for p in [root / "README.md", *sorted((root / "docs").rglob("*.md"))] if p.exists()]


def parse_tables(stdout: str) -> dict[str, str]:
    """The Markdown tables in a benchmark's output: id -> the table's lines (ending in a newline).

    A table is a run of consecutive lines starting with ``|``. Its id is the one given by a
    ``<!-- table: ID -->`` line just before it, else its ordinal (``"1"``, ``"2"``, ...) among the
    tables without an explicit id.
    """
    tables: dict[str, str] = {}
    lines = stdout.splitlines()
    k, ordinal, pending_id = 0, 0, None
    while k < len(lines):
        line = lines[k].rstrip()
        m = TABLE_ID_RE.match(line)
        if m:
            pending_id = m.group(1)
            k += 1
            continue
        if line.startswith("|"):
            start = k
            while k < len(lines) and lines[k].rstrip().startswith("|"):
                k += 1
            if pending_id is None:
                ordinal += 1
                tid = str(ordinal)
            else:
                tid = pending_id
            if tid in tables:
                raise ValueError(f"two tables with the id {tid!r}")
            tables[tid] = "".join(x.rstrip() + "\n" for x in lines[start:k])
            pending_id = None
            continue
        if line.strip():
            pending_id = None  # the id line must come just before its table (blank lines allowed)
        k += 1
    return tables


def skipped_tables(stdout: str) -> dict[str, str]:
    """The tables a benchmark said it skipped: id -> the reason it printed."""
    return {m.group(1): m.group(2) for m in (SKIPPED_RE.match(x.rstrip()) for x in stdout.splitlines()) if m}


def regions(text: str) -> list[tuple[str, str]]:
    """(name, body) of every generated region of a page, in order."""
    return [(m.group("name"), m.group("body")) for m in REGION_RE.finditer(text)]


def marker_problems(text: str) -> list[str]:
    """Markers that do not pair up into regions (unbalanced, nested, misspelt): one line each."""
    problems = []
    spans = [m.span() for m in REGION_RE.finditer(text)]
    for m in MARKER_RE.finditer(text):
        if not any(a <= m.start() < b for a, b in spans):
            problems.append(f"marker {m.group(0)!r} at offset {m.start()} is not part of a begin/end pair")
    for name, body in regions(text):
        if "<!-- bench:" in body:
            problems.append(f"region {name!r} holds another marker")
    return problems


def outside_regions(text: str) -> str:
    """The page with every generated region's body removed (the markers stay)."""
    return REGION_RE.sub(lambda m: f"<!-- bench:{m.group('name')} begin -->\n<!-- bench:{m.group('name')} end -->",
                         text)


def replace_regions(text: str, tables: dict[str, str], caption: dict[str, str]) -> tuple[str, list[str]]:
    """Rewrite the bodies of the regions named in ``tables``; return the new page and the names rewritten.

    ``tables``: region name -> Markdown table; ``caption``: script -> the line written under each of
    its tables. Regions not in ``tables`` and everything outside the regions stay as they are.
    """
    done = []

    def sub(m):
        name = m.group("name")
        if name not in tables:
            return m.group(0)
        done.append(name)
        script = name.split("/", 1)[0]
        body = f"\n{tables[name]}\n{caption[script]}\n\n"
        return f"<!-- bench:{name} begin -->\n{body}<!-- bench:{name} end -->"

    return REGION_RE.sub(sub, text), done


def write_atomically(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and one rename."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return " ".join(line.split(":", 1)[1].split())
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def _version(*dists: str) -> str | None:
    from importlib import metadata

    for d in dists:
        try:
            return metadata.version(d)
        except metadata.PackageNotFoundError:
            continue
    return None


def _git_commit(root: Path) -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "--short=10", "HEAD"], cwd=root, capture_output=True,
                              text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "src", "benchmarks"], cwd=root,
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown commit"
    if not head:
        return "unknown commit"
    return head + (" with local changes" if dirty else "")


def load_and_date() -> dict[str, str]:
    """The machine's load averages (1, 5, 15 min) and the date now (UTC)."""
    try:
        load = "{:.2f} {:.2f} {:.2f}".format(*os.getloadavg())
    except OSError:
        load = "unknown"
    return {"load": load, "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}


def environment(root: Path | None = None) -> dict[str, str]:
    """Machine and versions of this run: date, cpu, cores, load, python, numpy, scipy, numba, opencv, psdcal."""
    root = ROOT if root is None else root
    libs = {
        "numpy": _version("numpy"),
        "scipy": _version("scipy"),
        "numba": _version("numba"),
        "OpenCV": _version("opencv-python-headless", "opencv-python", "opencv-contrib-python",
                           "opencv-contrib-python-headless"),
    }
    return {
        **load_and_date(),
        "cpu": _cpu_model(),
        "cores": str(os.cpu_count() or "?"),
        "python": platform.python_version(),
        **{k: (v or "not installed") for k, v in libs.items()},
        "psdcal": f"{_version('psdcal') or '?'}, commit {_git_commit(root)}",
    }


def caption_line(script: str, args: list[str], env: dict[str, str], quick: bool) -> str:
    """The line written under a generated table: how, when, where and with what it was measured."""
    cmd = " ".join([f"benchmarks/{script}.py", *args])
    mode = " **quick mode: small sizes, not for comparison**" if quick else ""
    return (f"<small>Generated by `python3 tasks.py bench` (`{cmd}`){mode} on {env['date']}; "
            f"{env['cpu']}, {env['cores']} cores, load {env['load']} (1, 5, 15 min); Python {env['python']}, "
            f"numpy {env['numpy']}, scipy {env['scipy']}, numba {env['numba']}, OpenCV {env['OpenCV']}; "
            f"psdcal {env['psdcal']}.</small>")
