"""``swarmvo bench registration``: accuracy and speed of rigid registration under outliers.

The paper's Figures 6 and 7 as a reproducible grid: for every noise sigma x outlier ratio
cell, ``--trials`` simulated stereo point-pair problems (``estimator.rendered.simulation``) are
solved by every method on the *same* pair, and the cell records success rate, translation and
rotation error, time and inlier precision/recall. Outputs: ``registration.json`` (table +
metadata + per-trial values), ``figure6_position_error.png``, ``figure7_time.png``, a
Markdown copy of the printed tables, and a PASS/MISS check of pso-robust against its targets
(``registration_report.py``).

Only the estimator is timed (never the simulation), on whatever threads the process has:
run it as ``OMP_NUM_THREADS=1 swarmvo bench registration`` for one-core numbers.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from estimator.bench.peers import INLIER_QUANTILE, PEERS, oracle, peer_missing_package, run_peer
from estimator.bench.registration_report import (
    SUCCESS_ROTATION_DEG,
    SUCCESS_TRANSLATION_M,
    check_targets,
    format_tables,
    format_targets,
    loadavg,
    machine_info,
    none_if_inf,
    write_outputs,
)
from estimator.registration.registry import (
    Estimator,
    RegistrationResult,
    available_methods,
    register,
)
from estimator.rendered.simulation import (
    SimulatedPair,
    rotation_error_deg,
    simulate_pair,
    translation_error,
)

__all__ = ["add_arguments", "check_targets", "run", "run_grid"]

SIGMAS = (0.005, 0.02, 0.05)
OUTLIER_RATIOS = (0.0, 0.2, 0.4, 0.6, 0.8, 0.9, 0.95)
TRIALS = 50
QUICK_SIGMAS = (0.02,)
QUICK_OUTLIER_RATIOS = (0.0, 0.5, 0.9)
QUICK_TRIALS = 5
N_POINTS = 400
OURS = tuple(name.value for name in Estimator)
DEFAULT_METHODS = (*OURS, *PEERS, "oracle")

NOT_INSTALLED = "not installed (pip install 'swarmvo[bench]'; missing {package})"

Runner = Callable[[SimulatedPair, float, int], RegistrationResult]


# ----------------------------------------------------------------------------- command line


def _floats(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(item) for item in text.split(",") if item.strip())
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers: {error}") from None
    if not values:
        raise argparse.ArgumentTypeError("expected at least one number")
    return values


def _names(text: str) -> tuple[str, ...]:
    names = tuple(item.strip() for item in text.split(",") if item.strip())
    if not names:
        raise argparse.ArgumentTypeError("expected at least one method name")
    return names


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Rigid registration under noise and outliers (paper Figs. 6-7). "
        "Time it on one core: OMP_NUM_THREADS=1 swarmvo bench registration"
    )
    parser.add_argument("--sigmas", type=_floats, help=f"noise sigmas in m (default {SIGMAS})")
    parser.add_argument(
        "--outlier-ratios", type=_floats, help=f"outlier ratios (default {OUTLIER_RATIOS})"
    )
    parser.add_argument("--trials", type=int, help=f"trials per cell (default {TRIALS})")
    parser.add_argument(
        "--methods",
        type=_names,
        default=DEFAULT_METHODS,
        help=f"comma-separated methods (default {','.join(DEFAULT_METHODS)})",
    )
    parser.add_argument("--seed", type=int, default=0, help="master seed (default 0)")
    parser.add_argument(
        "--points", type=int, default=N_POINTS, help="points drawn before visibility culling"
    )
    parser.add_argument(
        "--peer-max-iterations",
        type=int,
        default=100_000,
        help="iteration cap of the MAGSAC++ and Open3D peers (default 100000)",
    )
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/registration"))
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"small grid: sigmas {QUICK_SIGMAS}, ratios {QUICK_OUTLIER_RATIOS}, "
        f"{QUICK_TRIALS} trials (explicit flags still win)",
    )
    parser.add_argument(
        "--strict", action="store_true", help="exit 1 when a pso-robust target is missed"
    )
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument(
        "--mode",
        choices=("paper", "stereo"),
        default="paper",
        help="paper: isotropic 3D noise (Figs. 6-7); stereo: points triangulated from pixel "
        "noise on the EuRoC and a KITTI-like rig (results in registration-stereo)",
    )


def run(args: argparse.Namespace) -> int:
    if args.mode == "stereo":
        from estimator.bench.registration_stereo import run_stereo

        default = args.out == Path("benchmarks/results/registration")
        return run_stereo(args, args.out.with_name("registration-stereo") if default else args.out)
    sigmas = args.sigmas or (QUICK_SIGMAS if args.quick else SIGMAS)
    ratios = args.outlier_ratios or (QUICK_OUTLIER_RATIOS if args.quick else OUTLIER_RATIOS)
    trials = args.trials if args.trials is not None else (QUICK_TRIALS if args.quick else TRIALS)
    if "OMP_NUM_THREADS" not in os.environ:
        print(
            "note: OMP_NUM_THREADS is not set; for one-core timings run "
            "OMP_NUM_THREADS=1 swarmvo bench registration",
            file=sys.stderr,
        )
    report = run_grid(
        sigmas=sigmas,
        outlier_ratios=ratios,
        trials=trials,
        methods=args.methods,
        seed=args.seed,
        n_points=args.points,
        peer_max_iterations=args.peer_max_iterations,
        progress=not args.no_progress,
    )
    if sys.argv and Path(sys.argv[0]).name == "swarmvo":
        report["command"] = " ".join(["swarmvo", *sys.argv[1:]])
    tables = format_tables(report)
    checks = format_targets(report)
    print(tables)
    print(checks)
    inliers = format_tables(report, "inliers")
    write_outputs(report, args.out, text=f"{tables}\n{checks}\n\n{inliers}")
    print(f"wrote {args.out / 'registration.json'} and figures to {args.out}")
    missed = report["targets"]["missed"] if report["targets"] else 0
    return 1 if args.strict and missed else 0


# ----------------------------------------------------------------------------- the grid


def _validate(
    sigmas: Sequence[float], outlier_ratios: Sequence[float], trials: int, n_points: int, seed: int
) -> None:
    if seed < 0:
        raise ValueError(f"--seed must be >= 0, got {seed}")
    if not sigmas or any(not (sigma > 0.0 and np.isfinite(sigma)) for sigma in sigmas):
        raise ValueError(f"noise sigmas must be finite and > 0 m, got {list(sigmas)}")
    if not outlier_ratios or any(not 0.0 <= ratio < 1.0 for ratio in outlier_ratios):
        raise ValueError(f"outlier ratios must be in [0, 1), got {list(outlier_ratios)}")
    if trials < 1:
        raise ValueError(f"--trials must be >= 1, got {trials}")
    if n_points < 3:
        raise ValueError(f"--points must be >= 3, got {n_points}")


def _resolve(methods: Sequence[str], peer_max_iterations: int) -> dict[str, Runner | str]:
    """Method name -> runner, or the reason it cannot run (only for uninstalled peers)."""
    if not methods:
        raise ValueError("no methods to run")
    if len(set(methods)) != len(methods):
        raise ValueError(f"methods listed twice in {list(methods)}")
    if peer_max_iterations < 1:
        raise ValueError(f"--peer-max-iterations must be >= 1, got {peer_max_iterations}")
    own = [name for name in methods if name != "oracle" and name not in PEERS]
    registered: list[str] = []
    if own:
        try:
            registered = available_methods()
        except ImportError as error:
            raise ValueError(f"the swarmvo estimators could not be loaded: {error}") from error
    unknown = [name for name in own if name not in registered]
    if unknown:
        raise ValueError(
            f"unknown method(s) {unknown}; swarmvo estimators: {registered}, "
            f"peers: {list(PEERS)}, and 'oracle'"
        )
    runners: dict[str, Runner | str] = {}
    for name in methods:
        if name == "oracle":
            runners[name] = lambda pair, sigma, seed: oracle(
                pair.source, pair.target, pair.inlier_mask
            )
        elif name in PEERS:
            missing = peer_missing_package(name)
            runners[name] = (
                NOT_INSTALLED.format(package=missing)
                if missing
                else _peer_runner(name, peer_max_iterations)
            )
        else:
            runners[name] = _own_runner(name)
    return runners


def _peer_runner(name: str, max_iterations: int) -> Runner:
    def solve(pair: SimulatedPair, sigma: float, seed: int) -> RegistrationResult:
        return run_peer(
            name,
            pair.source,
            pair.target,
            noise_sigma=sigma,
            seed=seed,
            max_iterations=max_iterations,
        )

    return solve


def _own_runner(name: str) -> Runner:
    def solve(pair: SimulatedPair, sigma: float, seed: int) -> RegistrationResult:
        return register(pair.source, pair.target, method=name, seed=seed)

    return solve


def trial_seeds(seed: int, sigma: float, ratio: float, trial: int) -> tuple[int, int]:
    """(simulation seed, estimator seed) from the master seed, the cell *values* and the trial.

    Keyed on values rather than grid indices, so a sub-grid (``--sigmas 0.02``) replays
    exactly the pairs of the full grid.
    """
    key = [seed, round(sigma * 1e6), round(ratio * 1e6), trial]
    sim_seed, method_seed = np.random.SeedSequence(key).generate_state(2)
    return int(sim_seed), int(method_seed)


@dataclass
class _Samples:
    """Per-trial values of one method in one cell."""

    translation_error: list[float]
    rotation_error: list[float]
    time_s: list[float]
    support: list[int]
    precision: list[float]
    recall: list[float]
    reported_success: list[bool]

    @classmethod
    def empty(cls) -> _Samples:
        return cls([], [], [], [], [], [], [])

    def add(self, result: RegistrationResult, pair: SimulatedPair) -> None:
        usable = np.isfinite(result.rotation).all() and np.isfinite(result.translation).all()
        self.translation_error.append(
            translation_error(result.translation, pair.translation) if usable else np.inf
        )
        self.rotation_error.append(
            rotation_error_deg(result.rotation, pair.rotation) if usable else np.inf
        )
        self.time_s.append(result.elapsed_s)
        estimated = np.asarray(result.inliers, dtype=bool)
        true = pair.inlier_mask
        hits = int((estimated & true).sum())
        self.support.append(int(result.support))
        self.precision.append(hits / estimated.sum() if estimated.any() else np.nan)
        self.recall.append(hits / true.sum() if true.any() else np.nan)
        self.reported_success.append(bool(result.success))


def _stat(function: Callable[[np.ndarray], float], values: np.ndarray) -> float | None:
    """``function`` of the finite values (None when there are none)."""
    finite = values[np.isfinite(values)]
    return float(function(finite)) if len(finite) else None


def _summarise(samples: _Samples) -> dict:
    t_err = np.asarray(samples.translation_error)
    r_err = np.asarray(samples.rotation_error)
    time_ms = 1e3 * np.asarray(samples.time_s)
    success = (r_err < SUCCESS_ROTATION_DEG) & (t_err < SUCCESS_TRANSLATION_M)
    precision = np.asarray(samples.precision)
    recall = np.asarray(samples.recall)
    return {
        "status": "ok",
        "trials": len(t_err),
        "success_rate": float(success.mean()),
        "reported_success_rate": float(np.mean(samples.reported_success)),
        "no_estimate": int((~np.isfinite(t_err)).sum()),
        # Medians over all trials (a trial without an estimate counts as +inf error);
        # means over the trials that produced an estimate.
        "median_translation_error_m": none_if_inf(np.median(t_err)),
        "mean_translation_error_m": _stat(np.mean, t_err),
        "p95_translation_error_m": none_if_inf(np.percentile(t_err, 95)),
        "median_rotation_error_deg": none_if_inf(np.median(r_err)),
        "mean_rotation_error_deg": _stat(np.mean, r_err),
        "median_time_ms": float(np.median(time_ms)),
        "p95_time_ms": float(np.percentile(time_ms, 95)),
        "mean_time_ms": float(np.mean(time_ms)),
        "mean_support": float(np.mean(samples.support)),
        "mean_inlier_precision": _stat(np.mean, precision),
        "mean_inlier_recall": _stat(np.mean, recall),
        # Per-trial values (4 significant digits) let anyone re-derive or re-plot the cell.
        "per_trial": {
            "translation_error_m": _rounded(t_err),
            "rotation_error_deg": _rounded(r_err),
            "time_ms": _rounded(time_ms),
        },
    }


def _rounded(values: np.ndarray) -> list[float | None]:
    return [float(f"{value:.4g}") if np.isfinite(value) else None for value in values]


def _warm_up(runners: dict[str, Runner | str], sigma: float, n_points: int) -> None:
    """One untimed call per method, so JIT compilation and lazy imports stay out of timings."""
    pair = simulate_pair(n_points, sigma, 0.5, rng=0)
    for name, runner in runners.items():
        if isinstance(runner, str):
            continue
        try:
            runner(pair, sigma, 0)
        except ValueError as error:
            raise ValueError(f"{name} failed on the warm-up pair: {error}") from error


def _run_cell(
    runners: dict[str, Runner | str],
    sigma: float,
    ratio: float,
    trials: int,
    seed: int,
    n_points: int,
    bar: tqdm,
) -> dict:
    """Every method on the same ``trials`` simulated pairs of one (sigma, outlier ratio) cell."""
    bar.set_description(f"sigma={sigma:g} e={ratio:g}")
    samples = {name: _Samples.empty() for name in runners}
    pairs, inliers = [], []
    for trial in range(trials):
        sim_seed, method_seed = trial_seeds(seed, sigma, ratio, trial)
        pair = simulate_pair(n_points, sigma, ratio, rng=sim_seed)
        pairs.append(len(pair.source))
        inliers.append(int(pair.inlier_mask.sum()))
        for name, runner in runners.items():
            if isinstance(runner, str):
                continue
            try:
                result = runner(pair, sigma, method_seed)
            except ValueError as error:
                raise ValueError(
                    f"{name} failed at sigma={sigma:g} e={ratio:g} trial {trial} "
                    f"(simulation seed {sim_seed}, method seed {method_seed}): {error}"
                ) from error
            samples[name].add(result, pair)
        bar.update()
    return {
        "sigma": sigma,
        "outlier_ratio": ratio,
        "mean_pairs": float(np.mean(pairs)),
        "mean_true_inliers": float(np.mean(inliers)),
        "min_true_inliers": int(np.min(inliers)),
        "methods": {
            name: {"status": runner} if isinstance(runner, str) else _summarise(samples[name])
            for name, runner in runners.items()
        },
    }


def run_grid(
    *,
    sigmas: Sequence[float] = SIGMAS,
    outlier_ratios: Sequence[float] = OUTLIER_RATIOS,
    trials: int = TRIALS,
    methods: Sequence[str] = DEFAULT_METHODS,
    seed: int = 0,
    n_points: int = N_POINTS,
    peer_max_iterations: int = 100_000,
    progress: bool = True,
) -> dict:
    """Run every method on the same simulated pairs of every cell; return the report dict."""
    sigmas, outlier_ratios = tuple(map(float, sigmas)), tuple(map(float, outlier_ratios))
    _validate(sigmas, outlier_ratios, trials, n_points, seed)
    runners = _resolve(methods, peer_max_iterations)
    started = dt.datetime.now(dt.UTC)
    machine = machine_info()
    _warm_up(runners, sigmas[0], n_points)
    bar = tqdm(
        total=len(sigmas) * len(outlier_ratios) * trials,
        disable=not progress,
        unit="trial",
        file=sys.stderr,
    )
    with bar:
        cells = [
            _run_cell(runners, sigma, ratio, trials, seed, n_points, bar)
            for sigma in sigmas
            for ratio in outlier_ratios
        ]
    machine["loadavg_end"] = loadavg()
    report = {
        "benchmark": "registration",
        "started_utc": started.isoformat(timespec="seconds"),
        "finished_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "grid": {
            "sigmas_m": list(sigmas),
            "outlier_ratios": list(outlier_ratios),
            "trials": trials,
            "points_drawn": n_points,
            "seed": seed,
            "methods": list(runners),
            "peer_max_iterations": peer_max_iterations,
        },
        "success_criterion": {
            "rotation_error_deg_below": SUCCESS_ROTATION_DEG,
            "translation_error_m_below": SUCCESS_TRANSLATION_M,
        },
        "peer_inlier_threshold": (
            f"tau = sqrt(chi2_3({INLIER_QUANTILE})) * sigma ~ 3.37 sigma, the same for every peer"
        ),
        "peers": {name: peer.summary for name, peer in PEERS.items() if name in runners},
        "machine": machine,
        "cells": cells,
    }
    report["targets"] = check_targets(report)
    return report
