"""IMU samples from a client (REST body, form field or WebSocket message) as checked arrays."""

from __future__ import annotations

import numpy as np
from pydantic import ValidationError

from service.errors import Refusal
from service.schemas import ImuBatchIn, ImuSample
from service.sessions.imu_buffer import ImuSamples
from service.settings import ServiceSettings


def parse_imu(text: str | bytes, settings: ServiceSettings) -> ImuSamples:
    """Validated IMU samples (finite numbers, bounded count) as arrays, from JSON text."""
    try:
        batch = ImuBatchIn.model_validate_json(text)
    except ValidationError as error:
        raise Refusal(422, f"invalid IMU samples: {brief(error)}", "validation") from error
    return imu_arrays(batch.samples, settings)


def imu_arrays(samples: list[ImuSample], settings: ServiceSettings) -> ImuSamples:
    """Checked samples as arrays; 413 beyond the batch limit."""
    if len(samples) > settings.max_imu_batch:
        raise Refusal(
            413,
            f"{len(samples)} IMU samples in one batch; the limit is {settings.max_imu_batch}",
            "too_large",
        )
    return ImuSamples(
        np.array([s.timestamp_ns for s in samples], dtype=np.int64),
        np.array([s.gyro for s in samples], dtype=float).reshape(-1, 3),
        np.array([s.accel for s in samples], dtype=float).reshape(-1, 3),
    )


def brief(error: ValidationError, skip: int = 0) -> str:
    """The first few problems of a validation error on one line (``skip``: leading location
    parts to leave out, such as the tag of a union member)."""
    parts = []
    for item in error.errors()[:5]:
        location = ".".join(str(p) for p in item.get("loc", ())[skip:])
        parts.append(f"{location}: {item.get('msg')}" if location else str(item.get("msg")))
    more = len(error.errors()) - 5
    return "; ".join(parts) + (f" (and {more} more)" if more > 0 else "")
