"""The compiled covariance-scale statistic gives NumPy's numbers to the last bit
(estimator.backend.scale_kernels)."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.backend.covariance_scale import _median, solve_factor_spectra
from estimator.backend.scale_kernels import spectra_statistic


def _samples(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues and weights spread over six decades, as whitened covariances give."""
    spread = 10 ** rng.uniform(-3, 3, (count, 1))
    return rng.exponential(1, (count, 3)) * spread, rng.exponential(1, (count, 3)) * spread


@pytest.mark.parametrize("count", [1, 2, 3, 7, 8, 9, 10, 17, 128, 129, 255, 400, 1031])
def test_the_compiled_median_and_mean_are_numpys(count: int) -> None:
    """Every block size of NumPy's pairwise sum (below 8, up to 128, halved above)."""
    rng = np.random.default_rng(count)
    for _ in range(20):
        eigenvalues, weights = _samples(rng, count)
        scale = float(np.exp(rng.uniform(-2.8, 2.8)))
        q = (weights / (scale * eigenvalues + 1.0)).sum(axis=1)
        assert spectra_statistic(eigenvalues, weights, scale, True) == _median(q)
        assert spectra_statistic(eigenvalues, weights, scale, False) == float(np.mean(q))


def test_a_nan_sample_makes_the_median_nan() -> None:
    eigenvalues, weights = _samples(np.random.default_rng(3), 9)
    weights[4, 1] = np.nan
    assert np.isnan(spectra_statistic(eigenvalues, weights, 1.0, True))


@pytest.mark.parametrize("statistic", [_median, np.mean])
def test_the_compiled_bisection_finds_numpys_factor(statistic) -> None:
    """Same factor, bit for bit, as the bisection over the NumPy statistic (a wrapper that the
    compiled path does not recognise)."""
    rng = np.random.default_rng(5)
    for count in (10, 400):
        eigenvalues, weights = _samples(rng, count)
        weights *= 3.0 / np.median(weights.sum(axis=1) / (eigenvalues.mean(axis=1) + 1.0))
        bounds = (1 / 16, 16.0)
        compiled = solve_factor_spectra(statistic, 2.5, (eigenvalues, weights), bounds)
        reference = solve_factor_spectra(
            lambda q: statistic(q), 2.5, (eigenvalues, weights), bounds
        )
        assert compiled == reference
        assert bounds[0] < compiled < bounds[1]  # a solved factor, not a bound
