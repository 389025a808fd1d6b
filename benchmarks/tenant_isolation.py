"""Two API keys on one worker process: does the heaviest session the limits allow slow the other?

A real ``swarmvo serve --workers 1`` on loopback. Key B streams the real EuRoC MH_01 clip with
the default configuration (with its IMU) at 20 Hz over HTTP, one frame at a time; its latency
is send -> pose answered, in alternating blocks: B alone, then B while key A sends the same clip
back to back (always one frame in the worker) with the most expensive configuration the work
limits allow (every bound of ``service.limits`` at its maximum). Reports B's latency
percentiles, the ratio of B's p95 with A to B's p95 alone, whether any of B's frames was
resumed (its pipeline reset), and A's frame rate and answers.

    python benchmarks/tenant_isolation.py            # writes benchmarks/results/service/
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from server_wait import wait_healthy
from swarmvo_client import Client, open_local_sequence

from service.limits import CONFIG_BOUNDS, OPTION_BOUNDS

PROJECT_ROOT = Path(__file__).resolve().parents[1]
DATASET = PROJECT_ROOT.parent / "shared" / "data" / "euroc_mh01_moving"
KEY_A, KEY_B = "isolation-key-a", "isolation-key-b"


def heaviest_config(matcher: str) -> dict:
    """Every work bound at its maximum (pso-robust options), with the given temporal matcher."""
    config: dict = {"frontend": {"temporal_matcher": matcher}, "registration": {}, "backend": {}}
    for bound in CONFIG_BOUNDS:
        config[bound.section][bound.key] = bound.maximum
    config["registration"]["options"] = dict(OPTION_BOUNDS["pso-robust"])
    return config


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def start_server(folder: Path) -> tuple[subprocess.Popen, str]:
    port = _free_port()
    env = {**os.environ, "SWARMVO_API_KEYS": f"{KEY_A},{KEY_B}", "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen(
        [sys.executable, "-m", "estimator.cli.main", "serve", "--port", str(port), "--data-dir",
         str(folder), "--workers", "1", "--log-level", "warning"],
        cwd=PROJECT_ROOT, env=env, stdout=(folder / "server.log").open("wb"),
        stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        wait_healthy(url, process, 60, poll_s=0.1)
    except RuntimeError:
        process.kill()
        raise
    return process, url


class Tenant:
    """One key, one session over the clip; frames read once, timestamps kept increasing."""

    def __init__(self, url: str, key: str, config: dict) -> None:
        self.sequence = open_local_sequence(DATASET)
        self.client = Client(url, key, timeout=120)
        files = self.sequence.calibration_files
        self.session = self.client.create_session_euroc(
            files["cam0"], files["cam1"], files.get("imu0"), config=config
        )
        self.pairs = [(f.timestamp_ns, f.left.read_bytes(), f.right.read_bytes())
                      for f in self.sequence.frames]
        self.sent = 0
        self.last_ns: int | None = None

    def send_next(self) -> tuple[float, object]:
        count = len(self.pairs)
        lap, position = divmod(self.sent, count)
        timestamp, left, right = self.pairs[position]
        span = self.pairs[-1][0] - self.pairs[0][0] + 50_000_000
        stamp = timestamp + lap * span
        imu = None
        if self.sequence.imu is not None and lap == 0:
            imu = self.sequence.imu.between(self.last_ns, stamp)
        start = time.perf_counter()
        pose = self.client.send_frame(self.session.id, stamp, left, right, imu)
        self.sent += 1
        self.last_ns = stamp
        return time.perf_counter() - start, pose


def stream_b(tenant: Tenant, frames: int, rate_hz: float) -> tuple[list[float], list[bool]]:
    latencies, resumed = [], []
    period = 1.0 / rate_hz
    next_send = time.perf_counter()
    for _ in range(frames):
        next_send += period
        seconds, pose = tenant.send_next()
        latencies.append(seconds)
        resumed.append(bool(pose.resumed))
        time.sleep(max(0.0, next_send - time.perf_counter()))
    return latencies, resumed


def _percentiles(values: list[float]) -> dict[str, float]:
    array = np.array(values) * 1000
    return {"p50_ms": float(np.percentile(array, 50)), "p95_ms": float(np.percentile(array, 95)),
            "max_ms": float(array.max())}


def run(frames: int, matcher: str, rounds: int) -> dict:
    """Alternate blocks of B alone and B with A, so that a drifting machine load hits both."""
    folder = Path(tempfile.mkdtemp(prefix="swarmvo-isolation-"))
    process, url = start_server(folder)
    flood: Flood | None = None
    try:
        b = Tenant(url, KEY_B, {})
        a = Tenant(url, KEY_A, heaviest_config(matcher))
        stream_b(b, 5, 20.0)  # first frames (pipeline build) out of the measurement
        a.send_next()
        flood = Flood(a)
        flood.thread.start()
        blocks = alternate_blocks(b, flood, max(1, frames // rounds), rounds)
        flood.stop.set()
        flood.thread.join(timeout=120)
    finally:
        if flood is not None:
            flood.stop.set()
        process.terminate()
        process.wait(timeout=60)
    return summary(matcher, blocks, flood)


class Flood:
    """Key A sending its frames back to back from a thread whenever ``active`` is set."""

    def __init__(self, tenant: Tenant) -> None:
        self.tenant = tenant
        self.latency: list[float] = []
        self.answers: list[str] = []
        self.active, self.stop = threading.Event(), threading.Event()
        self.thread = threading.Thread(target=self._send)

    def _send(self) -> None:
        while not self.stop.is_set():
            if not self.active.wait(0.1):
                continue
            try:
                seconds, pose = self.tenant.send_next()
                self.latency.append(seconds)
                self.answers.append(str(pose.status))
            except Exception as error:  # an answered refusal counts as an answer here
                self.answers.append(type(error).__name__)


@dataclass
class Blocks:
    """B's latencies alone and with A, whether its frames were resumed, and A's share."""

    alone: list[float] = field(default_factory=list)
    shared: list[float] = field(default_factory=list)
    resumed: list[bool] = field(default_factory=list)
    shared_time: float = 0.0
    a_during_last: int = 0


def alternate_blocks(b: Tenant, flood: Flood, block: int, rounds: int) -> Blocks:
    """``rounds`` times: ``block`` frames of B alone, then ``block`` frames with A flooding."""
    blocks = Blocks()
    for _ in range(rounds):
        latencies, flags = stream_b(b, block, 20.0)
        blocks.alone += latencies
        blocks.resumed += flags
        flood.active.set()
        time.sleep(0.5)
        started = time.perf_counter()
        answered_before = len(flood.latency)
        latencies, flags = stream_b(b, block, 20.0)
        blocks.shared_time += time.perf_counter() - started
        blocks.a_during_last = len(flood.latency) - answered_before
        flood.active.clear()
        blocks.shared += latencies
        blocks.resumed += flags
        time.sleep(0.5)
    return blocks


def summary(matcher: str, blocks: Blocks, flood: Flood) -> dict:
    alone, shared, shared_time = blocks.alone, blocks.shared, blocks.shared_time
    a_latency, a_answers = flood.latency, flood.answers
    return {
        "a_config": heaviest_config(matcher),
        "b_frames_each": len(alone),
        "b_alone": _percentiles(alone),
        "b_with_a": _percentiles(shared),
        "b_p95_ratio": float(np.percentile(shared, 95) / np.percentile(alone, 95)),
        "b_resumed_frames": int(sum(blocks.resumed)),
        "a_frames_answered": len(a_latency),
        "a_frames_in_last_block": blocks.a_during_last,
        "a_latency": _percentiles(a_latency) if a_latency else {},
        "a_answers": {k: a_answers.count(k) for k in sorted(set(a_answers))},
        "shared_window_s": shared_time,
        "a_frames_per_s": len(a_latency) / shared_time if shared_time else 0.0,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=90, help="B frames alone (and with A)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path,
                        default=PROJECT_ROOT / "benchmarks" / "results" / "service")
    args = parser.parse_args()
    if not DATASET.is_dir():
        print(f"EuRoC clip not found at {DATASET}", file=sys.stderr)
        return 2
    rows = {}
    for matcher in ("descriptor", "klt"):
        rows[matcher] = run(args.frames, matcher, args.rounds)
    print("| A's matcher | B p50 alone | B p95 alone | B p50 with A | B p95 with A | p95 ratio "
          "| B resumed | A frames/s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for matcher, row in rows.items():
        alone, shared = row["b_alone"], row["b_with_a"]
        print(f"| {matcher} | {alone['p50_ms']:.0f} ms | {alone['p95_ms']:.0f} ms "
              f"| {shared['p50_ms']:.0f} ms | {shared['p95_ms']:.0f} ms "
              f"| {row['b_p95_ratio']:.2f} | {row['b_resumed_frames']} "
              f"| {row['a_frames_per_s']:.1f} |")
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                           "load_average_1m": os.getloadavg()[0]},
               "dataset": DATASET.name, "runs": rows}
    (args.out / "tenant_isolation.json").write_text(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
