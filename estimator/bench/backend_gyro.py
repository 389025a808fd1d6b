"""``swarmvo bench backend``, part ``gyro``: the real EuRoC V1_02 gyro against ground truth.

Preintegrated rotation over 20 Hz steps with the ground-truth gyro bias and with none; then the
graph with vision-like noisy relative poses estimating the bias online.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimator.backend import FusionBackend
from estimator.backend.imu import preintegrate_gyro, rotation_params
from estimator.bench.markdown import titled_table
from estimator.config import BackendConfig
from estimator.geometry import rotation_angle_deg
from estimator.rendered.scenario import FrontendMeasurement, simulate_frontend
from estimator.types import ImuBatch, ImuNoise

if TYPE_CHECKING:
    import gtsam

__all__ = ["bench_gyro"]


def _euroc_20hz(root: Path):
    from estimator.formats.datasets import (
        read_euroc_ground_truth,
        read_euroc_imu,
        read_euroc_imu_noise,
    )

    imu = read_euroc_imu(root / "mav0/imu0/data.csv")
    truth = read_euroc_ground_truth(root / "mav0/state_groundtruth_estimate0/data.csv")
    noise = read_euroc_imu_noise(root / "mav0/imu0/sensor.yaml")
    inside = np.flatnonzero(
        (truth.timestamps_ns >= imu.timestamps_ns[0] + 100_000_000)
        & (truth.timestamps_ns <= imu.timestamps_ns[-1])
    )
    buckets = truth.timestamps_ns[inside] // 50_000_000
    rows = inside[np.concatenate([[True], np.diff(buckets) > 0])]
    return imu, noise, truth.timestamps_ns[rows], truth.poses[rows], truth.gyro_bias[rows]


def bench_gyro(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """Per-step rotation error of preintegration, vision-like poses and the graph; JSON, table."""
    if not (args.euroc_imu / "mav0").is_dir():
        return {"skipped": f"{args.euroc_imu} not found"}, "gyro: skipped (no data)\n"
    imu, noise, stamps, poses, bias = _euroc_20hz(args.euroc_imu)
    truth_steps = np.swapaxes(poses[:-1, :3, :3], 1, 2) @ poses[1:, :3, :3]
    params = rotation_params(noise)
    rows: dict[str, dict[str, float]] = {}
    for name, biases in (("gyro, ground-truth bias", bias), ("gyro, zero bias", None)):
        errors = _preintegration_errors(imu, params, stamps, truth_steps, biases)
        rows[name] = _rms_max(errors)
    # Online bias: the graph with the real gyro and vision-like noisy relative poses.
    measurements = simulate_frontend(poses, np.eye(4), seed=args.seed)
    fused_poses, estimates, increments = _run_graph(imu, noise, stamps, measurements)
    fused_steps = np.swapaxes(fused_poses[:-1, :3, :3], 1, 2) @ fused_poses[1:, :3, :3]
    vision = np.stack([m.relative_pose[:3, :3] for m in measurements[1:]])
    rows["vision-like relative poses alone"] = _rms_max(_step_errors(vision, truth_steps))
    rows["graph (bias online): consecutive output poses"] = _rms_max(
        _step_errors(fused_steps, truth_steps)
    )
    rows["graph (bias online): motion X_k-1 -> X_k solved at frame k"] = _rms_max(
        _step_errors(np.stack(increments), truth_steps)
    )
    result = _gyro_result(stamps, rows, bias, estimates)
    return result, _gyro_table(result, rows)


def _preintegration_errors(
    imu: ImuBatch,
    params: gtsam.PreintegratedRotationParams,
    stamps: np.ndarray,
    truth_steps: np.ndarray,
    biases: np.ndarray | None,
) -> np.ndarray:
    """Angle (deg) between the preintegrated gyro rotation and the truth at every step."""
    errors = []
    for k in range(len(stamps) - 1):
        pre = preintegrate_gyro(
            imu.timestamps_ns,
            imu.gyro,
            stamps[k],
            stamps[k + 1],
            params,
            None if biases is None else biases[k],
        )
        errors.append(rotation_angle_deg(pre.delta_rotation.T @ truth_steps[k]))
    return np.asarray(errors)


def _run_graph(
    imu: ImuBatch, noise: ImuNoise, stamps: np.ndarray, measurements: list[FrontendMeasurement]
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Feed the back end frame by frame; its body poses, gyro biases and solved rotations.

    The rotations are the motion X_k-1 -> X_k as solved when frame k arrives, before later
    frames smooth it: what a live consumer of the odometry gets.
    """
    backend = FusionBackend(BackendConfig(), np.eye(4), noise)
    fused, estimates, increments = [], [], []
    for k, stamp in enumerate(stamps):
        start = stamps[k - 1] if k else stamp - 100_000_000
        out = backend.add_frame(
            int(stamp),
            None if k == 0 else measurements[k].relative_pose,
            measurements[k].residuals,
            measurements[k].inlier_count,
            imu.between(int(start), int(stamp)),
        )
        fused.append(out.body_pose)
        estimates.append(out.gyro_bias)
        if out.body_motion is not None:
            increments.append(out.body_motion[:3, :3])
    return np.stack(fused), np.stack(estimates), increments


def _step_errors(rotations: np.ndarray, truth_steps: np.ndarray) -> np.ndarray:
    """Angle (deg) between each estimated per-step rotation and the true one."""
    return rotation_angle_deg(np.swapaxes(rotations, 1, 2) @ truth_steps)


def _rms_max(errors: np.ndarray) -> dict[str, float]:
    """RMS and worst of per-step angle errors, the two numbers each table row shows."""
    return {"rms_deg": float(np.sqrt(np.mean(errors**2))), "max_deg": float(errors.max())}


def _gyro_result(
    stamps: np.ndarray,
    rows: dict[str, dict[str, float]],
    bias: np.ndarray,
    estimates: np.ndarray,
) -> dict[str, Any]:
    """The JSON of the part: per-step rotation errors and how the online bias converged."""
    bias_error = np.linalg.norm(estimates - bias, axis=1)
    half = len(bias_error) // 2
    return {
        "steps": len(stamps) - 1,
        "duration_s": float((stamps[-1] - stamps[0]) * 1e-9),
        "rotation_per_step": rows,
        "bias_error_final_rad_s": float(bias_error[-1]),
        "bias_error_mean_second_half_rad_s": float(bias_error[half:].mean()),
        "bias_true_final_rad_s": bias[-1].tolist(),
        "bias_estimated_final_rad_s": estimates[-1].tolist(),
        "bias_error_initial_rad_s": float(np.linalg.norm(bias[0])),
    }


def _gyro_table(result: dict[str, Any], rows: dict[str, dict[str, float]]) -> str:
    """The Markdown table of the rotation errors, then one line on the bias estimate."""
    table = titled_table(
        f"Real gyro, EuRoC V1_02 ({result['steps']} steps of 50 ms, {result['duration_s']:.0f} s)",
        ["relative rotation per 20 Hz step", "RMS deg", "max deg"],
        [[name, f"{row['rms_deg']:.4f}", f"{row['max_deg']:.4f}"] for name, row in rows.items()],
    )
    return table + (
        f"\nOnline gyro bias (starts at 0; true |b| = {result['bias_error_initial_rad_s']:.4f} "
        f"rad/s): final error {result['bias_error_final_rad_s']:.4f} rad/s, mean over the "
        f"second half {result['bias_error_mean_second_half_rad_s']:.4f} rad/s.\n"
    )
