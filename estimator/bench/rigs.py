"""``swarmvo bench rigs``: ``swarmvo run`` without a configuration on other stereo rigs.

A user with a RealSense or a ZED pair runs the odometry with no config file: what depends on
the rig (depth range, feature budget, search window, ...) follows from its calibration and
frame rate (``estimator/rig_settings.py``). This renders (once, reused afterwards) the same
handheld-like flight for each rig of ``estimator/rendered/camera.py`` at its usual frame rate
(``swarmvo synth --camera``: a 20 m loop in 10 s through a textured hall, image noise, motion
blur, gain changes, a simulated IMU) and runs pso-robust on it vision alone and fused with the
IMU, with the derived settings (the default) and with the EuRoC-tuned constants alone
(``--no-rig-settings`` of ``swarmvo bench driving``; what the rig got before). Rendered
images, so this shows that each rig is tracked without a configuration, not how accurately
real ones are. One flight per ``--seeds`` (scene, textures, noise): a single flight's ATE moves by
10 % with the matches a setting changes. Writes ``rigs.json`` (rig -> settings -> mode -> seed
-> metrics) and ``rigs.md``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any

from estimator.formats.datasets import open_sequence
from estimator.pipeline import build_config, run_sequence, summarize
from estimator.rendered.cache import rendered_once
from estimator.rendered.camera import CAMERAS, CameraName
from estimator.rendered.synthetic import SynthOptions

__all__ = ["FRAME_RATES", "add_arguments", "rendered_flight", "run", "seed_mean", "table"]

# Each rig at the rate it usually streams at (the IMU at ten samples per frame).
FRAME_RATES: dict[CameraName, float] = {"euroc": 20.0, "realsense": 30.0, "zed": 30.0}
MODES = ("vision", "fused")
SETTINGS = {"derived": True, "euroc constants": False}  # label -> rig_settings
# A hand-held camera: sensor noise (grey levels), blur over half the frame interval, gain.
NOISE, BLUR, BRIGHTNESS = 3.0, 0.5, 0.2
FLIGHT_S, LENGTH_M = 10.0, 20.0
COLUMNS = (
    ("ate_rmse_m", "ATE mm", 1000.0, "{:.2f}"),
    ("final_drift_pct", "final drift %", 1.0, "{:.2f}"),
    ("rpe_rot_rmse_deg", "deg/frame", 1.0, "{:.4f}"),
    ("frames_failed", "lost", 1, "{:d}"),
    ("matches_median", "matches", 1.0, "{:.0f}"),
    ("fps", "frames/s", 1.0, "{:.1f}"),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/rigs"))
    parser.add_argument("--rigs", nargs="+", choices=tuple(FRAME_RATES), default=list(FRAME_RATES))
    parser.add_argument(
        "--seeds", type=int, nargs="+", default=[0, 1, 2], help="one rendered flight each"
    )
    parser.add_argument(
        "--data",
        type=Path,
        default=Path(tempfile.gettempdir()) / "swarmvo-bench",
        help="where the rendered flights are written once and reused (kept out of --out)",
    )


def rendered_flight(data: Path, rig: CameraName, seed: int, frames: int | None = None) -> Path:
    """The hand-held flight seen by ``rig``, rendered into ``data`` once (again when the
    renderer changed: estimator/rendered/cache.py)."""
    fps = FRAME_RATES[rig]
    frames = frames or round(FLIGHT_S * fps)
    options = SynthOptions(
        frames=frames, length_m=LENGTH_M * (frames - 1) / (FLIGHT_S * fps), fps=fps,
        imu_rate_hz=10 * fps, seed=seed, noise=NOISE, blur=BLUR, brightness=BRIGHTNESS,
        camera=rig,
    )  # fmt: skip
    options.validate()
    return rendered_once(data / f"flight_{rig}_{frames}f_seed{seed}", options)


def _row(label: str, metrics: dict[str, Any]) -> str:
    cells = []
    for key, _, scale, fmt in COLUMNS:
        value = metrics.get(key)
        cells.append("-" if value is None else fmt.format(value * scale))
    return f"| {label} | " + " | ".join(cells) + " |"


Runs = dict[str, dict[str, dict[str, dict[str, dict[str, Any]]]]]  # rig/settings/mode/seed


def seed_mean(by_seed: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The flights of one rig, settings and mode together: means, lost frames summed."""
    runs = list(by_seed.values())
    mean: dict[str, Any] = {
        key: sum(run[key] for run in runs) / len(runs)
        for key, *_ in COLUMNS
        if all(run.get(key) is not None for run in runs)
    }
    mean["frames_failed"] = sum(run["frames_failed"] for run in runs)
    return mean


def table(results: Runs) -> str:
    """Markdown: per rig, settings and mode a row per seed and their mean."""
    header = "| rig / settings / mode / seed | " + " | ".join(t for _, t, _, _ in COLUMNS) + " |"
    lines = [header, "|" + "---|" * (len(COLUMNS) + 1)]
    for rig, by_settings in results.items():
        camera = CAMERAS[rig]
        name = (
            f"{rig} ({camera.width}x{camera.height}, {camera.baseline * 100:g} cm, "
            f"{FRAME_RATES[rig]:g} Hz)"
        )
        for settings, by_mode in by_settings.items():
            for mode, by_seed in by_mode.items():
                label = f"{name} / {settings} / {mode}"
                lines += [_row(f"{label} / {seed}", run) for seed, run in by_seed.items()]
                lines.append(_row(f"**{label} / mean** (lost: total)", seed_mean(by_seed)))
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    results: Runs = {
        rig: {settings: {mode: {} for mode in MODES} for settings in SETTINGS}
        for rig in args.rigs
    }
    for rig in args.rigs:
        for seed in args.seeds:
            sequence = open_sequence(rendered_flight(args.data, rig, seed))
            for settings, derive in SETTINGS.items():
                for mode in MODES:
                    fused = mode == "fused"
                    result = run_sequence(
                        sequence, build_config(seed=0, imu=fused), use_imu=fused,
                        progress=True, rig_settings=derive,
                    )  # fmt: skip
                    metrics, _ = summarize(result)
                    results[rig][settings][mode][str(seed)] = metrics
                    print(_row(f"{rig} / {settings} / {mode} / {seed}", metrics), flush=True)
    text = table(results)
    print("\n" + text)
    (out / "rigs.md").write_text(text)
    (out / "rigs.json").write_text(json.dumps(results, indent=2) + "\n")
    return 0
