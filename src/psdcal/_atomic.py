"""Write output files so that a failure never leaves a half-written, mixed or lost file.

The output policy every writing command follows (docs/guide/files-and-errors.md):

- every output is written to a temporary file beside its target, whose name
  starts with :data:`TMP_PREFIX` and carries the writer's process id, and is
  renamed over the target only when it is complete;
- the outputs of one command form a *set* (:func:`output_set`): all are
  staged first and renamed together only after the whole command succeeded,
  so a failure leaves every old output untouched. Before the renames start a
  small journal (``.psdcal-commit-PID-*.json``) lists them; a run killed
  between two renames is rolled forward by the next run (:func:`recover`),
  a run killed before the journal existed is rolled back (its temporaries
  deleted), so a set is never left mixed;
- :func:`guard_outputs` refuses, before any work, an output that is an input
  (same file after resolving links), an output that exists (unless
  ``--force``), an output that is a directory or whose parent is a file or
  cannot be written, and a wrong file extension.
"""
from __future__ import annotations

import contextlib
import errno
import contextvars
import os
from pathlib import Path

#: Prefix of every temporary file psdcal writes (stale ones are removed by the next run).
TMP_PREFIX = ".psdcal-tmp-"
#: Prefix of the journal of a set of renames in progress.
JOURNAL_PREFIX = ".psdcal-commit-"

_CURRENT_SET: contextvars.ContextVar = contextvars.ContextVar("psdcal_output_set", default=None)


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    return True


def _owner_pid(name: str, prefix: str) -> int | None:
    rest = name[len(prefix):]
    head = rest.split("-", 1)[0]
    try:
        return int(head)
    except ValueError:
        return None


def recover(directory) -> int:
    """Finish or undo what a killed psdcal left in ``directory``; return the number of files touched.

    A journal of a dead process is rolled forward (its remaining renames are
    done: the whole set was complete when it was written); then temporaries
    of dead processes are deleted (their set never reached the journal, so
    the old outputs are still whole).
    """
    d = Path(directory)
    n = 0
    try:
        entries = list(d.iterdir())
    except OSError:
        return 0
    for p in entries:
        if p.name.startswith(JOURNAL_PREFIX) and p.name.endswith(".json"):
            pid = _owner_pid(p.name, JOURNAL_PREFIX)
            if pid is None or _pid_alive(pid):
                continue
            import json  # here, not at the top: `psdcal --help` imports this module

            try:
                pairs = json.loads(p.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                pairs = []
            for tmp, target in pairs if isinstance(pairs, list) else []:
                with contextlib.suppress(OSError):
                    if os.path.exists(tmp):
                        os.replace(tmp, target)
                        n += 1
            with contextlib.suppress(OSError):
                p.unlink()
    for p in entries:
        if p.name.startswith(TMP_PREFIX):
            pid = _owner_pid(p.name, TMP_PREFIX)
            if pid is None or _pid_alive(pid):
                continue
            with contextlib.suppress(OSError):
                p.unlink()
                n += 1
    return n


class _OutputSet:
    """Temporaries staged by one command, renamed together by :func:`output_set`."""

    def __init__(self):
        self.pairs: list[tuple[Path, Path]] = []

    def commit(self) -> None:
        if not self.pairs:
            return
        journal = None
        if len(self.pairs) > 1:
            import json

            first = self.pairs[0][1].parent
            body = json.dumps([[str(t.resolve()), str(p.resolve())] for t, p in self.pairs])
            fd, jt = _create_private(first, f"{TMP_PREFIX}{os.getpid()}-journal.", ".json")
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                fh.write(body)
                fh.flush()
                os.fsync(fh.fileno())
            journal = first / (f"{JOURNAL_PREFIX}{os.getpid()}-" + Path(jt).name[len(TMP_PREFIX):])
            os.replace(jt, journal)
        for tmp, path in self.pairs:
            os.replace(tmp, path)
        if journal is not None:
            journal.unlink()
        self.pairs.clear()

    def discard(self) -> None:
        for tmp, _ in self.pairs:
            with contextlib.suppress(OSError):
                tmp.unlink()
        self.pairs.clear()


@contextlib.contextmanager
def output_set():
    """Group every :func:`atomic_path` write made in the body into one all-or-nothing set.

    Nested use joins the outer set. On an exception every staged temporary
    is removed and no target changes.
    """
    if _CURRENT_SET.get() is not None:
        yield _CURRENT_SET.get()
        return
    s = _OutputSet()
    token = _CURRENT_SET.set(s)
    try:
        yield s
    except BaseException:
        s.discard()
        raise
    else:
        try:
            s.commit()
        except BaseException:
            s.discard()
            raise
    finally:
        _CURRENT_SET.reset(token)


def _mkstemp_beside(path: Path, suffix: str | None):
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _create_private(path.parent, f"{TMP_PREFIX}{os.getpid()}-{path.name[:80]}.",
                              suffix or path.suffix or ".tmp")
    os.close(fd)
    return tmp


#: Flags of :func:`_create_private`: a new file only (never an existing one or a link's target), not inherited.
_CREATE_FLAGS = os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0) \
    | getattr(os, "O_BINARY", 0) | getattr(os, "O_NOINHERIT", 0)


def _create_private(folder, prefix: str, suffix: str) -> tuple[int, Path]:
    """Create a new empty file ``folder/prefix<random>suffix`` readable by its owner only (0600), as
    ``tempfile.mkstemp`` does (without loading tempfile, random and shutil: some 5 ms of a short command):
    ``(open file descriptor, absolute path)``."""
    for _ in range(10000):
        tmp = os.path.abspath(os.path.join(folder, f"{prefix}{os.urandom(6).hex()}{suffix}"))
        try:
            fd = os.open(tmp, _CREATE_FLAGS, 0o600)
        except FileExistsError:
            continue  # (1 in 2^48) another file has that name
        return fd, Path(tmp)
    raise FileExistsError(errno.EEXIST, "no usable temporary file name found", str(folder))


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None):
    """Yield a temporary path beside ``path``; move it over ``path`` only on success.

    If the body raises, the temporary file is removed and ``path`` is untouched.
    Inside :func:`output_set` the rename waits until the whole set succeeded.
    """
    path = Path(path)
    tmp = _mkstemp_beside(path, suffix)
    # mkstemp makes the file private (0600): give it the mode an ordinary
    # open() would (the existing file's, or 0666 less the umask)
    try:
        mode = path.stat().st_mode & 0o7777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    os.chmod(tmp, mode)
    s = _CURRENT_SET.get()
    try:
        yield tmp
        if s is not None:
            s.pairs.append((tmp, path))
            tmp = None
        else:
            os.replace(tmp, path)
    finally:
        if tmp is not None and tmp.exists():
            tmp.unlink()


def write_text_atomic(path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def _same(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.abspath(os.path.realpath(a)) == os.path.abspath(os.path.realpath(b))


def guard_outputs(inputs, outputs, force: bool = False, *, suffixes=None, dirs=(), merge=()) -> None:
    """Check the outputs of a command before it does any work (the output policy).

    Parameters
    ----------
    inputs : iterable of (option, path)
        The files the command reads (``None`` paths are skipped).
    outputs : iterable of (option, path)
        The files it will write (``None`` skipped).
    force : bool
        Replace existing outputs (``--force``).
    suffixes : dict option -> tuple of str, optional
        Allowed extensions (lower case, with the dot) of an output.
    dirs : iterable of (option, path)
        Output folders (created if missing; must not be a file).
    merge : iterable of str
        Options whose file is updated in place (may exist without ``--force``).

    Raises
    ------
    psdcal.errors.InputError
        One line naming the option and the file.
    """
    from psdcal.errors import InputError

    ins = [(o, Path(p)) for o, p in inputs if p is not None and str(p) != "-"]
    outs = [(o, Path(p)) for o, p in outputs if p is not None and str(p) != "-"]
    for opt, d in dirs:
        if d is None:
            continue
        d = Path(d)
        if d.exists() and not d.is_dir():
            raise InputError("is a file, expected a folder", path=d, field=opt)
        for anc in d.parents:
            if anc.exists():
                if not anc.is_dir():
                    raise InputError(f"{anc} is a file, cannot create the folder", path=d, field=opt)
                if not d.exists() and not os.access(anc, os.W_OK | os.X_OK):
                    raise InputError(f"cannot create the folder: {anc} is not writable", path=d, field=opt)
                break
        if d.exists() and not os.access(d, os.W_OK | os.X_OK):
            raise InputError("folder not writable (permission or read-only file system)", path=d, field=opt)
        recover(d)
    seen = {}
    for opt, p in outs:
        for iopt, q in ins:
            if _same(p, q):
                raise InputError(f"would overwrite the input given as {iopt}; choose another output", path=p, field=opt)
        key = os.path.abspath(os.path.realpath(p))
        if key in seen:
            raise InputError(f"the same file is also given as {seen[key]}", path=p, field=opt)
        seen[key] = opt
        if suffixes and opt in suffixes and p.suffix.lower() not in suffixes[opt]:
            raise InputError(f"unsupported extension {p.suffix or '(none)'!r}; use {', '.join(suffixes[opt])}",
                             path=p, field=opt)
        if p.is_dir():
            raise InputError("is a folder, expected a file", path=p, field=opt)
        parent = p.parent
        for anc in (parent, *parent.parents):
            if anc.exists():
                if not anc.is_dir():
                    raise InputError(f"{anc} is a file, not a folder", path=p, field=opt)
                break
        if parent.exists() and not os.access(parent, os.W_OK | os.X_OK):
            raise InputError("folder not writable (permission or read-only file system)", path=p, field=opt)
        if p.exists() and not force and opt not in merge:
            raise InputError("exists; give --force to replace it", path=p, field=opt)
        if parent.exists():
            recover(parent)


def guard_set_in_dir(opt: str, out_dir, names, inputs=(), force: bool = False) -> None:
    """:func:`guard_outputs` for a command that writes the files ``names`` into the folder ``out_dir``."""
    out_dir = Path(out_dir)
    guard_outputs(inputs, [(opt, out_dir / n) for n in names], force, dirs=[(opt, out_dir)])


def staged(path) -> Path:
    """The file to read for ``path`` now: its staged temporary inside :func:`output_set`, else ``path``.

    A command that reads back an output it wrote earlier (``locate --track``) reads it here.
    """
    s = _CURRENT_SET.get()
    path = Path(path)
    if s is not None:
        for tmp, target in reversed(s.pairs):
            if target == path:
                return tmp
    return path


@contextlib.contextmanager
def immediate():
    """Write at once (outside any :func:`output_set`): for scratch files a command reads back itself."""
    token = _CURRENT_SET.set(None)
    try:
        yield
    finally:
        _CURRENT_SET.reset(token)
