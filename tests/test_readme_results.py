"""The README's result tables and docs/results.md are the ones `swarmvo bench report` makes from
the benchmark result files, not numbers typed by hand."""

from __future__ import annotations

from pathlib import Path

import pytest

from estimator.bench import report
from estimator.bench.readme import markers, read_block, write_block

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", sorted(report.AREAS))
def test_readme_summary_equals_the_result_files(name):
    assert read_block(ROOT / "README.md", name) == report.summaries()[name].strip()


def test_a_changed_result_file_makes_the_readme_stale(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    for source in report.RESULTS.rglob("*"):
        if source.is_file() and source.suffix in {".json", ".md"}:
            target = results / source.relative_to(report.RESULTS)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(source.read_bytes())
    readme, docs = tmp_path / "README.md", tmp_path / "results.md"
    readme.write_text((ROOT / "README.md").read_text())
    docs.write_text(report.full_results(results))
    assert report.stale(readme, docs, results) == []
    odometry = results / "odometry" / "odometry.json"
    odometry.write_text(odometry.read_text().replace('"ate_rmse_m": 0.00', '"ate_rmse_m": 0.09', 1))
    assert "README.md: real" in report.stale(readme, docs, results)
    assert "results.md" in report.stale(readme, docs, results)


def test_write_block_replaces_only_the_block(tmp_path):
    begin, end = markers("demo")
    path = tmp_path / "README.md"
    path.write_text(f"intro\n{begin}\nold\n{end}\noutro\n")
    write_block(path, "demo", "| a |\n")
    assert read_block(path, "demo") == "| a |"
    assert path.read_text().startswith("intro\n") and path.read_text().endswith(end + "\noutro\n")
    with pytest.raises(ValueError, match="no"):
        write_block(path, "other", "x")


def test_docs_results_equal_the_result_files():
    """``docs/results.md`` is what ``swarmvo bench report`` makes of the result files now."""
    from estimator.bench import report

    assert (ROOT / "docs" / "results.md").read_text() == report.full_results(report.RESULTS), (
        "docs/results.md is stale: run `swarmvo bench report --docs-only`"
    )


def test_docs_results_follow_a_changed_result_file(tmp_path):
    """Changing one result number changes the generated text, so a stale file cannot pass."""
    import shutil

    from estimator.bench import report

    copy = tmp_path / "results"
    skip = shutil.ignore_patterns("*.png", "seed*", "rendered*")
    shutil.copytree(report.RESULTS, copy, ignore=skip)
    before = report.full_results(copy)
    table = copy / "frontend" / "frontend.md"
    table.write_text(table.read_text() + "\nchanged\n")
    assert report.full_results(copy) != before


def test_report_docs_only_and_missing_readme_blocks(tmp_path, capsys):
    """Without the README's summary blocks: one error line, nothing written; --docs-only writes
    the docs file alone and --check then finds it up to date."""
    import argparse

    from estimator.bench import report

    readme, docs = tmp_path / "README.md", tmp_path / "results.md"
    readme.write_text("# no blocks here\n")
    args = argparse.Namespace(
        results=report.RESULTS, readme=readme, docs=docs, check=False, docs_only=False
    )
    assert report.run(args) == 2
    assert "no '<!-- real-results" in capsys.readouterr().out and not docs.exists()
    args.docs_only = True
    assert report.run(args) == 0
    assert docs.read_text() == report.full_results(report.RESULTS)
    assert readme.read_text() == "# no blocks here\n"
    args.check = True
    assert report.run(args) == 0
    docs.write_text(docs.read_text() + "edited by hand\n")
    assert report.run(args) == 1
