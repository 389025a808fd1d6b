"""The README's Python example runs and gives the poses of ``run_sequence``."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from estimator.config import SwarmvoConfig
from estimator.formats.datasets import open_sequence
from estimator.pipeline import run_sequence

README = Path(__file__).resolve().parents[1] / "README.md"
FRAMES = 6


def _python_example() -> str:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.DOTALL)
    assert len(blocks) == 1, "the README has one Python example"
    return blocks[0]


@pytest.mark.slow
def test_the_readme_python_example_equals_run_sequence(euroc_v101_micro):
    code = _python_example()
    assert '"path/to/euroc_or_kitti"' in code and "range(len(sequence))" in code
    code = code.replace('"path/to/euroc_or_kitti"', repr(str(euroc_v101_micro)))
    code = code.replace("range(len(sequence))", f"range({FRAMES})")  # a short run
    namespace: dict = {}
    exec(compile(code, str(README), "exec"), namespace)
    odometry = namespace["odometry"]
    expected = run_sequence(open_sequence(euroc_v101_micro), SwarmvoConfig(), limit=FRAMES)
    assert len(namespace["smoothed"]) > 0 and namespace["report"].timestamp_ns == (
        expected.reports[-1].timestamp_ns
    )
    np.testing.assert_array_equal(namespace["report"].pose, expected.reports[-1].pose)
    assert odometry.config == expected.config  # the rig's derived settings, as run_sequence's
