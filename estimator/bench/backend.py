"""``swarmvo bench backend``: what the GTSAM back end adds, and what it costs per frame.

Four parts, each printed as a table and stored in ``backend.json`` / ``backend.md``:

1. ``gyro`` - real EuRoC V1_02 IMU (fast motion): preintegrated rotation over 20 Hz steps
   against ground truth, with the ground-truth gyro bias and with none; then the graph with
   vision-like noisy relative poses estimating the bias online.
2. ``simulated`` - a long smooth trajectory (default 2000 frames at 20 Hz) with a simulated
   200 Hz IMU and simulated front-end relative poses (clean, and with 20 % broken frames:
   half failed, half grossly wrong); fused vs front-end-only ATE and the per-frame back-end
   time (p50 / p95 / max, and the first vs last 10 % of frames to show it stays flat).
3. ``pipeline`` - the whole ``Odometry`` on a rendered sequence with 20 % broken frames and on
   EuRoC V1_01 micro (standing still, real IMU): front-end-only vs fused (the online answer
   per frame, and the smoother's final estimates) with / without IMU. With ``--seeds`` it
   also renders one sequence per seed and tabulates front end vs fused ATE for each.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimator.backend import FusionBackend
from estimator.backend.imu import preintegrate_gyro, rotation_params
from estimator.config import BackendConfig
from estimator.geometry import make_pose, rotation_angle_deg
from estimator.rendered.scenario import (
    Scenario,
    aligned_ate,
    chain,
    simulate_frontend,
    smooth_trajectory,
)
from estimator.types import ImuNoise

if TYPE_CHECKING:
    from estimator.pipeline import RunResult

__all__ = ["add_arguments", "run"]

SHARED = Path(__file__).resolve().parents[2].parent / "shared/data"
# EuRoC-like camera mount for the simulated runs: ~90 deg about z, a few cm offset.
SIM_BODY_FROM_CAMERA = make_pose(
    np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), [-0.02, -0.06, 0.01]
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/backend"))
    parser.add_argument("--frames", type=int, default=2000, help="simulated run length")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--isam2-frames",
        type=int,
        default=600,
        help="length of the full-history iSAM2 comparison run (its cost grows per frame)",
    )
    parser.add_argument("--rendered-frames", type=int, default=200)
    parser.add_argument(
        "--seeds",
        type=_seed_list,
        default=None,
        help="pipeline part: also run these rendered seeds (e.g. 0-9 or 0,3,5), one row each",
    )
    parser.add_argument(
        "--standstill-s",
        type=float,
        default=0.0,
        help="pipeline part: the rendered body stands still this long before flying",
    )
    parser.add_argument(
        "--parts",
        nargs="+",
        choices=("gyro", "simulated", "pipeline"),
        default=["gyro", "simulated", "pipeline"],
    )
    parser.add_argument("--euroc-imu", type=Path, default=SHARED / "euroc_v102_imu_segment")
    parser.add_argument("--euroc-micro", type=Path, default=SHARED / "euroc_v101_micro")
    parser.add_argument(
        "--data",
        type=Path,
        default=Path(tempfile.gettempdir()) / "swarmvo-bench",
        help="where the rendered sequence is written once and reused",
    )


# ----------------------------------------------------------------------------- helpers


def _seed_list(text: str) -> list[int]:
    """``0-9`` or ``0,3,5`` (or both, comma separated) -> a list of seeds."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            first, _, last = part.strip().partition("-")
            seeds += list(range(int(first), int(last or first) + 1))
    except ValueError:
        seeds = []
    if not seeds:
        raise argparse.ArgumentTypeError(f"seeds must look like 0-9 or 0,3,5, got {text!r}")
    return seeds


def _ms_stats(seconds: np.ndarray) -> dict[str, float]:
    ms = np.asarray(seconds) * 1e3
    tenth = max(len(ms) // 10, 1)
    return {
        "p50_ms": float(np.percentile(ms, 50)),
        "p95_ms": float(np.percentile(ms, 95)),
        "max_ms": float(ms.max()),
        "first10pct_p50_ms": float(np.median(ms[:tenth])),
        "last10pct_p50_ms": float(np.median(ms[-tenth:])),
    }


def _table(title: str, header: list[str], rows: list[list[str]]) -> str:
    lines = [f"### {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- 1. real gyro


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
    if not (args.euroc_imu / "mav0").is_dir():
        return {"skipped": f"{args.euroc_imu} not found"}, "gyro: skipped (no data)\n"
    imu, noise, stamps, poses, bias = _euroc_20hz(args.euroc_imu)
    params = rotation_params(noise)
    truth_steps = np.swapaxes(poses[:-1, :3, :3], 1, 2) @ poses[1:, :3, :3]

    def step_errors(biases: np.ndarray | None) -> np.ndarray:
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

    rows: dict[str, dict[str, float]] = {}
    for name, biases in (("gyro, ground-truth bias", bias), ("gyro, zero bias", None)):
        errors = step_errors(biases)
        rows[name] = {"rms_deg": float(np.sqrt(np.mean(errors**2))), "max_deg": float(errors.max())}

    # Online bias: the graph with the real gyro and vision-like noisy relative poses.
    measurements = simulate_frontend(poses, np.eye(4), seed=args.seed)
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
    fused_poses, estimates = np.stack(fused), np.stack(estimates)
    fused_steps = np.swapaxes(fused_poses[:-1, :3, :3], 1, 2) @ fused_poses[1:, :3, :3]
    errors = rotation_angle_deg(np.swapaxes(fused_steps, 1, 2) @ truth_steps)
    vision = np.stack([m.relative_pose[:3, :3] for m in measurements[1:]])
    vision_errors = rotation_angle_deg(np.swapaxes(vision, 1, 2) @ truth_steps)
    rows["vision-like relative poses alone"] = {
        "rms_deg": float(np.sqrt(np.mean(vision_errors**2))),
        "max_deg": float(vision_errors.max()),
    }
    rows["graph (bias online): consecutive output poses"] = {
        "rms_deg": float(np.sqrt(np.mean(errors**2))),
        "max_deg": float(errors.max()),
    }
    increment_errors = rotation_angle_deg(np.swapaxes(np.stack(increments), 1, 2) @ truth_steps)
    rows["graph (bias online): motion X_k-1 -> X_k solved at frame k"] = {
        "rms_deg": float(np.sqrt(np.mean(increment_errors**2))),
        "max_deg": float(increment_errors.max()),
    }
    bias_error = np.linalg.norm(estimates - bias, axis=1)
    half = len(bias_error) // 2
    result = {
        "steps": len(stamps) - 1,
        "duration_s": float((stamps[-1] - stamps[0]) * 1e-9),
        "rotation_per_step": rows,
        "bias_error_final_rad_s": float(bias_error[-1]),
        "bias_error_mean_second_half_rad_s": float(bias_error[half:].mean()),
        "bias_true_final_rad_s": bias[-1].tolist(),
        "bias_estimated_final_rad_s": estimates[-1].tolist(),
        "bias_error_initial_rad_s": float(np.linalg.norm(bias[0])),
    }
    table = _table(
        f"Real gyro, EuRoC V1_02 ({result['steps']} steps of 50 ms, {result['duration_s']:.0f} s)",
        ["relative rotation per 20 Hz step", "RMS deg", "max deg"],
        [[name, f"{row['rms_deg']:.4f}", f"{row['max_deg']:.4f}"] for name, row in rows.items()],
    )
    table += (
        f"\nOnline gyro bias (starts at 0; true |b| = {result['bias_error_initial_rad_s']:.4f} "
        f"rad/s): final error {result['bias_error_final_rad_s']:.4f} rad/s, mean over the "
        f"second half {result['bias_error_mean_second_half_rad_s']:.4f} rad/s.\n"
    )
    return result, table


# ----------------------------------------------------------------------------- 2. simulated


def _drive(scenario, measurements, config: BackendConfig, imu: bool):
    backend = FusionBackend(config, SIM_BODY_FROM_CAMERA, ImuNoise() if imu else None)
    stamps = scenario.timestamps_ns
    poses, seconds, statuses = [], [], Counter()
    for k, measurement in enumerate(measurements):
        start = stamps[k - 1] if k else stamps[0] - 10**9
        batch = scenario.imu.between(int(start), int(stamps[k])) if imu else None
        begin = time.perf_counter()
        out = backend.add_frame(
            int(stamps[k]),
            None if k == 0 else measurement.relative_pose,
            measurement.residuals,
            measurement.inlier_count,
            batch,
        )
        seconds.append(time.perf_counter() - begin)
        poses.append(out.pose)
        statuses[str(out.status)] += 1
    return np.stack(poses), np.asarray(seconds), dict(statuses)


def bench_simulated(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    scenario = smooth_trajectory(args.frames, seed=args.seed)
    truth = scenario.body_poses @ SIM_BODY_FROM_CAMERA
    path = float(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum())
    runs = [
        ("fixed-lag, IMU", BackendConfig(), True),
        ("fixed-lag, no IMU", BackendConfig(), False),
    ]
    result: dict[str, Any] = {"frames": args.frames, "path_length_m": path, "cases": {}}
    rows = []
    for broken in (0.0, 0.2):
        measurements = simulate_frontend(
            scenario.body_poses, SIM_BODY_FROM_CAMERA, seed=args.seed + 1, broken_fraction=broken
        )
        relative = [m.relative_pose for m in measurements]
        case: dict[str, Any] = {
            "front end, hold on failure": {"ate_m": aligned_ate(chain(relative, hold=True), truth)},
            "front end, constant velocity on failure": {
                "ate_m": aligned_ate(chain(relative, hold=False), truth)
            },
        }
        for name, config, imu in runs:
            poses, seconds, statuses = _drive(scenario, measurements, config, imu)
            ate = aligned_ate(poses, truth)
            case[name] = {"ate_m": ate, "statuses": statuses, **_ms_stats(seconds)}
        if broken > 0.0:
            # Full-history iSAM2 on the first frames only: enough to show its cost growing.
            count = min(args.isam2_frames, args.frames)
            short = Scenario(
                scenario.timestamps_ns[:count],
                scenario.body_poses[:count],
                scenario.imu,
                scenario.gyro_bias,
            )
            poses, seconds, statuses = _drive(
                short, measurements[:count], BackendConfig(smoother="isam2"), True
            )
            case[f"iSAM2 full history, IMU (first {count} frames)"] = {
                "ate_m": aligned_ate(poses, truth[:count]),
                "statuses": statuses,
                **_ms_stats(seconds),
            }
        best_frontend = min(case[k]["ate_m"] for k in list(case)[:2])
        if broken > 0.0:
            count = min(args.isam2_frames, args.frames)
            # The short run is compared with the front end over the same frames.
            case_short = min(
                aligned_ate(chain(relative[:count], hold=h), truth[:count]) for h in (True, False)
            )
        else:
            case_short = best_frontend
        for name, row in case.items():
            reference = case_short if name.startswith("iSAM2") else best_frontend
            gain = 100.0 * (1.0 - row["ate_m"] / reference)
            timing = (
                f"{row['p50_ms']:.2f} / {row['p95_ms']:.2f} / {row['max_ms']:.1f} | "
                f"{row['first10pct_p50_ms']:.2f} -> {row['last10pct_p50_ms']:.2f}"
                if "p50_ms" in row
                else "- | -"
            )
            lost = row.get("statuses", {}).get("lost", 0)
            rows.append(
                [
                    f"{broken:.0%}",
                    name,
                    f"{row['ate_m']:.3f}",
                    f"{gain:+.0f} %",
                    str(lost) if "statuses" in row else "-",
                    timing,
                ]
            )
        result["cases"][f"broken_{broken:.2f}"] = case
    table = _table(
        f"Simulated: {args.frames} frames at 20 Hz, {path:.0f} m path, 200 Hz IMU "
        f"(seed {args.seed})",
        [
            "broken",
            "trajectory",
            "ATE m",
            "vs best front end",
            "lost",
            "back end ms p50 / p95 / max",
            "p50 first -> last 10 %",
        ],
        rows,
    )
    return result, table


# ----------------------------------------------------------------------------- 3. pipeline


# Whole-pipeline runs of this benchmark, by (sequence folder, seed, IMU): the default rendered
# seed appears both in the detailed table and in the per-seed one, and runs only once.
_Runs = dict[tuple[Path, int, bool], "RunResult"]


def _pipeline_run(runs: _Runs, path: Path, seed: int, imu: bool) -> RunResult:
    """``RunResult`` of the default pipeline (pso-robust, back end on) on ``path``."""
    from estimator.formats.datasets import open_sequence
    from estimator.pipeline import build_config, run_sequence
    from estimator.registration.methods import DEFAULT_ESTIMATOR

    key = (path, seed, imu)
    if key not in runs:
        config = build_config(DEFAULT_ESTIMATOR, seed, imu=imu, backend=True)
        runs[key] = run_sequence(open_sequence(path), config, use_imu=imu)
    return runs[key]


def _metrics(run: RunResult, which: str) -> dict[str, Any]:
    """Trajectory metrics of one kind of pose of a run (see ``RunResult.poses``)."""
    from estimator.evaluation.metrics import evaluate_trajectory

    sequence = run.sequence
    return evaluate_trajectory(
        run.timestamps_ns, run.poses(which), sequence.ground_truth, sequence.rig.left.T_BS
    ).metrics


def _status_text(statuses: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(statuses.items()))


def _pipeline_runs(
    runs: _Runs, name: str, path: Path, seed: int
) -> tuple[dict[str, Any], list[list[str]]]:
    result: dict[str, Any] = {}
    rows = []
    for imu in (True, False):
        run = _pipeline_run(runs, path, seed, imu)
        fuse = np.array([r.timings_s.get("fuse", np.nan) for r in run.reports])
        statuses = dict(Counter(str(r.status) for r in run.reports))
        rejected = sum("rejected" in r.message for r in run.reports)
        suffix = "IMU" if imu else "no IMU"
        variants = [(f"fused, {suffix}", "pose"), (f"fused smoothed, {suffix}", "smoothed")]
        if imu:
            variants.insert(0, ("front end only", "frontend_pose"))
        for label, which in variants:
            metrics = _metrics(run, which)
            entry = {
                "ate_rmse_m": metrics["ate_rmse_m"],
                "final_drift_m": metrics["final_drift_m"],
                "final_rot_drift_deg": metrics["final_rot_drift_deg"],
            }
            if which != "frontend_pose":
                entry.update(
                    statuses=statuses,
                    rejected_by_gate=rejected,
                    fuse_p50_ms=float(np.nanmedian(fuse) * 1e3),
                    fuse_max_ms=float(np.nanmax(fuse) * 1e3),
                )
            result[label] = entry
            rows.append(
                [
                    name,
                    label,
                    f"{entry['ate_rmse_m']:.4f}",
                    f"{entry['final_drift_m']:.4f}",
                    f"{entry['final_rot_drift_deg']:.3f}",
                    _status_text(statuses) if which != "frontend_pose" else "-",
                    f"{entry['fuse_p50_ms']:.1f} / {entry['fuse_max_ms']:.1f}"
                    if which != "frontend_pose"
                    else "-",
                ]
            )
    return result, rows


def _rendered(args: argparse.Namespace, seed: int) -> Path:
    """The rendered 20 %-broken sequence of ``seed``, written once into ``--data``."""
    from estimator.rendered.synthetic import SynthOptions, synthesize

    still = f"_still{args.standstill_s:g}s" if args.standstill_s > 0 else ""
    rendered = args.data / f"backend_rendered_{args.rendered_frames}f_broken20{still}_seed{seed}"
    if not (rendered / "mav0").is_dir():
        synthesize(
            rendered,
            SynthOptions(
                frames=args.rendered_frames,
                seed=seed,
                broken_fraction=0.2,
                standstill_s=args.standstill_s,
            ),
        )
    return rendered


def _seed_rows(args: argparse.Namespace, runs: _Runs) -> tuple[dict[str, Any], str]:
    """Front end vs fused (online and smoothed) ATE of the whole pipeline, one rendered seed
    per row, with IMU; the change is against the front end's ATE (target: -30 % or better)."""
    result: dict[str, Any] = {}
    rows = []
    changes: dict[str, list[float]] = {"pose": [], "smoothed": []}
    for seed in args.seeds:
        run = _pipeline_run(runs, _rendered(args, seed), seed, imu=True)
        ate = {
            which: _metrics(run, which)["ate_rmse_m"]
            for which in ("frontend_pose", "pose", "smoothed")
        }
        statuses = dict(Counter(str(r.status) for r in run.reports))
        change = {w: 100.0 * (ate[w] / ate["frontend_pose"] - 1.0) for w in changes}
        for which in changes:
            changes[which].append(change[which])
        result[str(seed)] = {"ate_m": ate, "change_pct": change, "statuses": statuses}
        rows.append(
            [
                str(seed),
                f"{1e3 * ate['frontend_pose']:.2f}",
                f"{1e3 * ate['pose']:.2f}",
                f"{change['pose']:+.1f} %",
                f"{1e3 * ate['smoothed']:.2f}",
                f"{change['smoothed']:+.1f} %",
                _status_text(statuses),
            ]
        )
    for which, label in (("pose", "online"), ("smoothed", "smoothed")):
        values = np.array(changes[which])
        met = int(np.sum(values <= -30.0))
        result[f"{label}_met"] = met
        result[f"{label}_mean_change_pct"] = float(values.mean())
        rows.append(
            [f"**{label}**", "", "", f"mean {values.mean():+.1f} %, {met}/{len(values)} <= -30 %"]
            + [""] * 3
        )
    table = _table(
        f"Rendered seeds ({args.rendered_frames} frames, 20 % broken, simulated IMU): "
        "ATE front end vs fused",
        [
            "seed",
            "front end mm",
            "fused mm",
            "change",
            "fused smoothed mm",
            "change",
            "statuses (fused)",
        ],
        rows,
    )
    return result, table


def bench_pipeline(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    rendered = _rendered(args, args.seed)
    label = "rendered, 20 % broken" + (
        f", {args.standstill_s:g} s standstill" if args.standstill_s > 0 else ""
    )
    datasets = {label: rendered}
    if (args.euroc_micro / "mav0").is_dir():
        datasets["EuRoC V1_01 micro"] = args.euroc_micro
    result: dict[str, Any] = {}
    rows: list[list[str]] = []
    runs: _Runs = {}
    for name, path in datasets.items():
        result[name], new_rows = _pipeline_runs(runs, name, path, args.seed)
        rows += new_rows
    table = _table(
        "Whole pipeline (Odometry, pso-robust): front end only vs fused",
        [
            "sequence",
            "trajectory",
            "ATE m",
            "final drift m",
            "final rot deg",
            "statuses",
            "fuse ms p50 / max",
        ],
        rows,
    )
    if args.seeds:
        result["seeds"], seed_table = _seed_rows(args, runs)
        table += "\n" + seed_table
    return result, table


# ----------------------------------------------------------------------------- entry point


def run(args: argparse.Namespace) -> int:
    if args.frames < 10:
        raise ValueError(f"--frames must be at least 10, got {args.frames}")
    if not 0.0 <= args.standstill_s <= 60.0:  # also refuses NaN, before anything is written
        raise ValueError(f"--standstill-s must be in [0, 60] s, got {args.standstill_s}")
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    parts = {"gyro": bench_gyro, "simulated": bench_simulated, "pipeline": bench_pipeline}
    results: dict[str, Any] = {}
    tables = []
    for name in args.parts:
        begin = time.perf_counter()
        results[name], table = parts[name](args)
        results[name]["wall_s"] = time.perf_counter() - begin
        print(table, flush=True)
        tables.append(table)
        # Written after every part, so a long run keeps what it has measured.
        (out / "backend.json").write_text(json.dumps(results, indent=2))
        (out / "backend.md").write_text("\n".join(tables))
    print(f"wrote {out / 'backend.json'} and {out / 'backend.md'}")
    return 0
