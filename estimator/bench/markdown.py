"""Markdown tables of the benchmarks' printed and stored reports."""

from __future__ import annotations

__all__ = ["titled_table"]


def titled_table(title: str, header: list[str], rows: list[list[str]]) -> str:
    """A markdown table under a ``### title`` heading."""
    lines = [f"### {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"
