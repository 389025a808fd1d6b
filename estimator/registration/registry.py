"""The one public entry point for rigid 3D-3D registration and its result type.

``register(source, target, method=...)`` validates the input once, then dispatches to an
estimator registered under ``method``. Estimators register themselves with
``@register_method(EstimatorSpec(...))`` (name and capabilities, ``methods.py``); every one
returns a :class:`RegistrationResult`.
"""

from __future__ import annotations

import time

import numpy as np

from estimator.registration.methods import (
    DEFAULT_ESTIMATOR,
    METHODS,
    SPECS,
    Estimator,
    EstimatorSpec,
    register_method,
)
from estimator.registration.result import RegistrationResult

__all__ = [
    "METHODS",
    "Estimator",
    "EstimatorSpec",
    "RegistrationResult",
    "available_methods",
    "estimator_spec",
    "register",
    "register_method",
]


def available_methods() -> list[str]:
    _load_builtin_methods()
    return sorted(METHODS)


def estimator_spec(method: str) -> EstimatorSpec:
    """The declared capabilities of estimator ``method`` (``ValueError`` for an unknown one)."""
    _load_builtin_methods()
    if method not in SPECS:
        raise ValueError(f"unknown method {method!r}; available: {', '.join(sorted(SPECS))}")
    return SPECS[method]


def _load_builtin_methods() -> None:
    # Imported for their @register_method side effect, at the first call: the swarm compiles
    # its numba kernels on import, which `import estimator` should not pay for.
    from estimator.registration import baselines, pso_support  # noqa: F401


def _validated(points: np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(points, dtype=float)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must be an (N, 3) array of points, got shape {array.shape}")
    if not np.isfinite(array).all():  # one pass in the common case, rows only on failure
        bad = ~np.isfinite(array).all(axis=1)
        rows = np.flatnonzero(bad)[:5].tolist()
        raise ValueError(f"{name} has {int(bad.sum())} row(s) with NaN or inf (first: {rows})")
    return array


def register(
    source: np.ndarray,
    target: np.ndarray,
    method: str = DEFAULT_ESTIMATOR,
    seed: int | None = None,
    **options,
) -> RegistrationResult:
    """Estimate R, t with target ~ R @ source + t from corresponding points, robust to outliers.

    Raises ``ValueError`` for malformed input (shape, NaN/inf, unknown method); returns a
    result with ``success=False`` (never raises) when the data cannot support an estimate.
    """
    _load_builtin_methods()
    source = _validated(source, "source")
    target = _validated(target, "target")
    if source.shape != target.shape:
        raise ValueError(f"source {source.shape} and target {target.shape} differ in shape")
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; available: {', '.join(sorted(METHODS))}")
    start = time.perf_counter()
    result = METHODS[method](source, target, seed=seed, **options)
    result.elapsed_s = time.perf_counter() - start
    result.method = method
    return result
