"""Follow a text file as another process writes it (``tail -F``), standard library only.

:class:`FileFollower` returns the complete lines added since the last call;
a last line without its newline waits for the rest. It notices when the file
is truncated (its size drops below what was read) or replaced (a new inode at
the same path, as ``mv new old`` or an atomic rewrite does): it then starts
again from the top of the new content and says so (``reset``), so that the
reader re-reads a CSV header. A file that does not exist yet is simply empty.

Each call is one ``stat`` and, only when the size or the inode changed, one
read of the new bytes: the cost does not depend on how many pages watch.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

#: At most this many bytes are read per call (a huge backlog is consumed over several calls).
MAX_READ = 8 << 20


@dataclass(frozen=True)
class Chunk:
    """What one :meth:`FileFollower.poll` found.

    Attributes
    ----------
    lines : tuple of str
        Complete new lines, without their line ends.
    reset : bool
        The file was truncated or replaced since the last call: ``lines``
        start at its top (a CSV header comes again).
    """

    lines: tuple = ()
    reset: bool = False


class FileFollower:
    """The complete lines appended to ``path`` since the previous :meth:`poll`."""

    def __init__(self, path):
        self.path = Path(path)
        self._ident = None  # (st_dev, st_ino) of the file being read
        self._offset = 0
        self._partial = b""
        self._size_seen = -1

    def poll(self) -> Chunk:
        """Read what was added; see :class:`Chunk`."""
        try:
            st = os.stat(self.path)
        except OSError:
            return Chunk()
        ident = (st.st_dev, st.st_ino)
        reset = False
        if self._ident is not None and (ident != self._ident or st.st_size < self._offset):
            reset = True  # replaced (new inode) or truncated: start over
            self._offset, self._partial = 0, b""
        if ident == self._ident and st.st_size == self._size_seen and not reset:
            return Chunk()
        self._ident = ident
        try:
            with open(self.path, "rb") as fh:
                if (os.fstat(fh.fileno()).st_dev, os.fstat(fh.fileno()).st_ino) != ident:
                    return Chunk(reset=reset)  # replaced between stat and open: next call
                fh.seek(self._offset)
                data = fh.read(MAX_READ)
        except OSError:
            return Chunk(reset=reset)
        self._offset += len(data)
        self._size_seen = st.st_size if len(data) < MAX_READ else -1
        data = self._partial + data
        cut = data.rfind(b"\n")
        if cut < 0:
            self._partial = data
            return Chunk(reset=reset)
        self._partial = data[cut + 1:]
        lines = data[:cut].split(b"\n")
        return Chunk(tuple(line.rstrip(b"\r").decode("utf-8", errors="replace") for line in lines), reset)
