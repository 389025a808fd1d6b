"""Fleet harness: PostgreSQL, 3 replicas and nginx on loopback; robots stream, replicas die.

1. renders flights with ``swarmvo synth`` (cached), starts a PostgreSQL cluster from Debian's
   server binaries, three replicas (uvicorn, one worker process each) and nginx with
   ``docker/nginx.conf`` in front;
2. failover: N robots stream their flights over WebSocket through nginx with the client's
   reliable stream (reconnect with backoff, resend what was not answered); mid-stream the replica
   holding most leases is killed with SIGKILL and started again a few seconds later (``--kills``
   times);
3. checks every answer against the database: acknowledged poses lost, duplicate poses, poses
   written without the lease (fencing column), the failover gap (kill -> next answered frame of
   an affected robot) and the pose jump at takeover (the step into the first frame the new owner
   computed, against the ground-truth step; ordinary steps for comparison);
4. overhead: one robot, one frame at a time, through nginx with leases against a direct
   connection to a replica without leases, in alternating blocks;
5. throughput: N robots through nginx with 1, 2 and 3 replicas in the upstream list.

Prints the table of the targets and writes ``benchmarks/results/cluster/cluster.json``.

    python benchmarks/cluster.py                     # the full run (a few minutes)
    python benchmarks/cluster.py --quick             # the short form CI runs (under a minute)
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import secrets
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from cluster_check import check, table
from local_cluster import PROJECT_ROOT, Balancer, Postgres, Replica, missing_tools
from swarmvo_client import Backoff, Client, LocalSequence, Pose, open_local_sequence
from swarmvo_client.reliable import Outage, ReliableStream
from swarmvo_client.replay import create_session_for, frame_imu

RESULTS = PROJECT_ROOT / "benchmarks" / "results" / "cluster"
CACHE = Path(tempfile.gettempdir()) / "swarmvo-cluster-flights"
TARGETS = {"lost": 0, "duplicates": 0, "unfenced": 0, "gap_p95_s": 2.0, "jump_m": 0.01,
           "overhead": 0.10}


@dataclass
class Options:
    robots: int = 4
    frames: int = 160
    flights: int = 2
    kills: int = 2
    down_s: float = 4.0
    window: int = 2
    lease_ttl_s: float = 0.5
    overhead_frames: int = 30
    overhead_rounds: int = 3
    level_s: float = 12.0
    levels: tuple[int, ...] = (1, 2, 3)


@dataclass
class RobotRun:
    name: str
    sequence: LocalSequence
    session_id: str = ""
    answers: dict[int, tuple[Pose, float]] = field(default_factory=dict)  # ts -> (pose, time)
    rejected: list[tuple[int, int, str]] = field(default_factory=list)
    reconnects: int = 0
    resent: int = 0
    duplicates: int = 0
    outages: list[Outage] = field(default_factory=list)  # the client's view of each break


# ----------------------------------------------------------------------------- set-up


def render_flights(count: int, frames: int) -> list[Path]:
    """Rendered flights (EuRoC layout, IMU, ground truth), cached between runs."""
    folders = []
    for seed in range(count):
        folder = CACHE / f"flight-{frames}-{seed}"
        if not (folder / "mav0" / "cam0" / "data.csv").exists():
            print(f"rendering flight {seed} ({frames} frames) ...", flush=True)
            subprocess.run(
                [sys.executable, "-m", "estimator.cli", "synth", str(folder), "--frames",
                 str(frames), "--length-m", str(frames * 0.05), "--seed", str(seed), "--quiet"],
                cwd=PROJECT_ROOT, check=True, timeout=900,
                env={**os.environ, "OMP_NUM_THREADS": "1"},
            )
        folders.append(folder)
    return folders


class Fleet:
    """The processes of one harness run; stopped whatever happens."""

    def __init__(self, folder: Path, options: Options) -> None:
        self.folder = folder
        self.key = secrets.token_hex(12)
        self.postgres = Postgres()
        self.database = "fleet"
        self.url = self.postgres.create_database(self.database)
        self.replicas = [Replica(f"r{i}", self.url, self.key, folder,
                                 lease_ttl_s=options.lease_ttl_s) for i in range(3)]
        self.direct: Replica | None = None
        self.balancer: Balancer | None = None

    def start(self, warm: bool = True) -> None:
        """Start everything; ``warm``: fill the JIT cache first, in one process.

        Each replica's worker runs the estimator on synthetic frames before the replica answers
        (service.estimator_adapter). With an empty cache (a fresh checkout) three workers would
        compile every kernel at once, for minutes on 2 cores, and could fail a frame ("no
        compiled object yet"); ``python -m service.warmup`` compiles them once, and the replicas
        then only load them.
        """
        if warm:
            subprocess.run([sys.executable, "-m", "service.warmup"], cwd=PROJECT_ROOT,
                           env={**os.environ, "OMP_NUM_THREADS": "1"}, check=True, timeout=900,
                           stdout=subprocess.DEVNULL)
        for replica in self.replicas:
            replica.start(wait=False)
        for replica in self.replicas:
            replica.wait_healthy()
        self.balancer = Balancer(self.upstreams(3), self.folder)
        self.balancer.start()

    def upstreams(self, count: int) -> list[str]:
        return [f"127.0.0.1:{r.port}" for r in self.replicas[:count]]

    def stop(self) -> None:
        if self.balancer is not None:
            self.balancer.stop()
        replicas = [*self.replicas, *([self.direct] if self.direct else [])]
        with ThreadPoolExecutor(len(replicas)) as pool:  # each drains for up to seconds
            list(pool.map(lambda replica: replica.stop(), replicas))
        self.postgres.remove()

    def sql(self, query: str, *params: object) -> list[tuple]:
        return self.postgres.query(self.database, query, *params)


def new_session(url: str, key: str, sequence: LocalSequence, name: str) -> str:
    with Client(url, key, timeout=60) as client:
        return create_session_for(client, sequence, {"seed": 0}, name).id


# ----------------------------------------------------------------------------- streaming


async def stream_robot(robot: RobotRun, url: str, key: str, window: int,
                       deadline: float | None = None, loop_frames: bool = False,
                       answer_timeout_s: float = 20.0) -> None:
    """Send the robot's frames with at most ``window`` unanswered; every frame answered once."""
    sequence = robot.sequence
    stream = ReliableStream(url, robot.session_id, key, backoff=Backoff(0.05, 0.5),
                            answer_timeout_s=answer_timeout_s, seed=hash(robot.name) % 1000)
    await stream.start()
    credit = asyncio.Semaphore(window)
    count = len(sequence.frames)
    period = sequence.frames[-1].timestamp_ns - sequence.frames[0].timestamp_ns + 50_000_000
    sent = 0

    async def produce() -> None:
        nonlocal sent
        index = 0
        while True:
            if not loop_frames and index >= count:
                return
            if deadline is not None and time.perf_counter() > deadline:
                return
            await credit.acquire()
            position = index % count
            stamp = sequence.frames[position].timestamp_ns + (index // count) * period
            left, right = sequence.frame_bytes(position)
            imu = frame_imu(sequence, position) if index < count else None
            await stream.send_frame(stamp, left, right, imu)
            sent += 1
            index += 1

    producer = asyncio.create_task(produce())
    try:
        received = 0
        while not (producer.done() and received >= sent):
            try:
                event = await asyncio.wait_for(stream.recv(), 1.0)
            except TimeoutError:
                if producer.done() and producer.exception() is not None:
                    await producer  # its error, not a silent hang
                continue
            received += 1
            credit.release()
            now = time.perf_counter()
            if isinstance(event, Pose):
                robot.answers[event.timestamp_ns] = (event, now)
            else:
                robot.rejected.append((getattr(event, "timestamp_ns", -1) or -1,
                                       getattr(event, "status", 0), str(event)))
    finally:
        producer.cancel()
        robot.reconnects += stream.stats.reconnects
        robot.outages += stream.stats.outages
        robot.resent += stream.stats.resent
        robot.duplicates += stream.stats.duplicates
        await stream.close()


# ----------------------------------------------------------------------------- failover


async def failover(fleet: Fleet, robots: list[RobotRun], options: Options) -> dict[str, Any]:
    """Robots stream through nginx; the busiest replica is killed and restarted mid-stream."""
    assert fleet.balancer is not None
    total = sum(len(r.sequence.frames) for r in robots)
    tasks = [asyncio.create_task(stream_robot(r, fleet.balancer.url, fleet.key, options.window))
             for r in robots]
    kills: list[dict[str, Any]] = []
    for kill in range(options.kills):
        target = total * (kill + 1) / (options.kills + 1.5)
        while sum(len(r.answers) for r in robots) < target and not all(t.done() for t in tasks):
            await asyncio.sleep(0.05)
        if all(t.done() for t in tasks):
            break
        holders = await asyncio.to_thread(
            fleet.sql, "SELECT lease_holder, id FROM sessions WHERE lease_holder IS NOT NULL")
        by_replica: dict[str, list[str]] = {}
        for holder, session_id in holders:
            by_replica.setdefault(holder, []).append(session_id)
        victim = max(fleet.replicas,
                     key=lambda r: len(by_replica.get(r.replica_id, [])))
        affected = by_replica.get(victim.replica_id, [])
        dead_id = victim.replica_id
        killed_at = time.perf_counter()
        await asyncio.to_thread(victim.kill)
        print(f"  killed {victim.name} (SIGKILL) holding {len(affected)} session(s)", flush=True)
        taken: dict[str, float] = {}
        kills.append({"replica": victim.name, "at": killed_at, "sessions": affected,
                      "lease_taken_at": taken})
        watcher = asyncio.create_task(_watch_takeover(fleet, affected, dead_id, taken))
        await asyncio.sleep(options.down_s)
        watcher.cancel()
        await asyncio.to_thread(victim.start)
        print(f"  restarted {victim.name}", flush=True)
    await asyncio.gather(*tasks)
    return {"kills": kills}


async def _watch_takeover(fleet: Fleet, sessions: list[str], dead_id: str,
                          taken: dict[str, float], period_s: float = 0.02) -> None:
    """When each session's lease passes from the killed replica to another (polled)."""
    while len(taken) < len(sessions):
        rows = await asyncio.to_thread(
            fleet.sql, "SELECT id, lease_holder FROM sessions WHERE id = ANY(%s)", sessions)
        now = time.perf_counter()
        for session_id, holder in rows:
            if holder is not None and holder != dead_id:
                taken.setdefault(session_id, now)
        await asyncio.sleep(period_s)


# ----------------------------------------------------------------------------- speed


async def overhead(fleet: Fleet, sequence: LocalSequence, options: Options) -> dict[str, Any]:
    """Per-frame round trip, one frame at a time: nginx + lease against direct, no lease."""
    assert fleet.balancer is not None and fleet.direct is not None
    times: dict[str, list[float]] = {"direct": [], "fleet": []}
    for round_index in range(options.overhead_rounds):
        for mode, url in (("direct", fleet.direct.url), ("fleet", fleet.balancer.url)):
            robot = RobotRun(f"{mode}-{round_index}", _cut(sequence, options.overhead_frames))
            robot.session_id = await asyncio.to_thread(new_session, url, fleet.key,
                                                       robot.sequence, robot.name)
            began = time.perf_counter()
            await stream_robot(robot, url, fleet.key, window=1)
            answered = sorted(when for _pose, when in robot.answers.values())
            rounds = np.diff([began, *answered])[3:]  # the first frames build the pipeline
            times[mode] += rounds.tolist()
    direct, fleet_ms = np.median(times["direct"]), np.median(times["fleet"])
    return {"direct_ms": 1000 * float(direct), "fleet_ms": 1000 * float(fleet_ms),
            "overhead": float(fleet_ms / direct - 1), "frames_per_mode": len(times["direct"])}


async def throughput(fleet: Fleet, sequences: list[LocalSequence], options: Options
                     ) -> list[dict[str, Any]]:
    """Frames/s of N robots through nginx with 1, 2, 3 replicas upstream."""
    assert fleet.balancer is not None
    levels = []
    for count in options.levels:
        await asyncio.to_thread(fleet.balancer.reload, fleet.upstreams(count))
        robots = [RobotRun(f"load{count}-{i}", sequences[i % len(sequences)])
                  for i in range(options.robots)]
        for robot in robots:
            robot.session_id = await asyncio.to_thread(new_session, fleet.balancer.url,
                                                       fleet.key, robot.sequence, robot.name)
        cpu_before = sum(r.cpu_seconds() for r in fleet.replicas[:count])
        began = time.perf_counter()
        deadline = began + options.level_s
        await asyncio.gather(*(stream_robot(r, fleet.balancer.url, fleet.key, options.window,
                                            deadline, loop_frames=True) for r in robots))
        elapsed = time.perf_counter() - began
        cpu = sum(r.cpu_seconds() for r in fleet.replicas[:count]) - cpu_before
        answered = sum(len(r.answers) for r in robots)
        cores = os.cpu_count() or 1
        levels.append({
            "replicas": count, "robots": len(robots), "seconds": round(elapsed, 2),
            "frames": answered, "frames_per_s": answered / elapsed,
            "frames_per_s_per_core": answered / elapsed / min(cores, count),
            "replica_cpu_ms_per_frame": 1000 * cpu / max(answered, 1),
            "rejected": sum(len(r.rejected) for r in robots),
        })
        print(f"  {count} replica(s): {answered / elapsed:.1f} frames/s", flush=True)
    await asyncio.to_thread(fleet.balancer.reload, fleet.upstreams(3))
    return levels


def _cut(sequence: LocalSequence, frames: int) -> LocalSequence:
    from dataclasses import replace

    return replace(sequence, frames=sequence.frames[:frames])


# ----------------------------------------------------------------------------- report


def run(options: Options, folder: Path, speed: bool = True) -> dict[str, Any]:
    """The whole harness in ``folder``; returns the result document."""
    flights = [open_local_sequence(f) for f in render_flights(options.flights, options.frames)]
    fleet = Fleet(folder, options)
    try:
        started = time.perf_counter()
        fleet.start()
        print(f"PostgreSQL, 3 replicas and nginx up in {time.perf_counter() - started:.1f} s",
              flush=True)
        robots = [RobotRun(f"robot{i}", flights[i % len(flights)]) for i in range(options.robots)]
        for robot in robots:
            assert fleet.balancer is not None
            robot.session_id = new_session(fleet.balancer.url, fleet.key, robot.sequence,
                                           robot.name)
        print(f"failover: {len(robots)} robots x {options.frames} frames, "
              f"{options.kills} kill(s)", flush=True)
        outcome = asyncio.run(failover(fleet, robots, options))
        result: dict[str, Any] = {"failover": check(fleet, robots, outcome)}
        if speed:
            fleet.direct = Replica("direct", fleet.url, fleet.key, folder, leases=False)
            fleet.direct.start()
            print("overhead: nginx + lease against a direct connection", flush=True)
            result["overhead"] = asyncio.run(overhead(fleet, flights[0], options))
            fleet.direct.stop()
            print("throughput with 1, 2, 3 replicas", flush=True)
            result["throughput"] = asyncio.run(throughput(fleet, flights, options))
    finally:
        fleet.stop()
    result["options"] = asdict(options)
    result["machine"] = {"cpus": os.cpu_count(), "platform": platform.platform(),
                         "python": platform.python_version()}
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the short form (CI)")
    parser.add_argument("--robots", type=int)
    parser.add_argument("--frames", type=int)
    parser.add_argument("--kills", type=int)
    parser.add_argument("--no-speed", action="store_true", help="failover checks only")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    reason = missing_tools()
    if reason is not None:
        print(f"cannot run the cluster: {reason}", file=sys.stderr)
        return 2
    options = quick_options() if args.quick else Options()
    for name in ("robots", "frames", "kills"):
        if getattr(args, name) is not None:
            setattr(options, name, getattr(args, name))
    with tempfile.TemporaryDirectory(prefix="swarmvo-cluster-") as folder:
        result = run(options, Path(folder), speed=not (args.quick or args.no_speed))
    args.out.mkdir(parents=True, exist_ok=True)
    name = "cluster-quick.json" if args.quick else "cluster.json"
    (args.out / name).write_text(json.dumps(result, indent=2) + "\n")
    print()
    print(table(result))
    print(f"\nwrote {args.out / name}")
    failover = result["failover"]
    broken = (failover["acknowledged_poses_lost"] or failover["duplicate_poses"]
              or failover["poses_without_lease"] or failover["frames_unanswered"])
    return 1 if broken else 0


def quick_options() -> Options:
    return Options(robots=2, frames=60, flights=1, kills=1, down_s=2.0, window=2)


if __name__ == "__main__":
    sys.exit(main())
