"""The library API the apps share: a sequence in, a run's poses, metrics and files out.

``run_sequence`` feeds every frame of a :class:`~estimator.formats.datasets.Sequence` (and the
IMU samples since the previous frame) through :class:`~estimator.odometry.Odometry`;
``summarize`` scores the run against the ground truth; ``write_outputs`` and ``write_odometry``
write ``trajectory.tum``, ``trajectory_smoothed.tum``, ``metrics.json``, ``trajectory.png``,
``odometry.jsonl`` / ``odometry.tum`` and, for KITTI input, ``kitti/<sequence>.txt``.
``swarmvo run``, the benchmarks and the service's replay build on these.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
from pydantic import ValidationError
from tqdm import tqdm

from estimator.config import FRAME_INTERVAL_CONTEXT, SwarmvoConfig, explain_validation_error
from estimator.evaluation.metrics import TrajectoryEvaluation, evaluate_trajectory
from estimator.formats.datasets import GroundTruth, Sequence, UnreadableImageError
from estimator.registration.methods import Estimator
from estimator.rig_settings import (
    DerivedSetting,
    apply_rig_settings,
    backend_with_calibration_gains,
)
from estimator.types import FrameReport, FrameStatus

if TYPE_CHECKING:
    from estimator.backend.recording import BackendObserver
    from estimator.formats.odometry_msg import OdometryMessage
    from estimator.odometry.observation import MeasurementObserver

# The --estimator choices: every registered estimator, the default first.
ESTIMATORS: tuple[str, ...] = tuple(name.value for name in Estimator)
# IMU samples fed with the first frame: those of this window before it, from which the back end
# gravity-aligns its world (the API replay client sends the same window).
FIRST_FRAME_IMU_WINDOW_NS = 100_000_000


def _yaml_problem(error: yaml.YAMLError) -> str:
    """PyYAML's several-line message as one line: the problem and where it is in the file."""
    problem = getattr(error, "problem", None)
    mark = getattr(error, "problem_mark", None)
    if problem is None:
        return " ".join(str(error).split())
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    context = getattr(error, "context", None)
    return f"{problem}{where}" + (f" ({context})" if context else "")


def load_config(path: Path, frame_interval_s: float | None = None) -> SwarmvoConfig:
    """SwarmvoConfig from a JSON or YAML file (a clear error for unknown or invalid fields).

    ``frame_interval_s``: the input's frame period when known, for old keys counted in frames.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())  # YAML is a superset of JSON
    except yaml.YAMLError as error:
        raise ValueError(f"{path} is not valid JSON/YAML: {_yaml_problem(error)}") from None
    try:
        context = {FRAME_INTERVAL_CONTEXT: frame_interval_s}
        return SwarmvoConfig.model_validate(data or {}, context=context)
    except ValidationError as error:
        problems = explain_validation_error(error)
        raise ValueError(f"{path}: invalid configuration: {problems}") from None


@dataclass
class RunResult:
    sequence: Sequence
    config: SwarmvoConfig
    reports: list[FrameReport]
    wall_time_s: float
    # Final smoothed pose per frame timestamp (back end only; see FrameReport.final_poses).
    smoothed: dict[int, np.ndarray] = field(default_factory=dict)
    # Timestamps of the frames skipped because an image could not be read.
    skipped_ns: list[int] = field(default_factory=list)
    # Settings derived from the rig and frame rate (config holds the values used).
    derived: list[DerivedSetting] = field(default_factory=list)
    # The session's estimated stereo noise level and how well it fits (stereo_noise.py).
    noise: dict[str, Any] = field(default_factory=dict)
    # The right shutter's offset: configured, fitted, measured (frontend/shutter_offset.py).
    stereo_timing: dict[str, Any] = field(default_factory=dict)
    # The disparity offset: measured, in use (frontend/disparity_offset.py).
    disparity_offset: dict[str, Any] = field(default_factory=dict)
    # Times the front end went back to an older keyframe (odometry/revisits.py); None: off.
    keyframe_revisits: int | None = None

    @property
    def timestamps_ns(self) -> np.ndarray:
        return np.array([r.timestamp_ns for r in self.reports], dtype=np.int64)

    def poses(self, which: str = "pose") -> np.ndarray:
        """(N, 4, 4) per frame: ``pose`` (fused online answer, or the front end's without the
        back end), ``frontend_pose``, or ``smoothed`` (the back end's final estimates)."""
        if which == "smoothed":
            if len(self.smoothed) != len(self.reports):
                raise ValueError("no smoothed trajectory: the back end did not run")
            return np.array([self.smoothed[r.timestamp_ns] for r in self.reports])
        return np.array([getattr(r, which) for r in self.reports]).reshape(-1, 4, 4)


def build_config(
    estimator: str | None = None,
    seed: int | None = None,
    imu: bool | None = None,
    backend: bool | None = None,
    base: SwarmvoConfig | None = None,
) -> SwarmvoConfig:
    """``base`` (or the defaults) with the given fields overridden; None keeps the base value.

    Only the fields the user set are carried over, so that settings derived from the rig
    (estimator/rig_settings.py) can still tell a default from a configured value.
    """
    data = (base or SwarmvoConfig()).model_dump(exclude_unset=True)
    if estimator is not None:
        data.setdefault("registration", {})["method"] = estimator
    if seed is not None:
        data["seed"] = seed
    if backend is not None:
        data.setdefault("backend", {})["enabled"] = backend
    if imu is not None:
        data.setdefault("backend", {})["use_imu"] = imu
    try:
        return SwarmvoConfig.model_validate(data)
    except ValidationError as error:  # a flag's value (--seed -1): one plain line
        raise ValueError(f"invalid configuration: {explain_validation_error(error)}") from None


def run_sequence(
    sequence: Sequence,
    config: SwarmvoConfig,
    limit: int | None = None,
    use_imu: bool = True,
    progress: bool = False,
    strict: bool = False,
    rig_settings: bool = True,
    observer: MeasurementObserver | None = None,
    backend_observer: BackendObserver | None = None,
) -> RunResult:
    """Feed every frame (and the IMU samples since the previous frame) through ``Odometry``.

    The first frame gets the samples of ``FIRST_FRAME_IMU_WINDOW_NS`` before it, so that the
    back end can level its world with gravity. A frame whose image cannot be read is skipped
    with a warning (its IMU samples go to the next frame) unless ``strict``. With
    ``rig_settings`` the settings that follow from the rig and the frame rate are
    derived first (explicitly set values win). ``observer`` sees every measurement the
    frames make (``estimator/odometry/observation.py``), ``backend_observer`` everything the
    back end is given (``estimator/backend/recording.py``).
    """
    from estimator.odometry import Odometry  # the pipeline loads only when a run starts

    if limit is not None and limit < 2:
        raise ValueError(f"--limit must be at least 2 frames, got {limit}")
    derived: list[DerivedSetting] = []
    if rig_settings:
        config, derived = apply_rig_settings(config, sequence.rig, frame_interval_s(sequence))
    count = len(sequence) if limit is None else min(limit, len(sequence))
    skipped_ns = _missing_pairs(sequence, count, strict)
    imu_available = use_imu and sequence.imu is not None
    odometry = Odometry(
        sequence.rig,
        config,
        imu_noise=sequence.imu_noise if imu_available else None,
        observer=observer,
        backend_observer=backend_observer,
    )
    reports: list[FrameReport] = []
    previous_ns: int | None = None
    start = time.perf_counter()
    for index in tqdm(range(count), desc=sequence.name, unit="frame", disable=not progress):
        try:
            frame = sequence.load(index)
        except UnreadableImageError as error:
            if strict:
                raise
            warnings.warn(f"frame {index} skipped: {error}", stacklevel=1)
            skipped_ns.append(sequence.frames[index].timestamp_ns)
            continue
        imu = None
        if imu_available:
            start_ns = (
                previous_ns
                if previous_ns is not None
                else frame.timestamp_ns - FIRST_FRAME_IMU_WINDOW_NS
            )
            imu = sequence.imu_between(start_ns, frame.timestamp_ns)
        reports.append(odometry.process(frame, imu))
        previous_ns = frame.timestamp_ns
    smoothed = dict(pose for report in reports for pose in report.final_poses)
    smoothed.update(odometry.finish())
    elapsed = time.perf_counter() - start
    noise = odometry.noise.summary()
    skipped_ns.sort()
    timing = odometry.stereo_timing.summary()
    return RunResult(
        sequence, config, reports, elapsed, smoothed, skipped_ns, derived, noise, timing,
        odometry.disparity_offset.summary(), odometry.keyframe_revisits,
    )  # fmt: skip


def _missing_pairs(sequence: Sequence, count: int, strict: bool) -> list[int]:
    """Stamps of the pairs listed but without an image file, within the first ``count`` frames.

    They were left out when the sequence was opened (one warning line); a run counts them as
    skipped frames, as it does unreadable ones, or refuses them when ``strict``.
    """
    missing = list(sequence.missing_ns)
    if count < len(sequence):
        last_ns = sequence.frames[count - 1].timestamp_ns
        missing = [stamp for stamp in missing if stamp < last_ns]
    if missing and strict:
        raise UnreadableImageError(
            f"{len(missing)} stereo pair(s) listed without an image file (first at {missing[0]} ns)"
        )
    return missing


def frame_interval_s(sequence: Sequence) -> float | None:
    """Median time between frames (None for fewer than two frames)."""
    timestamps = sequence.timestamps_ns
    return float(np.median(np.diff(timestamps))) * 1e-9 if len(timestamps) > 1 else None


def _finite(value: Any) -> Any:
    """JSON-safe: NaN/inf become null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    return value


def summarize(
    result: RunResult, rpe_delta_m: float = 1.0
) -> tuple[dict[str, Any], dict[str, TrajectoryEvaluation]]:
    """metrics.json content and the evaluations behind it (empty without ground truth)."""
    reports = result.reports
    statuses = Counter(str(r.status) for r in reports)
    stages = sorted({stage for r in reports for stage in r.timings_s})
    medians = {
        stage: float(np.median([r.timings_s[stage] for r in reports if stage in r.timings_s]))
        for stage in stages
    }
    summary: dict[str, Any] = {
        "sequence": result.sequence.name,
        "format": result.sequence.format,
        "estimator": result.config.registration.method,
        "seed": result.config.seed,
        "backend": result.config.backend.enabled,
        "imu": (
            result.config.backend.enabled
            and result.config.backend.use_imu
            and result.sequence.imu is not None
        ),
        "frames": len(reports),
        "frames_skipped": len(result.skipped_ns),
        "frames_failed": len(reports) - statuses.get(str(FrameStatus.OK), 0),
        "status_counts": dict(statuses),
        "inliers_median": float(np.median([r.inliers for r in reports[1:]] or [0])),
        "matches_median": float(np.median([r.matches for r in reports[1:]] or [0])),
        "median_stage_time_s": medians,
        "wall_time_s": result.wall_time_s,
        "fps": len(reports) / result.wall_time_s if result.wall_time_s > 0 else None,
        "rig_settings": {
            f"{s.section}.{s.name}": {"value": s.value, "configured": s.overridden}
            for s in result.derived
        },
        "noise": result.noise or None,
        "stereo_time_offset": result.stereo_timing or None,
        "disparity_offset": result.disparity_offset or None,
        "keyframe_revisits": result.keyframe_revisits,
    }
    ground_truth = result.sequence.ground_truth
    if ground_truth is None:
        return _finite(summary), {}
    try:
        evaluations = _evaluations(result, ground_truth, rpe_delta_m)
    except ValueError as error:
        # E.g. ground truth that does not cover the frames: keep the run's outputs.
        summary["evaluation_error"] = str(error)
        return _finite(summary), {}
    main = evaluations["fused" if "fused" in evaluations else "frontend"]
    summary.update(main.metrics)
    summary["frames"] = len(reports)
    summary["frames_evaluated"] = main.metrics["frames"]
    if len(evaluations) > 1:
        for label, evaluation in evaluations.items():
            summary[label] = evaluation.metrics
    return _finite(summary), evaluations


def _evaluations(
    result: RunResult, ground_truth: GroundTruth, rpe_delta_m: float
) -> dict[str, TrajectoryEvaluation]:
    """The run's trajectories against the ground truth: the fused online answer, the
    smoother's final poses and the front end's, or the front end's alone without a back end."""
    sections = {"fused": "pose", "smoothed": "smoothed", "frontend": "frontend_pose"}
    if not result.config.backend.enabled:
        sections = {"frontend": "frontend_pose"}
    return {
        label: evaluate_trajectory(
            result.timestamps_ns,
            result.poses(attribute),
            ground_truth,
            result.sequence.rig.left.T_BS,
            rpe_delta_m,
        )
        for label, attribute in sections.items()
    }


def odometry_messages(result: RunResult, calibrated: bool = True) -> list[OdometryMessage]:
    """The run's answers as odometry messages; odom is levelled with the IMU samples before
    the first frame whenever the sequence has them (whatever the flags). ``calibrated``: with
    the covariance scale measured online (``OdometryBuilder``)."""
    from estimator.formats.odometry_msg import OdometryBuilder

    first_ns = result.reports[0].timestamp_ns
    first_imu = result.sequence.imu_between(first_ns - FIRST_FRAME_IMU_WINDOW_NS, first_ns)
    # A run without the rig settings applied still reports its rig's calibration error.
    backend = backend_with_calibration_gains(
        result.config.backend, result.sequence.rig, result.config.registration.use_point_sigmas
    )
    gyro = backend.enabled and backend.use_imu and result.sequence.imu is not None
    builder = OdometryBuilder(
        result.sequence.rig.left.T_BS,
        backend,
        first_imu.accel,
        calibrated=calibrated,
        gyro_calibrated=gyro and backend.covariance_scale != "off",
    )
    return [builder.build(report) for report in result.reports]


def write_odometry(
    result: RunResult, out: Path, export_bag: Path | None = None, storage: str = "sqlite3"
) -> None:
    """odometry.jsonl and odometry.tum, and the bag when asked for."""
    from estimator.formats.trajectory_io import write_tum

    messages = odometry_messages(result)
    with (out / "odometry.jsonl").open("w") as handle:
        for message in messages:
            handle.write(json.dumps(message.to_dict()) + "\n")
    write_tum(out / "odometry.tum", result.timestamps_ns, np.array([m.pose for m in messages]))
    if export_bag is not None:
        from estimator.formats.rosbag_write import write_odometry_bag

        camera = zip(result.timestamps_ns.tolist(), result.poses("pose"), strict=True)
        write_odometry_bag(export_bag, messages, camera, storage)  # type: ignore[arg-type]


def kitti_poses_path(result: RunResult, out: Path) -> Path | None:
    """Where a KITTI input's poses go in KITTI's format (``kitti/<sequence>.txt``), else None."""
    return (
        out / "kitti" / f"{result.sequence.name}.txt" if result.sequence.format == "kitti" else None
    )


def write_outputs(result: RunResult, out: Path) -> dict[str, Any]:
    from estimator.evaluation.plots import plot_run
    from estimator.formats.trajectory_io import write_kitti, write_tum
    from estimator.geometry import invert_pose

    out.mkdir(parents=True, exist_ok=True)
    summary, evaluations = summarize(result)
    write_tum(out / "trajectory.tum", result.timestamps_ns, result.poses("pose"))
    if result.config.backend.enabled:
        write_tum(out / "trajectory_smoothed.tum", result.timestamps_ns, result.poses("smoothed"))
    kitti_path = kitti_poses_path(result, out)
    if kitti_path is not None:
        # KITTI's devkit and evo read left-camera poses relative to the first frame, one per
        # image, as 12 numbers (the top 3x4 block, row-major).
        poses = result.poses("pose")
        kitti_path.parent.mkdir(exist_ok=True)
        write_kitti(kitti_path, invert_pose(poses[0]) @ poses)
    (out / "metrics.json").write_text(json.dumps(summary, indent=2) + "\n")
    plot_run(
        out / "trajectory.png",
        result.timestamps_ns,
        result.poses("pose"),
        np.array([r.inliers for r in result.reports]),
        evaluations,
        title=f"{result.sequence.name} - {result.config.registration.method}",
    )
    return summary
