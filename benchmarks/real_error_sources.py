"""Where the vision-alone relative-pose error on a real clip comes from.

The odometry is run once (vision alone, default configuration, or the JSON config given with
``--config``) and every accepted estimate is recorded with its inlier pairs and the frames it
relates. Against the ground truth each relative pose is then taken apart:

- by keyframe age (how far the frame is from the frame it was measured against), rotation and
  translation, and the share of the rotation error that all measurements of one keyframe have
  in common;
- by pixel component: the pose refined again with the current pixels (u, v) or the current
  disparity replaced by where the ground truth puts the reference point, so that the
  component left alone carries all of the error;
- against calibration-like explanations: a disparity offset (a stereo extrinsic error about
  the vertical axis), a baseline scale, and a linear per-axis rotation gain;
- against a time offset of the reference's positions;
- against the gyro (an independent sensor, its bias fitted as one constant): is the rotation
  error the vision's or the ground truth's;
- against the noise model: the rotation NEES (3 DOF) under the refinement's covariance, and the
  refit after dropping the pairs with the largest residuals against the ground truth.

    OMP_NUM_THREADS=1 python benchmarks/real_error_sources.py [DATASET] [--config CFG.json]

Prints markdown tables (nothing is written).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from clip_args import quiet_sequence
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from estimator.config import SwarmvoConfig
from estimator.evaluation.metrics import camera_ground_truth
from estimator.odometry import MeasurementKind, ObservedMeasurement
from estimator.pipeline import build_config, load_config, run_sequence
from estimator.registration.refine import refine_pose_mahalanobis

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT.parent / "shared/data/euroc_mh01_moving"
AGE_BINS_S = ((0.0, 0.06), (0.06, 0.11), (0.11, 0.21), (0.21, 10.0))


@dataclass
class Problem:
    """One accepted estimate: inlier pairs (current q, reference p), their covariances, the
    estimated and the true T_ref_cur (rectified frames) and the keyframe age."""

    q: np.ndarray
    p: np.ndarray
    cov_q: np.ndarray
    cov_p: np.ndarray
    estimate: np.ndarray
    truth: np.ndarray
    reference_ns: int
    age_s: float


def record(path: Path, config: SwarmvoConfig | None) -> tuple[list[tuple], object]:
    """Every accepted estimate of a vision-alone run: (ref ns, cur ns, q, p, covs, T)."""
    sequence = quiet_sequence(path)
    raw: list[tuple] = []

    def recording(measured: ObservedMeasurement) -> None:
        pose, pairs = measured.reference_from_current, measured.pairs
        if measured.kind is not MeasurementKind.REGISTRATION or pose is None or pairs is None:
            return
        assert measured.inliers is not None and measured.point_covariances is not None
        mask = np.asarray(measured.inliers)
        cov_q, cov_p = measured.point_covariances
        raw.append(
            (measured.reference.timestamp_ns, measured.timestamp_ns,
             pairs.current_points[mask], pairs.reference_points[mask],
             cov_q[mask], cov_p[mask], pose)
        )  # fmt: skip

    run_sequence(sequence, build_config(imu=False, base=config), use_imu=False, observer=recording)
    return raw, sequence


def true_relatives(raw: list[tuple], sequence, offset_ns: int = 0) -> list[np.ndarray]:
    """Ground-truth T_ref_cur in the rectified frame; ``offset_ns`` shifts the positions only."""
    stamps = np.array(sorted({r[0] for r in raw} | {r[1] for r in raw}))
    poses = camera_ground_truth(sequence.ground_truth, stamps, sequence.rig.left.T_BS)
    if offset_ns:
        shifted = sequence.ground_truth.interpolate(stamps + offset_ns)
        body = sequence.ground_truth.interpolate(stamps)
        body[:, :3, 3] = shifted[:, :3, 3]
        poses = body @ sequence.rig.left.T_BS
    truth = dict(zip(stamps, poses, strict=True))
    rect = np.eye(4)
    rect[:3, :3] = sequence.rig.rectification.R_left
    return [rect @ np.linalg.inv(truth[r[0]]) @ truth[r[1]] @ rect.T for r in raw]


def rotation_error_deg(rotation: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.degrees(Rotation.from_matrix(rotation.T @ truth[:3, :3]).as_rotvec())


def rms(values: np.ndarray) -> float:
    values = np.asarray(values, dtype=float)
    return float(np.sqrt(np.mean(np.sum(values.reshape(len(values), -1) ** 2, axis=1))))


def refit(problem: Problem, q: np.ndarray, p: np.ndarray, keep: np.ndarray | None = None):
    """The Mahalanobis refinement again, from the estimate, on (possibly changed) pairs."""
    keep = np.ones(len(q), bool) if keep is None else keep
    return refine_pose_mahalanobis(
        q[keep], p[keep], problem.cov_q[keep], problem.cov_p[keep],
        problem.estimate[:3, :3], problem.estimate[:3, 3],
    )  # fmt: skip


class Camera:
    """Rectified pinhole with the stereo baseline: points <-> (u, v, disparity)."""

    def __init__(self, rectification) -> None:
        self.f, self.cx, self.cy = rectification.fx, rectification.cx, rectification.cy
        self.b = rectification.baseline

    def pixels(self, points: np.ndarray) -> np.ndarray:
        z = points[:, 2]
        return np.column_stack(
            [self.f * points[:, 0] / z + self.cx, self.f * points[:, 1] / z + self.cy,
             self.f * self.b / z]
        )  # fmt: skip

    def points(self, pixels: np.ndarray, baseline_scale: float = 1.0) -> np.ndarray:
        z = self.f * self.b * baseline_scale / pixels[:, 2]
        return np.column_stack(
            [(pixels[:, 0] - self.cx) * z / self.f, (pixels[:, 1] - self.cy) * z / self.f, z]
        )


def by_age(problems: list[Problem]) -> list[str]:
    rot = np.array([rotation_error_deg(x.estimate[:3, :3], x.truth) for x in problems])
    trans = np.array([1000 * (x.estimate[:3, 3] - x.truth[:3, 3]) for x in problems])
    ages = np.array([x.age_s for x in problems])
    lines = ["| keyframe age s | n | rotation RMS deg | translation RMS mm |", "|---|---|---|---|"]
    for low, high in AGE_BINS_S:
        m = (ages > low) & (ages <= high)
        lines.append(f"| {low}-{high} | {m.sum()} | {rms(rot[m]):.4f} | {rms(trans[m]):.2f} |")
    lines.append(f"| all | {len(problems)} | {rms(rot):.4f} | {rms(trans):.2f} |")
    keyframes = np.array([x.reference_ns for x in problems])
    shared = np.zeros_like(rot)
    for k in np.unique(keyframes):
        shared[keyframes == k] = rot[keyframes == k].mean(axis=0)
    lines.append(
        f"\nRotation error shared by a keyframe's measurements (their mean): {rms(shared):.4f} "
        f"deg RMS, the rest {rms(rot - shared):.4f} ({len(np.unique(keyframes))} keyframes)."
    )
    return lines


def oracle_components(problems: list[Problem], camera: Camera) -> list[str]:
    """Pose errors with the current (u, v) or disparity replaced by the ground truth's."""
    rows = {"measured": [], "(u, v) from ground truth": [], "disparity from ground truth": []}
    for x in problems:
        truth_pixels = camera.pixels((x.p - x.truth[:3, 3]) @ x.truth[:3, :3])
        measured = camera.pixels(x.q)
        variants = {
            "measured": measured,
            "(u, v) from ground truth": np.column_stack([truth_pixels[:, :2], measured[:, 2]]),
            "disparity from ground truth": np.column_stack([measured[:, :2], truth_pixels[:, 2]]),
        }
        for name, pixels in variants.items():
            result = refit(x, camera.points(pixels), x.p)
            rows[name].append(
                (rotation_error_deg(result.rotation, x.truth),
                 1000 * (result.translation - x.truth[:3, 3]))
            )  # fmt: skip
    lines = ["| current pixels | rotation RMS deg | translation RMS mm |", "|---|---|---|"]
    for name, values in rows.items():
        rot = np.array([v[0] for v in values])
        trans = np.array([v[1] for v in values])
        lines.append(f"| {name} | {rms(rot):.4f} | {rms(trans):.2f} |")
    return lines


def calibration_scan(problems: list[Problem], camera: Camera) -> list[str]:
    """A disparity offset and a baseline scale applied to every point, and the rotation gain."""

    def errors(offset_px: float, scale: float) -> tuple[float, float]:
        rot, trans = [], []
        for x in problems:
            q, p = camera.pixels(x.q), camera.pixels(x.p)
            q[:, 2] -= offset_px
            p[:, 2] -= offset_px
            result = refit(x, camera.points(q, scale), camera.points(p, scale))
            rot.append(rotation_error_deg(result.rotation, x.truth))
            trans.append(1000 * (result.translation - x.truth[:3, 3]))
        return rms(np.array(rot)), rms(np.array(trans))

    lines = ["| disparity offset px | baseline scale | rotation RMS deg | translation RMS mm |",
             "|---|---|---|---|"]  # fmt: skip
    for offset, scale in ((0, 1), (-0.5, 1), (-0.25, 1), (0.25, 1), (0.5, 1), (0, 0.99), (0, 1.01)):
        lines.append(f"| {offset} | {scale} | " + " | ".join(f"{v:.4f}" for v in errors(offset, scale)) + " |")  # fmt: skip  # noqa: E501
    measured = np.array([Rotation.from_matrix(x.estimate[:3, :3]).as_rotvec() for x in problems])
    true = np.array([Rotation.from_matrix(x.truth[:3, :3]).as_rotvec() for x in problems])
    gain, *_ = np.linalg.lstsq(true, measured, rcond=None)
    lines.append(
        f"\nLinear rotation gain (measured = G truth), diagonal {np.round(np.diag(gain), 4)}, "
        f"largest off-diagonal {np.abs(gain - np.diag(np.diag(gain))).max():.4f}; rotation RMS "
        f"{np.degrees(rms(measured - true)):.4f} deg, after removing it "
        f"{np.degrees(rms(measured - true @ gain)):.4f} deg (fitted on the same data)."
    )
    return lines


def time_offset_scan(raw: list[tuple], problems: list[Problem], sequence) -> list[str]:
    lines = ["| reference positions shifted ms | translation RMS mm |", "|---|---|"]
    for offset_ms in (-2, 0, 2, 4, 6):
        truths = true_relatives(raw, sequence, int(offset_ms * 1e6))
        pairs = zip(problems, truths, strict=True)
        trans = [1000 * (x.estimate[:3, 3] - t[:3, 3]) for x, t in pairs]
        lines.append(f"| {offset_ms} | {rms(np.array(trans)):.2f} |")
    return lines


def gyro_rotation(sequence, start_ns: int, end_ns: int, bias: np.ndarray) -> np.ndarray:
    """Body rotation from the gyro over [start, end] (1 ms steps, linear interpolation)."""
    imu = sequence.imu
    steps = max(int((end_ns - start_ns) / 1e6), 2)
    edges = np.linspace(start_ns, end_ns, steps + 1)
    middle = (edges[:-1] + edges[1:]) / 2
    stamps = imu.timestamps_ns.astype(float)
    rates = np.column_stack([np.interp(middle, stamps, imu.gyro[:, k]) for k in range(3)])
    increments = Rotation.from_rotvec((rates - bias) * (edges[1] - edges[0]) / 1e9)
    rotation = Rotation.identity()
    for increment in increments:
        rotation = rotation * increment
    return rotation.as_matrix()


def against_gyro(raw: list[tuple], problems: list[Problem], sequence) -> list[str]:
    """Rotation RMS of the gyro (constant bias fitted) against the ground truth and vision."""
    if sequence.imu is None:
        return ["No IMU in this dataset."]
    camera_to_body = sequence.rig.left.T_BS[:3, :3]
    rect = sequence.rig.rectification.R_left
    to_camera = rect @ camera_to_body.T

    def residuals(bias: np.ndarray, targets: list[np.ndarray]) -> np.ndarray:
        return np.concatenate([
            Rotation.from_matrix(
                (to_camera @ gyro_rotation(sequence, r[0], r[1], bias) @ to_camera.T).T @ target
            ).as_rotvec()
            for r, target in zip(raw, targets, strict=True)
        ])  # fmt: skip

    lines = ["| gyro against | fitted bias rad/s | rotation RMS deg |", "|---|---|---|"]
    for name, targets in (
        ("ground truth", [x.truth[:3, :3] for x in problems]),
        ("vision", [x.estimate[:3, :3] for x in problems]),
    ):
        fit = least_squares(residuals, np.zeros(3), args=(targets,))
        error = np.degrees(rms(fit.fun.reshape(-1, 3)))
        lines.append(f"| {name} | {np.round(fit.x, 4)} | {error:.4f} |")
    return lines


def noise_model(problems: list[Problem], camera: Camera) -> list[str]:
    nees, predicted, actual = [], [], []
    for x in problems:
        result = refit(x, x.q, x.p)
        error = np.radians(rotation_error_deg(result.rotation, x.truth))
        covariance = result.covariance[:3, :3]
        nees.append(error @ np.linalg.solve(covariance, error))
        predicted.append(np.degrees(np.sqrt(np.trace(covariance))))
        actual.append(np.degrees(np.linalg.norm(error)))
    lines = [
        f"Rotation NEES (3 DOF, expected median 2.37): median {np.median(nees):.1f}, mean "
        f"{np.mean(nees):.1f}; predicted RMS {rms(np.array(predicted)):.4f} deg, actual "
        f"{rms(np.array(actual)):.4f} deg.",
        "",
        "| pairs dropped (largest residual against the ground truth) | rotation RMS deg |",
        "|---|---|",
    ]
    for fraction in (0.0, 0.1, 0.2, 0.4):
        rot = []
        for x in problems:
            truth_pixels = camera.pixels((x.p - x.truth[:3, 3]) @ x.truth[:3, :3])
            residual = np.linalg.norm(camera.pixels(x.q)[:, :2] - truth_pixels[:, :2], axis=1)
            keep = residual <= np.quantile(residual, 1 - fraction)
            rot.append(rotation_error_deg(refit(x, x.q, x.p, keep).rotation, x.truth))
        lines.append(f"| {fraction:.0%} | {rms(np.array(rot)):.4f} |")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", nargs="?", type=Path, default=DEFAULT)
    parser.add_argument("--config", type=Path, help="SwarmvoConfig as JSON")
    args = parser.parse_args()
    if not args.dataset.is_dir():
        parser.error(f"dataset folder not found: {args.dataset}")
    try:
        config = load_config(args.config) if args.config else None
    except (FileNotFoundError, ValueError) as error:
        parser.error(str(error))
    raw, sequence = record(args.dataset, config)
    truths = true_relatives(raw, sequence)
    problems = [
        Problem(r[2], r[3], r[4], r[5], r[6], t, r[0], (r[1] - r[0]) / 1e9)
        for r, t in zip(raw, truths, strict=True)
    ]
    camera = Camera(sequence.rig.rectification)
    print(f"{sequence.name}: {len(problems)} accepted estimates, vision alone\n")
    for title, lines in (
        ("Error by keyframe age", by_age(problems)),
        ("Which pixel component carries the error", oracle_components(problems, camera)),
        ("Calibration-like explanations", calibration_scan(problems, camera)),
        ("Time offset of the reference's positions", time_offset_scan(raw, problems, sequence)),
        ("Against the gyro", against_gyro(raw, problems, sequence)),
        ("Noise model", noise_model(problems, camera)),
    ):
        print(f"### {title}\n")
        print("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
