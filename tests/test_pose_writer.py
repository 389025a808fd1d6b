"""Group commit of poses: batched across sessions, each caller waits for its own commit."""

from __future__ import annotations

import asyncio
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from service.answer import FrameAnswer, matrix_of
from service.pose_writer import PoseWriter
from service.storage import PendingPose, Store


def _pose(session_id: str, index: int) -> FrameAnswer:
    matrix = matrix_of([float(index)] * 16)
    return FrameAnswer(
        session_id=session_id, index=index, timestamp_ns=1000 + index, pose=matrix,
        frontend_pose=matrix, relative_pose=matrix, status="ok", matches=0, inliers=0,
        support=0, timings_s={}, message="", resumed=False,
    )


def _store(tmp_path: Path) -> tuple[Store, list[str]]:
    store = Store.open(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    sessions = [store.create_session("o", f"s{k}", {}, {}, None, (8, 8)).id for k in range(3)]
    return store, sessions


def test_waiting_poses_share_a_transaction_and_all_are_stored(tmp_path: Path) -> None:
    store, sessions = _store(tmp_path)
    batches: list[int] = []
    add_poses = store.add_poses

    def counting(poses: list[PendingPose]) -> None:
        batches.append(len(poses))
        add_poses(poses)

    store.add_poses = counting  # type: ignore[method-assign]

    async def main() -> None:
        writer = PoseWriter(store, ThreadPoolExecutor(2))
        for index in range(4):
            await asyncio.gather(*(writer.add(PendingPose(_pose(sid, index))) for sid in sessions))

    asyncio.run(main())
    assert max(batches) > 1  # the poses of the sessions waiting together went in one commit
    for sid in sessions:
        record = store.get_session(sid, "o")
        assert record is not None and record.frame_count == 4
        last = store.last_pose(sid)
        assert last is not None and last.index == 3 and last.timestamp_ns == 1003


def test_a_bad_pose_fails_only_its_own_frame(tmp_path: Path) -> None:
    store, sessions = _store(tmp_path)

    async def main() -> list[object]:
        writer = PoseWriter(store, ThreadPoolExecutor(2))
        await writer.add(PendingPose(_pose(sessions[0], 0)))
        # Frame index 0 of session 0 exists already: that pose breaks the batch's uniqueness.
        return await asyncio.gather(
            writer.add(PendingPose(_pose(sessions[0], 0))),
            writer.add(PendingPose(_pose(sessions[1], 0))),
            writer.add(PendingPose(_pose(sessions[2], 0))),
            return_exceptions=True,
        )

    outcomes = asyncio.run(main())
    assert isinstance(outcomes[0], Exception)
    assert outcomes[1:] == [None, None]
    for sid in sessions[1:]:
        stored = store.get_session(sid, "o")
        assert stored is not None and stored.frame_count == 1


def test_poses_waiting_for_a_batch_are_stored_at_shutdown_even_if_nobody_waits(
    tmp_path: Path,
) -> None:
    """A commit is running, a batch of three waits behind it, and the frames that handed those
    poses in are cancelled (their sessions closed): ``drained`` still stores every pose before
    the I/O pool stops."""
    store, sessions = _store(tmp_path)
    add_poses = store.add_poses
    batches: list[int] = []

    def slow(poses: list[PendingPose]) -> None:
        time.sleep(0.2)
        batches.append(len(poses))
        add_poses(poses)

    store.add_poses = slow  # type: ignore[method-assign]

    async def main() -> None:
        pool = ThreadPoolExecutor(2)
        writer = PoseWriter(store, pool)
        first = asyncio.ensure_future(writer.add(PendingPose(_pose(sessions[0], 0))))
        await asyncio.sleep(0.05)  # its commit is running now
        waiting = [asyncio.ensure_future(writer.add(PendingPose(_pose(sid, 1))))
                   for sid in sessions]
        await asyncio.sleep(0)
        for frame in (first, *waiting):
            frame.cancel()
        await writer.drained()
        pool.shutdown(wait=True, cancel_futures=False)

    asyncio.run(main())
    assert batches == [1, 3]
    for sid in sessions:
        last = store.last_pose(sid)
        assert last is not None and (last.index, last.timestamp_ns) == (1, 1001)
