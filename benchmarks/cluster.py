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
import itertools
import json
import os
import platform
import secrets
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
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

    def start(self, warm: Path | None = None) -> None:
        """Start everything; ``warm``: a flight the estimator runs a few frames of first.

        The replicas compile nothing before their first session, and three processes filling
        an empty JIT cache at once can fail a frame ("no compiled object yet"): one run fills
        it while the replicas start, and they all load it.
        """
        warming = None
        if warm is not None:
            warming = subprocess.Popen(
                [sys.executable, "-m", "estimator.cli", "run", str(warm), "--limit", "3",
                 "--quiet", "--out", str(self.folder / "warm-up")],
                cwd=PROJECT_ROOT, env={**os.environ, "OMP_NUM_THREADS": "1"},
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )
        for replica in self.replicas:
            replica.start(wait=False)
        for replica in self.replicas:
            replica.wait_healthy()
        self.balancer = Balancer(self.upstreams(3), self.folder)
        self.balancer.start()
        if warming is not None and warming.wait(timeout=600) != 0:
            raise RuntimeError(f"the warm-up run on {warm} failed")

    def upstreams(self, count: int) -> list[str]:
        return [f"127.0.0.1:{r.port}" for r in self.replicas[:count]]

    def stop(self) -> None:
        if self.balancer is not None:
            self.balancer.stop()
        for replica in [*self.replicas, *([self.direct] if self.direct else [])]:
            replica.stop()
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


def _camera_poses(sequence: LocalSequence, body_from_camera: np.ndarray
                  ) -> dict[int, np.ndarray]:
    """Ground-truth left-camera poses at the frame timestamps (exact ground-truth rows)."""
    assert sequence.gt_timestamps_ns is not None and sequence.gt_positions is not None
    assert sequence.gt_rotations is not None
    rows = {int(t): i for i, t in enumerate(sequence.gt_timestamps_ns)}
    poses = {}
    for frame in sequence.frames:
        i = rows.get(frame.timestamp_ns)
        if i is None:
            continue
        body = np.eye(4)
        body[:3, :3], body[:3, 3] = sequence.gt_rotations[i], sequence.gt_positions[i]
        poses[frame.timestamp_ns] = body @ body_from_camera
    return poses


def _step_error(poses: dict[int, np.ndarray], truth: dict[int, np.ndarray], previous: int,
                current: int) -> float | None:
    """|estimated step - true step| of the camera from ``previous`` to ``current`` [m]."""
    if not all(t in poses and t in truth for t in (previous, current)):
        return None
    estimated = np.linalg.inv(poses[previous]) @ poses[current]
    true = np.linalg.inv(truth[previous]) @ truth[current]
    return float(np.linalg.norm(estimated[:3, 3] - true[:3, 3]))


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


def _phases(robot: RobotRun, kill: dict[str, Any]) -> dict[str, float] | None:
    """Where one affected robot's failover gap went, in seconds from the kill:

    - ``noticed``: the client saw its stream break (nginx closed it when the replica died);
    - ``reconnected``: a replica greeted it again through nginx;
    - ``lease_taken``: the new owner holds the session's lease (the old one expired first);
    - ``answered``: the first frame answered again (state restored, pipeline built, frame
      computed and stored).
    """
    at = kill["at"]
    outage = next((o for o in robot.outages if o.lost_at >= at - 0.05), None)
    taken = kill["lease_taken_at"].get(robot.session_id)
    if outage is None or outage.answered_at is None:
        return None
    return {
        "noticed": outage.lost_at - at,
        "reconnected": (outage.reconnected_at or outage.answered_at) - at,
        "lease_taken": (taken if taken is not None else outage.answered_at) - at,
        "answered": outage.answered_at - at,
        "connections": outage.connections,
    }


def check(fleet: Fleet, robots: list[RobotRun], run: dict[str, Any]) -> dict[str, Any]:
    """Compare what robots were answered with what the database holds."""
    lost = mismatched = duplicates = unfenced = unanswered = 0
    takeover_jumps: list[float] = []
    ordinary: list[float] = []
    gaps: list[float] = []
    problems: list[str] = []
    with Client(fleet.replicas[0].url, fleet.key, timeout=60) as client:
        calibrations = {r.name: client.get_session(r.session_id).calibration for r in robots}
    for robot in robots:
        rows = fleet.sql(
            "SELECT timestamp_ns, frame_index, pose::text, fence_token, writer, resumed "
            "FROM poses WHERE session_id = %s ORDER BY frame_index", robot.session_id)
        stored = {int(r[0]): r for r in rows}
        duplicates += len(rows) - len(stored)
        unanswered += len(robot.sequence.frames) - len(robot.answers)
        for stamp, (pose, _when) in robot.answers.items():
            row = stored.get(stamp)
            if row is None:
                lost += 1
                problems.append(f"{robot.name}: {stamp} answered, not stored")
            elif json.loads(row[2]) != pose.pose.reshape(16).tolist() or row[1] != pose.index:
                mismatched += 1
                problems.append(f"{robot.name}: {stamp} stored differs from the answer "
                                f"(index {row[1]} vs {pose.index})")
        # Fencing: tokens never go back along the trajectory and each has one writer.
        writers: dict[int, set[str]] = {}
        highest = 0
        for _stamp, _index, _pose, token, writer, _resumed in rows:
            if token is None or token < highest:
                unfenced += 1
                continue
            highest = token
            writers.setdefault(token, set()).add(writer)
        unfenced += sum(len(w) - 1 for w in writers.values())
        # Pose jump: the step into each frame a new owner computed first, against the truth.
        body_from_camera = np.array(calibrations[robot.name]["left"]["T_BS"], dtype=float)
        truth = _camera_poses(robot.sequence, body_from_camera)
        estimated = {int(r[0]): np.array(json.loads(r[2])).reshape(4, 4) for r in rows}
        stamps = [int(r[0]) for r in rows]
        for previous, current, row in zip(stamps, stamps[1:], rows[1:], strict=False):
            error = _step_error(estimated, truth, previous, current)
            if error is not None:
                (takeover_jumps if row[5] else ordinary).append(error)
    phases: list[dict[str, float]] = []
    for kill in run["kills"]:
        for robot in robots:
            if robot.session_id not in kill["sessions"]:
                continue
            after = [when for _pose, when in robot.answers.values() if when > kill["at"]]
            if after:
                gaps.append(min(after) - kill["at"])
            phase = _phases(robot, kill)
            if phase is not None:
                phases.append({k: round(v, 3) for k, v in phase.items()})
    return {
        "acknowledged_poses_lost": lost + mismatched,
        "duplicate_poses": duplicates,
        "poses_without_lease": unfenced,
        "frames_unanswered": unanswered,
        "problems": problems[:10],
        "frames_rejected": sum(len(r.rejected) for r in robots),
        "rejections": [rej for r in robots for rej in r.rejected][:10],
        "answers_from_stored_pose": sum(r.duplicates for r in robots),
        "reconnects": sum(r.reconnects for r in robots),
        "frames_resent": sum(r.resent for r in robots),
        "failover_gaps_s": [round(g, 3) for g in gaps],
        "failover_gap_p95_s": _p95(gaps),
        "failover_phases_s": phases,
        "failover_phase_median_s": _phase_medians(phases),
        "takeover_jumps_m": [round(j, 5) for j in takeover_jumps],
        "takeover_jump_max_m": max(takeover_jumps) if takeover_jumps else None,
        "ordinary_step_error_median_m": float(np.median(ordinary)) if ordinary else None,
        "ordinary_step_error_p95_m": _p95(ordinary),
    }


def _p95(values: list[float]) -> float | None:
    return float(np.percentile(values, 95)) if values else None


PHASES = ("noticed", "reconnected", "lease_taken", "answered")


def _phase_medians(phases: list[dict[str, float]]) -> dict[str, float]:
    """Median time of each phase boundary after the kill, and of each phase itself."""
    if not phases:
        return {}
    medians = {name: float(np.median([p[name] for p in phases])) for name in PHASES}
    steps = {f"{b} - {a}": float(np.median([p[b] - p[a] for p in phases]))
             for a, b in itertools.pairwise(PHASES)}
    return {**medians, **steps}


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
        fleet.start(warm=render_flights(1, options.frames)[0])
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


def table(result: dict[str, Any]) -> str:
    failover = result["failover"]
    rows = [
        ("acknowledged poses lost", failover["acknowledged_poses_lost"], "0"),
        ("duplicate poses", failover["duplicate_poses"], "0"),
        ("poses written without the lease", failover["poses_without_lease"], "0"),
        ("frames never answered", failover["frames_unanswered"], "0"),
        ("failover gap p95 [s]", _fmt(failover["failover_gap_p95_s"]), "<= 2"),
        *_phase_rows(failover.get("failover_phase_median_s", {})),
        ("pose jump at takeover, max [mm]", _fmt(failover["takeover_jump_max_m"], 1000),
         "<= 10"),
        ("ordinary step error median / p95 [mm]",
         f"{_fmt(failover['ordinary_step_error_median_m'], 1000)} / "
         f"{_fmt(failover['ordinary_step_error_p95_m'], 1000)}", "-"),
    ]
    if "overhead" in result:
        over = result["overhead"]
        rows.append(("per-frame overhead nginx + lease", f"{100 * over['overhead']:+.1f} % "
                     f"({over['fleet_ms']:.1f} vs {over['direct_ms']:.1f} ms)", "<= 10 %"))
    for level in result.get("throughput", []):
        rows.append((f"frames/s, {level['replicas']} replica(s), {level['robots']} robots",
                     f"{level['frames_per_s']:.1f} ({level['frames_per_s_per_core']:.1f} per "
                     f"core, {level['replica_cpu_ms_per_frame']:.0f} ms CPU/frame)", "-"))
    width = max(len(r[0]) for r in rows)
    lines = [f"{'measure':<{width}}  {'value':<44}  target", "-" * (width + 56)]
    lines += [f"{name:<{width}}  {value!s:<44}  {target}" for name, value, target in rows]
    return "\n".join(lines)


def _phase_rows(medians: dict[str, float]) -> list[tuple[str, str, str]]:
    """The gap's phases: median time after the kill at which each one ended."""
    labels = {"noticed": "stream broken seen by the client", "reconnected":
              "greeted again through nginx", "lease_taken": "lease taken by the new owner",
              "answered": "first frame answered"}
    return [(f"  median: {labels[name]} [s after kill]", _fmt(medians[name]), "-")
            for name in PHASES if name in medians]


def _fmt(value: float | None, scale: float = 1.0) -> str:
    return "n/a" if value is None else f"{value * scale:.2f}"


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
