"""benchmarks/frontend_profile.py: per-frame rows of a CPU profile, and its argument checks."""

from __future__ import annotations

import cProfile
import pstats
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import frontend_profile


def _busy(seconds: float) -> None:
    end = time.process_time() + seconds
    while time.process_time() < end:
        pass


def _light() -> int:
    return sum(range(100))


def test_rows_are_per_frame_and_ordered_by_own_time() -> None:
    profiler = cProfile.Profile(time.process_time)
    profiler.enable()
    for _ in range(6):
        _busy(0.01)
        _light()
    profiler.disable()
    rows = frontend_profile.profile_rows(pstats.Stats(profiler), frames=3, top=50)
    by_name = {row["function"].split(" ")[0]: row for row in rows}
    assert by_name["_busy"]["calls_per_frame"] == pytest.approx(2.0)
    assert by_name["_light"]["calls_per_frame"] == pytest.approx(2.0)
    # Two 10 ms busy loops per frame: at least 20 ms of CPU per frame, cumulative.
    assert by_name["_busy"]["cumulative_ms_per_frame"] >= 19.0
    own = [row["own_ms_per_frame"] for row in rows]
    assert own == sorted(own, reverse=True)
    assert len(frontend_profile.profile_rows(pstats.Stats(profiler), frames=3, top=2)) == 2
    table = frontend_profile.markdown(rows[:2], "title")
    assert table.count("\n| `") == 2
    with pytest.raises(ValueError):
        frontend_profile.profile_rows(pstats.Stats(profiler), frames=0, top=5)


def test_bad_arguments_give_a_one_line_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert frontend_profile.main(["--top", "0"]) == 2
    assert frontend_profile.main(["--data", "/nonexistent/clip", "--frames", "5"]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 2 and all(line.startswith("error: ") for line in errors)


def test_rows_can_be_ordered_by_cumulative_time() -> None:
    profiler = cProfile.Profile(time.process_time)
    profiler.enable()
    for _ in range(2):
        _busy(0.005)
    profiler.disable()
    rows = frontend_profile.profile_rows(pstats.Stats(profiler), 2, 50, sort="cumulative")
    cumulative = [row["cumulative_ms_per_frame"] for row in rows]
    assert cumulative == sorted(cumulative, reverse=True)
    with pytest.raises(ValueError, match="sort"):
        frontend_profile.profile_rows(pstats.Stats(profiler), 2, 5, sort="calls")
