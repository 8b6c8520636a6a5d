"""Resource guards: refuse, before allocating, what would not fit in memory.

A command that would allocate more than :func:`budget_bytes` (half the
memory available now, or ``PSDCAL_MAX_BYTES`` from the environment) stops
with one line naming the option that asked for it.
"""
from __future__ import annotations

import os


def available_bytes() -> int:
    """Memory available now (Linux ``MemAvailable``; else the physical memory), bytes."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 8 << 30


def budget_bytes() -> int:
    """The most one command may allocate: ``PSDCAL_MAX_BYTES`` or half the available memory."""
    env = os.environ.get("PSDCAL_MAX_BYTES")
    if env:
        try:
            return int(float(env))
        except ValueError:
            pass
    return available_bytes() // 2


def _fmt(n: float) -> str:
    for unit, k in (("GiB", 30), ("MiB", 20), ("kiB", 10)):
        if n >= 1 << k:
            return f"{n / (1 << k):.3g} {unit}"
    return f"{n:.0f} B"


def check_bytes(n_bytes: float, what: str, option: str | None = None) -> None:
    """InputError when ``n_bytes`` exceed :func:`budget_bytes` (a message naming ``option``)."""
    from psdcal.errors import InputError

    budget = budget_bytes()
    if not n_bytes <= budget:
        raise InputError(f"{what} needs about {_fmt(n_bytes)}, more than the {_fmt(budget)} this machine can give "
                         "(PSDCAL_MAX_BYTES sets the limit); choose a smaller value", field=option)
