"""Per-measurement relative-pose error of each estimator variant on a real clip.

The odometry is run once (default configuration, vision alone) and every 3D-3D problem it
hands to the estimator is recorded with the frames it relates. Each problem is then solved
again by every variant, and the relative pose is compared with the ground truth's. This isolates
the estimator from what it does to tracking (keyframes, predictions), which a trajectory ATE
mixes in. Variants: pso-robust with the scalar per-pair depth sigma (the former default), with
no per-pair noise (isotropic threshold), with the stereo covariances (Mahalanobis support, the
default), msac and pso; each without and with the Mahalanobis refinement on its inliers.

    OMP_NUM_THREADS=1 python benchmarks/real_frame_errors.py [../shared/data/euroc_mh01_moving]

Writes ``benchmarks/results/odometry/frame_errors.json`` and ``frame_errors.md``.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
from clip_args import quiet_sequence

from estimator.evaluation.metrics import camera_ground_truth
from estimator.geometry import rotation_angle_deg
from estimator.odometry import MeasurementKind, ObservedMeasurement
from estimator.pipeline import build_config, run_sequence
from estimator.registration.refine import refine_pose_mahalanobis
from estimator.registration.registry import register

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT.parent / "shared/data/euroc_mh01_moving"
OUT = ROOT / "benchmarks/results/odometry"


def record(path: Path) -> tuple[list[tuple], object]:
    """Every estimator problem of a default vision-alone run, with both frames' timestamps."""
    sequence = quiet_sequence(path)
    problems: list[tuple] = []
    config = build_config(imu=False)
    needed = config.frontend.min_matches

    def recording(measured: ObservedMeasurement) -> None:
        pairs = measured.pairs
        if measured.kind is not MeasurementKind.REGISTRATION or pairs is None:
            return
        if len(pairs) < needed:
            return
        depth_sigma = np.hypot(
            measured.reference.points.depth_sigma[pairs.reference_index],
            measured.points.depth_sigma[pairs.current_index],
        )
        problems.append(
            (measured.reference.timestamp_ns, measured.timestamp_ns, pairs.current_points,
             pairs.reference_points, depth_sigma, measured.point_covariances,
             measured.gate_chi2)
        )  # fmt: skip

    run_sequence(sequence, config, use_imu=False, observer=recording)
    return problems, sequence


VARIANTS = {
    "pso-robust + depth sigmas (former default)": ("pso-robust", lambda p: {"sigmas": p[4]}),
    "pso-robust isotropic": ("pso-robust", lambda p: {}),
    "pso-robust + covariances (default)": (
        "pso-robust",
        lambda p: {"source_cov": p[5][0], "target_cov": p[5][1], "gate_chi2": p[6]},
    ),
    "msac": ("msac", lambda p: {}),
    "pso": ("pso", lambda p: {}),
}  # fmt: skip


def main() -> int:
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT
    problems, sequence = record(path)
    rectify = sequence.rig.rectification.R_left
    stamps = np.array(sorted({p[0] for p in problems} | {p[1] for p in problems}))
    poses = camera_ground_truth(sequence.ground_truth, stamps, sequence.rig.left.T_BS)
    truth = dict(zip(stamps, poses, strict=True))
    results: dict[str, dict] = {}
    for name, (method, options) in VARIANTS.items():
        for refine in (False, True):
            results[f"{name} | refine {'on' if refine else 'off'}"] = variant_errors(
                problems, truth, rectify, method, options, refine
            )
    text = table(sequence.name, len(problems), results)
    print(text)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "frame_errors.md").write_text(text)
    (OUT / "frame_errors.json").write_text(
        json.dumps({"sequence": sequence.name, "problems": len(problems), **results}, indent=2)
        + "\n"
    )
    return 0


def variant_errors(
    problems: list[tuple],
    truth: dict,
    rectify: np.ndarray,
    method: str,
    options: Callable[[tuple], dict],
    refine: bool,
) -> dict[str, float]:
    """Rotation and translation errors of one variant over every recorded problem."""
    rotations, translations = [], []
    for problem in problems:
        relative = np.linalg.inv(truth[problem[0]]) @ truth[problem[1]]
        true_r = rectify @ relative[:3, :3] @ rectify.T
        true_t = rectify @ relative[:3, 3]
        rotation, translation = solve(problem, method, options(problem), refine)
        rotations.append(rotation_angle_deg(rotation.T @ true_r))
        translations.append(float(np.linalg.norm(translation - true_t)))
    rot, trans = np.array(rotations), np.array(translations)
    return {
        "rotation_rms_deg": float(np.sqrt(np.mean(rot**2))),
        "rotation_median_deg": float(np.median(rot)),
        "translation_rms_mm": float(1000 * np.sqrt(np.mean(trans**2))),
    }


def solve(
    problem: tuple, method: str, options: dict, refine: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The variant's (R, t) for one problem, refined on its inliers when asked and possible."""
    source, target = problem[2], problem[3]
    result = register(source, target, method=method, seed=0, **options)
    rotation, translation = result.rotation, result.translation
    if refine and result.success:
        mask = result.inliers
        cov = problem[5]
        refined = refine_pose_mahalanobis(
            source[mask], target[mask], cov[0][mask], cov[1][mask], rotation, translation
        )
        if refined.success:
            rotation, translation = refined.rotation, refined.translation
    return rotation, translation


def table(sequence_name: str, problems: int, results: dict[str, dict]) -> str:
    """The markdown table of frame_errors.md."""
    lines = [
        f"{sequence_name}: {problems} estimator problems of a default vision-alone run, "
        "relative pose vs ground truth (which has its own error)",
        "",
        "| estimator | refinement | rotation RMS deg | rotation median deg | translation RMS mm |",
        "|---|---|---|---|---|",
    ]
    for label, row in results.items():
        name, refine = label.split(" | ")
        lines.append(
            f"| {name} | {refine.split()[-1]} | {row['rotation_rms_deg']:.4f} | "
            f"{row['rotation_median_deg']:.4f} | {row['translation_rms_mm']:.2f} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
