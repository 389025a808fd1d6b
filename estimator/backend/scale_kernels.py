"""Compiled inner loop of the covariance-scale bisection (``covariance_scale.py``).

The bisection evaluates the median (session factor) or the mean (time-local factor) of
q_n(s) = sum_k f_nk^2 / (s lambda_nk + 1) over up to 400 decomposed samples about 40 times a
frame; in NumPy each evaluation is half a dozen array passes and temporaries, which made the
calibration the back end's largest Python cost. One compiled pass gives the same numbers to
the last bit: the three terms are added left to right (what NumPy's ``sum(axis=1)`` does
for three columns), the mean uses NumPy's pairwise summation, and the median picks the same
order statistics (``tests/test_scale_kernels.py`` compares both on random samples). The
scale ``s`` itself is computed by the caller with NumPy's ``exp``, whose last bit differs
from the compiled one's.
"""

from __future__ import annotations

import numpy as np

from estimator.compiled import kernel

__all__ = ["spectra_statistic"]

_BLOCK = 128  # NumPy's pairwise-summation block (PW_BLOCKSIZE)


@kernel()
def _block_sum(values: np.ndarray, start: int, count: int) -> float:
    """NumPy's pairwise sum of at most ``_BLOCK`` values: eight running sums, then the rest."""
    if count < 8:
        total = 0.0
        for i in range(count):
            total += values[start + i]
        return total
    partial = np.empty(8)
    for j in range(8):
        partial[j] = values[start + j]
    i = 8
    while i < count - count % 8:
        for j in range(8):
            partial[j] += values[start + i + j]
        i += 8
    total = ((partial[0] + partial[1]) + (partial[2] + partial[3])) + (
        (partial[4] + partial[5]) + (partial[6] + partial[7])
    )
    while i < count:
        total += values[start + i]
        i += 1
    return total


@kernel()
def _split(count: int) -> int:
    half = count // 2
    return half - half % 8


@kernel()
def _pairwise_sum(values: np.ndarray) -> float:
    """Sum in NumPy's pairwise order (``np.add.reduce``): blocks of ``_BLOCK`` halved
    recursively, here with an explicit stack (a cached recursive function crashes Numba)."""
    starts = np.zeros(64, dtype=np.int64)
    counts = np.zeros(64, dtype=np.int64)
    right_pending = np.zeros(64, dtype=np.bool_)  # the left half is summed, in ``lefts``
    lefts = np.zeros(64)
    top, counts[0] = 0, values.shape[0]
    while True:
        if counts[top] > _BLOCK:  # descend into the left half
            right_pending[top] = False
            starts[top + 1], counts[top + 1] = starts[top], _split(counts[top])
            top += 1
            continue
        value = _block_sum(values, starts[top], counts[top])
        while True:  # hand the finished sum up until a right half remains to be summed
            top -= 1
            if top < 0:
                return value
            if not right_pending[top]:
                lefts[top], right_pending[top] = value, True
                half = _split(counts[top])
                starts[top + 1], counts[top + 1] = starts[top] + half, counts[top] - half
                top += 1
                break
            value = lefts[top] + value


@kernel()
def _median(values: np.ndarray) -> float:
    """``np.median`` of a 1-D array, NaN when one value is NaN."""
    count = values.shape[0]
    if count == 0:
        return np.nan
    for value in values:
        if np.isnan(value):
            return np.nan
    half = count // 2
    ordered = np.partition(values, half)
    if count % 2:
        return ordered[half]
    return (np.max(ordered[:half]) + ordered[half]) / 2.0


@kernel("float64[:, ::1], float64[:, ::1], float64, bool")
def spectra_statistic(
    eigenvalues: np.ndarray, weights: np.ndarray, scale: float, median: bool
) -> float:
    """Median (``median``) or mean of q_n(scale) over the samples, (N, 3) arrays each."""
    count = eigenvalues.shape[0]
    q = np.empty(count)
    for n in range(count):
        q[n] = (
            weights[n, 0] / (scale * eigenvalues[n, 0] + 1.0)
            + weights[n, 1] / (scale * eigenvalues[n, 1] + 1.0)
        ) + weights[n, 2] / (scale * eigenvalues[n, 2] + 1.0)
    if median:
        return _median(q)
    if count == 0:
        return np.nan
    return _pairwise_sum(q) / count
