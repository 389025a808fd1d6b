"""Does the refinement's covariance match its errors, and which errors can the residuals see?

Runs the front end alone (default configuration) over a sequence and, for every refined
measurement T_ref_cur, checks two covariances of the refinement (registration/refine.py): the
median-scaled inverse Hessian and the robust sandwich.

* against ground truth: NEES per DOF of each measurement with the covariance the frame report
  carries (with the back end's fit floor), once with each (``registration.refine_covariance``
  "median" and "sandwich-reported"; the poses are the same);
* without ground truth, split in halves: the inliers are split at random in two halves, each
  refined alone; if the per-point errors are independent, the difference of the two poses has
  the covariance Sigma_a + Sigma_b. An error common to every point of a frame (calibration,
  a shared disparity bias) cancels in that difference: a split-half NEES near 1 with a
  ground-truth NEES far above it says that the missing error is common to the frame.

    OMP_NUM_THREADS=1 python benchmarks/measurement_covariance.py SEQUENCE [--limit N]

Prints one markdown table row per covariance (2026-12-03: docs/frontend.md, "The covariance the
refinement hands on").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gtsam
import numpy as np
from clip_args import quiet_sequence

from estimator.config import SwarmvoConfig
from estimator.evaluation.consistency import measurement_nees
from estimator.geometry import invert_pose, make_pose
from estimator.odometry import MeasurementKind, MeasurementObserver, ObservedMeasurement
from estimator.pipeline import build_config, run_sequence
from estimator.registration.refine import RefinementResult, refine_pose_mahalanobis

MODELS = {"median-scaled": "covariance", "sandwich": "sandwich_covariance"}


def _nees(error: np.ndarray, covariance: np.ndarray) -> tuple[float, float, float]:
    """NEES per DOF of the whole error, of its rotation and of its translation."""
    return (
        float(error @ np.linalg.solve(covariance, error)) / 6.0,
        float(error[:3] @ np.linalg.solve(covariance[:3, :3], error[:3])) / 3.0,
        float(error[3:] @ np.linalg.solve(covariance[3:, 3:], error[3:])) / 3.0,
    )


def _split_half(pairs, inliers, point_covariances, pose, config, rng) -> list | None:
    """Both halves' refinements from the frame's pose; None when a half cannot be refined."""
    order = rng.permutation(np.flatnonzero(inliers))
    halves = (order[: len(order) // 2], order[len(order) // 2 :])
    current_cov, reference_cov = point_covariances
    results = []
    for half in halves:
        result = refine_pose_mahalanobis(
            pairs.current_points[half], pairs.reference_points[half], current_cov[half],
            reference_cov[half], pose[:3, :3], pose[:3, 3],
            robust_scale=config.registration.refine_robust_scale, sandwich=True,
        )  # fmt: skip
        if not result.success or result.sandwich_covariance is None:
            return None
        results.append(result)
    return results


def _difference(halves: list[RefinementResult]) -> np.ndarray:
    first, second = (make_pose(h.rotation, h.translation) for h in halves)
    return np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(invert_pose(first) @ second)))


def run(path: Path, limit: int | None) -> None:
    sequence = quiet_sequence(path)
    assert sequence.ground_truth is not None
    rng = np.random.default_rng(0)
    split: dict[str, list] = {name: [] for name in MODELS}

    def recording(config: SwarmvoConfig) -> MeasurementObserver:
        """The split-half check of both covariances on each refined registration."""

        def check(measured: ObservedMeasurement) -> None:
            if measured.kind is not MeasurementKind.REGISTRATION or measured.covariance is None:
                return
            pose, inliers, pairs = measured.reference_from_current, measured.inliers, measured.pairs
            assert pose is not None and inliers is not None
            halves = _split_half(pairs, inliers, measured.point_covariances, pose, config, rng)
            if inliers.sum() >= 40 and halves is not None:
                difference = _difference(halves)
                for name, key in MODELS.items():
                    total = getattr(halves[0], key) + getattr(halves[1], key)
                    split[name].append(_nees(difference, total))

        return check

    summaries = {}
    for name, setting in (("median-scaled", "median"), ("sandwich", "sandwich-reported")):
        base = SwarmvoConfig.model_validate({"registration": {"refine_covariance": setting}})
        config = build_config(backend=False, imu=False, base=base)
        observer = recording(config) if name == "sandwich" else None
        result = run_sequence(sequence, config, use_imu=False, limit=limit, observer=observer)
        check = measurement_nees(result.reports, sequence.ground_truth, sequence.rig.left.T_BS)
        summaries[name] = check.summary()
    # The split-half check of both covariances is recorded on one run (the same halves).
    rows = [(name, summaries[name], np.array(split[name]).reshape(-1, 3)) for name in MODELS]
    _report(path, rows)


def _report(path: Path, rows: list) -> None:
    """Per covariance: the ground-truth NEES as reported (floored) and the split-half NEES."""
    print(f"{path.name}: NEES per DOF (rotation, translation; median)")
    print("| covariance | against ground truth, as reported | split-half, no ground truth |")
    print("|---|---|---|")
    for name, summary, split in rows:
        truth = (f"{summary['mean_nees_per_dof']:.2f} ({summary['rotation_per_dof']:.2f}, "
                 f"{summary['translation_per_dof']:.2f}; {summary['median_nees_per_dof']:.2f}); "
                 f"{summary['windows']} measurements")
        halves = (f"{split[:, 0].mean():.2f} ({split[:, 1].mean():.2f}, {split[:, 2].mean():.2f};"
                  f" {np.median(split[:, 0]):.2f}); {len(split)} frames")
        print(f"| {name} | {truth} | {halves} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence", type=Path)
    parser.add_argument("--limit", type=int, default=None, help="first N frames only")
    args = parser.parse_args()
    if not args.sequence.is_dir():
        parser.error(f"no sequence at {args.sequence}")
    if args.limit is not None and args.limit < 2:
        parser.error("--limit must be at least 2 frames")
    run(args.sequence, args.limit)


if __name__ == "__main__":
    main()
