"""How much of the real MH_01 ATE is the ground truth's own: its clock and its lever arm.

Diagnostics, not the headline metric (that stays the ATE after SE(3) alignment at the frames'
own timestamps, docs/datasets-and-evaluation.md). From the stored odometry runs (refinement on,
vision alone and fused, four estimators) and the clip's IMU and ground truth
(``estimator.evaluation.ground_truth_checks``):

* clocks: the ground truth's body rate against the gyro; its positions' second difference
  against the accelerometer (no camera); and, without any ground truth, vision's
  frame-to-frame rotations against the gyro over the same intervals (vision runs);
* per run: the ATE at 0 (= the headline), with the ground-truth positions read later or
  earlier (best shift), with a lever arm of the camera in the body frame fitted, with both;
* per run, held out: each correction fitted on one half of the frames and applied to the
  other half (a correction that belongs to the reference carries over);
* per run: the scale of the Sim(3) fit onto the ground truth, on the whole run and on each
  half (above 1: the estimated path is too short; the rig's calibration sets the scale).

    python benchmarks/ground_truth_timing.py [--results DIR] [--data SEQUENCE] [--out DIR]

Writes ``ground_truth.json`` and ``ground_truth.md`` into ``--out`` (default
benchmarks/results/ground_truth) and prints the markdown (2026-12-03: docs/datasets-and-
evaluation.md, "How far the MH_01 ground truth can be trusted").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
from clip_args import quiet_sequence

from estimator.evaluation import ground_truth_checks as checks
from estimator.evaluation.ground_truth_checks import CorrectionKind
from estimator.evaluation.metrics import camera_ground_truth, similarity_scale
from estimator.formats.datasets import Sequence
from estimator.formats.trajectory_io import read_tum

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared/data/euroc_mh01_moving"
DEFAULT_RESULTS = ROOT / "benchmarks/results/odometry/euroc_mh01_moving"
DEFAULT_OUT = ROOT / "benchmarks/results/ground_truth"
ESTIMATORS = ("pso-robust", "msac", "pso", "svd")
MODES = ("vision", "fused")
CLOCK_SHIFTS_MS = np.arange(-10, 11)  # 1 ms steps: the clocks agree to well under that
ATE_SHIFTS_MS = np.arange(-10, 31)  # the positions' best shift is several ms late
# Multiples of the ground truth's 5 ms rows (reading between rows smooths its noise).
ACCELEROMETER_SHIFTS_MS = np.arange(-30, 31, 5)
ACCELEROMETER_HALF_WINDOW_S = 0.1


def run_name(estimator: str, mode: str) -> str:
    return f"{estimator}_refine-on_{mode}"


def _seconds(shifts_ms: np.ndarray) -> np.ndarray:
    return np.asarray(shifts_ms, dtype=float) * 1e-3


def _mm(values: Any) -> Any:
    return (np.asarray(values, dtype=float) * 1e3).tolist()


def open_clip(path: Path) -> Sequence:
    sequence = quiet_sequence(path)
    if sequence.imu is None or sequence.ground_truth is None:
        raise ValueError(f"{path} needs both an IMU and a ground truth")
    return sequence


def read_run(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """The run's stamps and left-camera poses (N, 4, 4) from its trajectory.tum."""
    return read_tum(folder / "trajectory.tum")


def _scan(scan: checks.ShiftScan, scale: float) -> dict[str, Any]:
    return {
        "best_shift_ms": scan.best_shift_s * 1e3,
        "at_best": scan.best_value * scale,
        "at_0": scan.value_at(0.0) * scale,
        "at_edge": scan.at_edge,
        "curve": (scan.values * scale).tolist(),
    }


def gyro_check(sequence: Sequence) -> dict[str, Any]:
    """Gyro against the ground truth's body rate (rad/s RMS, bias removed)."""
    scan = checks.gyro_ground_truth_offset(
        sequence.imu, sequence.ground_truth, _seconds(CLOCK_SHIFTS_MS)
    )
    return {"unit": "rad/s", **_scan(scan, 1.0)}


def accelerometer_check(sequence: Sequence) -> dict[str, Any]:
    """The ground-truth positions' acceleration against the accelerometer (m/s^2 RMS)."""
    scan = checks.accelerometer_ground_truth_offset(
        sequence.imu, sequence.ground_truth, _seconds(ACCELEROMETER_SHIFTS_MS),
        ACCELEROMETER_HALF_WINDOW_S,
    )  # fmt: skip
    return {"unit": "m/s^2", "half_window_s": ACCELEROMETER_HALF_WINDOW_S, **_scan(scan, 1.0)}


def camera_check(sequence: Sequence, folder: Path) -> dict[str, Any]:
    """Vision's frame-to-frame rotations against the gyro (mdeg per frame RMS), no GT."""
    stamps, poses = read_run(folder)
    scan = checks.camera_gyro_offset(
        stamps, poses[:, :3, :3], sequence.imu, sequence.rig.left.T_BS[:3, :3],
        _seconds(CLOCK_SHIFTS_MS),
    )  # fmt: skip
    return {"unit": "mdeg per frame", **_scan(scan, np.degrees(1.0) * 1e3)}


def _correction(fit: checks.Correction) -> dict[str, Any]:
    return {
        "shift_ms": fit.shift_s * 1e3,
        "lever_arm_mm": _mm(fit.lever_arm_m),
        "ate_mm": fit.ate_m * 1e3,
    }


def run_check(sequence: Sequence, folder: Path) -> dict[str, Any]:
    """One run: the ATE at 0, each correction fitted on the whole run and held out."""
    stamps, poses = read_run(folder)
    positions = poses[:, :3, 3]
    truth, T_BS, shifts = sequence.ground_truth, sequence.rig.left.T_BS, _seconds(ATE_SHIFTS_MS)
    at_zero = checks.corrected_ate(stamps, positions, truth, T_BS, 0.0, np.zeros(3))
    result: dict[str, Any] = {"frames": len(stamps), "ate_at_0_mm": at_zero * 1e3}
    metrics = folder / "metrics.json"
    if metrics.is_file():
        result["headline_ate_mm"] = json.loads(metrics.read_text())["ate_rmse_m"] * 1e3
    scan = checks.ate_versus_shift(stamps, positions, truth, T_BS, shifts)
    result["ate_curve_mm"] = _mm(scan.values)
    result["shift_at_edge"] = scan.at_edge
    run = checks.RunPositions(stamps, positions, truth, T_BS)
    for kind in CorrectionKind:
        fit = checks.fit_correction(run, kind, shifts)
        held = checks.held_out_check(run, kind, shifts)
        result[kind.value] = {
            **_correction(fit),
            "held_out": {
                "fits": [_correction(half) for half in held.fits],
                "ate_plain_mm": _mm(held.ate_plain_m),
                "ate_corrected_mm": _mm(held.ate_corrected_m),
            },
        }
    return result


def scale_check(sequence: Sequence, folder: Path) -> dict[str, float]:
    """Sim(3) scale of the run onto the ground truth: whole run, first and second half."""
    stamps, poses = read_run(folder)
    covered = sequence.ground_truth.covers(stamps)
    stamps, poses = stamps[covered], poses[covered]
    truth = camera_ground_truth(sequence.ground_truth, stamps, sequence.rig.left.T_BS)
    half = len(stamps) // 2
    parts = {"all": slice(None), "first_half": slice(0, half), "second_half": slice(half, None)}
    return {
        name: similarity_scale(stamps[part], poses[part], truth[part])
        for name, part in parts.items()
    }


def compute(results: Path, data: Path) -> dict[str, Any]:
    sequence = open_clip(data)
    folders = {run_name(e, m): results / run_name(e, m) for m in MODES for e in ESTIMATORS}
    present = {name: path for name, path in folders.items() if (path / "trajectory.tum").is_file()}
    if not present:
        raise FileNotFoundError(f"no */trajectory.tum of the runs {sorted(folders)} in {results}")
    return {
        "kind": "diagnostic: not the headline metric (ATE at the frames' own timestamps)",
        "sequence": data.name,
        "convention": "shift s: the other series (ground truth; gyro in camera_vs_gyro) read "
        "at t + s; a minimum at s > 0 means its stamps run s late",
        "clock_shifts_ms": CLOCK_SHIFTS_MS.tolist(),
        "accelerometer_shifts_ms": ACCELEROMETER_SHIFTS_MS.tolist(),
        "ate_shifts_ms": ATE_SHIFTS_MS.tolist(),
        "gyro_vs_ground_truth": gyro_check(sequence),
        "accelerometer_vs_ground_truth": accelerometer_check(sequence),
        "camera_vs_gyro": {
            name: camera_check(sequence, path)
            for name, path in present.items()
            if name.endswith("_vision")
        },
        "runs": {name: run_check(sequence, path) for name, path in present.items()},
        "scale": {name: scale_check(sequence, path) for name, path in present.items()},
    }


def markdown(result: dict[str, Any]) -> str:
    """The tables of ground_truth.md."""
    gyro, accel = result["gyro_vs_ground_truth"], result["accelerometer_vs_ground_truth"]
    lines = [
        f"# Ground-truth timing and lever arm: {result['sequence']} (diagnostic)",
        "",
        "Not the headline metric: the project's ATE stays the one at the frames' own "
        "timestamps with T_BS as calibrated. Shift s: the other series read at t + s.",
        "",
        "| clock check | best shift | RMS there | RMS at 0 |",
        "|---|---|---|---|",
        f"| gyro vs ground-truth body rate | {gyro['best_shift_ms']:+.2f} ms | "
        f"{gyro['at_best']:.5f} rad/s | {gyro['at_0']:.5f} rad/s |",
        f"| ground-truth positions (2nd difference, +-{accel['half_window_s'] * 1e3:.0f} ms) vs "
        f"accelerometer (no camera) | {accel['best_shift_ms']:+.2f} ms | "
        f"{accel['at_best']:.4f} m/s^2 | {accel['at_0']:.4f} m/s^2 |",
    ]
    for name, check in result["camera_vs_gyro"].items():
        lines.append(
            f"| {name} rotations vs gyro (no GT) | {check['best_shift_ms']:+.2f} ms | "
            f"{check['at_best']:.2f} mdeg/frame | {check['at_0']:.2f} mdeg/frame |"
        )
    lines += [
        "",
        "ATE (mm) with the ground truth corrected, fitted on the whole run:",
        "",
        "| run | ATE at 0 | GT shift -> ATE | lever arm (body, mm) -> ATE "
        "| shift + lever arm -> ATE |",
        "|---|---|---|---|---|",
    ]
    for name, run in result["runs"].items():
        shift, lever, both = (run[kind.value] for kind in CorrectionKind)
        lines.append(
            f"| {name} | {run['ate_at_0_mm']:.2f} | {shift['shift_ms']:+.1f} ms -> "
            f"{shift['ate_mm']:.2f} | {_vector(lever['lever_arm_mm'])} -> {lever['ate_mm']:.2f} | "
            f"{both['shift_ms']:+.1f} ms, {_vector(both['lever_arm_mm'])} -> {both['ate_mm']:.2f} |"
        )
    lines += [
        "",
        "Held out: fitted on one half of the frames, applied to the other (ATE mm of the first "
        "/ second half, each aligned on its own: plain -> with the other half's correction; "
        "the fitted values of the first / second half):",
        "",
        "| run | shift | lever arm | shift + lever arm |",
        "|---|---|---|---|",
    ]
    for name, run in result["runs"].items():
        cells = [_held_out(run[kind.value]["held_out"], kind) for kind in CorrectionKind]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Scale of the Sim(3) fit of each run onto the ground truth (above 1: the estimated "
        "path is too short; a stereo rig's scale comes from its calibration):",
        "",
        "| run | whole run | first half | second half |",
        "|---|---|---|---|",
    ]
    for name, scale in result["scale"].items():
        lines.append(
            f"| {name} | {scale['all']:.4f} | {scale['first_half']:.4f} | "
            f"{scale['second_half']:.4f} |"
        )
    return "\n".join(lines) + "\n"


def _vector(values: list[float]) -> str:
    return "(" + ", ".join(f"{value:.0f}" for value in values) + ")"


def _held_out(held: dict[str, Any], kind: CorrectionKind) -> str:
    plain, corrected = held["ate_plain_mm"], held["ate_corrected_mm"]
    fitted = []
    for fit in held["fits"]:
        parts = []
        if kind is not CorrectionKind.LEVER_ARM:
            parts.append(f"{fit['shift_ms']:+.1f} ms")
        if kind is not CorrectionKind.SHIFT:
            parts.append(_vector(fit["lever_arm_mm"]))
        fitted.append(" ".join(parts))
    return (
        f"{plain[0]:.2f} -> {corrected[0]:.2f} / {plain[1]:.2f} -> {corrected[1]:.2f} "
        f"({' / '.join(fitted)})"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, default=DEFAULT_RESULTS, help="run folders")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the EuRoC clip")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args()
    if not args.results.is_dir():
        parser.error(f"no run folders at {args.results}")
    if not (args.data / "mav0").is_dir():
        parser.error(f"no EuRoC clip at {args.data}")
    try:
        result = compute(args.results, args.data)
    except (FileNotFoundError, ValueError) as error:
        parser.error(str(error))
    text = markdown(result)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ground_truth.json").write_text(json.dumps(result, indent=2) + "\n")
    (args.out / "ground_truth.md").write_text(text)
    print(text, end="")


if __name__ == "__main__":
    main()
