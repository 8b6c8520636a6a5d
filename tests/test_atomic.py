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


def test_private_temporaries_are_new_owner_only_files(tmp_path):
    """The staging files (made without tempfile): new (never an existing name), mode 0600, absolute, named
    prefix + random + suffix, distinct."""
    import os
    import stat

    from psdcal._atomic import _CREATE_FLAGS, _create_private

    made = []
    for _ in range(50):
        fd, p = _create_private(tmp_path, "pre.", ".sfx")
        os.close(fd)
        made.append(p)
        assert p.is_absolute() and p.parent == tmp_path and p.name.startswith("pre.") and p.name.endswith(".sfx")
        assert stat.S_IMODE(p.stat().st_mode) == 0o600 and p.stat().st_size == 0
    assert len(set(made)) == len(made)
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "elsewhere")
    with pytest.raises(FileExistsError):  # O_EXCL: an existing name (even a dangling link) is never opened
        os.open(link, _CREATE_FLAGS, 0o600)
    assert not (tmp_path / "elsewhere").exists()
