"""Prometheus metrics, one registry per app so several apps (tests) never collide."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest

# 1 ms .. 10 s: odometry stages sit in the middle, queueing pushes towards the top.
_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5, 1, 2.5, 5, 10)


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.frames = Counter(
            "swarmvo_frames_processed",
            "Frames answered with a pose, by odometry status",
            ["status"],
            registry=self.registry,
        )
        self.stage_latency = Histogram(
            "swarmvo_stage_latency_seconds",
            "Time per processing stage (queue wait, decode, odometry stages, persist, total)",
            ["stage"],
            buckets=_BUCKETS,
            registry=self.registry,
        )
        self.sessions_active = Gauge(
            "swarmvo_sessions_active",
            "Sessions with a live odometry pipeline in memory",
            registry=self.registry,
        )
        self.errors = Counter(
            "swarmvo_errors",
            "Refused or failed requests, by kind",
            ["kind"],
            registry=self.registry,
        )
        self.dropped = Counter(
            "swarmvo_frames_dropped",
            "Frames not processed because a session queue was full, by policy",
            ["policy"],
            registry=self.registry,
        )

        self.worker_restarts = Counter(
            "swarmvo_worker_restarts",
            "Worker processes replaced after dying unexpectedly",
            registry=self.registry,
        )

    def render(self) -> bytes:
        return generate_latest(self.registry)
