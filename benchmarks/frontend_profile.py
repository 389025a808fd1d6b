"""Where a frame's CPU time goes, per function and per OpenCV call, on one core.

``swarmvo bench frontend`` times the stages; this profiles the functions inside them: a fresh
odometry (vision alone, back end off, the settings derived from the rig as in ``swarmvo run``
and ``bench frontend`` unless ``--no-rig-settings``) runs over a clip held in memory under
``cProfile`` with CPU time (``time.process_time``: on a shared machine wall time also counts
waiting for a core), after a short warm-up (compiled kernels, first allocations). Each row
is one function with its calls, own time and cumulative time per frame, in milliseconds,
ordered by own time or, with ``--sort cumulative``, by cumulative time (where a stage's
functions sit together).

    OMP_NUM_THREADS=1 python benchmarks/frontend_profile.py --data ../shared/data/euroc_mh01_moving

Prints a Markdown table and writes ``profile.md`` and ``profile.json`` to ``--out``
(docs/performance.md, "Offline front end").
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import sys
import time
from pathlib import Path
from typing import Any

import cv2

from estimator.bench.frontend import bench_config
from estimator.config import SwarmvoConfig
from estimator.formats.datasets import open_sequence
from estimator.odometry import Odometry

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "euroc_mh01_moving"
WARM_UP_FRAMES = 3
SORT_KEYS = ("own", "cumulative")


def profile_rows(
    stats: pstats.Stats, frames: int, top: int, sort: str = "own"
) -> list[dict[str, Any]]:
    """The ``top`` functions by own (or ``sort="cumulative"``) time, with calls, own and
    cumulative ms per frame."""
    if sort not in SORT_KEYS:
        raise ValueError(f"sort must be one of {SORT_KEYS}, got {sort!r}")
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    rows = []
    for (path, line, name), (_, calls, own, cumulative, _) in stats.stats.items():  # type: ignore[attr-defined]
        where = f"{Path(path).name}:{line}" if line else path
        rows.append(
            {
                "function": f"{name} ({where})" if path != "~" else name,
                "calls_per_frame": calls / frames,
                "own_ms_per_frame": own * 1e3 / frames,
                "cumulative_ms_per_frame": cumulative * 1e3 / frames,
            }
        )
    rows.sort(key=lambda row: (-row[f"{sort}_ms_per_frame"], row["function"]))
    return rows[:top]


def markdown(rows: list[dict[str, Any]], title: str) -> str:
    lines = [
        title,
        "",
        "| function | calls / frame | own ms / frame | cumulative ms / frame |",
        "|---|---:|---:|---:|",
    ]
    for row in rows:
        lines.append(
            f"| `{row['function']}` | {row['calls_per_frame']:.2f} | "
            f"{row['own_ms_per_frame']:.3f} | {row['cumulative_ms_per_frame']:.3f} |"
        )
    return "\n".join(lines) + "\n"


def _profile(data: Path, frames: int | None, rig_settings: bool) -> tuple[pstats.Stats, int]:
    sequence = open_sequence(data)
    count = len(sequence) if frames is None else min(frames, len(sequence))
    if count < 2:
        raise ValueError(f"need at least 2 frames, {data} gives {count}")
    loaded = [sequence.load(i) for i in range(count)]
    # Only the back end marked as set: a dump of the whole model would mark every field as
    # the user's, and no rig-derived setting would take effect.
    config = SwarmvoConfig.model_validate({"backend": {"enabled": False}})
    config, _ = bench_config(config, sequence, rig_settings)
    warm_up = Odometry(sequence.rig, config, imu_noise=sequence.imu_noise)
    for frame in loaded[:WARM_UP_FRAMES]:
        warm_up.process(frame)
    odometry = Odometry(sequence.rig, config, imu_noise=sequence.imu_noise)
    profiler = cProfile.Profile(time.process_time)
    profiler.enable()
    for frame in loaded:
        odometry.process(frame)
    profiler.disable()
    return pstats.Stats(profiler), count


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="EuRoC sequence")
    parser.add_argument("--frames", type=int, default=None, help="use only the first N frames")
    parser.add_argument("--top", type=int, default=30, help="rows of the table")
    parser.add_argument("--sort", choices=SORT_KEYS, default="own", help="order of the rows")
    parser.add_argument(
        "--no-rig-settings", dest="rig_settings", action="store_false",
        help="keep the configuration's defaults instead of deriving settings from the rig",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("/tmp/frontend-profile"))
    args = parser.parse_args(argv)
    if args.top < 1 or (args.frames is not None and args.frames < 2):
        print("error: --top must be >= 1 and --frames >= 2", file=sys.stderr)
        return 2
    cv2.setNumThreads(1)
    try:
        stats, count = _profile(args.data, args.frames, args.rig_settings)
    except (OSError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    rows = profile_rows(stats, count, args.top, args.sort)
    title = (
        f"CPU profile of {count} frames of {args.data.name} (vision alone, back end off, "
        f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}, load average "
        f"{os.getloadavg()[0]:.1f})"
    )
    table = markdown(rows, title)
    print(table, end="")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "profile.md").write_text(table)
    (args.out / "profile.json").write_text(json.dumps({"frames": count, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
