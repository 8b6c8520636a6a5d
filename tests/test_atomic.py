"""Atomic output files: nothing is lost on failure, modes are ordinary."""
import os

import pytest

from psdcal._atomic import atomic_path, write_text_atomic


def test_failure_keeps_the_old_file(tmp_path):
    p = tmp_path / "out.txt"
    p.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert p.read_text() == "old"
    assert [f.name for f in tmp_path.iterdir()] == ["out.txt"]  # no temporary left


def test_new_file_gets_umask_mode_and_existing_keeps_its_mode(tmp_path):
    old = os.umask(0o022)
    try:
        p = tmp_path / "new.txt"
        write_text_atomic(p, "x")
        assert p.stat().st_mode & 0o777 == 0o644
        q = tmp_path / "exec.sh"
        q.write_text("a")
        q.chmod(0o751)
        write_text_atomic(q, "b")
        assert q.stat().st_mode & 0o777 == 0o751 and q.read_text() == "b"
    finally:
        os.umask(old)
