"""``swarmvo bench driving``: the pipeline on rendered KITTI-like drives.

Renders (once, reused afterwards) one drive per seed (``swarmvo synth --scenario driving``:
1241x376, 718.9 px, 0.54 m baseline, 10 Hz, 8-15 m/s with turns, street structure from 3 m to
beyond 80 m, a simulated 100 Hz IMU) and runs each estimator through ``swarmvo run``'s
pipeline with the default configuration (settings derived from the rig), in each ``--modes``:
``vision`` alone (no IMU, as KITTI's odometry benchmark) and ``fused`` with the IMU. With a
fused mode the drives are written in the EuRoC layout (which has the IMU) and both modes run
on the same files; vision alone uses KITTI's layout (no IMU; its poses also in KITTI's format).
Per run: final drift (% of path), RPE rotation (deg per frame), frames not tracked, median
temporal matches per frame, frames/s, and KITTI's segment errors. Writes ``driving.json``
(estimator -> mode -> seed) and ``driving.md`` (the printed table) and checks the targets
(final drift <= 1 %, <= 0.03 deg/frame, no frame lost, median >= 300 matches/frame, >= 30
frames/s) and that fused is no worse than vision in rotation. ``--traffic``, ``--noise``,
``--blur`` and ``--brightness`` render the drives among moving vehicles and through imperfect
cameras (as ``swarmvo synth`` takes them): rendered images are cleaner than a real car's, so the
targets are also checked with sensor noise, motion blur and gain changes.
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
from estimator.rendered.synthetic import Layout, SynthOptions, synthesize

__all__ = ["MODES", "add_arguments", "run"]

MODES = ("vision", "fused")

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
        "--traffic",
        type=float,
        default=0.0,
        help="moving vehicles per 100 m of road and a lead vehicle (swarmvo synth --traffic)",
    )
    parser.add_argument("--noise", type=float, default=0.0, help="image noise sigma [grey levels]")
    parser.add_argument(
        "--blur", type=float, default=0.0, help="motion blur: exposure / frame interval (0..1)"
    )
    parser.add_argument(
        "--brightness", type=float, default=0.0, help="relative amplitude of gain changes"
    )
    parser.add_argument(
        "--modes",
        nargs="+",
        choices=MODES,
        default=list(MODES),
        help="vision alone and/or fused with the rendered IMU (the EuRoC layout then)",
    )
    parser.add_argument(
        "--no-rig-settings",
        dest="rig_settings",
        action="store_false",
        help="keep the EuRoC-tuned frontend defaults (for comparison)",
    )


def _layout(modes: list[str]) -> Layout:
    """KITTI's layout for vision alone (as KITTI has no IMU), EuRoC's when fused runs too."""
    return "euroc" if "fused" in modes else "kitti"


def _scene(args: argparse.Namespace) -> dict[str, float]:
    """What the drives are rendered with beyond the defaults: traffic and the cameras'
    imperfections (as ``swarmvo synth`` takes them), only those that are set."""
    values = {name: getattr(args, name) for name in ("traffic", "noise", "blur", "brightness")}
    return {name: value for name, value in values.items() if value}


def _scene_note(scene: dict[str, float]) -> str:
    """The table's first lines: what the drives had beyond a static street and ideal cameras."""
    lines = []
    if "traffic" in scene:
        vehicles = f"{scene['traffic']:g} moving vehicles per 100 m and a lead vehicle"
        lines.append(f"With traffic: {vehicles}.")
    cameras = []
    if "noise" in scene:
        cameras.append(f"image noise sigma {scene['noise']:g} grey levels")
    if "blur" in scene:
        cameras.append(f"motion blur over {100 * scene['blur']:g} % of the frame interval")
    if "brightness" in scene:
        cameras.append(f"gains varying by +-{100 * scene['brightness']:g} % (per camera)")
    if cameras:
        lines.append("Cameras: " + ", ".join(cameras) + ".")
    return "".join(f"{line}\n\n" for line in lines)


def _rendered(args: argparse.Namespace, seed: int, layout: Layout) -> Path:
    frames, length = (40, 44.0) if args.quick else (args.frames, args.length_m)
    scene = _scene(args)
    suffix = ("" if layout == "kitti" else "_euroc") + "".join(
        f"_{name}{value:g}" for name, value in scene.items()
    )
    root = args.data / f"driving_{frames}f_{length:g}m_seed{seed}{suffix}"
    if not (root / ("image_0" if layout == "kitti" else "mav0")).is_dir():
        options = SynthOptions.driving(
            frames=frames, length_m=length, seed=seed, layout=layout, **scene
        )
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


def _fused_verdict(estimator: str, by_mode: dict[str, dict[str, dict[str, Any]]]) -> str | None:
    """Seeds where fused is worse in rotation than vision alone (beyond 5 %), if both ran."""
    vision, fused = by_mode.get("vision"), by_mode.get("fused")
    if not vision or not fused:
        return None
    worse = [
        seed
        for seed in fused
        if seed in vision
        and fused[seed]["rpe_rot_rmse_deg"] > 1.05 * vision[seed]["rpe_rot_rmse_deg"]
    ]
    if not worse:
        return f"{estimator}: fused rotation no worse than vision alone on every seed: PASS"
    return f"{estimator}: fused rotation worse than vision alone on seeds {', '.join(worse)}: MISS"


def _table(results: dict[str, dict[str, dict[str, dict[str, Any]]]]) -> str:
    header = "| estimator / mode / seed | " + " | ".join(t for _, t, _ in COLUMNS) + " |"
    lines = [header, "|" + "---|" * (len(COLUMNS) + 1)]
    verdicts = []
    for estimator, by_mode in results.items():
        for mode, runs in by_mode.items():
            lines.extend(_lane_rows(f"{estimator} {mode}", runs, verdicts))
        fused_verdict = _fused_verdict(estimator, by_mode)
        if fused_verdict is not None:
            verdicts.append(fused_verdict)
    return "\n".join([*lines, "", *verdicts]) + "\n"


def _lane_rows(label: str, runs: dict[str, dict[str, Any]], verdicts: list[str]) -> list[str]:
    """One lane's rows (a seed each, then the mean) and its worst-seed verdict."""
    lines = [_row(f"{label} seed {seed}", summary) for seed, summary in runs.items()]
    if runs:
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
        lines.append(_row(f"**{label} mean** (lost: total)", mean))
        verdicts.append(f"{label}, worst seed: {_verdict(worst)}")
    return lines


def run(args: argparse.Namespace) -> int:
    SynthOptions.driving(**_scene(args)).validate()  # before anything is written
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    seeds = args.seeds[:1] if args.quick else args.seeds
    modes = [mode for mode in MODES if mode in args.modes]
    layout = _layout(modes)
    results: dict[str, dict[str, dict[str, dict[str, Any]]]] = {
        estimator: {mode: {} for mode in modes} for estimator in args.estimators
    }
    for seed in seeds:
        sequence = open_sequence(_rendered(args, seed, layout), layout)
        for estimator in args.estimators:
            for mode in modes:
                config = build_config(estimator, seed=0)
                result = run_sequence(
                    sequence,
                    config,
                    use_imu=mode == "fused",
                    progress=True,
                    rig_settings=args.rig_settings,
                )
                summary = write_outputs(result, out / f"seed{seed}" / estimator / mode)
                results[estimator][mode][str(seed)] = summary
                print(_row(f"{estimator} {mode} seed {seed}", summary), flush=True)
    table = _scene_note(_scene(args)) + _table(results)
    print("\n" + table)
    if not args.quick:
        (out / "driving.md").write_text(table)
        (out / "driving.json").write_text(json.dumps(results, indent=2) + "\n")
    return 0
