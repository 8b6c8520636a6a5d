"""Printing of the benchmarks' result tables (plain or Markdown)."""
from __future__ import annotations


def print_table(head, lines, markdown: bool = False) -> None:
    """Print rows of strings under a header, as a Markdown table or right-aligned columns."""
    if markdown:
        print("| " + " | ".join(head) + " |")
        print("|" + "|".join("---" for _ in head) + "|")
        for line in lines:
            print("| " + " | ".join(line) + " |")
        return
    w = [max(len(h), *(len(line[k]) for line in lines)) for k, h in enumerate(head)]
    print("  ".join(h.rjust(w[k]) for k, h in enumerate(head)))
    for line in lines:
        print("  ".join(v.rjust(w[k]) for k, v in enumerate(line)))
