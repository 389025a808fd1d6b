"""IMU samples from a client (REST body, form field or WebSocket message) as checked arrays."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import ValidationError

from service.errors import Refusal
from service.schemas import ImuBatchIn
from service.sessions import ImuSamples
from service.settings import ServiceSettings


def parse_imu(text: str | bytes | dict[str, Any], settings: ServiceSettings) -> ImuSamples:
    """Validated IMU samples (finite numbers, bounded count) as arrays."""
    try:
        if isinstance(text, dict):
            batch = ImuBatchIn.model_validate(text)
        else:
            batch = ImuBatchIn.model_validate_json(text)
    except ValidationError as error:
        raise Refusal(422, f"invalid IMU samples: {brief(error)}", "validation") from error
    if len(batch.samples) > settings.max_imu_batch:
        raise Refusal(
            413,
            f"{len(batch.samples)} IMU samples in one batch; the limit is "
            f"{settings.max_imu_batch}",
            "too_large",
        )
    return ImuSamples(
        np.array([s.timestamp_ns for s in batch.samples], dtype=np.int64),
        np.array([s.gyro for s in batch.samples], dtype=float).reshape(-1, 3),
        np.array([s.accel for s in batch.samples], dtype=float).reshape(-1, 3),
    )


def brief(error: ValidationError) -> str:
    """The first few problems of a validation error on one line."""
    parts = []
    for item in error.errors()[:5]:
        location = ".".join(str(p) for p in item.get("loc", ()))
        parts.append(f"{location}: {item.get('msg')}" if location else str(item.get("msg")))
    more = len(error.errors()) - 5
    return "; ".join(parts) + (f" (and {more} more)" if more > 0 else "")
