"""HTTP clients (sync and async) over httpx; every error status becomes an exception."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

import httpx
import numpy as np

from swarmvo_client.errors import error_for
from swarmvo_client.models import ImuData, Pose, Session

DEFAULT_TIMEOUT = httpx.Timeout(60.0, connect=10.0)
TrajectoryFormat = Literal["tum", "kitti", "json"]


def _bytes(value: bytes | str | Path) -> bytes:
    return value if isinstance(value, bytes) else Path(value).read_bytes()


def _headers(api_key: str | None) -> dict[str, str]:
    return {"Authorization": f"Bearer {api_key}"} if api_key else {}


def _check(response: httpx.Response) -> httpx.Response:
    if response.status_code >= 400:
        try:
            detail = response.json().get("detail", response.text)
        except (ValueError, AttributeError):
            detail = response.text
        raise error_for(response.status_code, str(detail))
    return response


def _frame_form(
    timestamp_ns: int, left: bytes, right: bytes, imu: ImuData | None
) -> tuple[dict[str, str], dict[str, tuple[str, bytes]]]:
    data = {"timestamp_ns": str(int(timestamp_ns))}
    if imu is not None and len(imu):
        data["imu"] = json.dumps({"samples": imu.to_samples()})
    files = {"left": ("left.png", left), "right": ("right.png", right)}
    return data, files


def _euroc_form(
    cam0: bytes | str | Path,
    cam1: bytes | str | Path,
    imu0: bytes | str | Path | None,
    config: dict[str, Any] | None,
    name: str,
) -> tuple[dict[str, str], dict[str, tuple[str, bytes]]]:
    files = {"cam0": ("cam0.yaml", _bytes(cam0)), "cam1": ("cam1.yaml", _bytes(cam1))}
    if imu0 is not None:
        files["imu0"] = ("imu0.yaml", _bytes(imu0))
    return {"name": name, "config": json.dumps(config or {})}, files


def _kitti_form(
    calib: bytes | str | Path, width: int, height: int, config: dict[str, Any] | None, name: str
) -> tuple[dict[str, str], dict[str, tuple[str, bytes]]]:
    data = {"width": str(width), "height": str(height), "name": name,
            "config": json.dumps(config or {})}
    return data, {"calib": ("calib.txt", _bytes(calib))}


def _smoothed(response: httpx.Response) -> list[tuple[int, np.ndarray]]:
    return [
        (int(item["timestamp_ns"]), np.array(item["pose"], dtype=float))
        for item in response.json()["poses"]
    ]


def _trajectory(response: httpx.Response, format: TrajectoryFormat) -> list[Pose] | str:
    if format == "json":
        return [Pose.from_json(p) for p in response.json()["poses"]]
    return response.text


class Client:
    """Synchronous client: ``Client("http://127.0.0.1:8000", api_key="...")``."""

    def __init__(
        self,
        url: str,
        api_key: str | None = None,
        timeout: httpx.Timeout | float = DEFAULT_TIMEOUT,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.url = url.rstrip("/")
        self.api_key = api_key
        self._http = httpx.Client(
            base_url=self.url, headers=_headers(api_key), timeout=timeout, transport=transport
        )

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        return _check(self._http.request(method, path, **kwargs))

    def health(self) -> dict[str, Any]:
        return self._request("GET", "/healthz").json()

    def metrics(self) -> str:
        return self._request("GET", "/metrics").text

    def create_session(
        self,
        calibration: dict[str, Any],
        config: dict[str, Any] | None = None,
        imu_noise: dict[str, float] | None = None,
        name: str = "",
    ) -> Session:
        body = {"name": name, "calibration": calibration, "config": config or {},
                "imu_noise": imu_noise}
        return Session.from_json(self._request("POST", "/v1/sessions", json=body).json())

    def create_session_euroc(
        self,
        cam0_yaml: bytes | str | Path,
        cam1_yaml: bytes | str | Path,
        imu0_yaml: bytes | str | Path | None = None,
        config: dict[str, Any] | None = None,
        name: str = "",
    ) -> Session:
        data, files = _euroc_form(cam0_yaml, cam1_yaml, imu0_yaml, config, name)
        response = self._request("POST", "/v1/sessions/euroc", data=data, files=files)
        return Session.from_json(response.json())

    def create_session_kitti(
        self,
        calib_txt: bytes | str | Path,
        width: int,
        height: int,
        config: dict[str, Any] | None = None,
        name: str = "",
    ) -> Session:
        data, files = _kitti_form(calib_txt, width, height, config, name)
        response = self._request("POST", "/v1/sessions/kitti", data=data, files=files)
        return Session.from_json(response.json())

    def get_session(self, session_id: str) -> Session:
        return Session.from_json(self._request("GET", f"/v1/sessions/{session_id}").json())

    def list_sessions(self) -> list[Session]:
        sessions = self._request("GET", "/v1/sessions").json()["sessions"]
        return [Session.from_json(s) for s in sessions]

    def delete_session(self, session_id: str) -> None:
        self._request("DELETE", f"/v1/sessions/{session_id}")

    def send_frame(
        self,
        session_id: str,
        timestamp_ns: int,
        left: bytes,
        right: bytes,
        imu: ImuData | None = None,
    ) -> Pose:
        """Encoded images exactly as stored (PNG/JPEG); answers once the pose is stored."""
        data, files = _frame_form(timestamp_ns, left, right, imu)
        response = self._request(
            "POST", f"/v1/sessions/{session_id}/frames", data=data, files=files
        )
        return Pose.from_json(response.json())

    def send_imu(self, session_id: str, imu: ImuData) -> int:
        """Buffer IMU samples for the next frames; returns how many are waiting."""
        body = {"samples": imu.to_samples()}
        return int(self._request("POST", f"/v1/sessions/{session_id}/imu", json=body)
                   .json()["buffered"])

    def trajectory(self, session_id: str, format: TrajectoryFormat = "json") -> list[Pose] | str:
        response = self._request(
            "GET", f"/v1/sessions/{session_id}/trajectory", params={"format": format}
        )
        return _trajectory(response, format)

    def smoothed(self, session_id: str) -> list[tuple[int, np.ndarray]]:
        """The back end's stored final poses, oldest first: (timestamp_ns, 4x4 left camera)."""
        return _smoothed(self._request("GET", f"/v1/sessions/{session_id}/smoothed"))

    def finish(self, session_id: str) -> list[tuple[int, np.ndarray]]:
        """End of stream: the back end's last poses are made final (and stored); returns them.

        Frames sent afterwards are still processed, from the last stored pose on."""
        return _smoothed(self._request("POST", f"/v1/sessions/{session_id}/finish"))


class AsyncClient:
    """Asynchronous twin of :class:`Client` (``async with AsyncClient(url, key) as c``)."""

    def __init__(
        self,
        url: str,
        api_key: str | None = None,
        timeout: httpx.Timeout | float = DEFAULT_TIMEOUT,
        transport: httpx.AsyncBaseTransport | None = None,
    ) -> None:
        self.url = url.rstrip("/")
        self.api_key = api_key
        self._http = httpx.AsyncClient(
            base_url=self.url, headers=_headers(api_key), timeout=timeout, transport=transport
        )

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self) -> None:
        await self._http.aclose()

    async def _request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        return _check(await self._http.request(method, path, **kwargs))

    async def health(self) -> dict[str, Any]:
        return (await self._request("GET", "/healthz")).json()

    async def create_session(
        self,
        calibration: dict[str, Any],
        config: dict[str, Any] | None = None,
        imu_noise: dict[str, float] | None = None,
        name: str = "",
    ) -> Session:
        body = {"name": name, "calibration": calibration, "config": config or {},
                "imu_noise": imu_noise}
        return Session.from_json((await self._request("POST", "/v1/sessions", json=body)).json())

    async def create_session_euroc(
        self,
        cam0_yaml: bytes | str | Path,
        cam1_yaml: bytes | str | Path,
        imu0_yaml: bytes | str | Path | None = None,
        config: dict[str, Any] | None = None,
        name: str = "",
    ) -> Session:
        data, files = _euroc_form(cam0_yaml, cam1_yaml, imu0_yaml, config, name)
        response = await self._request("POST", "/v1/sessions/euroc", data=data, files=files)
        return Session.from_json(response.json())

    async def create_session_kitti(
        self,
        calib_txt: bytes | str | Path,
        width: int,
        height: int,
        config: dict[str, Any] | None = None,
        name: str = "",
    ) -> Session:
        data, files = _kitti_form(calib_txt, width, height, config, name)
        response = await self._request("POST", "/v1/sessions/kitti", data=data, files=files)
        return Session.from_json(response.json())

    async def get_session(self, session_id: str) -> Session:
        response = await self._request("GET", f"/v1/sessions/{session_id}")
        return Session.from_json(response.json())

    async def list_sessions(self) -> list[Session]:
        sessions = (await self._request("GET", "/v1/sessions")).json()["sessions"]
        return [Session.from_json(s) for s in sessions]

    async def delete_session(self, session_id: str) -> None:
        await self._request("DELETE", f"/v1/sessions/{session_id}")

    async def send_frame(
        self,
        session_id: str,
        timestamp_ns: int,
        left: bytes,
        right: bytes,
        imu: ImuData | None = None,
    ) -> Pose:
        data, files = _frame_form(timestamp_ns, left, right, imu)
        response = await self._request(
            "POST", f"/v1/sessions/{session_id}/frames", data=data, files=files
        )
        return Pose.from_json(response.json())

    async def send_imu(self, session_id: str, imu: ImuData) -> int:
        body = {"samples": imu.to_samples()}
        response = await self._request("POST", f"/v1/sessions/{session_id}/imu", json=body)
        return int(response.json()["buffered"])

    async def finish(self, session_id: str) -> list[tuple[int, np.ndarray]]:
        """End of stream (see :meth:`Client.finish`)."""
        return _smoothed(await self._request("POST", f"/v1/sessions/{session_id}/finish"))

    async def trajectory(
        self, session_id: str, format: TrajectoryFormat = "json"
    ) -> list[Pose] | str:
        response = await self._request(
            "GET", f"/v1/sessions/{session_id}/trajectory", params={"format": format}
        )
        return _trajectory(response, format)
