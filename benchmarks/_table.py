"""Printing of the benchmarks' result tables (plain or Markdown)."""
from __future__ import annotations


def print_table(head, lines, markdown: bool = False, table_id: str | None = None) -> None:
    """Print rows of strings under a header, as a Markdown table or right-aligned columns.

    ``table_id`` (Markdown only) prints ``<!-- table: ID -->`` before the table: the name its
    generated region in the docs uses (``benchmarks/_docgen.py``; without it, the table's number).
    """
    if markdown:
        if table_id is not None:
            print(f"<!-- table: {table_id} -->")
        print("| " + " | ".join(head) + " |")
        print("|" + "|".join("---" for _ in head) + "|")
        for line in lines:
            print("| " + " | ".join(line) + " |")
        return
    w = [max(len(h), *(len(line[k]) for line in lines)) for k, h in enumerate(head)]
    print("  ".join(h.rjust(w[k]) for k, h in enumerate(head)))
    for line in lines:
        print("  ".join(v.rjust(w[k]) for k, v in enumerate(line)))


def print_skipped(table_id: str, reason: str, markdown: bool = False) -> None:
    """Say that table ``table_id`` was not made here (its data are absent): its region in the docs stays as it was."""
    if markdown:
        print(f"<!-- table: {table_id} skipped: {reason} -->")
    else:
        print(f"(table {table_id} skipped: {reason})")
