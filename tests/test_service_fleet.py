"""The fleet on real processes: PostgreSQL, three replicas and nginx (docker/nginx.conf).

- the short form of the cluster harness (benchmarks/cluster.py): robots stream through nginx, the
  busiest replica is killed with SIGKILL and restarted; no acknowledged pose is lost, none is
  stored twice, none is written without the lease, every frame is answered;
- the database goes away for 5 s: frames get 503 with Retry-After, the stream continues after;
- a replica paused with SIGSTOP past its lease and resumed cannot write for the session that
  another replica took over (the fencing token is checked by the database);
- two replicas racing for one session: one pose per frame, the same answer to both clients.

Skipped with a reason when nginx or the PostgreSQL server binaries are absent; CI installs both.
"""

from __future__ import annotations

import asyncio
import json
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import httpx
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import cluster
from local_cluster import missing_tools

pytestmark = pytest.mark.slow
FRAMES = 20


@pytest.fixture(scope="module")
def fleet() -> Iterator[cluster.Fleet]:
    reason = missing_tools()
    if reason is not None:
        pytest.skip(f"the fleet needs nginx and PostgreSQL: {reason}")
    with tempfile.TemporaryDirectory(prefix="swarmvo-fleet-test-") as folder:
        running = cluster.Fleet(Path(folder), cluster.Options(lease_ttl_s=1.0))
        try:
            running.start()
            yield running
        finally:
            running.stop()


@pytest.fixture(scope="module")
def flight() -> cluster.LocalSequence:
    (folder,) = cluster.render_flights(1, FRAMES)
    return cluster.open_local_sequence(folder)


def _robot(fleet: cluster.Fleet, sequence: cluster.LocalSequence, name: str,
           url: str | None = None) -> cluster.RobotRun:
    robot = cluster.RobotRun(name, sequence)
    robot.session_id = cluster.new_session(url or fleet.replicas[0].url, fleet.key, sequence, name)
    return robot


def _assert_consistent(report: dict, robots: int) -> None:
    shown = json.dumps(report)[:3000]  # with its problems and rejections, to tell why
    assert report["acknowledged_poses_lost"] == 0, shown
    assert report["duplicate_poses"] == 0, shown
    assert report["poses_without_lease"] == 0, shown
    assert report["frames_unanswered"] == 0, shown
    assert report["frames_rejected"] == 0, report


def test_replica_killed_mid_stream_loses_nothing(
    fleet: cluster.Fleet, flight: cluster.LocalSequence
) -> None:
    assert fleet.balancer is not None
    robots = [_robot(fleet, flight, f"robot{i}", fleet.balancer.url) for i in range(2)]
    options = cluster.Options(robots=2, frames=FRAMES, kills=1, down_s=1.5, window=2)
    outcome = asyncio.run(cluster.failover(fleet, robots, options))
    report = cluster.check(fleet, robots, outcome)
    _assert_consistent(report, 2)
    (kill,) = outcome["kills"]
    assert kill["sessions"], "the killed replica held no session: nothing was tested"
    # Every robot of the killed replica was answered again after the kill (a new owner).
    assert len(report["failover_gaps_s"]) == len(kill["sessions"])
    # Where the gap went: the client saw the break, was greeted again, then answered.
    phases = report["failover_phases_s"]
    assert len(phases) == len(kill["sessions"]), report
    assert all(0 <= p["noticed"] <= p["reconnected"] <= p["answered"] for p in phases), phases
    assert report["reconnects"] >= len(kill["sessions"])
    # The new owner continued from the stored state: the step into its first frame is close
    # to the true one (a restart at rest would be off by the whole 5 cm step).
    assert report["takeover_jumps_m"] and report["takeover_jump_max_m"] < 0.02, report
    writers = fleet.sql("SELECT count(DISTINCT writer) FROM poses WHERE session_id = %s",
                        kill["sessions"][0])
    assert writers[0][0] >= 2


def _post_frame(url: str, key: str, session_id: str, sequence: cluster.LocalSequence,
                index: int, offset_ns: int = 0) -> httpx.Response:
    left, right = sequence.frame_bytes(index)
    return httpx.post(
        f"{url}/v1/sessions/{session_id}/frames",
        headers={"Authorization": f"Bearer {key}"},
        files={"left": ("l.png", left, "image/png"), "right": ("r.png", right, "image/png")},
        data={"timestamp_ns": str(sequence.frames[index].timestamp_ns + offset_ns)},
        timeout=60,
    )


def test_database_down_for_5_s_gives_503_and_the_stream_continues(
    fleet: cluster.Fleet, flight: cluster.LocalSequence
) -> None:
    assert fleet.balancer is not None
    url = fleet.balancer.url
    robot = _robot(fleet, flight, "outage", url)
    probe = _robot(fleet, flight, "probe", url)
    assert _post_frame(url, fleet.key, probe.session_id, flight, 0).status_code == 200

    async def scenario() -> list[httpx.Response]:
        streaming = asyncio.create_task(cluster.stream_robot(robot, url, fleet.key, window=2))
        while len(robot.answers) < 8:
            await asyncio.sleep(0.05)
        await asyncio.to_thread(fleet.postgres.stop)
        down_at = time.monotonic()
        answers: list[httpx.Response] = []
        while time.monotonic() - down_at < 5.0:
            answers.append(await asyncio.to_thread(
                _post_frame, url, fleet.key, probe.session_id, flight, 1))
            await asyncio.sleep(1.0)
        await asyncio.to_thread(fleet.postgres.start)
        await streaming
        return answers

    during = asyncio.run(scenario())
    assert during and all(r.status_code == 503 for r in during), [r.text for r in during]
    assert all(int(r.headers["Retry-After"]) >= 1 for r in during)
    assert all("database" in r.json()["detail"] for r in during)
    report = cluster.check(fleet, [robot], {"kills": []})
    _assert_consistent(report, 1)
    # The probe's frame is taken once the database is back.
    assert _post_frame(url, fleet.key, probe.session_id, flight, 1).status_code == 200


def test_replica_paused_past_its_lease_cannot_write(
    fleet: cluster.Fleet, flight: cluster.LocalSequence
) -> None:
    paused, taker = fleet.replicas[1], fleet.replicas[2]
    robot = _robot(fleet, flight, "paused", paused.url)

    async def scenario() -> None:
        stream = cluster.ReliableStream(paused.url, robot.session_id, fleet.key)
        await stream.start()
        for index in range(6):
            left, right = flight.frame_bytes(index)
            await stream.send_frame(flight.frames[index].timestamp_ns, left, right,
                                    cluster.frame_imu(flight, index))
        while len(robot.answers) < 2:  # answered by the replica about to be paused
            event = await asyncio.wait_for(stream.recv(), 60)
            assert isinstance(event, cluster.Pose), event
            robot.answers[event.timestamp_ns] = (event, time.perf_counter())
        paused.pause()  # frames 2..5 are queued, or computed in its worker process
        try:
            await stream.close()
            await asyncio.sleep(2.5 * 1.0)  # past the lease
            # The robot goes on through the other replica: it resends what was not answered.
            rest = cluster.RobotRun("rest", replace(flight, frames=flight.frames[2:]),
                                    robot.session_id)
            await cluster.stream_robot(rest, taker.url, fleet.key, window=2)
            robot.answers.update(rest.answers)
            robot.rejected += rest.rejected
        finally:
            paused.resume()

    asyncio.run(scenario())
    # Resumed, the replica goes on with the frames it had: one computed in its worker meets the
    # fence (a refused write, logged); one still queued finds the lease held by the taker (a
    # refusal, counted). Which of the two happens depends on where the pause caught them.
    refused = _refusals_after_resume(paused, timeout_s=30.0)
    assert refused, paused.log.read_text()[-2000:]
    report = cluster.check(fleet, [robot], {"kills": []})
    _assert_consistent(report, 1)
    rows = fleet.sql("SELECT writer, count(*), min(frame_index) FROM poses WHERE session_id = %s "
                     "GROUP BY writer ORDER BY 3", robot.session_id)
    assert [w for w, _n, _i in rows] == [paused.replica_id, taker.replica_id], rows
    assert rows[0][1] <= 6 and sum(n for _w, n, _i in rows) == FRAMES


def _refusals_after_resume(replica: cluster.Replica, timeout_s: float) -> list[str]:
    """How the resumed replica was stopped from writing: fenced writes (its log) and frames
    refused because another replica held the lease (its metrics); waits until one shows."""
    deadline = time.monotonic() + timeout_s
    while True:
        found = []
        if "no longer holds the lease" in replica.log.read_text():
            found.append("fenced write")
        metrics = httpx.get(f"{replica.url}/metrics", timeout=10).text
        held = [line for line in metrics.splitlines()
                if line.startswith('swarmvo_errors_total{kind="lease_held"}')]
        if held and float(held[0].split()[-1]) > 0:
            found.append("lease held")
        if found or time.monotonic() > deadline:
            return found
        time.sleep(0.25)


def test_replica_paused_past_its_lease_through_nginx_hands_the_session_over(
    fleet: cluster.Fleet, flight: cluster.LocalSequence
) -> None:
    """Through the balancer: the stream stalls on the paused replica (it still accepts
    connections); nginx gives up on it after its read timeout and hashes the reconnecting
    robot to the next replica, which takes the lease over. Resumed, the paused replica
    writes nothing more for the session."""
    assert fleet.balancer is not None
    url = fleet.balancer.url
    robot = _robot(fleet, flight, "stalled", url)

    async def scenario() -> cluster.Replica:
        streaming = asyncio.create_task(
            cluster.stream_robot(robot, url, fleet.key, window=2, answer_timeout_s=3.0))
        while len(robot.answers) < 4:
            await asyncio.sleep(0.02)
        (holder,) = await asyncio.to_thread(
            fleet.sql, "SELECT lease_holder FROM sessions WHERE id = %s", robot.session_id)
        paused = next(r for r in fleet.replicas if r.replica_id == holder[0])
        paused.pause()
        try:
            await asyncio.wait_for(streaming, 120)
        finally:
            paused.resume()
        await asyncio.sleep(2.0)  # whatever the resumed replica had in hand is refused
        return paused

    paused = asyncio.run(scenario())
    report = cluster.check(fleet, [robot], {"kills": []})
    _assert_consistent(report, 1)
    rows = fleet.sql("SELECT writer, count(*), min(frame_index), max(frame_index) FROM poses "
                     "WHERE session_id = %s GROUP BY writer ORDER BY 3", robot.session_id)
    assert rows[0][0] == paused.replica_id and len(rows) >= 2, rows
    # Not one pose of the paused replica after the takeover.
    assert rows[0][3] < rows[1][2] and sum(r[1] for r in rows) == FRAMES, rows
    assert report["reconnects"] >= 1


def test_two_replicas_racing_for_one_session_store_each_frame_once(
    fleet: cluster.Fleet, flight: cluster.LocalSequence
) -> None:
    first, second = fleet.replicas[0], fleet.replicas[1]
    robot = _robot(fleet, flight, "raced", first.url)
    twin = cluster.RobotRun("twin", flight, robot.session_id)

    async def scenario() -> None:
        await asyncio.gather(
            cluster.stream_robot(robot, first.url, fleet.key, window=2),
            cluster.stream_robot(twin, second.url, fleet.key, window=2),
        )

    asyncio.run(scenario())
    for run in (robot, twin):
        report = cluster.check(fleet, [run], {"kills": []})
        _assert_consistent(report, 1)
    # Both clients were given the same pose for every frame, whoever computed it.
    for stamp, (pose, _when) in robot.answers.items():
        assert twin.answers[stamp][0].pose.tolist() == pose.pose.tolist()
        assert twin.answers[stamp][0].index == pose.index


def test_lease_tokens_and_fenced_writes_in_the_database(fleet: cluster.Fleet) -> None:
    """The lease rules themselves, on the fleet's PostgreSQL: one holder at a time, the token
    rises with each change of holder, and a write under an old token changes nothing."""
    from service.answer import FrameAnswer, matrix_of
    from service.lease import LeaseBook, LeaseHeld
    from service.storage import LeaseLost, Store

    def bare(index: int, stamp: int, value: float) -> FrameAnswer:
        matrix = matrix_of([value] * 16)
        return FrameAnswer(
            session_id=session.id, index=index, timestamp_ns=stamp, pose=matrix,
            frontend_pose=matrix, relative_pose=matrix, status="ok", matches=0, inliers=0,
            support=0, timings_s={}, message="", resumed=False,
        )

    store = Store.open(fleet.url)
    try:
        session = store.create_session("owner", "lease", {}, {}, None, (64, 48))
        first, second = LeaseBook(store, "first", 0.3), LeaseBook(store, "second", 0.3)
        fence = first.acquire(session.id)
        assert fence is not None and first.acquire(session.id) == fence  # renewed, same token
        with pytest.raises(LeaseHeld) as held:
            second.acquire(session.id)
        assert held.value.holder == "first" and 0 < held.value.retry_after_s <= 0.3
        store.add_pose(bare(0, 10, 1.0), fence, {"timestamp_ns": 10})
        time.sleep(0.4)  # expired, nobody took it: the holder may still write
        store.add_pose(bare(1, 20, 2.0), fence)
        time.sleep(0.4)
        taken = second.acquire(session.id)
        assert taken is not None and taken.token == fence.token + 1
        with pytest.raises(LeaseLost):
            store.add_pose(bare(2, 30, 3.0), fence)
        assert [p.timestamp_ns for p in store.poses(session.id)] == [10, 20]
        assert store.get_session(session.id).frame_count == 2  # type: ignore[union-attr]
        second.release(session.id, taken)
        again = first.acquire(session.id)
        assert again is not None and again.token == taken.token + 1
        assert store.resume_point(session.id)[1] is None  # the state went with pose 10 only
    finally:
        store.close()
