"""``swarmvo synth OUT_DIR``: render a stereo + IMU sequence with exact ground truth.

The output is an EuRoC/ASL folder (``OUT_DIR/mav0``) that ``swarmvo run`` reads unchanged.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from tqdm import tqdm

from estimator.synthetic import SynthOptions, synthesize


def add_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = SynthOptions()
    parser.add_argument("out_dir", type=Path, help="output folder (mav0/ is created inside)")
    parser.add_argument("--frames", type=int, default=defaults.frames)
    parser.add_argument(
        "--length-m", type=float, default=defaults.length_m, help="body path length [m]"
    )
    parser.add_argument("--fps", type=float, default=defaults.fps)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--noise", type=float, default=0.0, help="image noise sigma [grey levels]")
    parser.add_argument(
        "--brightness", type=float, default=0.0, help="relative amplitude of gain changes"
    )
    parser.add_argument(
        "--blur", type=float, default=0.0, help="motion blur: exposure / frame interval (0..1)"
    )
    parser.add_argument(
        "--broken-fraction",
        type=float,
        default=0.0,
        help="fraction of frames to break (black, heavy blur or a shuffled right image); "
        "listed in OUT_DIR/broken_frames.csv",
    )
    parser.add_argument(
        "--imu-noise-scale",
        type=float,
        default=defaults.imu_noise_scale,
        help="1 = EuRoC ADIS16448 noise and bias walk, 0 = perfect IMU",
    )
    parser.add_argument(
        "--standstill-s",
        type=float,
        default=defaults.standstill_s,
        help="seconds the body stands still before flying (extra frames before the flight)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    options = SynthOptions(
        frames=args.frames,
        length_m=args.length_m,
        fps=args.fps,
        seed=args.seed,
        noise=args.noise,
        brightness=args.brightness,
        blur=args.blur,
        broken_fraction=args.broken_fraction,
        imu_noise_scale=args.imu_noise_scale,
        standstill_s=args.standstill_s,
    )
    options.validate()
    start = time.perf_counter()
    frames = options.frames + round(options.standstill_s * options.fps)
    with tqdm(total=frames, unit="frame", disable=args.quiet) as bar:
        result = synthesize(args.out_dir, options, progress=bar.update)
    print(
        f"rendered {frames} stereo frames, body path {result.path_length_m:.2f} m, "
        f"{len(result.broken)} broken, in {time.perf_counter() - start:.1f} s -> "
        f"{result.root / 'mav0'}"
    )
    return 0
