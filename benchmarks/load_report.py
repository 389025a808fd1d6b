"""The load test's results: one ``LevelResult`` per level and run, printed as tables and
written as JSON (and, for several runs, a Markdown table) by ``benchmarks/load_test.py``."""

from __future__ import annotations

import json
import os
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class LevelResult:
    robots: int
    rate_hz: float
    duration_s: float
    sent: int
    answered: int
    dropped: int
    rejected: int
    unanswered: int
    sustained_fps: float
    offered_fps: float
    latency_p50_ms: float | None
    latency_p95_ms: float | None
    latency_p99_ms: float | None
    server_rss_mb_peak: float | None  # server and workers together
    # Proportional set size, server and workers together: pages shared between processes
    # (libraries, a fork's copy-on-write pages) are counted once in all instead of in each.
    server_pss_mb_peak: float | None
    # Peaks of the server process alone and of its workers together (sampled every 0.25 s).
    rss_mb_peak_by_role: dict[str, float]
    # CPU time of the server process itself and of its worker processes, per answered frame.
    server_cpu_ms_per_frame: dict[str, float]
    stage_median_ms: dict[str, float]
    reject_reasons: dict[str, int]
    run: int = 1
    # Frames the robots did not send because the server would have refused them (--hold-back).
    held_back: int = 0
    # CPU of the server process per frame it received (answered or refused): what a frame
    # costs it before any work is done on it.
    server_cpu_ms_per_received: float | None = None
    # Robots whose connection ended before their last answer, and why (their unanswered
    # frames are in ``unanswered``).
    disconnected: list[str] = field(default_factory=list)
    load_average_start: list[float] = field(default_factory=list)
    load_average_end: list[float] = field(default_factory=list)

    @property
    def cpu_ms_per_frame(self) -> float | None:
        """Server process plus worker processes, CPU per answered frame."""
        if not self.server_cpu_ms_per_frame:
            return None
        return sum(self.server_cpu_ms_per_frame.values())


def _fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def print_table(results: list[LevelResult]) -> None:
    header = (f"{'robots':>6} {'offered/s':>9} {'answered/s':>10} {'sent':>6} {'answered':>8} "
              f"{'dropped':>7} {'rejected':>8} {'lost':>5} {'p50 ms':>8} {'p95 ms':>8} "
              f"{'p99 ms':>8} {'RSS MB':>7}")
    print(header)
    print("-" * len(header))
    for r in results:
        print(f"{r.robots:>6} {r.offered_fps:>9.1f} {r.sustained_fps:>10.1f} {r.sent:>6} "
              f"{r.answered:>8} {r.dropped:>7} {r.rejected:>8} {r.unanswered:>5} "
              f"{_fmt(r.latency_p50_ms):>8} {_fmt(r.latency_p95_ms):>8} "
              f"{_fmt(r.latency_p99_ms):>8} {_fmt(r.server_rss_mb_peak, 0):>7}")
    print("\nmedian per-frame server time (ms):")
    for r in results:
        stages = ", ".join(f"{k} {v:.1f}" for k, v in r.stage_median_ms.items())
        print(f"  K={r.robots}: {stages}")
        if r.server_cpu_ms_per_frame:
            print("        server CPU per answered frame (ms): " + ", ".join(
                f"{k} {v:.1f}" for k, v in r.server_cpu_ms_per_frame.items()))
        if r.rss_mb_peak_by_role:
            print("        peak RSS (MB): " + ", ".join(
                f"{k} {v:.0f}" for k, v in r.rss_mb_peak_by_role.items())
                + f"; peak PSS of all {_fmt(r.server_pss_mb_peak, 0)}")
        if r.reject_reasons:
            print(f"        rejected: {r.reject_reasons}")
        if r.disconnected:
            print(f"        {len(r.disconnected)} robot(s) cut off: {r.disconnected[0]}")


RUNS_HEADER = (
    "| run | robots | offered/s | answered/s | sent | answered | dropped | rejected | lost "
    "| p50 ms | p95 ms | p99 ms | CPU ms/frame server | CPU ms/frame workers | CPU ms/frame total "
    "| server CPU ms/received | held back | cut off | RSS MB | PSS MB | load avg start -> end |"
)


def runs_table(results: list[LevelResult]) -> str:
    """Markdown table with one row per run, in the order they ran."""
    lines = [RUNS_HEADER, "|" + "---|" * RUNS_HEADER.count(" | ") + "---|"]
    for r in results:
        cpu = r.server_cpu_ms_per_frame
        load = "-"
        if r.load_average_start and r.load_average_end:
            load = f"{r.load_average_start[0]:.1f} -> {r.load_average_end[0]:.1f}"
        lines.append(
            f"| {r.run} | {r.robots} | {r.offered_fps:.1f} | {r.sustained_fps:.1f} | {r.sent} "
            f"| {r.answered} | {r.dropped} | {r.rejected} | {r.unanswered} "
            f"| {_fmt(r.latency_p50_ms)} | {_fmt(r.latency_p95_ms)} | {_fmt(r.latency_p99_ms)} "
            f"| {_fmt(cpu.get('server_process'))} | {_fmt(cpu.get('worker_processes'))} "
            f"| {_fmt(r.cpu_ms_per_frame)} | {_fmt(r.server_cpu_ms_per_received, 2)} "
            f"| {r.held_back} | {len(r.disconnected)} | {_fmt(r.server_rss_mb_peak, 0)} "
            f"| {_fmt(r.server_pss_mb_peak, 0)} | {load} |"
        )
    return "\n".join(lines)


def write_report(out: Path, machine: dict[str, Any], settings: dict[str, Any],
                 results: list[LevelResult], table: str) -> None:
    """``load_<stamp>.json`` in ``out``; with several runs per level also ``load_<stamp>.md``
    with every run's row, so a reader sees the spread and not only the best run."""
    out.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    report = {
        "created_utc": stamp,
        "machine": {**machine, "load_average_after": os.getloadavg()},
        "settings": settings,
        "levels": [{**asdict(r), "cpu_ms_per_frame": r.cpu_ms_per_frame} for r in results],
    }
    path = out / f"load_{stamp}.json"
    path.write_text(json.dumps(report, indent=2) + "\n")
    print(f"\nwrote {path}")
    if settings["runs"] > 1:
        markdown = out / f"load_{stamp}.md"
        markdown.write_text(
            f"{settings['runs']} consecutive runs of {settings['duration_s']:g} s per level at "
            f"{settings['rate_hz']:g} Hz per robot, {settings['encoding']} frames, executor "
            f"{settings['executor']}, {settings['workers']} workers, {os.cpu_count()} CPUs "
            f"({stamp}; JSON {path.name}).\n\n{table}\n"
        )
        print(f"wrote {markdown}")


def machine_before() -> dict[str, Any]:
    """The machine and its load before the levels run (the load after is added on writing)."""
    return {"cpus": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(), "load_average_before": os.getloadavg()}
