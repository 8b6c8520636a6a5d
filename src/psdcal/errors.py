"""Exceptions raised by psdcal.

Every error a user can cause derives from :class:`PsdcalError`; the CLI turns
it into one line on stderr and exit status 2.
"""
from __future__ import annotations


class PsdcalError(Exception):
    """Base class of all errors psdcal raises on purpose."""


class InputError(PsdcalError, ValueError):
    """Malformed input: names the file, the line (1-based, header = 1) and the field.

    Parameters
    ----------
    message : str
        What is wrong, in words a user can act on.
    path, line, field : optional
        Where it is wrong. Any of them may be None when it does not apply.
    """

    def __init__(self, message: str, *, path=None, line: int | None = None, field: str | None = None):
        self.path = None if path is None else str(path)
        self.line = line
        self.field = field
        self.detail = message
        where = []
        if self.path is not None:
            where.append(self.path if line is None else f"{self.path}:{line}")
        elif line is not None:
            where.append(f"line {line}")
        if field is not None:
            where.append(f"field '{field}'")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class DegenerateViewsError(PsdcalError, ValueError):
    """The views cannot determine the parameters (too few, collinear, coplanar...)."""


class ConvergenceError(PsdcalError, RuntimeError):
    """An iterative solver did not converge. ``result`` holds the last iterate when known."""

    def __init__(self, message: str, result=None):
        super().__init__(message)
        self.result = result


class ZeroSignalError(PsdcalError, ValueError):
    """The sum of the four PSD signals is (near) zero: no light, or a dead channel."""
