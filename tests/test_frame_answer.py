"""The client's ``Pose`` mirrors the server's one answer type, field by field."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
from swarmvo_client.models import Pose

from service.answer import FrameAnswer, OdometryOut, SmoothedPose, matrix_of


def _answer() -> FrameAnswer:
    rng = np.random.default_rng(4)
    flat = [float(v) for v in rng.normal(size=16)]
    odometry = {
        "header": {"stamp_ns": 7, "frame_id": "odom"}, "child_frame_id": "base_link",
        "pose": {"pose": {"position": {"x": 1.0, "y": 2.0, "z": 3.0},
                          "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                 "covariance": [0.0] * 36},
        "twist": {"twist": {"linear": {"x": 0.0, "y": 0.0, "z": 0.0},
                            "angular": {"x": 0.0, "y": 0.0, "z": 0.0}},
                  "covariance": [0.0] * 36},
        "status": "ok", "camera_pose": flat,
    }
    return FrameAnswer(
        session_id="s", index=3, timestamp_ns=2**62, pose=matrix_of(flat),
        frontend_pose=matrix_of(flat[::-1]), relative_pose=matrix_of(flat), status="degraded",
        matches=9, inliers=5, support=4, timings_s={"decode": 0.5}, message="m", resumed=True,
        imu_samples=11, odometry=OdometryOut.model_validate(odometry),
        smoothed=[SmoothedPose(timestamp_ns=5, pose=matrix_of(flat))],
    )


def test_client_pose_has_the_answer_fields_in_order() -> None:
    schema = FrameAnswer.model_json_schema()
    assert [f.name for f in fields(Pose)] == list(schema["properties"])


def test_client_reads_every_field_of_the_answer() -> None:
    answer = _answer()
    pose = Pose.from_json(answer.model_dump(mode="json"))
    for name, value in answer:
        read = getattr(pose, name)
        if name in ("pose", "frontend_pose", "relative_pose"):
            np.testing.assert_array_equal(read, np.array(value))
        elif name == "odometry":
            assert read == answer.model_dump(mode="json")["odometry"]
        elif name == "smoothed":
            assert [(t, p.tolist()) for t, p in read] == [(s.timestamp_ns, s.pose) for s in value]
        else:
            assert read == value, name
