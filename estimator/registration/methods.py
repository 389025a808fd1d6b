"""The table of registration estimators: their names, what each one takes, and its function.

``Estimator`` is the one list of names: the configuration, the CLI choices and the benchmark
lists come from it. Each estimator declares its capabilities where it registers, with
``@register_method(EstimatorSpec(...))``; ``registry.register`` looks the name up here. A module of
its own (and free of numerical imports) so that the configuration can name the estimators and an
estimator can register without importing the registry that imports it.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import StrEnum

from estimator.registration.result import RegistrationResult

__all__ = [
    "DEFAULT_ESTIMATOR",
    "METHODS",
    "SPECS",
    "Estimator",
    "EstimatorFn",
    "EstimatorSpec",
    "keyword_options",
    "register_method",
]

EstimatorFn = Callable[..., RegistrationResult]


class Estimator(StrEnum):
    """Name of a registration estimator (``register(..., method=name)``)."""

    PSO_ROBUST = "pso-robust"
    PSO = "pso"
    MSAC = "msac"
    SVD = "svd"


DEFAULT_ESTIMATOR: str = Estimator.PSO_ROBUST.value

# Per-pair inputs (arrays that come with the points) as opposed to tuning options.
_PER_PAIR_INPUTS = frozenset({"sigmas", "source_cov", "target_cov"})


@dataclass(frozen=True)
class EstimatorSpec:
    """What an estimator takes besides the two point sets."""

    name: Estimator
    summary: str
    # Tuning options accepted as keywords (``SwarmvoConfig.registration.options``); None: the
    # keyword-only parameters of the registered function (``keyword_options``).
    options: frozenset[str] | None = None
    # ``sigmas`` (N,): per-pair residual standard deviations.
    takes_sigmas: bool = False
    # ``source_cov`` / ``target_cov`` (N, 3, 3): per-point covariances (a Mahalanobis support).
    takes_covariances: bool = False


METHODS: dict[str, EstimatorFn] = {}
SPECS: dict[str, EstimatorSpec] = {}


def keyword_options(function: Callable[..., object]) -> frozenset[str]:
    """The tuning options of an estimator function: its keyword-only parameters but ``seed``."""
    parameters = inspect.signature(function).parameters.values()
    names = {p.name for p in parameters if p.kind is inspect.Parameter.KEYWORD_ONLY}
    return frozenset(names - {"seed"} - _PER_PAIR_INPUTS)


def register_method(spec: EstimatorSpec) -> Callable[[EstimatorFn], EstimatorFn]:
    """Decorator: make an estimator reachable as ``register(..., method=spec.name)``."""

    def decorate(function: EstimatorFn) -> EstimatorFn:
        options = keyword_options(function) if spec.options is None else spec.options
        METHODS[spec.name.value] = function
        SPECS[spec.name.value] = replace(spec, options=options)
        return function

    return decorate
