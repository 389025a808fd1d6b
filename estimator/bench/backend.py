"""``swarmvo bench backend``: what the GTSAM back end adds, and what it costs per frame.

Three parts (one module each: ``backend_gyro``, ``backend_simulated``, ``backend_pipeline``),
each printed as a table and stored in ``backend.json`` / ``backend.md``:

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
from pathlib import Path
from typing import Any

from estimator.bench.backend_gyro import bench_gyro
from estimator.bench.backend_pipeline import bench_pipeline
from estimator.bench.backend_simulated import bench_simulated

__all__ = ["add_arguments", "run"]

SHARED = Path(__file__).resolve().parents[2].parent / "shared/data"


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


def run(args: argparse.Namespace) -> int:
    if args.frames < 10:
        raise ValueError(f"--frames must be at least 10, got {args.frames}")
    if args.seed < 0:  # NumPy's generators take no negative seed
        raise ValueError(f"--seed must be >= 0, got {args.seed}")
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
