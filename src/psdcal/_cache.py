"""A computed attribute of an immutable object, computed once.

:class:`cached_attribute` is ``functools.cached_property`` without the lock
that Python 3.11 takes on each first access (a few microseconds, which
counts when a five-view calibration takes half a millisecond). The value is
stored in the instance's ``__dict__`` (so it works on frozen dataclasses);
two threads reading it first at once may both compute it, which is harmless
for the pure functions it is used with.
"""
from __future__ import annotations


class cached_attribute:  # noqa: N801 (used like ``property``)
    """Decorator: ``obj.name`` is ``fn(obj)``, computed on first access and then kept."""

    def __init__(self, fn):
        self.fn = fn
        self.name = fn.__name__
        self.__doc__ = fn.__doc__

    def __set_name__(self, owner, name):
        self.name = name

    def __get__(self, obj, owner=None):
        if obj is None:
            return self
        value = self.fn(obj)
        obj.__dict__[self.name] = value
        return value
