"""A JSON-lines log of the warnings a command prints (``psdcal --events FILE`` or ``PSDCAL_EVENTS=FILE``).

Commands print their warnings in several ways (``click.echo("warning: ...")``
on stdout or stderr, ``print`` in the live readers, rich's console in the
calibration table). Rather than change each, the command line wraps
``sys.stdout`` and ``sys.stderr`` while a command runs: every complete line
that contains ``warning:`` is also appended to the log as one JSON object::

    {"time": "2026-01-02T03:04:05.678901+00:00", "t_unix": 1767323045.678901,
     "command": "locate", "pid": 1234, "stream": "stderr", "level": "warning",
     "text": "the text after 'warning:'"}

The lines printed are unchanged. Each object is one ``write`` to a file opened
in append mode, so several commands may share one log (``psdcal dashboard
--events FILE`` follows it). Standard library only; the dashboard reads the format, it does not import this module.
"""
from __future__ import annotations

import json
import os
import re
import sys
import time
from contextlib import contextmanager
from datetime import datetime, timezone

#: A printed line that is a warning: the text after ``warning:`` is logged.
WARNING_RE = re.compile(r"\bwarning:\s*(.*)", re.IGNORECASE)
_ANSI_RE = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
#: The environment variable naming the log (the option ``psdcal --events`` wins).
ENV = "PSDCAL_EVENTS"


def event(text: str, *, command: str, stream: str = "", level: str = "warning", now: float | None = None) -> dict:
    """The JSON object of one logged line (see the module docstring)."""
    t = time.time() if now is None else float(now)
    return {"time": datetime.fromtimestamp(t, timezone.utc).isoformat(), "t_unix": t, "command": command,
            "pid": os.getpid(), "stream": stream, "level": level, "text": text}


def append_event(path, obj: dict) -> None:
    """Append one object as one line (one ``write`` in append mode, so concurrent writers do not interleave)."""
    fd = os.open(os.fspath(path), os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, (json.dumps(obj, ensure_ascii=False) + "\n").encode("utf-8"))
    finally:
        os.close(fd)


class _Tee:
    """A text stream that passes everything on and logs the complete lines that are warnings."""

    def __init__(self, stream, path, command: str, name: str):
        self._stream, self._path, self._command, self._name = stream, path, command, name
        self._partial = ""

    def write(self, s):
        n = self._stream.write(s)
        if isinstance(s, str) and s:
            text = self._partial + s
            *lines, self._partial = text.split("\n")
            for line in lines:
                self._log(line)
        return n

    def _log(self, line: str) -> None:
        m = WARNING_RE.search(_ANSI_RE.sub("", line))
        if m and m.group(1).strip():
            try:
                append_event(self._path, event(m.group(1).strip(), command=self._command, stream=self._name))
            except OSError:  # the log is a side channel: never fail the command for it
                pass

    def flush_partial(self) -> None:
        if self._partial:
            self._log(self._partial)
            self._partial = ""

    def flush(self):
        return self._stream.flush()

    def __getattr__(self, name):  # isatty, encoding, fileno, buffer...: those of the wrapped stream
        return getattr(self._stream, name)


@contextmanager
def logging_warnings(path, command: str):
    """While the block runs, warning lines printed on stdout/stderr are also appended to ``path``."""
    old = sys.stdout, sys.stderr
    tees = _Tee(sys.stdout, path, command, "stdout"), _Tee(sys.stderr, path, command, "stderr")
    sys.stdout, sys.stderr = tees
    try:
        yield
    finally:
        for t in tees:
            t.flush_partial()
        # restore only what we replaced (a block may have swapped the streams again)
        if sys.stdout is tees[0]:
            sys.stdout = old[0]
        if sys.stderr is tees[1]:
            sys.stderr = old[1]
