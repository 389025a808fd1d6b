"""``swarmvo bench backend``, part ``simulated``: the graph on a long simulated trajectory.

A smooth trajectory at 20 Hz with a simulated 200 Hz IMU and simulated front-end relative
poses (clean, and with 20 % broken frames); fused vs front-end-only ATE and the per-frame
back-end time, whose first and last 10 % show that it stays flat.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from typing import Any

import numpy as np

from estimator.backend import FusionBackend
from estimator.bench.markdown import titled_table
from estimator.config import BackendConfig
from estimator.geometry import make_pose
from estimator.rendered.scenario import (
    FrontendMeasurement,
    Scenario,
    aligned_ate,
    chain,
    simulate_frontend,
    smooth_trajectory,
)
from estimator.types import ImuNoise

__all__ = ["bench_simulated"]

# EuRoC-like camera mount for the simulated runs: ~90 deg about z, a few cm offset.
SIM_BODY_FROM_CAMERA = make_pose(
    np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), [-0.02, -0.06, 0.01]
)


def _ms_stats(seconds: np.ndarray) -> dict[str, float]:
    ms = np.asarray(seconds) * 1e3
    tenth = max(len(ms) // 10, 1)
    return {
        "p50_ms": float(np.percentile(ms, 50)),
        "p95_ms": float(np.percentile(ms, 95)),
        "max_ms": float(ms.max()),
        "first10pct_p50_ms": float(np.median(ms[:tenth])),
        "last10pct_p50_ms": float(np.median(ms[-tenth:])),
    }


def _drive(scenario, measurements, config: BackendConfig, imu: bool):
    backend = FusionBackend(config, SIM_BODY_FROM_CAMERA, ImuNoise() if imu else None)
    stamps = scenario.timestamps_ns
    poses, seconds, statuses = [], [], Counter()
    for k, measurement in enumerate(measurements):
        start = stamps[k - 1] if k else stamps[0] - 10**9
        batch = scenario.imu.between(int(start), int(stamps[k])) if imu else None
        begin = time.perf_counter()
        out = backend.add_frame(
            int(stamps[k]),
            None if k == 0 else measurement.relative_pose,
            measurement.residuals,
            measurement.inlier_count,
            batch,
        )
        seconds.append(time.perf_counter() - begin)
        poses.append(out.pose)
        statuses[str(out.status)] += 1
    return np.stack(poses), np.asarray(seconds), dict(statuses)


def bench_simulated(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """Front end alone vs the back end, with 0 % and 20 % broken frames; JSON and table."""
    scenario = smooth_trajectory(args.frames, seed=args.seed)
    truth = scenario.body_poses @ SIM_BODY_FROM_CAMERA
    path = float(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum())
    result: dict[str, Any] = {"frames": args.frames, "path_length_m": path, "cases": {}}
    rows: list[list[str]] = []
    for broken in (0.0, 0.2):
        case, best_frontend, short_reference = _simulated_case(scenario, truth, broken, args)
        rows += _case_rows(broken, case, best_frontend, short_reference)
        result["cases"][f"broken_{broken:.2f}"] = case
    return result, _simulated_table(args, path, rows)


def _simulated_case(
    scenario: Scenario, truth: np.ndarray, broken: float, args: argparse.Namespace
) -> tuple[dict[str, Any], float, float]:
    """Every trajectory for one fraction of broken frames, and the front-end ATEs to beat.

    Returns (case, best front-end ATE over all frames, best front-end ATE over the frames of
    the short iSAM2 run); the short run is only made with broken frames, where its cost
    growth and its robustness both show.
    """
    measurements = simulate_frontend(
        scenario.body_poses, SIM_BODY_FROM_CAMERA, seed=args.seed + 1, broken_fraction=broken
    )
    relative = [m.relative_pose for m in measurements]
    case: dict[str, Any] = {
        "front end, hold on failure": {"ate_m": aligned_ate(chain(relative, hold=True), truth)},
        "front end, constant velocity on failure": {
            "ate_m": aligned_ate(chain(relative, hold=False), truth)
        },
    }
    for name, imu in (("fixed-lag, IMU", True), ("fixed-lag, no IMU", False)):
        poses, seconds, statuses = _drive(scenario, measurements, BackendConfig(), imu)
        ate = aligned_ate(poses, truth)
        case[name] = {"ate_m": ate, "statuses": statuses, **_ms_stats(seconds)}
    best_frontend = min(case[k]["ate_m"] for k in list(case)[:2])
    if broken <= 0.0:
        return case, best_frontend, best_frontend
    count = min(args.isam2_frames, args.frames)
    case[f"iSAM2 full history, IMU (first {count} frames)"] = _isam2_row(
        scenario, measurements, truth, count
    )
    # The short run is compared with the front end over the same frames.
    short_reference = min(
        aligned_ate(chain(relative[:count], hold=h), truth[:count]) for h in (True, False)
    )
    return case, best_frontend, short_reference


def _isam2_row(
    scenario: Scenario, measurements: list[FrontendMeasurement], truth: np.ndarray, count: int
) -> dict[str, Any]:
    """Full-history iSAM2 on the first ``count`` frames only: enough to show its cost growing."""
    short = Scenario(
        scenario.timestamps_ns[:count],
        scenario.body_poses[:count],
        scenario.imu,
        scenario.gyro_bias,
    )
    poses, seconds, statuses = _drive(
        short, measurements[:count], BackendConfig(smoother="isam2"), True
    )
    return {
        "ate_m": aligned_ate(poses, truth[:count]),
        "statuses": statuses,
        **_ms_stats(seconds),
    }


def _case_rows(
    broken: float, case: dict[str, Any], best_frontend: float, short_reference: float
) -> list[list[str]]:
    """Table rows of one case; each ATE gain is against the best front end on its frames."""
    rows = []
    for name, row in case.items():
        reference = short_reference if name.startswith("iSAM2") else best_frontend
        gain = 100.0 * (1.0 - row["ate_m"] / reference)
        timing = (
            f"{row['p50_ms']:.2f} / {row['p95_ms']:.2f} / {row['max_ms']:.1f} | "
            f"{row['first10pct_p50_ms']:.2f} -> {row['last10pct_p50_ms']:.2f}"
            if "p50_ms" in row
            else "- | -"
        )
        lost = row.get("statuses", {}).get("lost", 0)
        rows.append(
            [
                f"{broken:.0%}",
                name,
                f"{row['ate_m']:.3f}",
                f"{gain:+.0f} %",
                str(lost) if "statuses" in row else "-",
                timing,
            ]
        )
    return rows


def _simulated_table(args: argparse.Namespace, path: float, rows: list[list[str]]) -> str:
    """The Markdown table of all cases, titled with the run's length and seed."""
    return titled_table(
        f"Simulated: {args.frames} frames at 20 Hz, {path:.0f} m path, 200 Hz IMU "
        f"(seed {args.seed})",
        [
            "broken",
            "trajectory",
            "ATE m",
            "vs best front end",
            "lost",
            "back end ms p50 / p95 / max",
            "p50 first -> last 10 %",
        ],
        rows,
    )
