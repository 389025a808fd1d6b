"""The fleet of docker/compose.yaml, running: robots through its balancer, a replica killed.

Started by docker/smoke_test.sh once ``docker compose up --scale swarmvo=3`` is healthy:

1. reads how long each replica's worker processes took to warm up (their log line: seconds
   when the image's JIT cache is used, minutes when it is not);
2. streams rendered flights through the balancer (127.0.0.1:8000) with the reliable client and
   measures each robot's first-frame latency;
3. mid-stream, kills (``docker kill``, SIGKILL) the replica container holding the most leases,
   starts it again a few seconds later and times it until it answers /healthz again;
4. checks every answer against PostgreSQL (benchmarks/cluster_check.py: no acknowledged pose
   lost, none twice, none without the lease, every frame answered) and writes a JSON report.

Exit status 1 when a check fails.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import psycopg

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cluster import RobotRun, new_session, open_local_sequence, render_flights, stream_robot
from cluster_check import check

WARMED = re.compile(r"worker process \d+ warmed up in ([0-9.]+) s")


def docker(*args: str) -> str:
    return subprocess.run(["docker", *args], check=True, capture_output=True, text=True,
                          timeout=120).stdout.strip()


def containers(project: str, service: str) -> list[str]:
    """Ids (12 hex digits, also each container's host name) of a compose service's containers."""
    listed = docker("ps", "-a", "--no-trunc", "--format", "{{.ID}}",
                    "--filter", f"label=com.docker.compose.project={project}",
                    "--filter", f"label=com.docker.compose.service={service}")
    return [line[:12] for line in listed.splitlines() if line]


@dataclass
class ComposeFleet:
    """What cluster_check.check needs of a fleet: a URL to ask, the key and SQL."""

    url: str
    key: str
    database_url: str

    @property
    def replicas(self) -> list[ComposeFleet]:
        return [self]

    def sql(self, query: str, *params: object) -> list[tuple]:
        with psycopg.connect(self.database_url, connect_timeout=10) as connection:
            return connection.execute(query, params).fetchall()


def warm_up_seconds(container: str) -> list[float]:
    logs = subprocess.run(["docker", "logs", container], capture_output=True, text=True,
                          timeout=60)
    return [float(m) for m in WARMED.findall(logs.stdout + logs.stderr)]


def wait_healthy(url: str, timeout_s: float) -> float:
    start = time.monotonic()
    while time.monotonic() - start < timeout_s:
        try:
            if httpx.get(f"{url}/healthz", timeout=2).status_code == 200:
                return time.monotonic() - start
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise RuntimeError(f"{url} not healthy within {timeout_s:.0f} s")


def container_url(container: str) -> str:
    address = docker("inspect", "-f",
                     "{{range .NetworkSettings.Networks}}{{.IPAddress}}{{end}}", container)
    return f"http://{address}:8000"


async def failover(fleet: ComposeFleet, robots: list[RobotRun], project: str,
                   down_s: float) -> dict[str, Any]:
    """Stream; at 40 % of the answers kill the busiest replica, start it again after down_s."""
    tasks = [asyncio.create_task(stream_robot(r, fleet.url, fleet.key, window=2))
             for r in robots]
    total = sum(len(r.sequence.frames) for r in robots)
    while sum(len(r.answers) for r in robots) < 0.4 * total:
        if all(t.done() for t in tasks):
            break
        await asyncio.sleep(0.05)
    holders = await asyncio.to_thread(
        fleet.sql, "SELECT lease_holder, id FROM sessions WHERE lease_holder IS NOT NULL")
    by_container: dict[str, list[str]] = {}
    for holder, session_id in holders:
        by_container.setdefault(holder.split("-")[0], []).append(session_id)
    victim = max(containers(project, "swarmvo"), key=lambda c: len(by_container.get(c, [])))
    killed_at = time.perf_counter()
    await asyncio.to_thread(docker, "kill", victim)
    print(f"killed replica container {victim} holding {len(by_container.get(victim, []))} "
          "session(s)", flush=True)
    await asyncio.sleep(down_s)
    await asyncio.to_thread(docker, "start", victim)
    restart_s = await asyncio.to_thread(wait_healthy, container_url(victim), 600.0)
    print(f"restarted it: answering /healthz after {restart_s:.1f} s", flush=True)
    await asyncio.gather(*tasks)
    kill = {"replica": victim, "at": killed_at, "sessions": by_container.get(victim, []),
            "lease_taken_at": {}}
    return {"kills": [kill], "restart_to_healthy_s": round(restart_s, 2)}


def first_frame_latency(robot: RobotRun, started: float) -> float:
    return min(when for _pose, when in robot.answers.values()) - started


def run(args: argparse.Namespace) -> dict[str, Any]:
    database = docker("inspect", "-f", "{{range .NetworkSettings.Networks}}{{.IPAddress}}{{end}}",
                      containers(args.project, "postgres")[0])
    fleet = ComposeFleet(args.url, args.key,
                         f"postgresql://swarmvo:{args.postgres_password}@{database}:5432/swarmvo")
    replicas = containers(args.project, "swarmvo")
    warm = {c: warm_up_seconds(c) for c in replicas}
    sequences = [open_local_sequence(f) for f in render_flights(args.robots, args.frames)]
    robots = []
    for index, sequence in enumerate(sequences):
        robot = RobotRun(f"robot{index}", sequence)
        robot.session_id = new_session(args.url, args.key, sequence, robot.name)
        robots.append(robot)
    started = time.perf_counter()
    outcome = asyncio.run(failover(fleet, robots, args.project, args.down_s))
    report = check(fleet, robots, outcome)  # type: ignore[arg-type]
    return {
        "replicas": len(replicas),
        "worker_warm_up_s": warm,
        "first_frame_latency_s": [round(first_frame_latency(r, started), 3) for r in robots],
        "restart_to_healthy_s": outcome["restart_to_healthy_s"],
        "restarted_worker_warm_up_s": warm_up_seconds(outcome["kills"][0]["replica"]),
        "killed_sessions": len(outcome["kills"][0]["sessions"]),
        **{k: report[k] for k in (
            "acknowledged_poses_lost", "duplicate_poses", "poses_without_lease",
            "frames_unanswered", "frames_rejected", "reconnects", "frames_resent",
            "failover_gaps_s", "takeover_jump_max_m", "ate_median_m", "problems")},
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--project", required=True, help="the compose project name")
    parser.add_argument("--key", required=True, help="an API key of the fleet")
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="the balancer")
    parser.add_argument("--postgres-password", default="swarmvo")
    parser.add_argument("--robots", type=int, default=2)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--down-s", type=float, default=3.0)
    parser.add_argument("--out", type=Path, required=True, help="JSON report")
    args = parser.parse_args(argv)
    result = run(args)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    passed = (result["acknowledged_poses_lost"] == result["duplicate_poses"]
              == result["poses_without_lease"] == result["frames_unanswered"]
              == result["frames_rejected"] == 0 and result["killed_sessions"] > 0
              and result["failover_gaps_s"])
    print("PASS" if passed else "FAIL", flush=True)
    return 0 if passed else 1


if __name__ == "__main__":
    raise SystemExit(main())
