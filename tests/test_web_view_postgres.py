"""The live view's pose columns on a live PostgreSQL (skips with test_service_postgres)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from test_service_postgres import Cluster, cluster, database  # noqa: F401 (fixtures)

from service.answer import FrameAnswer, matrix_of
from service.storage import Store
from service.web.feed import WorldFrame, pose_columns, read_poses


def _fill(store: Store) -> str:
    """Poses whose numbers a lossy path would change (-0.0, 0.1 + 0.2, 1/3, tiny values)."""
    record = store.create_session("owner", "view", {}, {}, None, (64, 48))
    rng = np.random.default_rng(5)
    awkward = [-0.0, 0.1 + 0.2, 1 / 3, 1e-300, -np.pi, 2.5e-7]
    for index in range(6):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        pose[:3, 3] = [awkward[index], awkward[-index - 1], rng.normal() * 1e3]
        frontend = pose.copy()
        frontend[:3, 3] += 0.5
        timings = {"queue_wait": 1e-3, "odometry": 0.1 + 0.2} if index % 2 else {"decode": 1 / 3}
        store.add_pose(FrameAnswer(
            session_id=record.id, index=index, timestamp_ns=10 * index, pose=pose.tolist(),
            frontend_pose=frontend.tolist(), relative_pose=matrix_of(np.eye(4).ravel().tolist()),
            status=("ok", "degraded", "lost")[index % 3], matches=0, inliers=index, support=0,
            timings_s=timings, message=f"frame {index} ✓", resumed=False,
        ))
    return record.id


def test_view_columns_are_the_same_on_postgresql(
    cluster: Cluster, database: str, tmp_path: Path  # noqa: F811 (the imported fixtures)
) -> None:
    """The database picks the numbers out of the JSON itself: both backends must agree."""
    stores = [Store.open(cluster.url(database)), Store.open(f"sqlite:///{tmp_path / 'v.db'}")]
    try:
        rows, messages = [], []
        for store in stores:
            session_id = _fill(store)
            stored = store.poses(session_id)
            rows.append([tuple(row) for row in read_poses(store, session_id, 1)])
            messages.append(pose_columns(read_poses(store, session_id), WorldFrame.of(stored[0])))
            poses = np.array([p.pose for p in stored]).reshape(-1, 4, 4)
            assert [row[5] for row in rows[-1]] == poses[1:, 0, 3].tolist()  # exact floats
            assert np.reshape(messages[-1].position, (-1, 3)).tolist() == np.round(
                poses[:, :3, 3], 4).tolist()
            assert messages[-1].status == "odlodl" and messages[-1].message == "frame 5 ✓"
            assert messages[-1].latency_ms[:2] == [333.33, 301.0]
        assert rows[0] == rows[1] and messages[0] == messages[1]
    finally:
        for store in stores:
            store.close()
