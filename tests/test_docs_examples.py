"""Runnable documentation: the ``<!-- run -->`` code blocks of README.md and docs/**/*.md.

Convention: a fenced code block immediately preceded by the line
``<!-- run -->`` is executed. All such blocks of one file run in order, in one
fresh temporary directory (so later blocks see the files earlier ones wrote):
``bash``/``sh``/``shell`` blocks with ``bash -euo pipefail`` and this
environment's ``psdcal`` first on PATH, ``python`` blocks with this
environment's interpreter. One test per file that has run blocks; a failing
block fails its file's test with the block's line and output. A marker that is
not followed by a fence, or a run block in a language the runner does not know,
is an error, never skipped.

A block must also show what it claims: every ``bash`` run block is followed,
before the next ``bash`` block, by a *check* (and every file ends with one): a
``python`` run block that asserts, or a hidden check, an HTML comment (not
rendered) that runs as Python in the same directory::

    <!-- check
    assert abs(csv_rows("xyz.csv")[0]["X_mm"] - truth) < 3 * sigma
    -->

A check sees ``out`` (stdout + stderr of the run block before it),
``csv_rows(path)`` (a list of dicts, numbers as floats), ``load_json(path)``,
``np`` and ``Path``; it compares the outputs with the simulated truth or with
the numbers the page shows. A page that must stay short (README.md) gets its
checks from :data:`ATTACHED_CHECKS` here instead.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MARKER = "<!-- run -->"
CHECK_OPEN, CHECK_CLOSE = "<!-- check", "-->"
CHECK_PRELUDE = """\
import csv, json, os, re
from pathlib import Path
import numpy as np
out = Path(os.environ["DOCS_LAST_OUTPUT"]).read_text()


def _num(v):
    try:
        return float(v)
    except (TypeError, ValueError):
        return v


def csv_rows(path):
    with open(path, newline="") as fh:
        return [{k: _num(v) for k, v in r.items()} for r in csv.DictReader(fh)]


def load_json(path):
    return json.loads(Path(path).read_text())


"""
FENCE = re.compile(r"^(?P<indent> {0,3})(?P<fence>`{3,}|~{3,})\s*(?P<info>[^`\s]*)")
LANGUAGES = {"bash": "bash", "sh": "bash", "shell": "bash", "python": "python", "py": "python"}
TIMEOUT_S = 120


@dataclass(frozen=True)
class Block:
    line: int  # 1-based line of the opening fence (of the check's comment)
    language: str  # "bash", "python" or "check"
    code: str


class RunBlockError(ValueError):
    """A ``<!-- run -->`` marker the runner cannot honour."""


def run_blocks(text: str, source: str = "<text>") -> list[Block]:
    """The run blocks of a Markdown text, in order.

    Raises
    ------
    RunBlockError
        A marker not immediately followed by a fence, an unclosed fence, or a
        language the runner does not run.
    """
    lines = text.splitlines()
    blocks = []
    i = 0
    in_fence = None
    while i < len(lines):
        m = FENCE.match(lines[i])
        if in_fence is not None:  # inside a fence, a marker is just text
            if m and m.group("fence")[0] == in_fence[0] and len(m.group("fence")) >= len(in_fence) and not m.group("info"):
                in_fence = None
            i += 1
            continue
        if m:
            in_fence = m.group("fence")
            i += 1
            continue
        if lines[i].strip() == CHECK_OPEN:
            body = []
            j = i + 1
            while j < len(lines) and lines[j].strip() != CHECK_CLOSE:
                body.append(lines[j])
                j += 1
            if j >= len(lines):
                raise RunBlockError(f"{source}:{i + 1}: the check is never closed with '{CHECK_CLOSE}'")
            if not blocks:
                raise RunBlockError(f"{source}:{i + 1}: a check before any run block")
            blocks.append(Block(line=i + 1, language="check", code="\n".join(body) + "\n"))
            i = j + 1
            continue
        if lines[i].strip() != MARKER:
            i += 1
            continue
        if i + 1 >= len(lines) or not (f := FENCE.match(lines[i + 1])):
            raise RunBlockError(f"{source}:{i + 1}: '{MARKER}' must be followed immediately by a fenced code block")
        info = f.group("info").lower()
        if info not in LANGUAGES:
            raise RunBlockError(f"{source}:{i + 2}: run block in language {info!r}; the runner runs {sorted(LANGUAGES)}")
        fence = f.group("fence")
        body = []
        j = i + 2
        while j < len(lines):
            c = FENCE.match(lines[j])
            if c and c.group("fence")[0] == fence[0] and len(c.group("fence")) >= len(fence) and not c.group("info"):
                break
            body.append(lines[j])
            j += 1
        else:
            raise RunBlockError(f"{source}:{i + 2}: the run block's fence is never closed")
        blocks.append(Block(line=i + 2, language=LANGUAGES[info], code="\n".join(body) + "\n"))
        i = j + 1
    if in_fence is not None:
        raise RunBlockError(f"{source}: a code fence is never closed")
    return blocks


#: Checks kept here for pages that must stay short (README.md: at most 250 lines, tests/test_repo_hygiene.py):
#: (page, text of a line of the run block, the check run after it). Same prelude as a ``<!-- check -->``.
ATTACHED_CHECKS = [
    ("README.md", "    -o xyz.csv --track track.csv --track-q 1e5", """\
cal, truth = load_json("calib.json"), load_json("cal/truth.json")
assert all(abs(cal["intrinsics"][n] - truth["intrinsics"][n]) < 4 * cal["std"][n] for n in ("f_mm", "cx_mm", "cy_mm"))
tag = [r for r in csv_rows("room/truth_track.csv") if r["emitter"] == "tag"]
for r in csv_rows("xyz.csv")[10:]:  # positions against the true track, in their stated sigmas
    for a in "XYZ":
        true = np.interp(r["t_s"], [q["t_s"] for q in tag], [q[f"{a}_mm"] for q in tag])
        assert abs(r[f"{a}_mm"] - true) < 4 * r[f"sigma_{a}_mm"], (r["t_s"], a)
"""),
    ("README.md", "calib = res.to_dict()", """\
f, sf = map(float, out.split()[:2])
assert abs(f - load_json("sim/truth.json")["intrinsics"]["f_mm"]) < 4 * sf and 0 < sf < 0.05
"""),
]


def with_attached_checks(blocks: list[Block], source: str) -> list[Block]:
    """``blocks`` with the :data:`ATTACHED_CHECKS` of ``source`` after their run blocks (each must find one)."""
    out = []
    mine = [(line, code) for page, line, code in ATTACHED_CHECKS if page == source]
    used = set()
    for b in blocks:
        out.append(b)
        for k, (line, code) in enumerate(mine):
            if b.language != "check" and any(line.strip() in ln for ln in b.code.splitlines()):
                out.append(Block(line=b.line, language="check", code=code))
                used.add(k)
    missing = [mine[k][0] for k in range(len(mine)) if k not in used]
    if missing:
        raise RunBlockError(f"{source}: attached checks find no run block with the line(s) {missing}")
    return out


def is_check(b: Block) -> bool:
    return b.language == "check" or (b.language == "python" and re.search(r"^\s*assert\b", b.code, re.M) is not None)


def unchecked_blocks(blocks: list[Block]) -> list[Block]:
    """Run blocks whose result no check looks at: a bash block with no check before the next bash block, or
    any block after the file's last check."""
    bad, pending = [], None
    for b in blocks:
        if is_check(b):
            pending = None
        elif b.language == "bash":
            if pending is not None and pending.language == "bash":
                bad.append(pending)
            pending = b  # a python block without asserts before it prepared its inputs
        elif pending is None:
            pending = b
    if pending is not None:
        bad.append(pending)
    return bad


def documentation_files() -> list[Path]:
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return [p for p in files if p.is_file()]


def files_with_run_blocks() -> list[Path]:
    return [p for p in documentation_files() if MARKER in p.read_text(encoding="utf-8")]


def run_file(path: Path, workdir: Path) -> None:
    """Run every block of ``path`` in ``workdir``; fail with the block's line and output."""
    source = path.relative_to(ROOT).as_posix()
    blocks = with_attached_checks(run_blocks(path.read_text(encoding="utf-8"), source), source)
    assert blocks, f"{source}: has '{MARKER}' but no run block"
    bindir = str(Path(sys.executable).parent)
    env = {**os.environ, "PATH": bindir + os.pathsep + os.environ.get("PATH", ""), "MPLBACKEND": "Agg",
           "NO_COLOR": "1", "PSDCAL_REPO": str(ROOT)}
    last = workdir.parent / f".{workdir.name}-last-output.txt"  # beside the folder, not in it
    last.write_text("")
    env["DOCS_LAST_OUTPUT"] = str(last)
    for b in blocks:
        if b.language == "bash":
            cmd = ["bash", "-euo", "pipefail", "-c", b.code]
        else:
            cmd = [sys.executable, "-c", (CHECK_PRELUDE if b.language == "check" else "") + b.code]
        try:
            proc = subprocess.run(cmd, cwd=workdir, env=env, capture_output=True, text=True, timeout=TIMEOUT_S,
                                  stdin=subprocess.DEVNULL)
        except subprocess.TimeoutExpired:
            pytest.fail(f"{source}:{b.line}: {b.language} block ran over {TIMEOUT_S} s")
        if proc.returncode != 0:
            out = (proc.stdout + proc.stderr)[-3000:]
            pytest.fail(f"{source}:{b.line}: {b.language} block exited {proc.returncode}:\n{b.code}\n--- output ---\n{out}")
        if b.language != "check":
            last.write_text(proc.stdout + proc.stderr)


@pytest.mark.parametrize("path", files_with_run_blocks(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_doc_examples_run(path, tmp_path):
    run_file(path, tmp_path)


def test_readme_has_a_runnable_example():
    assert run_blocks((ROOT / "README.md").read_text(encoding="utf-8"), "README.md")


@pytest.mark.parametrize("path", files_with_run_blocks(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_run_block_is_checked(path):
    """A run block that only has to exit 0 shows nothing: each is followed by a check of what it claims."""
    source = path.relative_to(ROOT).as_posix()
    bad = unchecked_blocks(with_attached_checks(run_blocks(path.read_text(encoding="utf-8"), source), source))
    assert not bad, f"{source}: run blocks at lines {[b.line for b in bad]} are followed by no check"


def test_every_marker_is_well_formed():
    """Parsing every documentation file: a malformed marker is an error even in a file not run here."""
    for p in documentation_files():
        run_blocks(p.read_text(encoding="utf-8"), p.relative_to(ROOT).as_posix())


# The runner itself: it must run what it should, fail what fails, and refuse what it cannot run.

def test_parser_finds_blocks_in_order_and_ignores_unmarked_and_fenced_markers():
    text = "\n".join([
        "intro", MARKER, "```bash", "echo one", "```", "", "```bash", "echo not run", "```",
        "````markdown", MARKER, "```bash", "echo inside an example", "```", "````",
        MARKER, "```python", "print(2)", "```",
    ])
    blocks = run_blocks(text)
    assert [(b.language, b.code) for b in blocks] == [("bash", "echo one\n"), ("python", "print(2)\n")]
    assert blocks[0].line == 3


@pytest.mark.parametrize("text", [
    MARKER + "\n\n```bash\necho x\n```\n",  # not immediately followed
    MARKER + "\n```console\n$ psdcal\n```\n",  # language not run
    MARKER + "\n```\necho x\n```\n",  # no language
    MARKER + "\n```bash\necho x\n",  # never closed
])
def test_parser_refuses_what_it_cannot_run(text):
    with pytest.raises(RunBlockError):
        run_blocks(text)


def test_runner_shares_one_directory_and_fails_on_error(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    good = tmp_path / "good.md"
    good.write_text("\n".join([MARKER, "```bash", "echo 41 > n.txt", "```", MARKER, "```python",
                               "assert int(open('n.txt').read()) + 1 == 42", "```"]) + "\n")
    work = tmp_path / "w1"
    work.mkdir()
    run_file(good, work)
    bad = tmp_path / "bad.md"
    bad.write_text("\n".join([MARKER, "```bash", "false | cat", "echo after", "```"]) + "\n")  # pipefail
    work2 = tmp_path / "w2"
    work2.mkdir()
    with pytest.raises(pytest.fail.Exception, match=r"bad.md:2: bash block exited 1"):
        run_file(bad, work2)


def test_checks_see_the_output_and_fail_on_a_wrong_claim(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    doc = tmp_path / "c.md"
    doc.write_text("\n".join([MARKER, "```bash", "echo 'f = 8.01 mm'", "printf 'a,b\\n1,2\\n' > t.csv", "```",
                              CHECK_OPEN, "assert 'f = 8.01' in out and csv_rows('t.csv')[0]['b'] == 2.0", CHECK_CLOSE,
                              MARKER, "```bash", "echo 'f = 9 mm'", "```", CHECK_OPEN, "assert 'f = 8' in out",
                              CHECK_CLOSE]) + "\n")
    blocks = run_blocks(doc.read_text())
    assert [b.language for b in blocks] == ["bash", "check", "bash", "check"]
    assert unchecked_blocks(blocks) == []
    work = tmp_path / "w"
    work.mkdir()
    with pytest.raises(pytest.fail.Exception, match=r"c.md:13: check block exited 1"):
        run_file(doc, work)


def test_unchecked_blocks_are_found():
    b = [Block(1, "bash", "x"), Block(2, "bash", "y"), Block(3, "check", "z"), Block(4, "python", "print(1)")]
    assert [x.line for x in unchecked_blocks(b)] == [1, 4]
    assert unchecked_blocks([Block(1, "python", "w = 1"), Block(2, "bash", "x"), Block(3, "python", "assert w")]) == []
    with pytest.raises(RunBlockError):
        run_blocks(CHECK_OPEN + "\nassert 1\n")  # a check before any run block
    with pytest.raises(RunBlockError):
        run_blocks(MARKER + "\n```bash\necho\n```\n" + CHECK_OPEN + "\nassert 1\n")  # never closed
