"""``swarmvo synth OUT_DIR``: render a stereo + IMU sequence with exact ground truth.

``--scenario flight`` (a EuRoC-like drone in a hall) or ``driving`` (a KITTI-like car in a
street). The output is an EuRoC/ASL folder (``OUT_DIR/mav0``), or with ``--layout kitti`` a
KITTI odometry folder (image_0/, image_1/, calib.txt, times.txt, poses.txt; no IMU), that
``swarmvo run`` reads unchanged.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path
from typing import get_args

from tqdm import tqdm

from estimator.rendered.camera import CAMERAS
from estimator.rendered.synthetic import (
    SCENARIO_CAMERAS,
    Layout,
    Scenario,
    SynthOptions,
    synthesize,
)


def _scenario_defaults(scenario: str) -> SynthOptions:
    return SynthOptions.driving() if scenario == "driving" else SynthOptions()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    flight, driving = SynthOptions(), SynthOptions.driving()

    def both(name: str, unit: str = "") -> str:
        flown, driven = getattr(flight, name), getattr(driving, name)
        return f"default {flown}{unit} (flight), {driven}{unit} (driving)"

    parser.add_argument("out_dir", type=Path, help="output folder (mav0/ is created inside)")
    parser.add_argument(
        "--scenario",
        choices=get_args(Scenario),
        default="flight",
        help="flight: EuRoC-like drone in a hall; driving: KITTI-like car in a street",
    )
    parser.add_argument(
        "--layout",
        choices=get_args(Layout),
        default="euroc",
        help="euroc: mav0/ with IMU and ground truth; kitti: image_0/, image_1/, calib.txt, "
        "times.txt, poses.txt (no IMU)",
    )
    pairs = ", ".join(
        f"{name} ({c.width}x{c.height}, {c.baseline * 100:g} cm)" for name, c in CAMERAS.items()
    )
    defaults = ", ".join(f"{camera} ({scenario})" for scenario, camera in SCENARIO_CAMERAS.items())
    parser.add_argument(
        "--camera", choices=tuple(CAMERAS), help=f"the stereo pair: {pairs}; default {defaults}"
    )
    parser.add_argument("--frames", type=int, help=both("frames"))
    parser.add_argument("--length-m", type=float, help="path length; " + both("length_m", " m"))
    parser.add_argument("--fps", type=float, help=both("fps"))
    parser.add_argument("--imu-rate-hz", type=float, help=both("imu_rate_hz"))
    parser.add_argument("--seed", type=int, default=flight.seed)
    parser.add_argument("--noise", type=float, default=0.0, help="image noise sigma [grey levels]")
    parser.add_argument(
        "--brightness", type=float, default=0.0, help="relative amplitude of gain changes"
    )
    parser.add_argument(
        "--blur", type=float, default=0.0, help="motion blur: exposure / frame interval (0..1)"
    )
    parser.add_argument(
        "--right-delay-ms",
        type=float,
        default=0.0,
        help="right shutter this many ms after the left (cameras without a shared trigger)",
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
        default=flight.imu_noise_scale,
        help="1 = EuRoC ADIS16448 noise and bias walk, 0 = perfect IMU",
    )
    parser.add_argument(
        "--standstill-s",
        type=float,
        default=flight.standstill_s,
        help="seconds the body stands still before flying (extra frames before the flight)",
    )
    parser.add_argument(
        "--traffic",
        type=float,
        default=0.0,
        help="driving: moving vehicles per 100 m of road (oncoming and in the next lane), "
        "plus a lead vehicle a fixed gap ahead in the car's lane (0: a static street)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    defaults = _scenario_defaults(args.scenario)
    given = {
        "frames": args.frames,
        "length_m": args.length_m,
        "fps": args.fps,
        "imu_rate_hz": args.imu_rate_hz,
    }
    options = replace(
        defaults,
        **{name: value for name, value in given.items() if value is not None},
        layout=args.layout,
        camera=args.camera,
        seed=args.seed,
        noise=args.noise,
        brightness=args.brightness,
        blur=args.blur,
        right_delay_ms=args.right_delay_ms,
        broken_fraction=args.broken_fraction,
        imu_noise_scale=args.imu_noise_scale,
        standstill_s=args.standstill_s,
        traffic=args.traffic,
    )
    options.validate()
    start = time.perf_counter()
    frames = options.frames + round(options.standstill_s * options.fps)
    with tqdm(total=frames, unit="frame", disable=args.quiet) as bar:
        result = synthesize(args.out_dir, options, progress=bar.update)
    where = result.root / "mav0" if options.layout == "euroc" else result.root
    print(
        f"rendered {frames} stereo frames ({options.scenario}, {options.layout} layout), body "
        f"path {result.path_length_m:.2f} m, {len(result.broken)} broken, in "
        f"{time.perf_counter() - start:.1f} s -> {where}"
    )
    return 0
