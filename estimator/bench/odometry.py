"""``swarmvo bench odometry``: whole-pipeline accuracy of each estimator on full sequences.

Renders (once, reused afterwards) a loop with exact ground truth (``estimator.synthetic``:
default 200 frames, 21 m body path, EuRoC-like rig and IMU), clean and with sensor effects
(image noise, gain changes, motion blur), and, when present, uses the real EuRoC V1_01 micro
sequence (standing still). Every estimator runs the
same frames through ``Odometry`` with the GTSAM back end; the table lists the fused and the
front-end-only accuracy. Outputs ``odometry.json`` and ``odometry.md`` (the printed table)
plus one ``swarmvo run`` style folder per run (the rendered images go to ``--data``). The
rendered-sequence targets (ATE < 1 % of the path, RPE rotation < 0.1 deg/frame) are checked
for pso-robust and printed PASS/MISS.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import warnings
from pathlib import Path
from typing import Any

from estimator.commands.run import ESTIMATORS, build_config, run_sequence, write_outputs
from estimator.datasets import open_sequence
from estimator.synthetic import SynthOptions, synthesize

__all__ = ["add_arguments", "run"]

DEFAULT_EUROC = Path(__file__).resolve().parents[2].parent / "shared/data/euroc_v101_micro"
DATASETS = ("rendered", "rendered_noisy", "euroc_v101_micro")
# Sensor effects of the noisy variant: image noise, gain changes, motion blur, IMU as EuRoC.
NOISY_EFFECTS = {"noise": 4.0, "brightness": 0.25, "blur": 0.5}
TARGET_ATE_PCT = 1.0
TARGET_RPE_ROT_DEG = 0.1
COLUMNS = (
    ("ate_rmse_m", "ATE m", "{:.4f}"),
    ("ate_pct_of_path", "ATE %", "{:.2f}"),
    ("rpe_trans_rmse_m", "RPE m/fr", "{:.4f}"),
    ("rpe_rot_rmse_deg", "RPE deg/fr", "{:.3f}"),
    ("eq20_rms", "eq20 RMS", "{:.4f}"),
    ("final_drift_m", "drift m", "{:.3f}"),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/odometry"))
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--length-m", type=float, default=21.0, help="rendered body path [m]")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--estimators", nargs="+", choices=ESTIMATORS, default=list(ESTIMATORS))
    parser.add_argument(
        "--euroc", type=Path, default=DEFAULT_EUROC, help="EuRoC folder (skipped if absent)"
    )
    parser.add_argument(
        "--data",
        type=Path,
        default=Path(tempfile.gettempdir()) / "swarmvo-bench",
        help="where the rendered sequence is written once and reused (kept out of --out)",
    )
    parser.add_argument("--datasets", nargs="+", choices=DATASETS, default=list(DATASETS))
    parser.add_argument("--quick", action="store_true", help="40 frames / 4 m, for a smoke run")


def _row(label: str, metrics: dict[str, Any]) -> str:
    cells = [
        "-" if metrics.get(key) is None else fmt.format(metrics[key]) for key, _, fmt in COLUMNS
    ]
    return f"| {label} | " + " | ".join(cells) + " |"


def _rendered(args: argparse.Namespace, noisy: bool) -> Path:
    """The rendered loop (clean or with sensor effects), rendered once into ``--data``."""
    frames, length = (40, 4.0) if args.quick else (args.frames, args.length_m)
    effects = NOISY_EFFECTS if noisy else {}
    suffix = "_noisy" if noisy else ""
    root = args.data / f"rendered{suffix}_{frames}f_{length:g}m_seed{args.seed}"
    if not (root / "mav0").is_dir():
        synthesize(root, SynthOptions(frames=frames, length_m=length, seed=args.seed, **effects))
    return root


def _table(results: dict[str, dict[str, Any]]) -> str:
    header = "| estimator / poses | " + " | ".join(title for _, title, _ in COLUMNS) + " |"
    rule = "|" + "---|" * (len(COLUMNS) + 1)
    lines: list[str] = []
    for name in DATASETS:
        if name not in results:
            continue
        runs = results[name]
        first = next(iter(runs.values()))
        lines += [f"\n{name}: {first['frames']} frames", "", header, rule]
        for estimator, summary in runs.items():
            for section in ("fused", "frontend"):
                lines.append(_row(f"{estimator} {section}", summary[section]))
        lines.append(
            "\nframes failed: "
            + ", ".join(f"{e} {r['frames_failed']}" for e, r in runs.items())
            + "; median time per frame: "
            + ", ".join(
                f"{e} {r['median_stage_time_s'].get('total', float('nan')):.3f} s"
                for e, r in runs.items()
            )
        )
    fused = results.get("rendered", {}).get("pso-robust", {}).get("fused")
    if fused is not None:
        ate_ok = fused["ate_pct_of_path"] is not None and fused["ate_pct_of_path"] < TARGET_ATE_PCT
        rot_ok = fused["rpe_rot_rmse_deg"] < TARGET_RPE_ROT_DEG
        lines.append(
            f"\npso-robust on the rendered loop: ATE {fused['ate_pct_of_path']:.2f} % of path "
            f"(target < {TARGET_ATE_PCT} %) {'PASS' if ate_ok else 'MISS'}; RPE rotation "
            f"{fused['rpe_rot_rmse_deg']:.3f} deg/frame (target < {TARGET_RPE_ROT_DEG}) "
            f"{'PASS' if rot_ok else 'MISS'}"
        )
    return "\n".join(lines).strip() + "\n"


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    results_file = out / "odometry.json"
    # Runs of a subset of datasets update the stored results instead of discarding the rest.
    results: dict[str, dict[str, Any]] = (
        json.loads(results_file.read_text()) if results_file.is_file() and not args.quick else {}
    )
    for name in args.datasets:
        if name == "euroc_v101_micro":
            if args.euroc is None or not (args.euroc / "mav0").is_dir():
                print(f"skipping {name}: no EuRoC data at {args.euroc}")
                continue
            path = args.euroc
        else:
            path = _rendered(args, noisy=name == "rendered_noisy")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # unpaired camera rows are expected in EuRoC
            sequence = open_sequence(path)
        results[name] = {}
        for estimator in args.estimators:
            config = build_config(estimator, args.seed, imu=True, backend=True)
            result = run_sequence(sequence, config, progress=True)
            summary = write_outputs(result, out / name / estimator)
            results[name][estimator] = summary
            for section in ("fused", "frontend"):
                print(_row(f"{name} {estimator} {section}", summary[section]), flush=True)
    table = _table(results)
    print("\n" + table)
    (out / "odometry.md").write_text(table)
    results_file.write_text(json.dumps(results, indent=2) + "\n")
    return 0
