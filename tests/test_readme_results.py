"""The README's result tables are the ones the benchmarks last wrote, not numbers typed by hand."""

from __future__ import annotations

from pathlib import Path

import pytest

from estimator.bench.readme import markers, read_block, write_block

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"

# README block name -> the table file its benchmark writes
BLOCKS = {
    "driving": RESULTS / "driving" / "driving.md",
    "odometry": RESULTS / "odometry" / "odometry.md",
    "perturbations": RESULTS / "perturbations" / "perturbations.md",
}


@pytest.mark.parametrize("name", sorted(BLOCKS))
def test_readme_block_equals_the_result_file(name):
    assert read_block(ROOT / "README.md", name) == BLOCKS[name].read_text().strip()


def test_write_block_replaces_only_the_block(tmp_path):
    begin, end = markers("demo")
    path = tmp_path / "README.md"
    path.write_text(f"intro\n{begin}\nold\n{end}\noutro\n")
    write_block(path, "demo", "| a |\n")
    assert read_block(path, "demo") == "| a |"
    assert path.read_text().startswith("intro\n") and path.read_text().endswith(end + "\noutro\n")
    with pytest.raises(ValueError, match="no"):
        write_block(path, "other", "x")
