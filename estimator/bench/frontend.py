"""``swarmvo bench frontend``: per-stage speed of the odometry on real 752x480 EuRoC frames.

Frames are read into memory first, so the timings are the pipeline's (rectify, detect, stereo,
temporal, estimate, fuse) and not the disk's. OpenCV runs on one thread; start the command with
``OMP_NUM_THREADS=1`` so that NumPy's BLAS does too (the value is recorded in the JSON). When
the data has ground truth the same run also reports the drift against it.

The two real clips have their own speed targets on one core: 120 frames/s on the V1_01
standstill clip (the default data) and 100 on the moving MH_01 clip
(``--data ../shared/data/euroc_mh01_moving``); other data is held to 30 (``--target-fps``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from estimator.config import SwarmvoConfig
from estimator.odometry import Odometry
from estimator.pipeline import frame_interval_s
from estimator.rig_settings import DerivedSetting, apply_rig_settings, format_settings

__all__ = ["add_arguments", "bench_config", "command_config", "run", "summarise"]

DEFAULT_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "euroc_v101_micro"
STAGES = ("rectify", "detect", "stereo", "temporal", "estimate", "fuse", "total")
TARGET_FPS = 30.0
# Frames/s on one core that the real clips must reach (by folder name).
CLIP_TARGET_FPS = {"euroc_v101_micro": 120.0, "euroc_mh01_moving": 100.0}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="EuRoC/KITTI sequence")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/frontend"))
    parser.add_argument(
        "--method", default=None, help="registration method (default: the config's)"
    )
    parser.add_argument("--tracking", choices=("keyframe", "frame"), default=None)
    parser.add_argument("--temporal-matcher", choices=("descriptor", "klt"), default=None)
    parser.add_argument(
        "--mode", choices=("detect", "track"), default=None,
        help="front end: detect every frame or follow tracks (default: the config's)",
    )  # fmt: skip
    parser.add_argument(
        "--detector", choices=("orb", "fast-brief", "sift"), default=None,
        help="feature detector (default: the config's)",
    )  # fmt: skip
    parser.add_argument("--backend", action="store_true", help="include the GTSAM back end")
    parser.add_argument("--repeat", type=int, default=3, help="passes over the sequence")
    parser.add_argument("--frames", type=int, default=None, help="use only the first N frames")
    parser.add_argument(
        "--target-fps", type=float, default=None,
        help="frames/s to reach (default: 120 on V1_01, 100 on MH_01, 30 otherwise)",
    )  # fmt: skip
    parser.add_argument(
        "--no-rig-settings", dest="rig_settings", action="store_false",
        help="keep the configuration's defaults instead of deriving settings from the rig",
    )  # fmt: skip


def command_config(args: argparse.Namespace) -> SwarmvoConfig:
    """The defaults with the command line's overrides, only those marked as set by the user:
    the rig-derived settings (``bench_config``) then fill the rest, as in ``swarmvo run``."""
    frontend = {
        name: value
        for name, value in (
            ("tracking", args.tracking),
            ("temporal_matcher", args.temporal_matcher),
            ("mode", args.mode),
            ("detector", args.detector),
        )
        if value is not None
    }
    data: dict[str, Any] = {"backend": {"enabled": bool(args.backend)}}
    if frontend:
        data["frontend"] = frontend
    if args.method is not None:
        data["registration"] = {"method": args.method}
    return SwarmvoConfig.model_validate(data)


def bench_config(
    config: SwarmvoConfig, sequence: Any, rig_settings: bool = True
) -> tuple[SwarmvoConfig, list[DerivedSetting]]:
    """The configuration ``swarmvo run`` would use on ``sequence``: the rig-derived settings
    (estimator/rig_settings.py) where the user left the default."""
    if not rig_settings:
        return config, []
    return apply_rig_settings(config, sequence.rig, frame_interval_s(sequence))


def summarise(timings: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Median and 95th percentile per stage, in milliseconds."""
    table = {}
    for stage in STAGES:
        values = np.array([t.get(stage, 0.0) for t in timings]) * 1e3
        table[stage] = {
            "median_ms": float(np.median(values)),
            "p95_ms": float(np.percentile(values, 95)),
        }
    return table


def _drift(sequence, reports) -> dict[str, float] | None:
    from estimator.evaluation.metrics import camera_ground_truth, eq20_errors, relative_to_first
    from estimator.geometry import invert_pose, rotation_angle_deg

    if sequence.ground_truth is None:
        return None
    timestamps = np.array([r.timestamp_ns for r in reports], dtype=np.int64)
    covered = sequence.ground_truth.covers(timestamps)
    if covered.sum() < 2:
        return None
    truth = relative_to_first(
        camera_ground_truth(sequence.ground_truth, timestamps[covered], sequence.rig.left.T_BS)
    )
    result = {}
    for name in ("frontend_pose", "pose"):
        poses = relative_to_first(np.array([getattr(r, name) for r in reports])[covered])
        final = invert_pose(truth[-1]) @ poses[-1]
        result[f"{name}_final_translation_error_m"] = float(np.linalg.norm(final[:3, 3]))
        result[f"{name}_final_rotation_error_deg"] = float(rotation_angle_deg(final[:3, :3]))
        result[f"{name}_eq20_rms"] = float(np.sqrt(np.mean(eq20_errors(poses, truth) ** 2)))
    result["ground_truth_path_m"] = float(
        np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum()
    )
    result.update(_against_images(sequence, reports, covered, truth))
    return result


def _against_images(sequence, reports, covered: np.ndarray, truth: np.ndarray) -> dict:
    """Final attitude change measured from the raw left images alone
    (estimator.evaluation.image_reference).

    A referee independent of stereo, the estimator and the ground truth's sensors: where the
    ground truth and the images disagree, this says which one the estimate follows.
    """
    from estimator.evaluation.image_reference import image_rotations
    from estimator.geometry import invert_pose, rotation_angle_deg

    first, last = np.flatnonzero(covered)[[0, -1]]
    try:
        (images,) = image_rotations(
            sequence.load(first).left, [sequence.load(last).left], sequence.rig.left
        )
    except ValueError:  # the views no longer overlap: no image-only referee
        return {}
    result = {
        "images_final_rotation_deg": float(rotation_angle_deg(images.rotation)),
        "ground_truth_vs_images_final_rotation_deg": float(
            rotation_angle_deg(images.rotation.T @ truth[-1, :3, :3])
        ),
    }
    for name in ("frontend_pose", "pose"):
        pose = invert_pose(getattr(reports[first], name)) @ getattr(reports[last], name)
        result[f"{name}_vs_images_final_rotation_deg"] = float(
            rotation_angle_deg(images.rotation.T @ pose[:3, :3])
        )
    return result


def _check_args(args: argparse.Namespace) -> None:
    """Refuse counts the timing loop cannot use, before any frame is read."""
    if args.repeat < 1:
        raise ValueError(f"--repeat must be >= 1, got {args.repeat}")
    if args.target_fps is not None and args.target_fps <= 0:
        raise ValueError(f"--target-fps must be > 0, got {args.target_fps}")


def _load_clip(args: argparse.Namespace) -> tuple[Any, list, list, float]:
    """The sequence, its frames and each frame's IMU samples, all in memory, and the load
    time: the timed loop then measures the pipeline and not the disk."""
    from estimator.formats.datasets import open_sequence

    sequence = open_sequence(args.data)
    count = len(sequence) if args.frames is None else min(args.frames, len(sequence))
    if count < 2:
        raise ValueError(f"need at least 2 frames, {args.data} gives {count}")
    start = time.perf_counter()
    frames = [sequence.load(i) for i in range(count)]
    load_s = time.perf_counter() - start
    imu = [
        sequence.imu_between(
            frames[i - 1].timestamp_ns if i else frames[0].timestamp_ns - 50_000_000,
            frames[i].timestamp_ns,
        )
        for i in range(count)
    ]
    return sequence, frames, imu, load_s


@dataclass
class _TimedRuns:
    """What the timed passes measured; ``reports`` are the last pass's."""

    timings: list[dict[str, float]] = field(default_factory=list)
    cpu_ms: list[float] = field(default_factory=list)
    walls: list[float] = field(default_factory=list)
    reports: list = field(default_factory=list)


def _timed_runs(
    sequence, config: SwarmvoConfig, frames: list, imu: list, repeat: int
) -> _TimedRuns:
    """``repeat`` passes of a fresh odometry over the frames, after a short warm-up."""
    # Warm-up: JIT compilation and first-call allocations are not the steady state.
    warmup = Odometry(sequence.rig, config, imu_noise=sequence.imu_noise)
    for frame, batch in zip(frames[:3], imu[:3], strict=True):
        warmup.process(frame, batch)

    runs = _TimedRuns()
    for _ in range(repeat):
        odometry = Odometry(sequence.rig, config, imu_noise=sequence.imu_noise)
        reports = []
        wall = time.perf_counter()
        for index, (frame, batch) in enumerate(zip(frames, imu, strict=True)):
            cpu = time.process_time()
            reports.append(odometry.process(frame, batch))
            if index:  # frame 0 has no estimate
                runs.cpu_ms.append((time.process_time() - cpu) * 1e3)
        runs.walls.append(time.perf_counter() - wall)
        runs.timings.extend(report.timings_s for report in reports[1:])
        runs.reports = reports
    return runs


def _speed(runs: _TimedRuns, count: int, target: float) -> dict[str, Any]:
    """Per-stage table and frames/s by three measures, against the clip's target."""
    table = summarise(runs.timings)
    fps_median = 1e3 / table["total"]["median_ms"]
    fps_wall = count / float(np.median(runs.walls))
    # CPU time is what one quiet core would need; wall time also counts waiting for a core
    # on a shared machine.
    fps_cpu = 1e3 / float(np.median(runs.cpu_ms))
    return {
        "stages": table,
        "fps_from_median_total": fps_median,
        "fps_wall_clock": fps_wall,
        "cpu_ms_per_frame": {
            "median": float(np.median(runs.cpu_ms)),
            "p95": float(np.percentile(runs.cpu_ms, 95)),
        },
        "fps_from_cpu_time": fps_cpu,
        "target_fps": target,
        "meets_target_wall": bool(fps_median >= target),
        "meets_target_cpu": bool(fps_cpu >= target),
    }


def _environment() -> dict[str, Any]:
    """Threads, versions and load: what a reader needs to compare two result files."""
    return {
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"),
        "opencv_threads": cv2.getNumThreads(),
        "opencv": cv2.__version__,
        "numpy": np.__version__,
        "machine": platform.machine(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def run(args: argparse.Namespace) -> int:
    """Time the odometry per stage on a clip held in memory; write frontend.json and .md."""
    _check_args(args)
    cv2.setNumThreads(1)
    sequence, frames, imu, load_s = _load_clip(args)
    config, derived = bench_config(command_config(args), sequence, args.rig_settings)
    if derived:
        print(format_settings(sequence.rig, frame_interval_s(sequence), derived))
    count = len(frames)
    runs = _timed_runs(sequence, config, frames, imu, args.repeat)
    reports = runs.reports
    target = args.target_fps or CLIP_TARGET_FPS.get(Path(args.data).resolve().name, TARGET_FPS)
    statuses = {str(s): sum(r.status == s for r in reports) for s in {r.status for r in reports}}
    result = {
        "data": str(args.data),
        "frames": count,
        "image_size": list(sequence.rig.size),
        "repeat": args.repeat,
        "config": config.model_dump(),
        "derived_settings": [
            {"name": f"{d.section}.{d.name}", "value": d.value, "overridden": d.overridden}
            for d in derived
        ],
        **_speed(runs, count, target),
        "median_matches": float(np.median([r.matches for r in reports[1:]])),
        "median_inliers": float(np.median([r.inliers for r in reports[1:]])),
        "status_counts": statuses,
        "drift": _drift(sequence, reports),
        "image_load_s": load_s,
        "environment": _environment(),
    }
    text = _markdown(result)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "frontend.json").write_text(json.dumps(result, indent=2) + "\n")
    (args.out / "frontend.md").write_text(text + "\n")
    print(f"wrote {args.out / 'frontend.json'} and {args.out / 'frontend.md'}")
    return 0


def _markdown(result: dict) -> str:
    config = result["config"]
    lines = [
        f"Front end on {result['frames']} frames {result['image_size'][0]}x"
        f"{result['image_size'][1]} x {result['repeat']} passes "
        f"(method {config['registration']['method']}, tracking {config['frontend']['tracking']}, "
        f"temporal matcher {config['frontend']['temporal_matcher']}, "
        f"{'front end mode track, ' if config['frontend'].get('mode') == 'track' else ''}"
        f"detector {config['frontend']['detector']}, "
        f"back end {'on' if config['backend']['enabled'] else 'off'}, "
        f"OMP_NUM_THREADS={result['environment']['OMP_NUM_THREADS']}, "
        f"load average {result['environment']['load_average']})",
        "",
        "| stage | median ms | p95 ms |",
        "|---|---:|---:|",
    ]
    for stage, row in result["stages"].items():
        lines.append(f"| {stage} | {row['median_ms']:.2f} | {row['p95_ms']:.2f} |")
    lines += [
        "",
        f"frames/s: {result['fps_from_median_total']:.1f} (median wall time per frame), "
        f"{result['fps_wall_clock']:.1f} (wall clock over the run), "
        f"{result['fps_from_cpu_time']:.1f} (median CPU time per frame, "
        f"{result['cpu_ms_per_frame']['median']:.1f} ms, p95 "
        f"{result['cpu_ms_per_frame']['p95']:.1f} ms); target {result['target_fps']:.0f}: "
        f"wall {'met' if result['meets_target_wall'] else 'NOT met'}, "
        f"CPU {'met' if result['meets_target_cpu'] else 'NOT met'}",
        f"median matches {result['median_matches']:.0f}, inliers {result['median_inliers']:.0f}, "
        f"status {result['status_counts']}",
    ]
    drift = result["drift"]
    if drift:
        lines.append(
            "drift vs ground truth (front end / fused): final translation "
            f"{drift['frontend_pose_final_translation_error_m'] * 100:.2f} / "
            f"{drift['pose_final_translation_error_m'] * 100:.2f} cm, final rotation "
            f"{drift['frontend_pose_final_rotation_error_deg']:.3f} / "
            f"{drift['pose_final_rotation_error_deg']:.3f} deg, eq. 20 RMS "
            f"{drift['frontend_pose_eq20_rms']:.4f} / {drift['pose_eq20_rms']:.4f} "
            f"(ground-truth path {drift['ground_truth_path_m'] * 100:.1f} cm)"
        )
    if drift and "images_final_rotation_deg" in drift:
        lines.append(
            "final rotation measured from the raw left images alone "
            f"{drift['images_final_rotation_deg']:.3f} deg; against it: front end "
            f"{drift['frontend_pose_vs_images_final_rotation_deg']:.3f} / fused "
            f"{drift['pose_vs_images_final_rotation_deg']:.3f} deg, ground truth "
            f"{drift['ground_truth_vs_images_final_rotation_deg']:.3f} deg"
        )
    return "\n".join(lines)
