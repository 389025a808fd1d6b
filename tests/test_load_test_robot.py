"""The load test's robot survives a connection the server cuts (a starved server closes streams
whose pings went unanswered): its frames are counted, the run goes on."""

from __future__ import annotations

import asyncio
import json
import sys
import time
from pathlib import Path

from websockets.asyncio.server import ServerConnection, serve

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import load_test
from load_report import LevelResult, runs_table


class TwoFrames:
    """Tiny PNG-like payloads; the stub server never decodes them."""

    raw = False

    def get(self, k: int) -> tuple[int, bytes, bytes, None]:
        return 1_000_000 * (k + 1), b"L" * 100, b"R" * 100, None


async def _cut_after_first_frame(connection: ServerConnection) -> None:
    await connection.send(json.dumps({"type": "hello", "queue_size": 8}))
    await connection.recv()  # the first frame's header
    await connection.recv()  # and its images
    connection.transport.abort()  # no close frame: what a ping timeout looks like


def test_a_robot_whose_connection_is_cut_reports_it_and_returns() -> None:
    async def scenario() -> load_test.RobotStats:
        async with serve(_cut_after_first_frame, "127.0.0.1", 0) as server:
            port = server.sockets[0].getsockname()[1]
            stats = load_test.RobotStats()
            start = asyncio.get_running_loop().time()
            await asyncio.wait_for(load_test.robot(
                f"http://127.0.0.1:{port}", "s1", TwoFrames(), rate=20.0, duration=1.0,
                drain=2.0, stats=stats, start_at=time.perf_counter(), hold_back=False), timeout=10)
            assert asyncio.get_running_loop().time() - start < 5
            return stats

    stats = asyncio.run(scenario())
    assert stats.disconnected is not None
    assert stats.sent >= 1 and stats.answered == 0


def test_the_runs_table_counts_the_robots_cut_off() -> None:
    result = LevelResult(
        robots=2, rate_hz=20.0, duration_s=1.0, sent=40, answered=10, dropped=0, rejected=0,
        unanswered=30, sustained_fps=10.0, offered_fps=40.0, latency_p50_ms=1.0,
        latency_p95_ms=2.0, latency_p99_ms=3.0, server_rss_mb_peak=None,
        server_pss_mb_peak=None, rss_mb_peak_by_role={}, server_cpu_ms_per_frame={},
        stage_median_ms={}, reject_reasons={}, disconnected=["ConnectionClosedError: x"],
    )
    header, _rule, row = runs_table([result]).splitlines()
    cells = dict(zip(header.split(" | "), row.split(" | "), strict=True))
    assert cells["cut off"] == "1"
