"""A session's IMU samples between frames: buffered as they arrive, handed to the frame they
precede, and only given up once that frame was actually used by the estimator."""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from estimator.types import ImuBatch


@dataclass
class ImuSamples:
    """IMU samples in arrival order (sorted and de-duplicated when consumed)."""

    timestamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamps_ns)


@dataclass
class ImuTake:
    """IMU samples chosen for a frame; the buffer only gives them up once the frame is used."""

    batch: ImuBatch | None
    remainder: list[ImuSamples]
    parts: int


class ImuBuffer:
    """Samples in arrival order, shared by the event loop (adding) and the consumer (taking)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._lock = threading.Lock()
        self._parts: list[ImuSamples] = []
        self._count = 0

    @property
    def count(self) -> int:
        return self._count

    def add(self, samples: ImuSamples) -> int | None:
        """Buffer the samples; the buffered count, or None (nothing added) past the limit."""
        with self._lock:
            if self._count + len(samples) > self.limit:
                return None
            self._parts.append(samples)
            self._count += len(samples)
            return self._count

    def peek(self, timestamp_ns: int, after_ns: int | None) -> ImuTake:
        """Samples with ``after_ns`` < t <= ``timestamp_ns``; later ones stay buffered."""
        with self._lock:
            parts = list(self._parts)
        if not parts:
            return ImuTake(None, [], 0)
        times = np.concatenate([p.timestamps_ns for p in parts])
        gyro = np.concatenate([p.gyro for p in parts])
        accel = np.concatenate([p.accel for p in parts])
        order = np.argsort(times, kind="stable")
        times, gyro, accel = times[order], gyro[order], accel[order]
        keep = np.ones(len(times), dtype=bool)
        keep[1:] = times[1:] != times[:-1]  # a repeated sample counts once
        times, gyro, accel = times[keep], gyro[keep], accel[keep]
        later = times > timestamp_ns
        remainder = [ImuSamples(times[later], gyro[later], accel[later])] if later.any() else []
        now = ~later
        if after_ns is not None:
            now &= times > after_ns
        batch = ImuBatch(times[now], gyro[now], accel[now]) if now.any() else None
        return ImuTake(batch, remainder, len(parts))

    def consume(self, take: ImuTake) -> None:
        """Remove what a frame used; samples that arrived meanwhile stay behind it."""
        with self._lock:
            self._parts = [*take.remainder, *self._parts[take.parts :]]
            self._count = sum(len(p) for p in self._parts)
