"""Run the psdcal CLI and SIGKILL itself at one chosen write event (the deterministic kill -9 test).

Usage: ``python killhook.py ARGV...`` with the environment

- ``PSDCAL_KILL_LOG``: a file where every event is appended as ``k kind name``;
- ``PSDCAL_KILL_AT``: the event number at which the process kills itself
  (``-1`` or absent: never, a dry run that lists the events).

Events: ``written`` when an output's body has been written (an
:func:`psdcal._atomic.atomic_path` block left: the file is staged, or, for
a writer that writes in place, already changed), and ``rename`` just before
an ``os.replace`` of a psdcal temporary (a journal or an output). Killing at
each of them in turn puts a kill in every window between the staged writes
and the renames, which random kill times rarely hit.
"""
from __future__ import annotations

import contextlib
import os
import signal
import sys

import psdcal._atomic as _atomic

_LOG = os.environ.get("PSDCAL_KILL_LOG")
_AT = int(os.environ.get("PSDCAL_KILL_AT", "-1"))
_count = [0]


def _event(kind: str, name: str) -> None:
    k = _count[0]
    _count[0] += 1
    if _LOG:
        with open(_LOG, "a", encoding="utf-8") as fh:
            fh.write(f"{k} {kind} {name}\n")
    if k == _AT:
        os.kill(os.getpid(), signal.SIGKILL)


_real_atomic_path = _atomic.atomic_path


@contextlib.contextmanager
def _atomic_path(path, suffix=None):
    with _real_atomic_path(path, suffix) as tmp:
        yield tmp
    _event("written", os.path.basename(str(path)))


_real_replace = os.replace


def _replace(src, dst, *args, **kwargs):
    if os.path.basename(os.fspath(src)).startswith(_atomic.TMP_PREFIX):
        name = os.path.basename(os.fspath(dst))
        _event("rename", "(journal)" if name.startswith(_atomic.JOURNAL_PREFIX) else name)  # its name has the pid
    return _real_replace(src, dst, *args, **kwargs)


# before psdcal.cli is imported, so that every `from psdcal._atomic import atomic_path` binds the hooked one
_atomic.atomic_path = _atomic_path
os.replace = _replace

if __name__ == "__main__":
    from psdcal.cli import main

    sys.exit(main(sys.argv[1:]))
