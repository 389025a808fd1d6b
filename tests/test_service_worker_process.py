"""What a worker process sets up for itself before its first frame."""

from __future__ import annotations

from pathlib import Path

import cv2
from fastapi.testclient import TestClient
from test_service_units import PidPipeline, ProcessFactory, new_session, send, settings_for

from estimator.types import FrameReport, ImuBatch, StereoFrame
from service.app import create_app
from service.estimator_adapter import PreparedSession


class ThreadCountPipeline(PidPipeline):
    """Answers with the number of OpenCV threads of the process it runs in."""

    def process(self, frame: StereoFrame, imu: ImuBatch | None = None) -> FrameReport:
        report = super().process(frame, imu)
        report.message = f"opencv_threads={cv2.getNumThreads()}"
        return report


class ThreadCountFactory(ProcessFactory):
    def create(self, prepared: PreparedSession, initial_pose, first_index):  # type: ignore[override]
        return ThreadCountPipeline(initial_pose, first_index, 0.0)


def test_worker_processes_run_opencv_on_one_thread(tmp_path: Path) -> None:
    settings = settings_for(tmp_path, executor="process", workers=1)
    with TestClient(create_app(settings, ThreadCountFactory())) as c:
        session = new_session(c)
        answer = send(c, session, 10)
    assert answer.status_code == 200, answer.text
    assert answer.json()["message"] == "opencv_threads=1"
