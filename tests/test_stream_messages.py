"""The stream validates a client message straight from its JSON text; a message must be taken
or refused exactly as when it is parsed first and then validated (the refusal's wording comes
from that second way)."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from service.messages import CLIENT_MESSAGE

SAMPLE = {"timestamp_ns": 5, "gyro": [0.1, 0.2, 0.3], "accel": [0, 0, 9.81]}
HEADER = {"type": "frame", "timestamp_ns": 10, "left_bytes": 4, "right_bytes": 4}
TEXTS = [
    json.dumps(HEADER),
    json.dumps({**HEADER, "imu": [SAMPLE, {**SAMPLE, "timestamp_ns": 6}]}),
    json.dumps({**HEADER, "unknown_field": 1}),
    json.dumps({**HEADER, "encoding": "raw8", "width": 2, "height": 2}),
    json.dumps({**HEADER, "encoding": "raw8"}),
    json.dumps({**HEADER, "timestamp_ns": "10"}),
    json.dumps({**HEADER, "timestamp_ns": 10.0}),
    json.dumps({**HEADER, "timestamp_ns": True}),
    json.dumps({**HEADER, "timestamp_ns": -1}),
    json.dumps({**HEADER, "timestamp_ns": 2**63}),
    json.dumps({**HEADER, "left_bytes": 0}),
    json.dumps({**HEADER, "encoding": "bmp"}),
    json.dumps({"type": "imu", "samples": [SAMPLE]}),
    json.dumps({"type": "imu", "samples": [{**SAMPLE, "gyro": [0.1, 0.2]}]}),
    json.dumps({"type": "imu", "samples": [{**SAMPLE, "gyro": [0.1, "0.2", 0.3]}]}),
    json.dumps({"type": "imu", "samples": [{**SAMPLE, "gyro": [0.1, True, 0.3]}]}),
    json.dumps({"type": "imu", "samples": [{**SAMPLE, "extra": 1}]}),
    '{"type": "imu", "samples": [{"timestamp_ns": 5, "gyro": [NaN, 0, 0], "accel": [0, 0, 1]}]}',
    '{"type": "imu", "samples": [{"timestamp_ns": 5, "gyro": [Infinity, 0, 0], '
    '"accel": [0, 0, 1]}]}',
    json.dumps({"type": "ping"}),
    json.dumps({"type": "close"}),
    json.dumps({"type": "close", "type2": "x"}),
    '{"type": "frame", "type": "ping"}',
]


def _parsed_then_validated(text: str) -> object:
    return CLIENT_MESSAGE.validate_python(json.loads(text))


@pytest.mark.parametrize("text", TEXTS)
def test_a_message_validated_from_its_text_is_taken_or_refused_as_when_parsed_first(
    text: str,
) -> None:
    try:
        expected = _parsed_then_validated(text)
    except ValidationError:
        with pytest.raises(ValidationError):
            CLIENT_MESSAGE.validate_json(text)
        return
    assert CLIENT_MESSAGE.validate_json(text) == expected
