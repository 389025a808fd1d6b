"""pso-robust on many pairs: the rigidity graph on a subset keeps the answer and the accuracy."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.registration.registry import register
from estimator.rendered.simulation import rotation_error_deg, simulate_pair, translation_error


def test_large_problems_build_the_graph_on_a_subset_and_stay_accurate() -> None:
    pair = simulate_pair(3000, 0.02, 0.5, rng=11)
    assert len(pair.source) > 1500  # well above the 512 pairs of the graph
    result = register(pair.source, pair.target, seed=3)
    assert result.success, result.message
    assert rotation_error_deg(result.rotation, pair.rotation) < 0.1
    assert translation_error(result.translation, pair.translation) < 0.01
    found = np.count_nonzero(result.inliers & pair.inlier_mask)
    assert found / np.count_nonzero(pair.inlier_mask) > 0.95
    assert found / result.support > 0.97


def test_a_graph_smaller_than_the_core_search_is_rejected() -> None:
    pair = simulate_pair(100, 0.02, 0.0, rng=1)
    with pytest.raises(ValueError, match="graph_pairs"):
        register(pair.source, pair.target, graph_pairs=16)
