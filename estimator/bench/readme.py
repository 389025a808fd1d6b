"""Result tables written into the README between markers, so that its numbers are always the
ones a benchmark wrote (``tests/test_readme_results.py`` checks that they still are)."""

from __future__ import annotations

from pathlib import Path


def markers(name: str) -> tuple[str, str]:
    """The begin and end comment of the README block named ``name``."""
    return (
        f"<!-- {name}-results: begin (written by swarmvo bench report) -->",
        f"<!-- {name}-results: end -->",
    )


def read_block(path: Path, name: str) -> str:
    """The table inside the block ``name`` of ``path``, stripped."""
    text = Path(path).read_text()
    begin, end = markers(name)
    start, stop = text.find(begin), text.find(end)
    if start < 0 or stop < start:
        raise ValueError(f"{path} has no {begin!r} ... {end!r} block")
    return text[start + len(begin) : stop].strip()


def write_block(path: Path, name: str, table: str) -> None:
    """Replace the block ``name`` of ``path`` with ``table``."""
    read_block(path, name)  # refuses a file without the block
    text = Path(path).read_text()
    begin, end = markers(name)
    start, stop = text.find(begin), text.find(end)
    path.write_text(f"{text[:start]}{begin}\n\n{table.strip()}\n\n{text[stop:]}")
