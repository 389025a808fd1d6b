"""The table of registration estimators: name -> function.

Estimators add themselves with ``@register_method("name")``; ``registry.register`` looks the
name up here. A module of its own so that an estimator can register without importing the
registry that imports it.
"""

from __future__ import annotations

from collections.abc import Callable

from estimator.registration.result import RegistrationResult

__all__ = ["METHODS", "EstimatorFn", "register_method"]

EstimatorFn = Callable[..., RegistrationResult]
METHODS: dict[str, EstimatorFn] = {}


def register_method(name: str) -> Callable[[EstimatorFn], EstimatorFn]:
    """Decorator: make an estimator reachable as ``register(..., method=name)``."""

    def decorate(function: EstimatorFn) -> EstimatorFn:
        METHODS[name] = function
        return function

    return decorate
