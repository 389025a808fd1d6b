"""Medians and quantiles of small float arrays without NumPy's generic machinery.

The estimate stage takes a handful of medians per frame over a few hundred values (the noise
model's residual scales, the refinement's variance factor, the support gate's flow). At that
size ``np.median`` spends ~15-20 us in argument handling, axis bookkeeping and its NaN check
around a partition that costs 2-3 us (``np.quantile`` ~30 us). These do the same partition and
the same arithmetic, so the results are bit for bit NumPy's (NaN included; ``quantile`` is
its default, linear method), which the tests check.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["column_medians", "median", "quantile"]


def median(values: np.ndarray) -> float:
    """``float(np.median(values))`` of a 1-D float array; NaN when it is empty or holds a NaN."""
    values = np.asarray(values, dtype=float)
    if values.ndim != 1:
        raise ValueError(f"median expects a 1-D array, got shape {values.shape}")
    count = len(values)
    if count == 0:
        return float("nan")
    half = count // 2
    # As np.median: the middle order statistic(s), and the maximum last, where a NaN would sort.
    kth = (half, count - 1) if count % 2 else (half - 1, half, count - 1)
    part = np.partition(values, kth)
    if np.isnan(part[-1]):
        return float("nan")
    if count % 2:
        return float(part[half])
    return float((part[half - 1] + part[half]) / 2.0)


def column_medians(values: np.ndarray) -> np.ndarray:
    """``np.median(values, axis=0)`` of an (N, K) float array with N >= 1, bit for bit."""
    values = np.asarray(values, dtype=float)
    if values.ndim != 2 or len(values) == 0:
        raise ValueError(f"column_medians expects a non-empty (N, K) array, got {values.shape}")
    count = len(values)
    half = count // 2
    kth = (half, count - 1) if count % 2 else (half - 1, half, count - 1)
    part = np.partition(values, kth, axis=0)
    middle = part[half] if count % 2 else (part[half - 1] + part[half]) / 2.0
    return np.where(np.isnan(part[-1]), np.nan, middle)


def quantile(values: np.ndarray, q: float) -> float | np.ndarray:
    """``np.quantile(values, q, axis=0)`` for a python float ``q`` in [0, 1] (linear method),
    bit for bit: a float for a 1-D array, one value per column for an (N, K) one (N >= 1)."""
    values = np.asarray(values, dtype=float)
    if values.ndim not in (1, 2) or len(values) == 0 or not 0.0 <= q <= 1.0:
        raise ValueError(f"quantile expects a non-empty 1-D or 2-D array and q in [0, 1], got "
                         f"shape {values.shape} and q={q}")  # fmt: skip
    count = len(values)
    virtual = (count - 1) * q  # NumPy's index for the linear method, then its neighbours
    below = min(math.floor(virtual), count - 1)
    above = min(below + 1, count - 1)
    part = np.partition(values, sorted({0, below, above, count - 1}), axis=0)
    low, high = part[below], part[above]
    gamma = virtual - below
    difference = high - low
    # NumPy's _lerp: from the nearer neighbour, so that q = 1 gives the maximum exactly.
    result = high - difference * (1 - gamma) if gamma >= 0.5 else low + difference * gamma
    result = np.where(np.isnan(part[-1]), np.nan, result)
    return float(result) if values.ndim == 1 else result
