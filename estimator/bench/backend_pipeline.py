"""``swarmvo bench backend``, part ``pipeline``: the whole ``Odometry``, front end vs fused.

On a rendered sequence with 20 % broken frames and on EuRoC V1_01 micro (standing still, real
IMU): front-end-only vs fused (the online answer per frame, and the smoother's final
estimates) with / without IMU. With ``--seeds`` it also renders one sequence per seed and
tabulates front end vs fused ATE for each.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimator.bench.markdown import titled_table

if TYPE_CHECKING:
    from estimator.pipeline import RunResult

__all__ = ["bench_pipeline"]


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
    table = titled_table(
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
    table = titled_table(
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
