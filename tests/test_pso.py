"""The generic swarm: converges, ranks lexicographically, stops on stagnation, is seeded."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.registration.pso import better, optimise


def _sphere(centre: np.ndarray):
    def objective(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(len(positions), dtype=int), np.sum((positions - centre) ** 2, axis=1)

    return objective


def test_swarm_finds_the_minimum_of_a_bowl() -> None:
    rng = np.random.default_rng(0)
    centre = np.array([1.5, -2.0, 0.5])
    start = rng.uniform(-5.0, 5.0, size=(20, 3))
    result = optimise(_sphere(centre), start, rng=rng, max_iterations=300, stagnation=30)
    np.testing.assert_allclose(result.position, centre, atol=1e-3)
    assert result.fitness < 1e-6
    assert 1 < result.iterations <= 301


def test_support_outranks_fitness() -> None:
    # Support peaks at x = 3 (a plateau of width 1) while the fitness alone prefers x = 0.
    def objective(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = positions[:, 0]
        return (np.abs(x - 3.0) < 0.5).astype(int), x**2

    rng = np.random.default_rng(1)
    start = np.linspace(-4.0, 4.0, 16)[:, None]
    result = optimise(objective, start, rng=rng, max_iterations=100, stagnation=20)
    assert result.support == 1
    # Among supported positions the lowest fitness is at the plateau's near edge, x -> 2.5.
    assert 2.5 <= result.position[0] < 2.7


def test_better_is_lexicographic() -> None:
    support = np.array([5, 5, 4, 6])
    fitness = np.array([1.0, 2.0, 0.0, 9.0])
    assert better(support, fitness, np.full(4, 5), np.full(4, 1.5)).tolist() == [
        True,
        False,
        False,
        True,
    ]


def test_stops_after_the_stagnation_window() -> None:
    def flat(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(len(positions), dtype=int), np.ones(len(positions))

    rng = np.random.default_rng(2)
    result = optimise(flat, rng.normal(size=(8, 2)), rng=rng, max_iterations=100, stagnation=5)
    assert result.iterations == 6  # the initial evaluation plus five without progress


def test_same_seed_same_run() -> None:
    centre = np.array([0.3, 0.2])
    runs = []
    for _ in range(2):
        rng = np.random.default_rng(42)
        start = rng.normal(size=(10, 2))
        runs.append(optimise(_sphere(centre), start, rng=rng, max_iterations=20, stagnation=20))
    assert np.array_equal(runs[0].position, runs[1].position)
    assert runs[0].fitness == runs[1].fitness


def test_non_finite_fitness_never_wins() -> None:
    def objective(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        fitness = np.sum(positions**2, axis=1)
        return np.zeros(len(positions), dtype=int), np.where(positions[:, 0] > 0, np.nan, fitness)

    rng = np.random.default_rng(3)
    result = optimise(objective, rng.normal(size=(12, 2)), rng=rng, max_iterations=50)
    assert np.isfinite(result.fitness)
    assert result.position[0] <= 0.0


def test_bad_arguments_raise_clear_errors() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="non-empty"):
        optimise(_sphere(np.zeros(2)), np.zeros((0, 2)), rng=rng)
    with pytest.raises(ValueError, match="stagnation"):
        optimise(_sphere(np.zeros(2)), np.zeros((3, 2)), rng=rng, stagnation=0)

    def wrong_shape(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(1, dtype=int), np.zeros(1)

    with pytest.raises(ValueError, match="one support and one fitness per particle"):
        optimise(wrong_shape, np.zeros((3, 2)), rng=rng)


def _reference_swarm(objective, start, rng, iterations, inertia, acceleration, max_speed):
    """Eqs. 4-5 written out plainly in numpy, with the same random draws, for a fixed length."""
    positions = np.array(start, dtype=float)
    velocity = np.zeros_like(positions)
    support, fitness = objective(positions)
    best, best_support, best_fitness = positions.copy(), support.copy(), fitness.copy()
    leader = int(np.lexsort((best_fitness, -best_support))[0])
    for _ in range(iterations):
        phi1, phi2 = rng.random((2, *positions.shape))
        velocity = (
            inertia * velocity
            + acceleration * phi1 * (best - positions)
            + acceleration * phi2 * (best[leader] - positions)
        )
        velocity = np.clip(velocity, -max_speed, max_speed)
        positions = positions + velocity
        support, fitness = objective(positions)
        improved = better(support, fitness, best_support, best_fitness)
        best[improved] = positions[improved]
        best_support = np.where(improved, support, best_support)
        best_fitness = np.where(improved, fitness, best_fitness)
        leader = int(np.lexsort((best_fitness, -best_support))[0])
    return best[leader], best_support[leader], best_fitness[leader]


def test_compiled_updates_follow_the_velocity_equations() -> None:
    """Same draws, same arithmetic: the run equals a plain numpy swarm step for step."""
    centre = np.array([0.4, -0.3, 0.8])

    def objective(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        distance = np.sum((positions - centre) ** 2, axis=1)
        return (distance < 0.5).astype(int), distance  # support plateau plus a bowl

    start = np.random.default_rng(5).normal(size=(9, 3))
    speed = np.array([0.3, 0.2, 0.5])  # per-axis clamp
    result = optimise(
        objective,
        start,
        rng=np.random.default_rng(6),
        max_iterations=25,
        stagnation=25,
        inertia=0.7,
        acceleration=1.4,
        max_speed=speed,
    )
    position, support, fitness = _reference_swarm(
        objective, start, np.random.default_rng(6), 25, 0.7, 1.4, speed
    )
    assert result.iterations == 26
    np.testing.assert_array_equal(result.position, position)
    assert (result.support, result.fitness) == (support, fitness)


def test_objective_may_keep_or_modify_its_input() -> None:
    seen: list[np.ndarray] = []

    def hoarding(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        seen.append(positions)
        fitness = np.sum(positions**2, axis=1)
        positions[:] = 1e9  # must not leak into the swarm
        return np.zeros(len(fitness), dtype=int), fitness

    rng = np.random.default_rng(8)
    result = optimise(hoarding, rng.normal(size=(6, 2)), rng=rng, max_iterations=10)
    assert np.abs(result.position).max() < 10.0
    assert len({id(array) for array in seen}) == len(seen) == result.iterations
