"""What a worker process sets up for itself before its first frame."""

from __future__ import annotations

from pathlib import Path

import cv2
from fastapi.testclient import TestClient
from test_service_units import DescribingFactory, new_session, send, settings_for

from estimator.types import StereoFrame
from service.app import create_app


def _opencv_threads(frame: StereoFrame, message: str) -> str:
    """The number of OpenCV threads of the process the frame ran in."""
    return f"opencv_threads={cv2.getNumThreads()}"


def test_worker_processes_run_opencv_on_one_thread(tmp_path: Path) -> None:
    settings = settings_for(tmp_path, executor="process", workers=1)
    with TestClient(create_app(settings, DescribingFactory(_opencv_threads))) as c:
        session = new_session(c)
        answer = send(c, session, 10)
    assert answer.status_code == 200, answer.text
    assert answer.json()["message"] == "opencv_threads=1"
