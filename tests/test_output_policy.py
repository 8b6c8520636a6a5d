"""The output policy: no input overwritten, existing outputs only with --force, sets all-or-nothing."""
import json
import os
from pathlib import Path

import pytest

from psdcal._atomic import JOURNAL_PREFIX, TMP_PREFIX, atomic_path, output_set, recover, write_text_atomic
from psdcal.cli import main


def run(args, capsys):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(err):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("psdcal: error:"), err
    assert "Traceback" not in err
    return lines[0]


@pytest.fixture()
def made(tmp_path, capsys):
    d = tmp_path / "sim"
    assert run(["simulate", "--images", "5", "--seed", "1", "-o", d], capsys)[0] == 0
    assert run(["calibrate", d / "points.csv", "-t", d / "template.csv", "-o", d / "c.json", "-q"], capsys)[0] == 0
    return d


def snapshot(d):
    return {p.name: p.read_bytes() for p in sorted(d.iterdir()) if p.is_file()}


@pytest.mark.parametrize("args, option", [
    (["calibrate", "{d}/points.csv", "-t", "{d}/template.csv", "-o", "{d}/points.csv", "--force"], "POINTS"),
    (["calibrate", "{d}/points.csv", "-t", "{d}/template.csv", "-o", "{d}/template.csv", "--force"], "--template"),
    (["report", "{d}/c.json", "-o", "{d}/c.json", "--force"], None),  # wrong extension or input: refused
    (["errormap", "--calib", "{d}/c.json", "--csv", "{d}/c.json", "-o", "{d}/m.png", "--force"], "--calib"),
    (["aoa", "{d}/points.csv", "--calib", "{d}/c.json", "-o", "{d}/points.csv", "--force"], "POINTS"),
    (["calibrate", "{d}/points.csv", "-t", "{d}/template.csv", "-o", "{d}/../sim/./points.csv", "--force"], "POINTS"),
])
def test_an_input_is_never_overwritten(made, capsys, args, option):
    before = snapshot(made)
    code, _, err = run([a.format(d=made) for a in args], capsys)
    assert code == 2
    line = one_error_line(err)
    if option:
        assert "would overwrite the input" in line and option in line
    assert snapshot(made) == before


def test_an_input_reached_through_a_link_is_not_overwritten(made, capsys):
    link = made.parent / "link.csv"
    link.symlink_to(made / "points.csv")
    before = snapshot(made)
    code, _, err = run(["calibrate", made / "points.csv", "-t", made / "template.csv", "-o", link, "--force"], capsys)
    assert code == 2 and "would overwrite the input" in one_error_line(err)
    assert snapshot(made) == before


def test_existing_output_needs_force(made, capsys):
    before = snapshot(made)
    code, _, err = run(["simulate", "--images", "5", "--seed", "2", "-o", made], capsys)
    assert code == 2 and "--force" in one_error_line(err)
    assert snapshot(made) == before
    code, _, _ = run(["simulate", "--images", "5", "--seed", "2", "-o", made, "--force"], capsys)
    assert code == 0
    assert json.loads((made / "truth.json").read_text())["seed"] == 2


def test_every_writing_command_has_force():
    from psdcal.cli import OUTPUT_PARAMS, _register, cli

    _register()

    def walk(group):
        for name, cmd in group.commands.items():
            if hasattr(cmd, "commands"):
                yield from walk(cmd)
            else:
                yield name, cmd

    writers = [(n, c) for n, c in walk(cli) if any(p.name in OUTPUT_PARAMS for p in c.params)]
    assert len(writers) >= 14
    for name, cmd in writers:
        assert any(p.name == "force" for p in cmd.params), name


def test_failed_run_leaves_the_old_set_whole(made, capsys, monkeypatch):
    before = snapshot(made)
    import psdcal.io as io

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(io, "write_json", boom)  # template.csv and points.csv are staged first
    code, _, err = run(["simulate", "--images", "5", "--seed", "3", "-o", made, "--force"], capsys)
    assert code == 2 and "No space left" in one_error_line(err)
    assert snapshot(made) == before
    assert not [p for p in made.iterdir() if p.name.startswith((TMP_PREFIX, JOURNAL_PREFIX))]


def test_wrong_extension_is_refused_before_writing(made, capsys):
    code, _, err = run(["errormap", "--calib", made / "c.json", "-o", made / "map.jpg"], capsys)
    assert code == 2 and ".jpg" in one_error_line(err)
    assert not (made / "map.jpg").exists()


@pytest.mark.parametrize("where", ["parent-is-file", "output-is-dir", "out-dir-is-file"])
def test_unwritable_places_are_one_line(made, capsys, where):
    if where == "parent-is-file":
        args = ["calibrate", made / "points.csv", "-t", made / "template.csv", "-o", made / "c.json" / "x.json"]
    elif where == "output-is-dir":
        (made / "d.json").mkdir()
        args = ["calibrate", made / "points.csv", "-t", made / "template.csv", "-o", made / "d.json", "--force"]
    else:
        args = ["simulate", "-o", made / "c.json"]
    before = snapshot(made)
    code, _, err = run(args, capsys)
    assert code == 2
    one_error_line(err)
    assert snapshot(made) == before


def test_read_only_folder_is_one_line(made, capsys, tmp_path):
    """A folder the user may not write: refused in one line, before any work, nothing written.

    As root (CI runs as root, and root writes anywhere) the command runs in a
    child process with its privileges dropped to uid/gid 65534, so the
    permission failure is the kernel's, as for any user.
    """
    import shutil
    import subprocess
    import sys
    import tempfile

    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        try:
            code, _, err = run(["calibrate", made / "points.csv", "-t", made / "template.csv", "-o", ro / "c.json"],
                               capsys)
            assert code == 2 and "not writable" in one_error_line(err)
            assert list(ro.iterdir()) == []
        finally:
            ro.chmod(0o755)
        return
    # root: a world-readable copy of the inputs (pytest's tmp_path is private to root) and a folder owned by root
    top = Path(tempfile.mkdtemp(prefix="psdcal-ro-"))
    try:
        top.chmod(0o755)
        for n in ("points.csv", "template.csv"):
            shutil.copy(made / n, top / n)
            (top / n).chmod(0o644)
        ro = top / "ro"
        ro.mkdir()
        ro.chmod(0o755)  # others may enter, not write
        src = str(Path(__file__).resolve().parents[1] / "src")
        env = {**os.environ, "PYTHONPATH": src + os.pathsep + os.environ.get("PYTHONPATH", ""), "HOME": str(top),
               "NUMBA_CACHE_DIR": str(top / "numba"), "MPLCONFIGDIR": str(top / "mpl")}
        proc = subprocess.run([sys.executable, "-m", "psdcal.cli", "calibrate", str(top / "points.csv"), "-t",
                               str(top / "template.csv"), "-o", str(ro / "c.json")], cwd=top, env=env,
                              capture_output=True, text=True, user=65534, group=65534, extra_groups=[], timeout=120)
        assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
        assert "not writable" in one_error_line(proc.stderr)
        assert list(ro.iterdir()) == []
    finally:
        shutil.rmtree(top, ignore_errors=True)


def test_permission_denied_while_writing_is_one_line(made, capsys, monkeypatch):
    """A permission failure the guard could not foresee (an ACL, a file system that refuses at write time).

    Simulated by the staging of the temporary file failing with EACCES, as
    root and as any user: exit 2, one line, the old outputs untouched, no
    temporary left.
    """
    from psdcal import _atomic

    before = snapshot(made)
    real = _atomic._create_private

    def denied(folder, *a, **k):
        if str(folder) == str(made):
            raise PermissionError(13, "Permission denied", str(made))
        return real(folder, *a, **k)

    monkeypatch.setattr(_atomic, "_create_private", denied)
    code, _, err = run(["simulate", "--images", "5", "--seed", "4", "-o", made, "--force"], capsys)
    assert code == 2 and "Permission denied" in one_error_line(err)
    assert snapshot(made) == before
    assert not [p for p in made.iterdir() if p.name.startswith((TMP_PREFIX, JOURNAL_PREFIX))]


def test_set_commits_all_or_nothing(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old a")
    b.write_text("old b")
    with pytest.raises(RuntimeError):
        with output_set():
            write_text_atomic(a, "new a")
            assert a.read_text() == "old a"  # staged, not yet renamed
            raise RuntimeError("second file failed")
    assert (a.read_text(), b.read_text()) == ("old a", "old b")
    with output_set():
        write_text_atomic(a, "new a")
        write_text_atomic(b, "new b")
    assert (a.read_text(), b.read_text()) == ("new a", "new b")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]


def _dead_pid():
    import subprocess
    import sys

    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_recover_rolls_a_journalled_set_forward_and_drops_orphans(tmp_path):
    pid = _dead_pid()
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("new a")  # the first rename happened before the kill
    b.write_text("old b")
    tb = tmp_path / f"{TMP_PREFIX}{pid}-b.txt.x.txt"
    tb.write_text("new b")
    (tmp_path / f"{JOURNAL_PREFIX}{pid}-x.json").write_text(json.dumps([[str(tmp_path / "gone"), str(a)], [str(tb), str(b)]]))
    orphan = tmp_path / f"{TMP_PREFIX}{pid}-c.txt.y.txt"
    orphan.write_text("half")
    live = tmp_path / f"{TMP_PREFIX}{os.getpid()}-d.txt.z.txt"
    live.write_text("in progress")
    recover(tmp_path)
    assert (a.read_text(), b.read_text()) == ("new a", "new b")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["a.txt", "b.txt", live.name])


def test_atomic_path_outside_a_set_is_immediate(tmp_path):
    p = tmp_path / "x.txt"
    with atomic_path(p) as tmp:
        assert tmp.name.startswith(TMP_PREFIX)
        tmp.write_text("1")
    assert p.read_text() == "1"


def test_demo_replaces_its_own_output_and_never_the_bundled_data(tmp_path, monkeypatch, capsys):
    """`python3 tasks.py demo` runs again and again (its output is replaced), but an --out that names a
    bundled input file is refused and the file stays byte-identical."""
    from importlib.resources import files

    from psdcal.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["demo"]) == 0
    first = (tmp_path / "demo_out" / "calibration.json").read_bytes()
    assert main(["demo"]) == 0
    assert (tmp_path / "demo_out" / "calibration.json").exists() and first
    bundled = files("psdcal") / "data" / "default_points.csv"
    before = bundled.read_bytes()
    capsys.readouterr()
    assert main(["demo", "-o", str(bundled)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "would overwrite the input" in err[0]
    assert bundled.read_bytes() == before
