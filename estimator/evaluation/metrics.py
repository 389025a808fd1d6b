"""Trajectory accuracy against ground truth, computed with evo's library API.

Metrics (all on left-camera poses; ground-truth body poses become camera poses through
``T_W_cam = T_W_body @ T_BS`` and are interpolated at the camera timestamps):

- ``ate_rmse_m``: absolute trajectory error, RMSE of position differences after the SE(3)
  Umeyama alignment of the estimate onto the ground truth (rotation + translation, no scale;
  evo's ``align``, or the Kabsch fit when evo rejects degenerate, e.g. collinear, positions).
- ``rpe_trans_rmse_m`` / ``rpe_rot_rmse_deg``: relative pose error between consecutive frames
  (delta = 1 frame): RMSE of the translation norm and of the rotation angle of
  ``(G_i^-1 G_j)^-1 (E_i^-1 E_j)``.
- ``rpe_dist_*``: the same over pairs ``delta_m`` metres apart along the ground-truth path,
  translation as a percentage of delta (KITTI style) and rotation in deg per metre.
- ``eq20_rms``: rotation error e_R = ||I - R_gt R_est^T||_F per frame (eq. 20), with both
  trajectories expressed relative to their own first pose (so the unknown world frame of the
  estimate plays no role), and its RMS over frames. It equals 2 sqrt(2) |sin(angle / 2)|.
- ``final_drift_m`` / ``final_rot_drift_deg``: position and rotation error of the last frame,
  both trajectories relative to their first pose; ``final_drift_pct`` = final_drift_m / path
  length x 100, reported only when the ground-truth path is at least ``MIN_PATH_FOR_PCT_M``
  long (null otherwise: a percentage of a few centimetres of travel means nothing).
- ``kitti_trans_err_pct`` / ``kitti_rot_err_deg_per_100m``: the KITTI odometry benchmark's
  segment errors (its devkit's definition): from every 10th frame, the first frame more than
  L = 100, 200, ..., 800 m further along the ground-truth path ends a segment; the error of the
  segment's relative pose, translation norm / L and rotation angle / L, averaged over all
  segments (``kitti_by_length_m`` per L). Null when the path has no 100 m segment.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from evo.core import metrics
from evo.core.filters import FilterException
from evo.core.geometry import GeometryException
from evo.core.trajectory import PoseTrajectory3D

from estimator.formats.datasets import GroundTruth
from estimator.geometry import invert_pose, kabsch, make_pose, rotation_angle_deg

__all__ = [
    "KITTI_SEGMENT_LENGTHS_M",
    "MIN_PATH_FOR_PCT_M",
    "TrajectoryEvaluation",
    "camera_ground_truth",
    "eq20_errors",
    "evaluate_trajectory",
    "kitti_segment_errors",
    "path_length",
    "similarity_scale",
]

MIN_PATH_FOR_PCT_M = 1.0
KITTI_SEGMENT_LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
KITTI_STEP_FRAMES = 10


@dataclass
class TrajectoryEvaluation:
    """Per-frame errors and the summary metrics of one estimated trajectory."""

    timestamps_ns: np.ndarray  # (M,) frames that have ground truth
    estimate: np.ndarray  # (M, 4, 4) as given
    reference: np.ndarray  # (M, 4, 4) ground-truth camera poses
    aligned: np.ndarray  # (M, 4, 4) estimate after SE(3) alignment onto the reference
    ate_errors_m: np.ndarray  # (M,)
    rpe_trans_m: np.ndarray  # (M - 1,)
    rpe_rot_deg: np.ndarray  # (M - 1,)
    eq20: np.ndarray  # (M,)
    metrics: dict[str, Any] = field(default_factory=dict)


def camera_ground_truth(
    ground_truth: GroundTruth, timestamps_ns: np.ndarray, T_BS: np.ndarray
) -> np.ndarray:
    """Ground-truth camera-in-world poses at the given times (interpolated where needed)."""
    return ground_truth.interpolate(timestamps_ns) @ np.asarray(T_BS, dtype=float)


def path_length(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


def similarity_scale(
    timestamps_ns: np.ndarray, estimate: np.ndarray, reference: np.ndarray
) -> float:
    """Scale of the Sim(3) Umeyama fit of the estimate's positions onto the reference's (evo):
    above 1 when the estimated path is too short.

    A stereo rig's metric scale comes from its calibrated baseline (and focal length), which
    the ATE after an SE(3) alignment cannot tell apart from other errors; a scale away from 1
    in every run and every estimator points at the calibration, or at the reference.
    """
    aligned = _evo_trajectory(np.asarray(timestamps_ns), np.asarray(estimate))
    _, _, scale = aligned.align(
        _evo_trajectory(np.asarray(timestamps_ns), np.asarray(reference)), correct_scale=True
    )
    return float(scale)


def relative_to_first(poses: np.ndarray) -> np.ndarray:
    return invert_pose(poses[0]) @ poses


def eq20_errors(estimate: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """||I - R_gt R_est^T||_F per frame, both trajectories relative to their first pose."""
    r_est = relative_to_first(estimate)[:, :3, :3]
    r_gt = relative_to_first(reference)[:, :3, :3]
    product = r_gt @ np.swapaxes(r_est, -1, -2)
    return np.linalg.norm(np.eye(3) - product, axis=(-2, -1))


def kitti_segment_errors(
    estimate: np.ndarray,
    reference: np.ndarray,
    lengths_m: tuple[float, ...] = KITTI_SEGMENT_LENGTHS_M,
    step_frames: int = KITTI_STEP_FRAMES,
) -> dict[str, Any] | None:
    """KITTI's segment errors of ``estimate`` against ``reference`` poses (both (N, 4, 4)).

    Returns the mean translation error (% of segment length), the mean rotation error
    (deg per 100 m), the segment count and the same per length; None without any segment.
    """
    distance = np.concatenate(
        [[0.0], np.cumsum(np.linalg.norm(np.diff(reference[:, :3, 3], axis=0), axis=1))]
    )
    translation: dict[float, list[float]] = {length: [] for length in lengths_m}
    rotation: dict[float, list[float]] = {length: [] for length in lengths_m}
    for first in range(0, len(reference), step_frames):
        for length in lengths_m:
            beyond = np.flatnonzero(distance > distance[first] + length)
            if len(beyond) == 0:
                continue
            last = int(beyond[0])
            true_delta = invert_pose(reference[first]) @ reference[last]
            estimated_delta = invert_pose(estimate[first]) @ estimate[last]
            error = invert_pose(estimated_delta) @ true_delta
            translation[length].append(float(np.linalg.norm(error[:3, 3])) / length)
            rotation[length].append(float(np.radians(rotation_angle_deg(error[:3, :3]))) / length)
    all_t = [value for values in translation.values() for value in values]
    if not all_t:
        return None
    all_r = [value for values in rotation.values() for value in values]
    to_deg_per_100m = 180.0 / np.pi * 100.0
    return {
        "kitti_trans_err_pct": float(np.mean(all_t)) * 100.0,
        "kitti_rot_err_deg_per_100m": float(np.mean(all_r)) * to_deg_per_100m,
        "kitti_segments": len(all_t),
        "kitti_by_length_m": {
            f"{length:g}": {
                "trans_err_pct": float(np.mean(translation[length])) * 100.0,
                "rot_err_deg_per_100m": float(np.mean(rotation[length])) * to_deg_per_100m,
                "segments": len(translation[length]),
            }
            for length in lengths_m
            if translation[length]
        },
    }


def _evo_trajectory(timestamps_ns: np.ndarray, poses: np.ndarray) -> PoseTrajectory3D:
    seconds = (timestamps_ns - timestamps_ns[0]) * 1e-9  # relative: keeps float precision
    return PoseTrajectory3D(poses_se3=list(poses), timestamps=seconds)


def _aligned(
    estimate: PoseTrajectory3D, reference: PoseTrajectory3D
) -> tuple[PoseTrajectory3D, str]:
    """Estimate moved by the SE(3) Umeyama fit of its positions onto the reference.

    evo refuses rank-deficient position sets (a straight line, standing still); the least-
    squares fit is then not unique but still well defined, and the det-guarded Kabsch fit
    gives one minimiser, so the ATE stays defined for such runs.
    """
    aligned = copy.deepcopy(estimate)
    try:
        aligned.align(reference, correct_scale=False)
        return aligned, "umeyama"
    except GeometryException:
        rotation, translation = kabsch(estimate.positions_xyz, reference.positions_xyz)
        aligned.transform(make_pose(rotation, translation))
        return aligned, "kabsch (degenerate positions)"


def _rmse(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if len(values) else float("nan")


def _rpe(
    reference: PoseTrajectory3D,
    estimate: PoseTrajectory3D,
    relation: metrics.PoseRelation,
    delta: float,
    unit: metrics.Unit,
) -> np.ndarray:
    metric = metrics.RPE(relation, delta=delta, delta_unit=unit, pairs_from_reference=True)
    metric.process_data((reference, estimate))
    return np.asarray(metric.error, dtype=float)


def evaluate_trajectory(
    timestamps_ns: np.ndarray,
    poses: np.ndarray,
    ground_truth: GroundTruth,
    T_BS: np.ndarray | None = None,
    rpe_delta_m: float = 1.0,
) -> TrajectoryEvaluation:
    """Compare estimated left-camera poses (N, 4, 4) at ``timestamps_ns`` with ground truth.

    Frames outside the ground-truth time range are left out (counted in
    ``frames_without_gt``); at least two frames must remain.
    """
    timestamps_ns, poses, covered = _covered_frames(timestamps_ns, poses, ground_truth)
    estimate = poses[covered]
    timestamps_ns = timestamps_ns[covered]
    reference = camera_ground_truth(
        ground_truth, timestamps_ns, np.eye(4) if T_BS is None else T_BS
    )
    traj_ref = _evo_trajectory(timestamps_ns, reference)
    traj_est = _evo_trajectory(timestamps_ns, estimate)
    traj_aligned, alignment = _aligned(traj_est, traj_ref)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_aligned))
    ate_errors = np.asarray(ape.error, dtype=float)
    rpe = _relative_errors(traj_ref, traj_est, rpe_delta_m)
    eq20 = eq20_errors(estimate, reference)
    summary: dict[str, Any] = {
        "frames": len(timestamps_ns),
        "frames_without_gt": int((~covered).sum()),
        "alignment": alignment,
        **_error_summary(estimate, reference, ate_errors, rpe, eq20, rpe_delta_m),
    }
    summary.update(kitti_segment_errors(estimate, reference) or {})
    return TrajectoryEvaluation(
        timestamps_ns=timestamps_ns,
        estimate=estimate,
        reference=reference,
        aligned=np.array(traj_aligned.poses_se3),
        ate_errors_m=ate_errors,
        rpe_trans_m=rpe["trans"],
        rpe_rot_deg=rpe["rot"],
        eq20=eq20,
        metrics=summary,
    )


def _covered_frames(
    timestamps_ns: np.ndarray, poses: np.ndarray, ground_truth: GroundTruth
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inputs as arrays, checked, and which frames the ground truth covers (at least 2)."""
    timestamps_ns = np.asarray(timestamps_ns, dtype=np.int64)
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(timestamps_ns):
        raise ValueError(
            f"need (N, 4, 4) poses for N timestamps, got {poses.shape} for {len(timestamps_ns)}"
        )
    if not np.isfinite(poses).all():
        raise ValueError("estimated poses contain NaN or inf")
    covered = ground_truth.covers(timestamps_ns)
    if covered.sum() < 2:
        raise ValueError(
            f"only {int(covered.sum())} of {len(timestamps_ns)} frames fall inside the "
            "ground-truth time range; need at least 2 to evaluate"
        )
    return timestamps_ns, poses, covered


def _relative_errors(
    traj_ref: PoseTrajectory3D, traj_est: PoseTrajectory3D, rpe_delta_m: float
) -> dict[str, np.ndarray]:
    """RPE per frame ("trans", "rot") and per ``rpe_delta_m`` of path ("dist_trans",
    "dist_rot"; empty when the path is shorter than one delta)."""
    translation = metrics.PoseRelation.translation_part
    rotation = metrics.PoseRelation.rotation_angle_deg
    errors = {
        "trans": _rpe(traj_ref, traj_est, translation, 1, metrics.Unit.frames),
        "rot": _rpe(traj_ref, traj_est, rotation, 1, metrics.Unit.frames),
    }
    try:
        errors["dist_trans"] = _rpe(
            traj_ref, traj_est, translation, rpe_delta_m, metrics.Unit.meters
        )
        errors["dist_rot"] = _rpe(traj_ref, traj_est, rotation, rpe_delta_m, metrics.Unit.meters)
    except FilterException:
        errors["dist_trans"] = errors["dist_rot"] = np.zeros(0)
    return errors


def _error_summary(
    estimate: np.ndarray,
    reference: np.ndarray,
    ate_errors: np.ndarray,
    rpe: dict[str, np.ndarray],
    eq20: np.ndarray,
    rpe_delta_m: float,
) -> dict[str, Any]:
    """The error statistics of ``TrajectoryEvaluation.metrics`` (after the frame counts)."""
    length = path_length(reference)
    final = invert_pose(relative_to_first(reference)[-1]) @ relative_to_first(estimate)[-1]
    final_drift = float(np.linalg.norm(final[:3, 3]))
    dist_trans, dist_rot = rpe["dist_trans"], rpe["dist_rot"]
    long_enough = length >= MIN_PATH_FOR_PCT_M
    return {
        "path_length_m": length,
        "ate_rmse_m": _rmse(ate_errors),
        "ate_mean_m": float(ate_errors.mean()),
        "ate_max_m": float(ate_errors.max()),
        "rpe_trans_rmse_m": _rmse(rpe["trans"]),
        "rpe_rot_rmse_deg": _rmse(rpe["rot"]),
        "rpe_rot_max_deg": float(rpe["rot"].max()),
        "rpe_delta_m": rpe_delta_m,
        "rpe_dist_pairs": len(dist_trans),
        "rpe_dist_trans_pct": _rmse(dist_trans) / rpe_delta_m * 100 if len(dist_trans) else None,
        "rpe_dist_rot_deg_per_m": _rmse(dist_rot) / rpe_delta_m if len(dist_rot) else None,
        "eq20_rms": _rmse(eq20),
        "eq20_max": float(eq20.max()),
        "final_drift_m": final_drift,
        "final_rot_drift_deg": float(rotation_angle_deg(final[:3, :3])),
        "final_drift_pct": final_drift / length * 100 if long_enough else None,
        "ate_pct_of_path": _rmse(ate_errors) / length * 100 if long_enough else None,
        "kitti_trans_err_pct": None,
        "kitti_rot_err_deg_per_100m": None,
        "kitti_segments": 0,
    }
