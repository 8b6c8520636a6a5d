"""Nothing in the repository points to a file outside it.

The conventions live in ``docs/model.md``; a clone must be complete without
the project's private workspace. Scanned: ``src/``, ``docs/``, ``tests/``,
``benchmarks/``, ``README.md``, ``tasks.py``, ``pyproject.toml``,
``mkdocs.yml`` and ``.ci/run`` (text files only).

The one allowed way to use data kept outside the repository is a test that
builds the path as ``Path(<repository root>).parent / "shared"`` and skips
when it is absent; such a file must contain a ``skip``.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCANNED_DIRS = ("src", "docs", "tests", "benchmarks")
SCANNED_FILES = ("README.md", "tasks.py", "pyproject.toml", "mkdocs.yml", ".ci/run")
SKIP_PARTS = {"__pycache__", ".pytest_cache", ".hypothesis"}
SKIP_SUFFIXES = {".png", ".jpg", ".jpeg", ".gif", ".npy", ".npz", ".h5", ".hdf5", ".tdms", ".nbi", ".nbc", ".pyc", ".pdf"}

# Built from pieces so that this file does not match itself.
_SPEC = "MODEL" + ".md"
_STYLE = "STYLE" + ".md"
FORBIDDEN = [
    (re.compile(re.escape(_SPEC)), "the outside model specification (cite docs/model.md#<section>)"),
    (re.compile(re.escape(_STYLE)), "the outside style guide"),
    (re.compile(r"\.\./+(shared|paper|spec|brief)\b"), "a relative path out of the repository"),
    (re.compile(r"/" + "work" + r"/"), "an absolute path of the workspace"),
    (re.compile(r"(?<![\w.])/(home|Users|root)/\w"), "an absolute home directory"),
    (re.compile(r"(?<![\w/.])/shared/"), "the shared folder"),
    (re.compile(r"[A-Za-z]:\\\\"), "a Windows absolute path"),
]
SHARED_WORD = re.compile(r"""["']shared["']""")
ALLOWED_SHARED = re.compile(r"""\.parent\s*/\s*["']shared["']""")


def scanned_files() -> list[Path]:
    files = []
    for d in SCANNED_DIRS:
        for p in sorted((ROOT / d).rglob("*")):
            rel = p.relative_to(ROOT)
            if not p.is_file() or SKIP_PARTS & set(rel.parts) or p.suffix.lower() in SKIP_SUFFIXES:
                continue
            if any(part.endswith(".egg-info") for part in rel.parts):
                continue
            files.append(p)
    files += [ROOT / f for f in SCANNED_FILES if (ROOT / f).is_file()]
    # This file spells the forbidden patterns out; test_the_rule_itself checks them instead.
    return [p for p in files if p != Path(__file__).resolve()]


def offending_lines(path: Path, root: Path = ROOT) -> list[str]:
    """Every line of ``path`` that points outside the repository, as ``file:line: why``."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        return []
    rel = path.relative_to(root).as_posix()
    is_test = rel.startswith("tests/") and path.suffix == ".py"
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        for pat, why in FORBIDDEN:
            if pat.search(line):
                out.append(f"{rel}:{n}: {why}: {line.strip()[:120]}")
        if SHARED_WORD.search(line) and not (is_test and ALLOWED_SHARED.search(line)):
            out.append(f"{rel}:{n}: 'shared' used as a path outside tests' Path(root).parent / \"shared\": {line.strip()[:120]}")
    if is_test and ALLOWED_SHARED.search(text) and "skip" not in text:
        out.append(f"{rel}: reads data outside the repository but never skips when it is absent")
    return out


def test_the_scan_covers_the_repository():
    files = {p.relative_to(ROOT).as_posix() for p in scanned_files()}
    for must in ("README.md", "docs/model.md", "src/psdcal/__init__.py", "tests/conftest.py", "tasks.py"):
        assert must in files


def test_no_reference_outside_the_repository():
    bad = [line for p in scanned_files() for line in offending_lines(p)]
    assert not bad, "references outside the repository:\n" + "\n".join(bad)


@pytest.mark.parametrize(
    "line, ok",
    [
        ("see " + _SPEC + " 5", False),
        ("src = '../" + "shared/data'", False),
        ("p = '/" + "work/shared/data/x.csv'", False),
        ("open('/home/alice/data.csv')", False),
        ("see docs/model.md#distortion", True),
        ("data = Path(ROOT).parent / 'shared' / 'data'", True),  # allowed in tests only
        ("psdcal reproduce --quick --out /tmp/repro", True),
    ],
)
def test_the_rule_itself(tmp_path, line, ok):
    """The patterns catch what they should and let the allowed forms through."""
    (tmp_path / "tests").mkdir()
    f = tmp_path / "tests" / "test_x.py"
    f.write_text(line + "\npytest.skip('absent')\n")
    assert (offending_lines(f, tmp_path) == []) == ok
    if "shared" in line and ok:  # the allowed form is for tests only, and only with a skip
        g = tmp_path / "guide.md"
        g.write_text(line + "\n")
        assert offending_lines(g, tmp_path)
        f.write_text(line + "\n")
        assert offending_lines(f, tmp_path)


def test_readme_is_a_front_door():
    """The README stays short (<= 250 lines): the details live in docs/."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    for needle in ("python3 tasks.py demo", "python3 tasks.py test", "docs/tutorial.md", "docs/model.md"):
        assert needle in text
