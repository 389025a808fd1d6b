"""``swarmvo bench consistency``: are the odometry covariances right? NEES over 1 s windows.

Runs rendered loops (``--seeds``, rendered once into ``--data``) and the real EuRoC MH_01
clip through the pipeline in three modes (fused with the IMU, back end without IMU, front end
only), turns the answers into odometry messages and computes the NEES of the base_link motion
over 1 s windows starting every ``--stride`` frames (``estimator.evaluation.consistency``;
overlapping windows are correlated, see there) with both covariance readings (``pose``,
``twist``). A consistent covariance gives a mean NEES per degree of freedom of 1;
the target is [0.5, 2]. Writes ``consistency.json`` and ``consistency.md`` (the table) under
``--out``; ``scale`` is the factor on the reported standard deviations that would make the
mean exactly 1 (sqrt of the mean per DOF); the median per DOF of a consistent estimate is 0.89
(chi-square with 6 DOF), and unlike the mean it is not carried by one bad window.

The row ``frontend measurement`` checks the front end's measurements one by one (keyframe to
frame, with the covariance each was reported with; ``estimator.consistency.measurement_nees``),
with ``lag1`` the correlation of consecutive errors against the same keyframe and across a
keyframe change; it checks the covariance the back end weighs (with the graph's floor), which
without the gyro is not the one the messages report.

With the IMU the covariances are scaled by the factor measured online against the gyro
(``estimator.backend.covariance_scale``: the session's, raised by a time-local one through
episodes of larger errors): the ``fused`` rows are what the messages
report, the ``fused fixed model`` rows the same run without the factor (the noise model
alone), ``fused measurement`` the front end's measurements of that run with the factor, and
``covariance scale`` the factor at the last frame (and its range over the run). The modes
without the IMU have no gyro to measure the factor against: they report the fit's covariance
with a smaller floor and a calibration error proportional to the motion
(``estimator.backend.systematic_noise``), and their twist covariance is the growth of that
drift. The calibration gains follow from each rig (``estimator.rig_settings``): the rendered
rigs declare their calibration exact, so theirs are 0.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import warnings
from pathlib import Path
from typing import Any

from estimator.evaluation.consistency import measurement_nees, relative_nees
from estimator.formats.datasets import open_sequence
from estimator.pipeline import build_config, odometry_messages, run_sequence
from estimator.rendered.cache import rendered_once
from estimator.rendered.synthetic import SynthOptions

__all__ = ["add_arguments", "run"]

DEFAULT_EUROC = Path(__file__).resolve().parents[2].parent / "shared/data/euroc_mh01_moving"
MODES = {"fused": (True, True), "backend-no-imu": (True, False), "frontend": (False, False)}
TARGET = (0.5, 2.0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/consistency"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--length-m", type=float, default=20.0, help="rendered body path [m]")
    parser.add_argument("--window-s", type=float, default=1.0)
    parser.add_argument(
        "--stride", type=int, default=1, help="frames between window starts (0: no overlap)"
    )
    parser.add_argument("--euroc", type=Path, default=DEFAULT_EUROC, help="skipped if absent")
    parser.add_argument(
        "--data",
        type=Path,
        default=Path(tempfile.gettempdir()) / "swarmvo-bench",
        help="where the rendered loops are written once and reused",
    )


def _sequences(args: argparse.Namespace) -> dict[str, Path]:
    paths: dict[str, Path] = {}
    for seed in args.seeds:
        # Re-rendered when the renderer changed: the folder's files also carry the rig's
        # calibration accuracy, which decides the covariances reported without the gyro.
        options = SynthOptions(frames=args.frames, length_m=args.length_m, seed=seed)
        root = args.data / f"rendered_{args.frames}f_{args.length_m:g}m_seed{seed}"
        paths[f"rendered seed {seed}"] = rendered_once(root, options)
    if (args.euroc / "mav0").is_dir():
        paths["euroc_mh01_moving"] = args.euroc
    else:
        print(f"skipping the real clip: no EuRoC data at {args.euroc}")
    return paths


def _evaluate(path: Path, window_s: float, stride: int | None) -> dict[str, dict[str, Any]]:
    """The rows of one sequence."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unpaired camera rows are expected in EuRoC
        sequence = open_sequence(path)
    assert sequence.ground_truth is not None
    rows: dict[str, dict[str, Any]] = {}
    for mode, (backend, imu) in MODES.items():
        config = build_config(backend=backend, imu=imu)
        run = run_sequence(sequence, config, use_imu=imu)
        readings = {mode: odometry_messages(run)}
        if imu:
            readings[f"{mode} fixed model"] = odometry_messages(run, calibrated=False)
        for name, messages in readings.items():
            for source in ("pose", "twist"):
                result = relative_nees(messages, sequence.ground_truth, window_s, source, stride)
                rows[f"{name} {source}"] = result.summary()
        if imu:
            check = measurement_nees(run.reports, sequence.ground_truth, sequence.rig.left.T_BS)
            rows[f"{mode} measurement"] = check.summary()
            scales = [report.covariance_scale for report in run.reports]
            rows["covariance scale"] = {
                "windows": len(scales), "last": scales[-1], "min": min(scales), "max": max(scales)
            }
        if mode == "frontend":
            check = measurement_nees(run.reports, sequence.ground_truth, sequence.rig.left.T_BS)
            rows["frontend measurement"] = check.summary()
    return rows


def _cell(summary: dict[str, Any]) -> str:
    if not summary.get("windows"):
        return "- (0)"
    if "last" in summary:
        return f"{summary['last']:.2f} (range {summary['min']:.2f}-{summary['max']:.2f})"
    per_dof = summary["mean_nees_per_dof"]
    verdict = "ok" if TARGET[0] <= per_dof <= TARGET[1] else "MISS"
    lag1 = ""
    if "lag1_same_reference" in summary:
        lag1 = (f"; lag1 same keyframe {summary['lag1_same_reference']:+.2f}, new "
                f"{summary['lag1_new_reference']:+.2f}; {summary['windows']} measurements")
    return (
        f"{per_dof:.2f} {verdict} (median {summary['median_nees_per_dof']:.2f}; rot "
        f"{summary['rotation_per_dof']:.2f}, trans {summary['translation_per_dof']:.2f}; "
        f"scale {math.sqrt(per_dof):.2f}{lag1})"
    )


def _table(results: dict[str, dict[str, dict[str, Any]]], window_s: float) -> str:
    names = list(results)
    lines = [
        f"Mean NEES per DOF of the base_link motion over {window_s:g} s windows "
        f"(target {TARGET[0]}-{TARGET[1]}); windows per sequence: "
        + ", ".join(f"{n} {next(iter(results[n].values()))['windows']}" for n in names)
        + " (the measurement rows: one per front-end measurement; the covariance scale row: "
        "the factor at the last frame)",
        "",
        "| mode / covariance | " + " | ".join(names) + " |",
        "|" + "---|" * (len(names) + 1),
    ]
    for row in next(iter(results.values())):
        lines.append(f"| {row} | " + " | ".join(_cell(results[n][row]) for n in names) + " |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for name, path in _sequences(args).items():
        results[name] = _evaluate(path, args.window_s, args.stride or None)
        print(f"{name}: done", flush=True)
    table = _table(results, args.window_s)
    print("\n" + table)
    (out / "consistency.md").write_text(table)
    (out / "consistency.json").write_text(json.dumps(results, indent=2) + "\n")
    return 0
