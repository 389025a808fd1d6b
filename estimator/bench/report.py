"""``swarmvo bench report``: the README's summary tables and ``docs/results.md``, made from the
result files the benchmarks wrote under ``benchmarks/results``.

Why a separate step: a benchmark writes its own JSON and table; the README shows one short
summary per area and the docs the full tables. Both are regenerated here, never typed by hand,
and ``--check`` (run by the test suite) fails when either no longer matches the result files.
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from estimator.bench.readme import read_block, write_block
from estimator.bench.rigs import seed_mean

__all__ = ["AREAS", "add_arguments", "full_results", "run", "summaries"]

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results"


def _mm(value: float | None) -> str:
    return "-" if value is None else f"{1000.0 * value:.1f}"


def _deg(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def _load(results: Path, relative: str) -> Any:
    return json.loads((results / relative).read_text())


def _lost(run: dict[str, Any]) -> str:
    return str(run.get("frames_failed", "-"))


def real_summary(results: Path) -> str:
    """Every estimator with the refinement on, on the real clips, vision alone and fused."""
    real = _load(results, "odometry/odometry.json")["real"]
    moving, standstill = real["euroc_mh01_moving"], real.get("euroc_v101_micro", {})
    rows = []
    for label, vision in moving.items():
        if not label.endswith(" vision") or "refine-off" in label:
            continue
        name = label.removesuffix(" vision").removesuffix(" refine-on")
        fused = moving.get(label.removesuffix(" vision") + " fused", {})
        still = standstill.get(label, {})
        rows.append([
            name,
            _mm(vision.get("ate_rmse_m")), _deg(vision.get("rpe_rot_rmse_deg")), _lost(vision),
            _mm(fused.get("ate_rmse_m")), _deg(fused.get("rpe_rot_rmse_deg")),
            _mm(still.get("final_drift_m")),
        ])
    header = [
        "estimator (refinement on)", "MH_01 vision ATE mm", "deg/frame", "lost",
        "MH_01 fused ATE mm", "deg/frame", "V1_01 standstill drift mm",
    ]
    return _table(header, rows)


def rendered_summary(results: Path) -> str:
    """The rendered loops (clean and noisy images), front end alone and fused with the IMU."""
    rendered = _load(results, "odometry/odometry.json").get("rendered", {})
    clean, noisy = rendered.get("rendered", {}), rendered.get("rendered_noisy", {})
    rows = []
    for name in clean:
        a, b = clean[name], noisy.get(name, {})
        rows.append([
            name,
            _mm(a.get("frontend", {}).get("ate_rmse_m")), _mm(a.get("ate_rmse_m")),
            _mm(b.get("frontend", {}).get("ate_rmse_m")), _mm(b.get("ate_rmse_m")),
        ])
    header = ["estimator", "clean: front end ATE mm", "fused mm", "noisy: front end mm", "fused mm"]
    return _table(header, rows)


def perturbation_summary(results: Path) -> str:
    """The real clip as misbehaving cameras record it, default configuration."""
    runs = _load(results, "perturbations/perturbations.json")
    rows = []
    for perturbation, settings in runs.items():
        vision, fused = settings.get("vision/default", {}), settings.get("fused/default", {})
        rows.append([
            perturbation,
            _mm(vision.get("ate_rmse_m")), _deg(vision.get("rpe_rot_rmse_deg")), _lost(vision),
            _mm(fused.get("ate_rmse_m")), _deg(fused.get("rpe_rot_rmse_deg")),
        ])
    header = [
        "real MH_01 clip", "vision ATE mm", "deg/frame", "frames without vision",
        "fused ATE mm", "deg/frame",
    ]
    return _table(header, rows)


def driving_summary(results: Path) -> str:
    """Rendered drives with the rig-derived settings: mean over the seeds, lost frames summed,
    per estimator and mode (vision alone / fused; files without modes are vision alone)."""
    return _drives_table(results, "driving/driving.json")


def traffic_summary(results: Path) -> str:
    """The same drives among moving vehicles and a lead car (``bench driving --traffic``)."""
    return _drives_table(results, "driving-traffic/driving.json")


def imaging_summary(results: Path) -> str:
    """The drives with traffic through imperfect cameras (``bench driving --noise --blur
    --brightness``)."""
    return _drives_table(results, "driving-imaging/driving.json")


def _drives_table(results: Path, relative: str) -> str:
    runs = _load(results, relative)
    rows = []
    for name, by_mode in runs.items():
        first = next(iter(by_mode.values()), {})
        if "path_length_m" in first:  # estimator -> seed (vision alone only)
            by_mode = {"vision": by_mode}
        for mode, seeds in by_mode.items():
            drives = list(seeds.values())
            if not drives:
                continue
            rows.append([
                name,
                mode,
                str(len(drives)),
                f"{sum(d['path_length_m'] for d in drives):.0f}",
                f"{statistics.mean(d['final_drift_pct'] for d in drives):.2f}",
                f"{statistics.mean(d['rpe_rot_rmse_deg'] for d in drives):.4f}",
                str(sum(d["frames_failed"] for d in drives)),
                f"{min(d['matches_median'] for d in drives):.0f}",
                f"{statistics.mean(d['fps'] for d in drives):.1f}",
            ])
    header = [
        "estimator", "mode", "drives", "path m", "final drift % (mean)", "deg/frame (mean)",
        "lost frames", "median matches (worst drive)", "frames/s",
    ]
    return _table(header, rows)


def rigs_summary(results: Path) -> str:
    """Rendered hand-held flights seen by other rigs: vision alone and fused, per settings,
    the mean over the flights (seeds) and the lost frames of all of them."""
    runs = _load(results, "rigs/rigs.json")
    rows = []
    for rig, by_settings in runs.items():
        for settings, by_mode in by_settings.items():
            vision = seed_mean(by_mode.get("vision", {}))
            fused = seed_mean(by_mode.get("fused", {}))
            rows.append([
                rig, settings, str(len(by_mode.get("vision", {}))),
                _mm(vision.get("ate_rmse_m")), _deg(vision.get("rpe_rot_rmse_deg")),
                _mm(fused.get("ate_rmse_m")), _deg(fused.get("rpe_rot_rmse_deg")),
                str(vision["frames_failed"] + fused["frames_failed"]),
            ])  # fmt: skip
    header = [
        "rig", "settings", "flights", "vision ATE mm (mean)", "deg/frame", "fused ATE mm (mean)",
        "deg/frame", "lost frames",
    ]
    return _table(header, rows)


def registration_summary(results: Path) -> str:
    """The paper's simulation: worst success over the grid and the hardest cell's error/time."""
    cells = _load(results, "registration/registration.json")["cells"]
    hardest = max(cells, key=lambda c: (c["outlier_ratio"], -c["sigma"]))
    rows = []
    for method, stats in hardest["methods"].items():
        rates = [c["methods"][method]["success_rate"] for c in cells if method in c["methods"]]
        rows.append([
            method,
            f"{100 * min(rates):.0f} %",
            f"{100 * stats['success_rate']:.0f} %",
            _mm(stats.get("median_translation_error_m")),
            f"{stats['median_time_ms']:.3g}",
        ])
    where = f"outlier ratio {hardest['outlier_ratio']}, sigma {1000 * hardest['sigma']:.0f} mm"
    header = [
        "method", "worst success over the grid", f"success ({where})", "median error mm",
        "median ms",
    ]
    return _table(header, rows)


def frontend_summary(results: Path) -> str:
    """Front-end speed on one core: the stage medians and the frame rate."""
    runs = _load(results, "frontend/frontend.json")
    stages = runs["stages"]
    header = ["clip", "frames/s (CPU)"] + [f"{name} ms" for name in stages]
    row = [Path(runs["data"]).name, f"{runs['fps_from_cpu_time']:.0f}"]
    row += [f"{stage['median_ms']:.2f}" for stage in stages.values()]
    return _table(header, [row])


# load-test settings that change the numbers, shown with the table (key, label)
LOAD_SETTINGS = (
    ("executor", "executor"), ("encoding", "frames"), ("workers", "workers"),
    ("queue_size", "queue"), ("policy", "policy"), ("duration_s", "seconds per level"),
)


def load_summary(results: Path) -> str:
    """The newest service load run: robots streaming over WebSocket, latency and CPU per frame."""
    newest = sorted((results / "load").glob("load_*.json"))[-1]
    runs = json.loads(newest.read_text())
    rows = []
    for level in runs["levels"]:
        cpu = level.get("server_cpu_ms_per_frame", {})
        rows.append([
            str(level["robots"]), f"{level['rate_hz']:.0f}", str(level["sent"]),
            str(level["answered"]), str(level["dropped"] + level["rejected"]),
            f"{level['latency_p95_ms']:.0f}", f"{sum(cpu.values()):.1f}",
            f"{level.get('server_rss_mb_peak', float('nan')):.0f}",
        ])
    header = [
        "robots", "Hz", "frames sent", "answered", "dropped or refused", "p95 ms",
        "CPU ms/frame (server + workers)", "peak RSS MB",
    ]
    settings = runs.get("settings", {})
    setup = ", ".join(
        f"{label} {settings[key]}" for key, label in LOAD_SETTINGS if key in settings
    )
    return f"{newest.name}: {setup}\n\n" + _table(header, rows)


NEES_MODES = ("fused pose", "frontend pose")


def backend_summary(results: Path) -> str:
    """What the back end adds on the pipeline runs, and whether its covariances are honest."""
    pipeline = _load(results, "backend/backend.json")["pipeline"]
    consistency = _load(results, "consistency/consistency.json")
    rows = []
    for sequence in ("rendered, 20 % broken", "EuRoC V1_01 micro"):
        cases = pipeline.get(sequence, {})
        rows.append([
            sequence,
            _mm(cases.get("front end only", {}).get("ate_rmse_m")),
            _mm(cases.get("fused, IMU", {}).get("ate_rmse_m")),
            _mm(cases.get("fused smoothed, IMU", {}).get("ate_rmse_m")),
        ])
    table = _table(["sequence", "front end ATE mm", "fused mm", "smoothed mm"], rows)
    nees = [
        [sequence, *(f"{modes[m]['mean_nees_per_dof']:.2f}" for m in NEES_MODES)]
        for sequence, modes in consistency.items()
    ]
    header = ["sequence", "NEES/DOF fused pose (1 = honest)", "front end pose"]
    return table + "\n\n" + _table(header, nees)


@dataclass(frozen=True)
class Area:
    """One results area: its README summary and the full tables it points to in the docs."""

    title: str
    summary: Callable[[Path], str]
    tables: tuple[str, ...]  # result files (relative to benchmarks/results) shown in full
    command: str


AREAS: dict[str, Area] = {
    "real": Area(
        "Odometry on the real EuRoC clips", real_summary,
        ("odometry/odometry.md", "odometry/frame_errors.md"),
        "swarmvo bench odometry --parts real",
    ),
    "perturbations": Area(
        "Misbehaving cameras (the real MH_01 clip perturbed)", perturbation_summary,
        ("perturbations/perturbations.md",), "swarmvo bench perturbations",
    ),
    "rendered": Area(
        "Odometry on rendered loops", rendered_summary, (),
        "swarmvo bench odometry --parts rendered",
    ),
    "driving": Area(
        "Rendered KITTI-like drives", driving_summary, ("driving/driving.md",),
        "swarmvo bench driving",
    ),
    "traffic": Area(
        "Rendered drives with traffic", traffic_summary, ("driving-traffic/driving.md",),
        "swarmvo bench driving --traffic 2 --out benchmarks/results/driving-traffic",
    ),
    "imaging": Area(
        "Rendered drives with traffic through imperfect cameras", imaging_summary,
        ("driving-imaging/driving.md",),
        "swarmvo bench driving --traffic 2 --noise 3 --blur 0.1 --brightness 0.2 "
        "--out benchmarks/results/driving-imaging",
    ),
    "rigs": Area(
        "Other stereo rigs without a configuration (rendered)", rigs_summary,
        ("rigs/rigs.md",), "swarmvo bench rigs",
    ),
    "registration": Area(
        "Registration: the paper's simulation", registration_summary,
        (
            "registration/registration.md", "registration-stereo/registration_stereo.md",
            "registration-scaling/scaling.md",
        ),
        "swarmvo bench registration",
    ),
    "frontend": Area(
        "Front-end speed (one core)", frontend_summary, ("frontend/frontend.md",),
        "swarmvo bench frontend",
    ),
    "backend": Area(
        "Back end and covariances", backend_summary,
        ("backend/backend.md", "consistency/consistency.md"),
        "swarmvo bench backend; swarmvo bench consistency",
    ),
    "load": Area(
        "Service under load", load_summary, (), "python benchmarks/load_test.py",
    ),
}


def summaries(results: Path = RESULTS) -> dict[str, str]:
    """README block name -> summary table, for every area that has one."""
    return {name: area.summary(results) for name, area in AREAS.items()}


def full_results(results: Path = RESULTS) -> str:
    """The text of ``docs/results.md``: every area's summary and full tables."""
    parts = [
        "# Benchmark results",
        "",
        "Written by `swarmvo bench report` from the files under `benchmarks/results`; "
        "do not edit by hand. Each section names the command that wrote its result files.",
    ]
    for area in AREAS.values():
        parts += ["", f"## {area.title}", "", f"`{area.command}`"]
        parts += ["", area.summary(results)]
        for relative in area.tables:
            parts += ["", f"### `{relative}`", "", (results / relative).read_text().strip()]
    return "\n".join(parts) + "\n"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--results", type=Path, default=RESULTS, help="benchmark result files")
    parser.add_argument("--readme", type=Path, default=ROOT / "README.md")
    parser.add_argument("--docs", type=Path, default=ROOT / "docs" / "results.md")
    parser.add_argument(
        "--check", action="store_true", help="only report whether README and docs are up to date"
    )
    parser.add_argument(
        "--docs-only", action="store_true",
        help="write (or check) only the docs file, not the README's summary blocks",
    )


def stale(
    readme: Path | None, docs: Path, results: Path = RESULTS
) -> list[str]:
    """The README blocks (none when ``readme`` is None) and docs file that no longer match the
    result files."""
    out = [] if readme is None else [
        f"{readme.name}: {name}" for name, table in summaries(results).items()
        if read_block(readme, name) != table.strip()
    ]
    if not docs.exists() or docs.read_text() != full_results(results):
        out.append(str(docs.name))
    return out


def run(args: argparse.Namespace) -> int:
    readme = None if args.docs_only else args.readme
    if readme is not None:
        try:
            for name in AREAS:
                read_block(readme, name)
        except ValueError as error:
            print(f"swarmvo bench report: error: {error} (or use --docs-only)")
            return 2
    if args.check:
        behind = stale(readme, args.docs, args.results)
        for item in behind:
            print(f"out of date: {item} (run `swarmvo bench report`)")
        return 1 if behind else 0
    args.docs.write_text(full_results(args.results))
    if readme is None:
        print(f"wrote {args.docs}")
        return 0
    for name, table in summaries(args.results).items():
        write_block(readme, name, table)
    print(f"wrote {len(summaries(args.results))} summaries into {readme} and {args.docs}")
    return 0
