"""``swarmvo bench perturbations``: the real MH_01 clip as misbehaving cameras record it.

Every perturbation of :data:`estimator.rendered.perturb.PERTURBATIONS` (gain flicker per camera,
10 Hz, black / blurred / dropped frames, pixel noise, a late right shutter) runs through the whole
pipeline like ``swarmvo run``: vision alone (back end without the IMU, ``--no-imu``) and fused
with the clip's real IMU, for each estimator setting. The table lists the left-camera ATE after
SE(3) alignment, the RMS rotation error per frame and the frames without a vision estimate.
Outputs ``perturbations.json`` and ``perturbations.md`` (the printed table) under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

from estimator.config import SwarmvoConfig
from estimator.formats.datasets import Sequence, open_sequence
from estimator.pipeline import build_config, load_config, run_sequence, summarize
from estimator.registration.methods import Estimator
from estimator.rendered.perturb import PERTURBATIONS, perturb_sequence

__all__ = ["SETTINGS", "add_arguments", "run", "run_one"]

DEFAULT_DATA = Path(__file__).resolve().parents[2].parent / "shared/data/euroc_mh01_moving"
# Settings compared: the default, the swarm without per-point sigmas, MSAC, and the front end
# that follows corners by LK instead of detecting them again (track mode).
SETTINGS: dict[str, dict[str, Any]] = {
    "default": {},
    "no-sigmas": {"registration": {"use_point_sigmas": False}},
    Estimator.MSAC.value: {"registration": {"method": Estimator.MSAC.value}},
    "track": {"frontend": {"mode": "track"}},
}
MODES = ("vision", "fused")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="EuRoC sequence")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/perturbations"))
    parser.add_argument(
        "--perturbations", nargs="+", choices=list(PERTURBATIONS), default=list(PERTURBATIONS)
    )
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS), default=list(SETTINGS))
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    parser.add_argument("--config", type=Path, help="base SwarmvoConfig (JSON/YAML)")
    parser.add_argument("--seed", type=int, default=0, help="estimator and perturbation seed")
    parser.add_argument("--frames", type=int, default=None, help="use only the first N frames")
    parser.add_argument(
        "--compare",
        type=Path,
        help="an earlier perturbations.json: also print (and write) a before -> after table",
    )
    parser.add_argument(
        "--report-only", action="store_true", help="run nothing: tables from the stored results"
    )


def _config(
    setting: str, mode: str, seed: int, base: SwarmvoConfig | None = None
) -> SwarmvoConfig:
    # Only the fields set in ``base`` are carried over, as ``swarmvo run`` does: a full dump
    # would mark every field as configured and stop the rig-derived settings (the search
    # window that scales with the frame interval) from being derived.
    data = (base or SwarmvoConfig()).model_dump(exclude_unset=True)
    for section, values in SETTINGS[setting].items():
        data.setdefault(section, {}).update(values)
    return build_config(seed=seed, imu=mode == "fused", backend=True,
                        base=SwarmvoConfig.model_validate(data))  # fmt: skip


def run_one(
    sequence: Sequence,
    perturbation: str,
    setting: str,
    mode: str,
    seed: int = 0,
    limit: int | None = None,
    base: SwarmvoConfig | None = None,
) -> dict[str, Any]:
    """Metrics of one (perturbation, setting, mode) run, as ``swarmvo run`` would write them."""
    perturbed = perturb_sequence(sequence, replace(PERTURBATIONS[perturbation], seed=seed))
    config = _config(setting, mode, seed, base)
    result = run_sequence(perturbed, config, limit, use_imu=config.backend.use_imu)
    summary, _ = summarize(result)
    summary["perturbation"], summary["setting"], summary["mode"] = perturbation, setting, mode
    return summary


def _cell(summary: dict[str, Any] | None) -> str:
    if summary is None:
        return "-"
    if summary.get("ate_rmse_m") is None:
        return f"no evaluation, {summary['frames_failed']} lost"
    return (
        f"{summary['ate_rmse_m'] * 1e3:.1f} mm / {summary['rpe_rot_rmse_deg']:.3f} deg, "
        f"{summary['frames_failed']} lost"
    )


def _short(summary: dict[str, Any] | None) -> str:
    if summary is None or summary.get("ate_rmse_m") is None:
        return "-"
    return (
        f"{summary['ate_rmse_m'] * 1e3:.1f} / {summary['rpe_rot_rmse_deg']:.3f} / "
        f"{summary['frames_failed']}"
    )


def _comparison(before: dict[str, dict[str, Any]], after: dict[str, dict[str, Any]]) -> str:
    """Before -> after per (perturbation, column) present in both: ATE mm / deg / lost."""
    columns = [(m, s) for m in MODES for s in SETTINGS
               if any(f"{m}/{s}" in runs for runs in after.values())
               and any(f"{m}/{s}" in runs for runs in before.values())]  # fmt: skip
    lines = [
        "ATE mm / RMS rotation error deg per frame / frames without a vision estimate, "
        "before -> after",
        "",
        "| perturbation | " + " | ".join(f"{m} {s}" for m, s in columns) + " |",
        "|---" * (len(columns) + 1) + "|",
    ]
    for name in PERTURBATIONS:
        if name in after and name in before:
            cells = [
                f"{_short(before[name].get(f'{m}/{s}'))} -> {_short(after[name].get(f'{m}/{s}'))}"
                for m, s in columns
            ]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _table(results: dict[str, dict[str, Any]]) -> str:
    columns = [(m, s) for m in MODES for s in SETTINGS
               if any(f"{m}/{s}" in runs for runs in results.values())]  # fmt: skip
    header = "| perturbation | " + " | ".join(f"{m} {s}" for m, s in columns) + " |"
    lines = [
        "ATE (left camera, SE(3)-aligned) / RMS rotation error per frame, frames without a "
        "vision estimate",
        "",
        header,
        "|---" * (len(columns) + 1) + "|",
    ]
    for name in PERTURBATIONS:
        if name in results:
            cells = [_cell(results[name].get(f"{m}/{s}")) for m, s in columns]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    results_file = out / "perturbations.json"
    # Partial runs update the stored results instead of discarding the rest.
    results: dict[str, dict[str, Any]] = (
        json.loads(results_file.read_text()) if results_file.is_file() else {}
    )
    if not (args.data / "mav0").is_dir():
        print(f"no EuRoC data at {args.data}")
        return 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unpaired camera rows are expected in EuRoC
        sequence = open_sequence(args.data)
    base = load_config(args.config) if args.config is not None else None
    for name in [] if args.report_only else args.perturbations:
        for mode in args.modes:
            for setting in args.settings:
                summary = run_one(sequence, name, setting, mode, args.seed, args.frames, base)
                results.setdefault(name, {})[f"{mode}/{setting}"] = summary
                print(f"{name:24s} {mode:6s} {setting:9s} {_cell(summary)}", flush=True)
                results_file.write_text(json.dumps(results, indent=2) + "\n")
    table = _table(results)
    if args.compare is not None:
        table += "\n" + _comparison(json.loads(Path(args.compare).read_text()), results)
    print("\n" + table)
    (out / "perturbations.md").write_text(table)
    return 0
