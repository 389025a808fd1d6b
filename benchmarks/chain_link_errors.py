"""Rotation errors of the previous-frame chain's links against their covariance, by image motion.

Runs the sequence vision alone (``--imu``: with the IMU fused, as the rendered bench does) with
``frontend.fuse_previous_frame`` on and records, for every frame, the keyframe measurement and
the frame-to-frame link before they are combined: their rotation error against the ground truth,
the rotation variance their covariance claims and their image motion (median flow of the
inliers over the focal length). The excess of the squared error over the claimed variance,
fitted as (rate x motion)^2 per axis, is what ``frontend.chain_link_rotation_bias`` models.
Where the ground truth has its own noise (EuRoC) the fit is an upper bound.

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/chain_link_errors.py DATASET [--imu]

Prints a markdown table (nothing is written). The measurements before they are combined come
from the odometry's observer (``estimator/odometry/observation.py``).
"""

from __future__ import annotations

import numpy as np
from clip_args import clip_parser, open_clip

from estimator.evaluation.metrics import camera_ground_truth
from estimator.odometry import MeasurementKind, MeasurementObserver, ObservedMeasurement
from estimator.odometry.chains import pose_difference
from estimator.pipeline import build_config, run_sequence

# (kind, frame index, reference timestamp, T_ref_cur of the left camera, 6x6 covariance, motion)
Record = tuple[str, int, int, np.ndarray, np.ndarray, float]


def _recorder(focal_px: float, records: list[Record]) -> MeasurementObserver:
    """An observer that keeps every keyframe measurement and chain link, before combination."""

    def record(measured: ObservedMeasurement) -> None:
        if measured.kind is MeasurementKind.REGISTRATION:
            return
        pose, covariance = measured.camera_reference_from_current, measured.covariance
        if pose is None or covariance is None:
            return
        moved = measured.inlier_flow_px
        motion = float(np.median(moved)) / focal_px if len(moved) else np.nan
        reference_ns = int(measured.reference.timestamp_ns)
        records.append(
            (measured.kind.value, measured.index, reference_ns, pose, covariance, motion)
        )

    return record


def _rows(kind: str, errors: np.ndarray, claimed: np.ndarray, motion: np.ndarray) -> list[str]:
    """Per motion tercile and overall: error and claimed RMS (mdeg, norm over three axes) and
    the fitted rate (excess variance per axis over motion squared)."""
    rows = []
    order = np.argsort(motion)
    for label, part in [*(("tercile", p) for p in np.array_split(order, 3)), ("all", order)]:
        excess = (errors[part] - claimed[part]).sum() / 3.0
        rate = np.sign(excess) * np.sqrt(abs(excess) / (motion[part] ** 2).sum())
        rows.append(
            f"| {kind} | {label} {motion[part].min():.4f}-{motion[part].max():.4f} | "
            f"{len(part)} | {np.degrees(np.sqrt(errors[part].mean())) * 1e3:.1f} | "
            f"{np.degrees(np.sqrt(claimed[part].mean())) * 1e3:.1f} | {rate:.4f} |"
        )
    return rows


def main() -> int:
    parser = clip_parser(__doc__.splitlines()[0])
    parser.add_argument("--imu", action="store_true", help="fuse the IMU (the rendered bench)")
    args = parser.parse_args()
    sequence = open_clip(parser, args.dataset)
    assert sequence.ground_truth is not None
    config = build_config("pso-robust", args.seed, imu=args.imu, backend=True)
    config.frontend.fuse_previous_frame = True
    records: list[Record] = []
    observer = _recorder(sequence.rig.rectification.fx, records)
    run = run_sequence(sequence, config, use_imu=args.imu, progress=False, observer=observer)
    truth = camera_ground_truth(sequence.ground_truth, run.timestamps_ns, sequence.rig.left.T_BS)
    position = {int(stamp): n for n, stamp in enumerate(run.timestamps_ns)}
    frame = {report.index: n for n, report in enumerate(run.reports)}
    print("| measurement | motion (flow / f) | count | rot error mdeg RMS | claimed | rate |")
    print("|---|---|---|---|---|---|")
    for kind in ("link", "keyframe"):
        chosen = [r for r in records if r[0] == kind]
        errors, claimed, motion = (np.zeros(len(chosen)) for _ in range(3))
        for n, (_, index, reference_ns, pose, covariance, moved) in enumerate(chosen):
            current, reference = truth[frame[index]], truth[position[reference_ns]]
            xi = pose_difference(np.linalg.inv(reference) @ current, pose)
            errors[n], claimed[n], motion[n] = xi[:3] @ xi[:3], np.trace(covariance[:3, :3]), moved
        for row in _rows(kind, errors, claimed, motion):
            print(row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
