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
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from server_wait import wait_healthy
from swarmvo_client import Client, DroppedFrame, Pose, open_local_sequence, stream
from swarmvo_client.models import ImuData

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
    load_average_start: list[float] = field(default_factory=list)
    load_average_end: list[float] = field(default_factory=list)

    @property
    def cpu_ms_per_frame(self) -> float | None:
        """Server process plus worker processes, CPU per answered frame."""
        if not self.server_cpu_ms_per_frame:
            return None
        return sum(self.server_cpu_ms_per_frame.values())


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


async def robot(url: str, session_id: str, frames: Frames, rate: float, duration: float,
                drain: float, stats: RobotStats, start_at: float, hold_back: bool) -> None:
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
                now = time.perf_counter()
                if isinstance(event, Pose):
                    stats.answered += 1
                    stats.latencies_s.append(now - sent_at[event.timestamp_ns])
                    stats.last_answer = now
                    for stage in ("queue_wait", "decode", "odometry", "transfer", "persist",
                                  "total"):
                        if stage in event.timings_s:
                            stats.stage_s.setdefault(stage, []).append(event.timings_s[stage])
                elif isinstance(event, DroppedFrame):
                    stats.dropped += 1
                else:
                    stats.rejected += 1
                    reason = event.detail.split(":")[0][:60]
                    stats.reject_reasons[reason] = stats.reject_reasons.get(reason, 0) + 1
        finally:
            producer.cancel()
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


async def run_level(url: str, frames: Frames, robots: int, rate: float, duration: float,
                    drain: float, config: dict, server_pid: int | None,
                    hold_back: bool = False) -> LevelResult:
    with Client(url, API_KEY) as client:
        files = frames.sequence.calibration_files
        sessions = [
            client.create_session_euroc(files["cam0"], files["cam1"], files.get("imu0"),
                                        config=config, name=f"load-robot-{k}")
            for k in range(robots)
        ]
    stats = [RobotStats() for _ in range(robots)]
    peak_rss: list[float] = []
    peak_pss: list[float] = []
    peak_role = {"server_process": 0.0, "worker_processes": 0.0}
    stop = asyncio.Event()

    async def sample_memory() -> None:
        while not stop.is_set() and server_pid is not None:
            by_pid = _rss_mb(server_pid)
            if by_pid:
                peak_rss.append(sum(by_pid.values()))
                peak_pss.append(_pss_mb(server_pid))
                server = by_pid.pop(server_pid, 0.0)
                peak_role["server_process"] = max(peak_role["server_process"], server)
                peak_role["worker_processes"] = max(
                    peak_role["worker_processes"], sum(by_pid.values())
                )
            await asyncio.sleep(0.25)

    sampler = asyncio.create_task(sample_memory())
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

    latencies = np.array([v for s in stats for v in s.latencies_s])
    sent = sum(s.sent for s in stats)
    answered = sum(s.answered for s in stats)
    dropped = sum(s.dropped for s in stats)
    rejected = sum(s.rejected for s in stats)
    firsts = [s.first_send for s in stats if s.first_send]
    lasts = [s.last_answer for s in stats if s.last_answer]
    window = (max(lasts) - min(firsts)) if firsts and lasts else 0.0
    stages: dict[str, list[float]] = {}
    reasons: dict[str, int] = {}
    for s in stats:
        for stage, values in s.stage_s.items():
            stages.setdefault(stage, []).extend(values)
        for reason, count in s.reject_reasons.items():
            reasons[reason] = reasons.get(reason, 0) + count

    cpu: dict[str, float] = {}
    per_received = None
    if cpu_after and answered:
        used = {p: t - cpu_before.get(p, 0.0) for p, t in cpu_after.items()}
        server_s = used.pop(server_pid, 0.0)
        cpu["server_process"] = server_s * 1000 / answered
        cpu["worker_processes"] = sum(used.values()) * 1000 / answered
        per_received = server_s * 1000 / sent

    def pct(q: float) -> float | None:
        return float(np.percentile(latencies, q) * 1000) if len(latencies) else None

    return LevelResult(
        robots=robots, rate_hz=rate, duration_s=duration, sent=sent, answered=answered,
        dropped=dropped, rejected=rejected, unanswered=sent - answered - dropped - rejected,
        sustained_fps=answered / window if window > 0 else 0.0, offered_fps=robots * rate,
        latency_p50_ms=pct(50), latency_p95_ms=pct(95), latency_p99_ms=pct(99),
        server_rss_mb_peak=max(peak_rss) if peak_rss else None,
        server_pss_mb_peak=max(peak_pss) if peak_pss else None,
        rss_mb_peak_by_role=peak_role if peak_rss else {},
        server_cpu_ms_per_frame=cpu,
        stage_median_ms={k: float(np.median(v) * 1000) for k, v in sorted(stages.items())},
        reject_reasons=reasons,
        held_back=sum(s.held_back for s in stats), server_cpu_ms_per_received=per_received,
        load_average_start=load_start,
        load_average_end=list(os.getloadavg()),
    )


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


RUNS_HEADER = (
    "| run | robots | offered/s | answered/s | sent | answered | dropped | rejected | lost "
    "| p50 ms | p95 ms | p99 ms | CPU ms/frame server | CPU ms/frame workers | CPU ms/frame total "
    "| server CPU ms/received | held back | RSS MB | PSS MB | load avg start -> end |"
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
            f"| {r.held_back} | {_fmt(r.server_rss_mb_peak, 0)} "
            f"| {_fmt(r.server_pss_mb_peak, 0)} | {load} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
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
    args = parser.parse_args(argv)
    levels = [int(k) for k in args.robots.split(",")]
    if any(k < 1 or k > 64 for k in levels) or not 0 < args.rate <= 100:
        parser.error("robots must be 1..64 and rate 0..100 Hz")
    if not 1 <= args.duration <= 600:
        parser.error("duration must be 1..600 s")
    if not 1 <= args.runs <= 20:
        parser.error("runs must be 1..20")
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
        results = []
        load_before = os.getloadavg()
        try:
            for k in levels:
                for run in range(1, args.runs + 1):
                    print(f"K={k}, run {run}/{args.runs}: {args.duration:.0f} s at {args.rate:g} "
                          "Hz per robot ...", flush=True)
                    result = asyncio.run(run_level(
                        url, frames, k, args.rate, args.duration, args.drain, config, pid,
                        args.hold_back))
                    result.run = run
                    results.append(result)
        finally:
            if process is not None:
                process.send_signal(signal.SIGTERM)
                try:
                    process.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    process.kill()
    print()
    print_table(results)
    table = runs_table(results)
    print()
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    report = {
        "created_utc": stamp,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "python": platform.python_version(), "load_average_before": load_before,
                    "load_average_after": os.getloadavg()},
        "settings": {"rate_hz": args.rate, "duration_s": args.duration,
                     "queue_size": args.queue_size, "policy": args.policy,
                     "workers": args.workers or os.cpu_count(), "config": config,
                     "runs": args.runs,
                     "executor": None if args.url else args.executor,
                     "encoding": args.encoding, "hold_back": args.hold_back,
                     "dataset": str(args.dataset), "image_size": [width, height]},
        "levels": [{**asdict(r), "cpu_ms_per_frame": r.cpu_ms_per_frame} for r in results],
    }
    path = args.out / f"load_{stamp}.json"
    path.write_text(json.dumps(report, indent=2) + "\n")
    print(f"\nwrote {path}")
    if args.runs > 1:
        settings = report["settings"]
        markdown = args.out / f"load_{stamp}.md"
        markdown.write_text(
            f"{args.runs} consecutive runs of {args.duration:g} s per level at {args.rate:g} Hz "
            f"per robot, {settings['encoding']} frames, executor {settings['executor']}, "
            f"{settings['workers']} workers, {os.cpu_count()} CPUs ({stamp}; JSON "
            f"{path.name}).\n\n{table}\n"
        )
        print(f"wrote {markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
