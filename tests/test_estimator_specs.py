"""The estimator registry is the one source of truth: names, options and per-pair inputs."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from estimator.cli.commands.run import add_arguments
from estimator.config import SwarmvoConfig, explain_validation_error
from estimator.pipeline import ESTIMATORS
from estimator.registration.methods import DEFAULT_ESTIMATOR, Estimator
from estimator.registration.registry import available_methods, estimator_spec, register
from estimator.rendered.simulation import simulate_pair
from service.limits import OPTION_BOUNDS

NAMES = [name.value for name in Estimator]


def _problem(count: int = 120):
    pair = simulate_pair(count, noise_sigma=0.01, outlier_ratio=0.3, rng=4)
    source, target = pair.source, pair.target
    count = len(source)
    rng = np.random.default_rng(5)
    # Anisotropic covariances (depth far less certain): they change a Mahalanobis support.
    scales = rng.uniform(0.005, 0.05, size=(count, 3)) ** 2
    covariance = np.zeros((count, 3, 3))
    covariance[:, [0, 1, 2], [0, 1, 2]] = scales
    return source, target, covariance


def test_every_registered_estimator_has_a_name_and_every_name_an_estimator() -> None:
    assert sorted(NAMES) == available_methods()
    for name in NAMES:
        assert estimator_spec(name).name == name


def test_unknown_estimator_spec_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="unknown method 'nope'; available: msac, pso"):
        estimator_spec("nope")


def test_config_cli_and_service_take_their_names_from_the_registry() -> None:
    schema = SwarmvoConfig.model_json_schema()
    assert schema["$defs"]["Estimator"]["enum"] == NAMES
    config = SwarmvoConfig.model_validate({"registration": {"method": "msac"}})
    assert type(config.registration.method) is str and config.registration.method == "msac"
    assert SwarmvoConfig().registration.method == DEFAULT_ESTIMATOR
    with pytest.raises(ValueError) as caught:
        SwarmvoConfig.model_validate({"registration": {"method": "msak"}})
    message = explain_validation_error(caught.value)
    assert message.startswith("registration.method:") and "'msac'" in message
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    (action,) = [a for a in parser._actions if a.dest == "estimator"]
    assert list(action.choices) == NAMES == list(ESTIMATORS)
    assert set(OPTION_BOUNDS) == set(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_service_bounds_name_options_the_estimator_takes(name: str) -> None:
    assert set(OPTION_BOUNDS[name]) <= estimator_spec(name).options


@pytest.mark.parametrize("name", NAMES)
def test_declared_options_are_accepted_and_others_rejected(name: str) -> None:
    source, target, _ = _problem()
    spec = estimator_spec(name)
    with pytest.raises(ValueError, match="unknown option"):
        register(source, target, method=name, seed=1, not_an_option=1)
    if "refits" in spec.options:
        assert register(source, target, method=name, seed=1, refits=2).rotation.shape == (3, 3)


@pytest.mark.parametrize("name", NAMES)
def test_declared_per_pair_inputs_match_what_the_estimator_does(name: str) -> None:
    source, target, covariance = _problem()
    spec = estimator_spec(name)
    sigmas = np.sqrt(covariance[:, 2, 2])
    if spec.takes_sigmas:
        register(source, target, method=name, seed=1, sigmas=sigmas)
    else:
        with pytest.raises(ValueError, match="unknown option"):
            register(source, target, method=name, seed=1, sigmas=sigmas)
    plain = register(source, target, method=name, seed=1)
    try:
        weighed = register(
            source, target, method=name, seed=1, source_cov=covariance, target_cov=covariance
        )
    except ValueError as error:
        assert not spec.takes_covariances, error
        return
    changed = not np.array_equal(plain.inliers, weighed.inliers) or not np.array_equal(
        plain.rotation, weighed.rotation
    )
    assert changed == spec.takes_covariances
