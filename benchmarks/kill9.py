"""kill -9 campaign over psdcal's writing commands (the output policy, docs/guide/files-and-errors.md).

Runs N kills (default 60) at random moments of `simulate`, `simulate --amplitudes`,
`errormap -o --csv`, `compare -o --json` and `aoa`, over earlier outputs and
into empty folders, and prints how each set ended: all old (A), all new (B),
all absent, or MIXED (a failure; the script then stops with an assertion).

    python benchmarks/kill9.py [N]
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.fuzz.killrun import run_kills  # noqa: E402


def main(n: int = 60) -> None:
    with tempfile.TemporaryDirectory() as d:
        out = run_kills(Path(d), n, seed=11)
    print(f"{n} kills; outcome per (scenario, start, final state):")
    for key, count in sorted(out.items()):
        print(f"  {key[0]:20s} {key[1]:7s} {key[2]:7s} {count}")
    print("no mixed set, no temporary left after recovery")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 60)
