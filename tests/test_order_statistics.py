"""The medians of ``order_statistics`` are ``np.median``'s, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.order_statistics import column_medians, median, quantile


@pytest.mark.parametrize("count", [1, 2, 3, 4, 7, 8, 100, 101, 399, 400])
def test_median_equals_numpy_bit_for_bit(count: int) -> None:
    rng = np.random.default_rng(count)
    for values in (
        rng.normal(size=count),
        rng.chisquare(3, size=count),
        np.round(rng.normal(size=count), 1),  # ties
        rng.normal(size=count) * 1e-300,
    ):
        expected = np.median(values)
        assert median(values) == expected


@pytest.mark.parametrize("count", [1, 2, 5, 6, 99, 100])
def test_column_medians_equal_numpy_bit_for_bit(count: int) -> None:
    rng = np.random.default_rng(100 + count)
    values = np.abs(rng.normal(size=(count, 3))) * [1.0, 0.5, 3.0]
    np.testing.assert_array_equal(column_medians(values), np.median(values, axis=0))


def test_nan_and_empty_follow_numpy() -> None:
    values = np.array([1.0, np.nan, 3.0, 2.0])
    assert np.isnan(median(values)) and np.isnan(np.median(values))
    columns = np.array([[1.0, 2.0], [np.nan, 3.0], [0.5, 1.0]])
    np.testing.assert_array_equal(column_medians(columns), np.median(columns, axis=0))
    assert np.isnan(median(np.array([])))


def test_the_input_is_left_as_it_was() -> None:
    values = np.array([5.0, 1.0, 4.0, 2.0, 3.0])
    kept = values.copy()
    median(values)
    column_medians(values[:, None])
    np.testing.assert_array_equal(values, kept)


def test_wrong_shapes_are_refused() -> None:
    with pytest.raises(ValueError, match="1-D"):
        median(np.ones((2, 2)))
    with pytest.raises(ValueError, match="non-empty"):
        column_medians(np.ones(3))
    with pytest.raises(ValueError, match="non-empty"):
        column_medians(np.ones((0, 3)))


@pytest.mark.parametrize("count", [1, 2, 3, 10, 99, 100, 101, 400, 1001])
def test_quantile_equals_numpy_bit_for_bit(count: int) -> None:
    rng = np.random.default_rng(200 + count)
    for values in (rng.chisquare(3, size=count), np.round(rng.normal(size=count), 1)):
        for q in (0.0, 0.1, 0.5, 0.9, 0.95, 0.999, 1.0):
            assert quantile(values, q) == np.quantile(values, q)
    columns = np.abs(rng.normal(size=(count, 3)))
    for q in (0.5, 0.9, 0.999):
        np.testing.assert_array_equal(quantile(columns, q), np.quantile(columns, q, axis=0))


def test_quantile_nan_and_bad_arguments() -> None:
    values = np.array([1.0, np.nan, 3.0, 2.0])
    assert np.isnan(quantile(values, 0.9)) and np.isnan(np.quantile(values, 0.9))
    columns = np.array([[1.0, 2.0], [np.nan, 3.0], [0.5, 1.0]])
    np.testing.assert_array_equal(quantile(columns, 0.9), np.quantile(columns, 0.9, axis=0))
    for bad in ((np.array([]), 0.5), (np.ones(3), 1.5), (np.ones((2, 2, 2)), 0.5)):
        with pytest.raises(ValueError, match="quantile expects"):
            quantile(*bad)
