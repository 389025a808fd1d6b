"""Load test: K simulated robots stream EuRoC-size stereo pairs at a fixed rate over WebSocket.

Each robot owns a session and sends 752x480 PNG pairs (EuRoC V1_01 micro, looped, timestamps
kept increasing) plus the IMU samples between frames, at ``--rate`` Hz like a camera would: it
never waits for answers. For each K the run reports sustained answered frames/s, latency
percentiles (send -> pose received), frames dropped/rejected by the server's queue policy or
never answered, and the memory of the server and its worker processes (RSS, which counts the
pages they share in each of them, and PSS, which shares them out). Loopback only
(127.0.0.1), every level is bounded in duration and in the time allowed to drain.

    python benchmarks/load_test.py                      # K = 1, 2, 4, 8; 15 s each
    python benchmarks/load_test.py --robots 4 --duration 30
    python benchmarks/load_test.py --executor thread    # the in-process thread pool instead
    python benchmarks/load_test.py --encoding raw8      # raw 8-bit pixels, no PNG decode
    python benchmarks/load_test.py --robots 8 --duration 30 --runs 5   # 5 consecutive runs
    python benchmarks/load_test.py --hold-back  # robots skip frames the server would refuse

With ``--runs N`` every level is run N times in a row against the same server; besides the JSON
a Markdown table of all runs (not the best of them) is written next to it, with the machine's
load average at the start and end of each run (other jobs on the machine inflate the numbers).
The result type, the tables and the report files live in ``load_report.py``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from load_report import LevelResult, machine_before, print_table, runs_table, write_report
from server_wait import wait_healthy
from swarmvo_client import Client, DroppedFrame, Pose, open_local_sequence, stream
from swarmvo_client.models import ImuData
from websockets.exceptions import ConnectionClosed

PROJECT_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATASET = PROJECT_ROOT.parent / "shared" / "data" / "euroc_v101_micro"
API_KEY = "load-test-key"


@dataclass
class RobotStats:
    sent: int = 0
    answered: int = 0
    dropped: int = 0
    rejected: int = 0
    held_back: int = 0  # not sent: the server's window for the session was full (--hold-back)
    latencies_s: list[float] = field(default_factory=list)
    first_send: float | None = None
    last_answer: float | None = None
    stage_s: dict[str, list[float]] = field(default_factory=dict)
    reject_reasons: dict[str, int] = field(default_factory=dict)
    disconnected: str | None = None  # why the connection ended early, if it did


class Frames:
    """Encoded frames of the dataset in memory, looped with ever-increasing timestamps."""

    def __init__(self, dataset: Path, raw: bool = False) -> None:
        self.sequence = open_local_sequence(dataset)
        self.pairs = [(f.left.read_bytes(), f.right.read_bytes()) for f in self.sequence.frames]
        self.raw = raw
        if raw:  # decoded once here: a robot sending raw8 holds the pixels already
            self.pairs = [(_grey_pixels(left), _grey_pixels(right)) for left, right in self.pairs]
        self.times = np.array([f.timestamp_ns for f in self.sequence.frames], dtype=np.int64)
        step = int(np.median(np.diff(self.times)))
        self.span = int(self.times[-1] - self.times[0]) + step

    def timestamp(self, k: int) -> int:
        loop, index = divmod(k, len(self.pairs))
        return int(self.times[index]) + loop * self.span

    def get(self, k: int) -> tuple[int, bytes, bytes, ImuData | None]:
        """Frame k of the endless sequence and the IMU samples since frame k - 1."""
        loop, index = divmod(k, len(self.pairs))
        offset = loop * self.span
        timestamp = self.timestamp(k)
        imu = None
        if self.sequence.imu is not None and k > 0:
            # Read the interval from the recording and shift it into this loop's time.
            part = self.sequence.imu.between(self.timestamp(k - 1) - offset, timestamp - offset)
            imu = ImuData(part.timestamps_ns + offset, part.gyro, part.accel)
        left, right = self.pairs[index]
        return timestamp, left, right, imu


def _grey_pixels(encoded: bytes) -> bytes:
    import cv2

    image = cv2.imdecode(np.frombuffer(encoded, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None or image.dtype != np.uint8 or image.ndim != 2:
        raise SystemExit("--encoding raw8 needs 8-bit grey images")
    return image.tobytes()


def _record(event: Any, stats: RobotStats, sent_at: dict[int, float], now: float) -> None:
    """Count one server message: a pose (its latency and server stages), a drop or a refusal."""
    if isinstance(event, Pose):
        stats.answered += 1
        stats.latencies_s.append(now - sent_at[event.timestamp_ns])
        stats.last_answer = now
        for stage in ("queue_wait", "decode", "odometry", "transfer", "persist", "total"):
            if stage in event.timings_s:
                stats.stage_s.setdefault(stage, []).append(event.timings_s[stage])
    elif isinstance(event, DroppedFrame):
        stats.dropped += 1
    else:
        stats.rejected += 1
        reason = event.detail.split(":")[0][:60]
        stats.reject_reasons[reason] = stats.reject_reasons.get(reason, 0) + 1


async def robot(url: str, session_id: str, frames: Frames, rate: float, duration: float,
                drain: float, stats: RobotStats, start_at: float, hold_back: bool) -> None:
    """One robot's stream; a connection the server closes (on a starved machine its pings go
    unanswered for longer than its timeout) ends this robot only, its frames counted lost."""
    try:
        await _robot_stream(url, session_id, frames, rate, duration, drain, stats, start_at,
                            hold_back)
    except (ConnectionClosed, OSError) as error:
        stats.disconnected = f"{type(error).__name__}: {error}"[:120]


async def _robot_stream(url: str, session_id: str, frames: Frames, rate: float,
                        duration: float, drain: float, stats: RobotStats, start_at: float,
                        hold_back: bool) -> None:
    sent_at: dict[int, float] = {}
    async with stream(url, session_id, API_KEY, hold_back=hold_back) as connection:
        done_sending = asyncio.Event()

        async def produce() -> None:
            k = 0
            while True:
                due = start_at + k / rate
                if due - start_at >= duration:
                    break
                delay = due - time.perf_counter()
                # Always yield, so answers are read even when sending runs late.
                await asyncio.sleep(max(delay, 0.0))
                timestamp, left, right, imu = frames.get(k)
                sent_at[timestamp] = time.perf_counter()
                stats.first_send = stats.first_send or sent_at[timestamp]
                if frames.raw:
                    width, height = frames.sequence.image_size
                    sent = await connection.send_raw_frame(timestamp, left, right, width,
                                                           height, imu)
                else:
                    sent = await connection.send_frame(timestamp, left, right, imu)
                stats.sent += sent
                stats.held_back += not sent
                k += 1
            done_sending.set()

        producer = asyncio.create_task(produce())
        received = 0
        deadline = start_at + duration + drain
        try:
            while not (done_sending.is_set() and received >= stats.sent):
                remaining = deadline - time.perf_counter()
                if remaining <= 0:
                    break
                try:
                    event = await asyncio.wait_for(connection.recv(), timeout=remaining)
                except TimeoutError:
                    break
                received += 1
                _record(event, stats, sent_at, time.perf_counter())
        finally:
            producer.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionClosed, OSError):
                await producer
        await connection.close()


def _tree(pid: int) -> list[int]:
    """``pid`` and all its descendants (the server's worker processes)."""
    found, pending = [], [pid]
    while pending:
        current = pending.pop()
        found.append(current)
        try:
            for task in Path(f"/proc/{current}/task").iterdir():
                pending += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError):
            continue
    return found


def _rss_mb(pid: int) -> dict[int, float]:
    """Resident memory (MB) of the server and of each of its worker processes, by pid."""
    found = {}
    for current in _tree(pid):
        try:
            for line in Path(f"/proc/{current}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    found[current] = int(line.split()[1]) / 1024
        except (OSError, ValueError):
            continue
    return found


def _pss_mb(pid: int) -> float:
    """Proportional set size (MB) of the server's whole process tree."""
    total = 0
    for current in _tree(pid):
        try:
            for line in Path(f"/proc/{current}/smaps_rollup").read_text().splitlines():
                if line.startswith("Pss:"):
                    total += int(line.split()[1])
                    break
        except (OSError, ValueError):
            continue
    return total / 1024


def _cpu_s(pid: int | None) -> dict[int, float]:
    """User + system CPU seconds of each process of the server's tree, by pid."""
    if pid is None:
        return {}
    ticks = os.sysconf("SC_CLK_TCK")
    times = {}
    for current in _tree(pid):
        try:
            fields = Path(f"/proc/{current}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        times[current] = (int(fields[11]) + int(fields[12])) / ticks
    return times


def _create_sessions(url: str, frames: Frames, robots: int, config: dict) -> list:
    """One session per robot, created before the clock starts."""
    with Client(url, API_KEY) as client:
        files = frames.sequence.calibration_files
        return [
            client.create_session_euroc(files["cam0"], files["cam1"], files.get("imu0"),
                                        config=config, name=f"load-robot-{k}")
            for k in range(robots)
        ]


@dataclass
class MemoryPeaks:
    """RSS and PSS of the server's process tree, sampled every 0.25 s while a level runs."""

    rss: list[float] = field(default_factory=list)
    pss: list[float] = field(default_factory=list)
    by_role: dict[str, float] = field(
        default_factory=lambda: {"server_process": 0.0, "worker_processes": 0.0}
    )

    async def sample(self, server_pid: int | None, stop: asyncio.Event) -> None:
        while not stop.is_set() and server_pid is not None:
            by_pid = _rss_mb(server_pid)
            if by_pid:
                self.rss.append(sum(by_pid.values()))
                self.pss.append(_pss_mb(server_pid))
                server = by_pid.pop(server_pid, 0.0)
                self.by_role["server_process"] = max(self.by_role["server_process"], server)
                self.by_role["worker_processes"] = max(
                    self.by_role["worker_processes"], sum(by_pid.values())
                )
            await asyncio.sleep(0.25)


def _server_cpu(cpu_before: dict[int, float], cpu_after: dict[int, float],
                server_pid: int | None, answered: int,
                sent: int) -> tuple[dict[str, float], float | None]:
    """CPU ms of the server process and of its workers per answered frame, and of the server
    process per received frame (what a frame costs it before any work is done on it)."""
    cpu: dict[str, float] = {}
    per_received = None
    if cpu_after and answered:
        used = {p: t - cpu_before.get(p, 0.0) for p, t in cpu_after.items()}
        server_s = used.pop(server_pid, 0.0)
        cpu["server_process"] = server_s * 1000 / answered
        cpu["worker_processes"] = sum(used.values()) * 1000 / answered
        per_received = server_s * 1000 / sent
    return cpu, per_received


def _merged(stats: list[RobotStats]) -> tuple[dict[str, list[float]], dict[str, int]]:
    """The robots' per-stage server times and refusal reasons, pooled."""
    stages: dict[str, list[float]] = {}
    reasons: dict[str, int] = {}
    for s in stats:
        for stage, values in s.stage_s.items():
            stages.setdefault(stage, []).extend(values)
        for reason, count in s.reject_reasons.items():
            reasons[reason] = reasons.get(reason, 0) + count
    return stages, reasons


def _level_result(stats: list[RobotStats], robots: int, rate: float, duration: float,
                  peaks: MemoryPeaks, cpu: dict[str, float], per_received: float | None,
                  load_start: list[float]) -> LevelResult:
    """Totals, throughput over the answering window and latency percentiles of one level."""
    latencies = np.array([v for s in stats for v in s.latencies_s])
    sent = sum(s.sent for s in stats)
    answered = sum(s.answered for s in stats)
    dropped = sum(s.dropped for s in stats)
    rejected = sum(s.rejected for s in stats)
    firsts = [s.first_send for s in stats if s.first_send]
    lasts = [s.last_answer for s in stats if s.last_answer]
    window = (max(lasts) - min(firsts)) if firsts and lasts else 0.0
    stages, reasons = _merged(stats)

    def pct(q: float) -> float | None:
        return float(np.percentile(latencies, q) * 1000) if len(latencies) else None

    return LevelResult(
        robots=robots, rate_hz=rate, duration_s=duration, sent=sent, answered=answered,
        dropped=dropped, rejected=rejected, unanswered=sent - answered - dropped - rejected,
        sustained_fps=answered / window if window > 0 else 0.0, offered_fps=robots * rate,
        latency_p50_ms=pct(50), latency_p95_ms=pct(95), latency_p99_ms=pct(99),
        server_rss_mb_peak=max(peaks.rss) if peaks.rss else None,
        server_pss_mb_peak=max(peaks.pss) if peaks.pss else None,
        rss_mb_peak_by_role=peaks.by_role if peaks.rss else {},
        server_cpu_ms_per_frame=cpu,
        stage_median_ms={k: float(np.median(v) * 1000) for k, v in sorted(stages.items())},
        reject_reasons=reasons,
        held_back=sum(s.held_back for s in stats), server_cpu_ms_per_received=per_received,
        disconnected=[s.disconnected for s in stats if s.disconnected],
        load_average_start=load_start,
        load_average_end=list(os.getloadavg()),
    )


async def run_level(url: str, frames: Frames, robots: int, rate: float, duration: float,
                    drain: float, config: dict, server_pid: int | None,
                    hold_back: bool = False) -> LevelResult:
    """K robots streaming at once against fresh sessions, deleted afterwards."""
    sessions = _create_sessions(url, frames, robots, config)
    stats = [RobotStats() for _ in range(robots)]
    peaks = MemoryPeaks()
    stop = asyncio.Event()
    sampler = asyncio.create_task(peaks.sample(server_pid, stop))
    load_start = list(os.getloadavg())
    cpu_before = _cpu_s(server_pid)
    start_at = time.perf_counter() + 0.5
    await asyncio.gather(*(robot(url, s.id, frames, rate, duration, drain, st, start_at,
                                 hold_back)
                           for s, st in zip(sessions, stats, strict=True)))
    stop.set()
    await sampler
    cpu_after = _cpu_s(server_pid)
    with Client(url, API_KEY) as client:
        for session in sessions:
            client.delete_session(session.id)
    cpu, per_received = _server_cpu(
        cpu_before, cpu_after, server_pid,
        sum(s.answered for s in stats), sum(s.sent for s in stats),
    )
    return _level_result(stats, robots, rate, duration, peaks, cpu, per_received, load_start)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def start_server(workers: int | None, queue_size: int, policy: str, executor: str,
                 data_dir: Path) -> tuple[subprocess.Popen, str]:
    port = _free_port()
    env = {**os.environ, "SWARMVO_API_KEYS": API_KEY, "SWARMVO_QUEUE_SIZE": str(queue_size),
           "SWARMVO_QUEUE_POLICY": policy, "SWARMVO_EXECUTOR": executor}
    command = [sys.executable, "-m", "estimator.cli.main", "serve", "--host", "127.0.0.1",
               "--port", str(port), "--data-dir", str(data_dir), "--log-level", "warning"]
    if workers:
        command += ["--workers", str(workers)]
    process = subprocess.Popen(command, cwd=PROJECT_ROOT, env=env)
    url = f"http://127.0.0.1:{port}"
    try:  # workers load the estimator first; slow on a busy machine
        wait_healthy(url, process, 180, poll_s=0.25)
    except RuntimeError:
        process.kill()
        raise
    return process, url


def _parse_args(argv: list[str] | None) -> tuple[argparse.ArgumentParser, argparse.Namespace]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", default="1,2,4,8", help="comma-separated K values")
    parser.add_argument("--rate", type=float, default=20.0, help="frames/s per robot")
    parser.add_argument("--duration", type=float, default=15.0, help="seconds of sending per K")
    parser.add_argument("--drain", type=float, default=20.0,
                        help="seconds allowed after sending stops for the last answers")
    parser.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    parser.add_argument("--url", help="use a running server (needs API key load-test-key)")
    parser.add_argument("--workers", type=int,
                        help="server worker processes/threads (default: cores)")
    parser.add_argument("--executor", choices=("process", "thread"), default="process",
                        help="where the server runs the odometry (SWARMVO_EXECUTOR)")
    parser.add_argument("--encoding", choices=("png", "raw8"), default="png",
                        help="frame payload: the dataset's PNG files or raw 8-bit pixels")
    parser.add_argument("--runs", type=int, default=1,
                        help="consecutive runs of every level against the same server")
    parser.add_argument("--hold-back", action="store_true",
                        help="robots do not send frames the server's full window would refuse")
    parser.add_argument("--queue-size", type=int, default=8)
    parser.add_argument("--policy", choices=("reject", "drop_oldest"), default="reject")
    parser.add_argument("--config", default="{}", help="estimator config overrides (JSON)")
    parser.add_argument("--out", type=Path, default=PROJECT_ROOT / "benchmarks/results/load",
                        help="folder for the JSON report")
    return parser, parser.parse_args(argv)


def _levels(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list[int]:
    """The K values to run; bounds keep a mistyped flag from flooding the machine."""
    levels = [int(k) for k in args.robots.split(",")]
    if any(k < 1 or k > 64 for k in levels) or not 0 < args.rate <= 100:
        parser.error("robots must be 1..64 and rate 0..100 Hz")
    if not 1 <= args.duration <= 600:
        parser.error("duration must be 1..600 s")
    if not 1 <= args.runs <= 20:
        parser.error("runs must be 1..20")
    return levels


def _stop_server(process: subprocess.Popen | None) -> None:
    if process is not None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()


def _run_levels(url: str, pid: int | None, frames: Frames, levels: list[int],
                args: argparse.Namespace, config: dict) -> list[LevelResult]:
    """Every level ``args.runs`` times in a row, in the order given."""
    results = []
    for k in levels:
        for run in range(1, args.runs + 1):
            print(f"K={k}, run {run}/{args.runs}: {args.duration:.0f} s at {args.rate:g} "
                  "Hz per robot ...", flush=True)
            result = asyncio.run(run_level(
                url, frames, k, args.rate, args.duration, args.drain, config, pid,
                args.hold_back))
            result.run = run
            results.append(result)
    return results


def _settings(args: argparse.Namespace, config: dict, image_size: list[int]) -> dict:
    """What the report needs to be reproduced; the executor only when this run chose it."""
    return {"rate_hz": args.rate, "duration_s": args.duration,
            "queue_size": args.queue_size, "policy": args.policy,
            "workers": args.workers or os.cpu_count(), "config": config,
            "runs": args.runs,
            "executor": None if args.url else args.executor,
            "encoding": args.encoding, "hold_back": args.hold_back,
            "dataset": str(args.dataset), "image_size": image_size}


def main(argv: list[str] | None = None) -> int:
    parser, args = _parse_args(argv)
    levels = _levels(parser, args)
    config = json.loads(args.config)
    frames = Frames(args.dataset, raw=args.encoding == "raw8")
    width, height = frames.sequence.image_size
    print(f"{len(frames.pairs)} stereo pairs of {width}x{height} from {args.dataset}, "
          f"{np.mean([len(a) + len(b) for a, b in frames.pairs]) / 1024:.0f} KiB per pair "
          f"({args.encoding}); server executor: {args.executor}")

    process = None
    with tempfile.TemporaryDirectory(prefix="swarmvo-load-") as folder:
        if args.url:
            url, pid = args.url, None
            if not url.startswith(("http://127.0.0.1", "http://localhost")):
                parser.error("the load test only targets 127.0.0.1/localhost")
        else:
            process, url = start_server(args.workers, args.queue_size, args.policy,
                                        args.executor, Path(folder))
            pid = process.pid
        machine = machine_before()
        try:
            results = _run_levels(url, pid, frames, levels, args, config)
        finally:
            _stop_server(process)
    print()
    print_table(results)
    table = runs_table(results)
    print()
    print(table)
    write_report(args.out, machine, _settings(args, config, [width, height]), results, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
