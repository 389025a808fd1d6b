"""``swarmvo run DATASET_DIR``: odometry over a whole EuRoC/KITTI sequence, with its metrics.

Writes ``trajectory.tum`` (left-camera poses, one line per input frame: the fused answer given
when the frame arrived, or the front end's without the back end), with the back end also
``trajectory_smoothed.tum`` (each frame's final estimate once the fixed-lag smoother has
finished with it), ``metrics.json`` (accuracy against ground truth when the dataset has it:
``fused``, ``smoothed`` and ``frontend`` sections; failures, per-stage median times) and
``trajectory.png`` into ``--out``, and the odometry in the robotics convention
(``estimator.formats.odometry_msg``): ``odometry.jsonl`` (one nav_msgs/Odometry-like JSON object per
frame) and ``odometry.tum`` (base_link in odom). ``DATASET`` may also be a ROS 1 ``.bag`` or a
ROS 2 bag folder (``--calibration`` and the topic flags; ``estimator.formats.rosbag_io``), and
``--export-bag`` writes the result as a bag (``estimator.formats.rosbag_write``). For KITTI input
it also writes ``kitti/<sequence>.txt``, the poses in KITTI's format. Before the run it derives
the frontend settings that follow from the rig and the frame rate (estimator/rig_settings.py)
and prints them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from estimator.cli.results_table import results_table
from estimator.evaluation.metrics import path_length
from estimator.formats.datasets import Sequence, open_sequence
from estimator.formats.folders import writable_folder
from estimator.pipeline import (
    ESTIMATORS,
    build_config,
    frame_interval_s,
    kitti_poses_path,
    load_config,
    run_sequence,
    write_odometry,
    write_outputs,
)
from estimator.registration.methods import DEFAULT_ESTIMATOR
from estimator.rig_settings import apply_rig_settings, format_settings

DESCRIPTION = """\
Run the odometry over a recorded stereo sequence (EuRoC folder with mav0/, KITTI sequence,
or a ROS 1 .bag / ROS 2 bag folder) and write the trajectory. The IMU is fused when the
dataset has one. At the end a results table: frames tracked / coasted / lost, path length,
ATE and RPE against the ground truth when the dataset has it, and the speed."""

EPILOG = """\
outputs (in --out, default runs/<sequence>):
  trajectory.tum            left-camera pose of every frame, as answered when it arrived
  trajectory_smoothed.tum   each frame's final estimate from the smoother (back end on)
  metrics.json              accuracy against ground truth, failures, stage times
  trajectory.png            top view against the ground truth
  odometry.jsonl / .tum     the odometry in the robotics convention (base_link in odom)

examples:
  swarmvo run ../shared/data/euroc_mh01_moving
  swarmvo run ../shared/data/euroc_mh01_moving --no-imu --out runs/vision-only
  swarmvo run recording.bag --calibration camchain.yaml"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dataset",
        type=Path,
        help="EuRoC (folder with mav0) or KITTI sequence, or a ROS 1 .bag / ROS 2 bag folder",
    )
    parser.add_argument("--format", choices=("euroc", "kitti"), help="default: detected")
    parser.add_argument(
        "--config",
        type=Path,
        help="SwarmvoConfig as JSON or YAML (the flags below override its fields)",
    )
    parser.add_argument(
        "--estimator",
        choices=ESTIMATORS,
        help=f"registration method (default: {DEFAULT_ESTIMATOR})",
    )
    parser.add_argument("--seed", type=int, help="default: 0")
    parser.add_argument("--out", type=Path, help="output folder (default: runs/<sequence>)")
    parser.add_argument("--limit", type=int, help="process only the first N frames")
    parser.add_argument(
        "--imu",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="feed the IMU to the back end when the dataset has one (default: yes)",
    )
    parser.add_argument(
        "--backend",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="fuse in the GTSAM back end (default: yes); --no-backend = front end only",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument(
        "--strict",
        action="store_true",
        help="stop at a missing or corrupt image (default: skip the frame with a warning)",
    )
    _add_bag_arguments(parser.add_argument_group("ROS bags"))


def _add_bag_arguments(bags: argparse._ArgumentGroup) -> None:
    """Calibration, topics and stereo pairing of a bag input, and the bag output."""
    bags.add_argument(
        "--calibration",
        type=Path,
        help="for a bag: EuRoC folder (cam0/cam1 sensor.yaml), Kalibr camchain YAML or rig file",
    )
    bags.add_argument("--left-topic", help="left images (default: guessed)")
    bags.add_argument("--right-topic", help="right images (default: guessed)")
    bags.add_argument("--imu-topic", help="sensor_msgs/Imu (default: the bag's only one)")
    bags.add_argument(
        "--stereo-sync-tolerance",
        type=float,
        metavar="MS",
        help="bags and EuRoC folders: pair left/right images whose stamps are nearest each "
        "other and at most MS milliseconds apart (default: a tenth of the frame period; 0 = "
        "equal stamps only); others are dropped with one warning",
    )
    bags.add_argument(
        "--export-bag",
        type=Path,
        help="also write the result as a bag: PATH.bag = ROS 1, else a ROS 2 folder",
    )
    bags.add_argument(
        "--export-storage",
        choices=("sqlite3", "mcap"),
        help="storage of a ROS 2 --export-bag (default: sqlite3)",
    )


def open_input(args: argparse.Namespace) -> Sequence:
    """The dataset folder, or a bag with its calibration and topics."""
    from estimator.formats.rosbag_io import is_bag

    tolerance_ms = args.stereo_sync_tolerance
    if tolerance_ms is not None and not tolerance_ms >= 0:
        raise ValueError(f"--stereo-sync-tolerance must be >= 0 ms, got {tolerance_ms}")
    tolerance = None if tolerance_ms is None else round(tolerance_ms * 1e6)
    if not is_bag(args.dataset):
        if args.calibration is not None:
            raise ValueError("--calibration is for bags; a dataset folder has its own")
        for flag in ("left_topic", "right_topic", "imu_topic"):
            if getattr(args, flag) is not None:
                raise ValueError(f"--{flag.replace('_', '-')} is for bags, not a dataset folder")
        return open_sequence(args.dataset, args.format, tolerance)
    from estimator.formats.bag_calibration import load_bag_calibration
    from estimator.formats.rosbag_io import open_bag

    if args.calibration is None:
        raise ValueError(
            "a bag needs --calibration: a EuRoC folder with cam0/cam1 sensor.yaml, a Kalibr "
            "camchain YAML or a rig JSON/YAML"
        )
    calibration = load_bag_calibration(args.calibration)
    return open_bag(
        args.dataset, calibration, args.left_topic, args.right_topic, args.imu_topic, tolerance
    )


def _check_writable(out: Path, bag: Path | None) -> None:
    """The output folder (and the bag's) take files: a run is not computed to be lost at the
    end for a mistyped or read-only path."""
    for folder in (out, *([bag.parent] if bag is not None else [])):
        writable_folder(folder)


def run(args: argparse.Namespace) -> int:
    if args.limit is not None and args.limit < 2:  # before the dataset is read
        raise ValueError(f"--limit must be at least 2 frames, got {args.limit}")
    if args.imu and args.backend is False:
        raise ValueError("--imu needs the back end (the IMU is fused there); drop --no-backend")
    if args.config is not None and not args.config.is_file():
        raise FileNotFoundError(f"config file not found: {args.config}")
    if args.export_bag is not None and args.export_bag.exists():
        raise ValueError(f"{args.export_bag} exists already; choose a new bag path")
    if args.export_storage is not None and args.export_bag is None:
        raise ValueError("--export-storage needs --export-bag")
    sequence = open_input(args)
    interval = frame_interval_s(sequence)
    # Read once the frame period is known: old keys counted in frames are converted with it.
    base = load_config(args.config, interval) if args.config is not None else None
    config = build_config(args.estimator, args.seed, args.imu, args.backend, base)
    config, derived = apply_rig_settings(config, sequence.rig, interval)
    print(format_settings(sequence.rig, interval, derived), flush=True)
    out = args.out if args.out is not None else Path("runs") / sequence.name
    _check_writable(out, args.export_bag)
    try:
        result = run_sequence(
            sequence,
            config,
            args.limit,
            config.backend.use_imu,
            progress=not args.quiet,
            strict=args.strict,
            rig_settings=False,
        )
    finally:
        getattr(sequence, "close", lambda: None)()  # a bag stops streaming
    result.derived = derived
    summary = write_outputs(result, out)
    write_odometry(result, out, args.export_bag, args.export_storage or "sqlite3")
    print(results_table(summary, path_length(result.poses())))
    measured = result.stereo_timing.get("measured_ms")
    if measured is not None:
        print(
            f"warning: the right shutter runs {measured:+.1f} ms after the left (measured from "
            f"the stereo rows, +-{result.stereo_timing['standard_error_ms']:.2f}); cameras "
            f"without a shared trigger cost depth accuracy: set "
            f"frontend.stereo_time_offset_ms: {measured:.1f} to undo it"
        )
    offset = result.disparity_offset
    if offset.get("measured") and offset.get("applied_px"):
        error = offset.get("standard_error_px")
        spread = "" if error is None else f", +-{error:.3f}"
        print(
            f"note: every disparity was {offset['applied_px']:+.2f} px off (measured from the "
            f"motion{spread}) and that was taken out; the stereo calibration is slightly off "
            f"(the right camera's principal point or yaw)"
        )
    kitti_path = kitti_poses_path(result, out)
    print(
        f"wrote {out / 'trajectory.tum'}, {out / 'metrics.json'}, {out / 'trajectory.png'}"
        + (f", {out / 'trajectory_smoothed.tum'}" if config.backend.enabled else "")
        + f", {out / 'odometry.jsonl'}, {out / 'odometry.tum'}"
        + (f", {args.export_bag}" if args.export_bag is not None else "")
        + (f", {kitti_path}" if kitti_path is not None else "")
    )
    return 0
