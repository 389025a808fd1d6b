"""``swarmvo bench driving``: the pipeline on rendered KITTI-like drives.

Renders (once, reused afterwards) one drive per seed (``swarmvo synth --scenario driving
--layout kitti``: 1241x376, 718.9 px, 0.54 m baseline, 10 Hz, 8-15 m/s with turns, street
structure from 3 m to beyond 80 m; no IMU, as KITTI's odometry benchmark) and runs each
estimator through ``swarmvo run``'s pipeline with the default configuration (settings derived
from the rig). Per run: final drift (% of path), RPE rotation (deg per frame), frames not
tracked, median temporal matches per frame, frames/s, and KITTI's segment errors. Writes
``driving.json`` and ``driving.md`` (the printed table) and checks the targets (final drift
<= 1 %, <= 0.03 deg/frame, no frame lost, median >= 300 matches/frame, >= 30 frames/s).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from estimator.formats.datasets import open_sequence
from estimator.pipeline import ESTIMATORS, build_config, run_sequence, write_outputs
from estimator.registration.methods import Estimator
from estimator.rendered.synthetic import SynthOptions, synthesize

__all__ = ["add_arguments", "run"]

TARGETS = {
    "final_drift_pct": 1.0,
    "rpe_rot_rmse_deg": 0.03,
    "frames_failed": 0,
    "matches_median": 300,
    "fps": 30.0,
}
COLUMNS = (
    ("final_drift_pct", "drift %", "{:.2f}"),
    ("rpe_rot_rmse_deg", "deg/frame", "{:.4f}"),
    ("frames_failed", "lost", "{:d}"),
    ("matches_median", "matches", "{:.0f}"),
    ("fps", "frames/s", "{:.1f}"),
    ("kitti_trans_err_pct", "KITTI t %", "{:.2f}"),
    ("kitti_rot_err_deg_per_100m", "KITTI deg/100m", "{:.3f}"),
    ("path_length_m", "path m", "{:.0f}"),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/driving"))
    parser.add_argument("--frames", type=int, default=470)
    parser.add_argument("--length-m", type=float, default=520.0, help="drive length [m]")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument(
        "--estimators",
        nargs="+",
        choices=ESTIMATORS,
        default=[Estimator.PSO_ROBUST.value, Estimator.MSAC.value],  # the swarm and the classic
    )
    parser.add_argument(
        "--data",
        type=Path,
        default=Path(tempfile.gettempdir()) / "swarmvo-bench",
        help="where the rendered drives are written once and reused (kept out of --out)",
    )
    parser.add_argument("--quick", action="store_true", help="40 frames / 44 m, one seed")
    parser.add_argument(
        "--no-rig-settings",
        dest="rig_settings",
        action="store_false",
        help="keep the EuRoC-tuned frontend defaults (for comparison)",
    )


def _rendered(args: argparse.Namespace, seed: int) -> Path:
    frames, length = (40, 44.0) if args.quick else (args.frames, args.length_m)
    root = args.data / f"driving_{frames}f_{length:g}m_seed{seed}"
    if not (root / "image_0").is_dir():
        options = SynthOptions.driving(frames=frames, length_m=length, seed=seed, layout="kitti")
        synthesize(root, options)
    return root


def _row(label: str, metrics: dict[str, Any]) -> str:
    cells = []
    for key, _, fmt in COLUMNS:
        value = metrics.get(key)
        cells.append("-" if value is None else fmt.format(value))
    return f"| {label} | " + " | ".join(cells) + " |"


def _verdict(metrics: dict[str, Any]) -> str:
    """PASS/MISS of each target (drift and rotation: at most; matches and speed: at least)."""
    checks = []
    for key, target in TARGETS.items():
        value = metrics.get(key)
        at_least = key in ("matches_median", "fps")
        ok = value is not None and (value >= target if at_least else value <= target)
        checks.append(f"{key} {'PASS' if ok else 'MISS'}")
    return ", ".join(checks)


def _table(results: dict[str, dict[str, dict[str, Any]]]) -> str:
    header = "| estimator / seed | " + " | ".join(title for _, title, _ in COLUMNS) + " |"
    lines = [header, "|" + "---|" * (len(COLUMNS) + 1)]
    verdicts = []
    for estimator, runs in results.items():
        for seed, summary in runs.items():
            lines.append(_row(f"{estimator} seed {seed}", summary))
        worst = {
            key: (
                min(r[key] for r in runs.values() if r.get(key) is not None)
                if key in ("matches_median", "fps")
                else max(r[key] for r in runs.values() if r.get(key) is not None)
            )
            for key in TARGETS
        }
        mean = {
            key: float(np.mean([r[key] for r in runs.values() if r.get(key) is not None]))
            for key, _, _ in COLUMNS
            if any(r.get(key) is not None for r in runs.values())
        }
        mean["frames_failed"] = int(sum(r["frames_failed"] for r in runs.values()))
        lines.append(_row(f"**{estimator} mean** (lost: total)", mean))
        verdicts.append(f"{estimator}, worst seed: {_verdict(worst)}")
    return "\n".join([*lines, "", *verdicts]) + "\n"


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    seeds = args.seeds[:1] if args.quick else args.seeds
    results: dict[str, dict[str, dict[str, Any]]] = {e: {} for e in args.estimators}
    for seed in seeds:
        sequence = open_sequence(_rendered(args, seed), "kitti")
        for estimator in args.estimators:
            config = build_config(estimator, seed=0)
            result = run_sequence(
                sequence, config, use_imu=False, progress=True, rig_settings=args.rig_settings
            )
            summary = write_outputs(result, out / f"seed{seed}" / estimator)
            results[estimator][str(seed)] = summary
            print(_row(f"{estimator} seed {seed}", summary), flush=True)
    table = _table(results)
    print("\n" + table)
    if not args.quick:
        (out / "driving.md").write_text(table)
        (out / "driving.json").write_text(json.dumps(results, indent=2) + "\n")
    return 0
