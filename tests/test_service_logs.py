"""A real server's log at debug level: no API key in any line, one line per expected client-side
event (refused handshake, disconnect mid-upload), and stalled connections are timed out."""

from __future__ import annotations

import asyncio
import json
import re
import socket
import time
from pathlib import Path

import httpx
import pytest
import websockets
from test_service_server import AUTH, KEY, OTHER_KEY, Server, _calibration, _png

TIMEOUT_S = 1


def _closed_within(port: int, payload: bytes, seconds: float) -> bytes:
    """What the server answers before closing a connection that sent ``payload`` and stalls."""
    with socket.create_connection(("127.0.0.1", port), timeout=seconds) as sock:
        sock.sendall(payload)
        received = b""
        while chunk := sock.recv(4096):  # TimeoutError (a failure) if never closed
            received += chunk
    return received


@pytest.mark.slow
def test_server_log_has_no_key_and_one_line_per_client_event(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    for name in ("REQUEST_HEADER_TIMEOUT_S", "REQUEST_BODY_TIMEOUT_S", "TIMEOUT_KEEP_ALIVE_S"):
        monkeypatch.setenv(f"SWARMVO_{name}", str(TIMEOUT_S))
    log = tmp_path / "server.log"
    server = Server(tmp_path / "data", log, "--log-level", "debug", "--workers", "1")
    try:
        with httpx.Client(base_url=server.url, headers=AUTH, timeout=30) as http:
            sid = http.post("/v1/sessions", json={"calibration": _calibration()}).json()["id"]
            ws_url = server.url.replace("http://", "ws://") + f"/v1/sessions/{sid}/stream"

            async def handshakes() -> list[int]:
                statuses = []
                for url, headers in (
                    (f"{ws_url}?token={KEY}", {}),
                    (ws_url, {"Authorization": f"Bearer {OTHER_KEY}"}),  # another key: 404
                    (f"{ws_url}?token=not-a-key-{KEY}", {}),  # 401
                    (ws_url.replace(sid, "f" * 32) + f"?token={KEY}", {}),  # 404
                ):
                    try:
                        async with websockets.connect(url, additional_headers=headers) as ws:
                            assert json.loads(await ws.recv())["type"] == "hello"
                            await ws.send(json.dumps({"type": "close"}))
                            statuses.append(101)
                    except websockets.InvalidStatus as refused:
                        statuses.append(refused.response.status_code)
                return statuses

            assert asyncio.run(handshakes()) == [101, 404, 401, 404]
            # A client that hangs up in the middle of its upload.
            head = (f"POST /v1/sessions/{sid}/frames HTTP/1.1\r\nHost: x\r\nAuthorization: "
                    f"Bearer {KEY}\r\nContent-Type: multipart/form-data; boundary=bb\r\n"
                    "Content-Length: 100000\r\n\r\n--bb\r\nContent-Disposition: form-data; "
                    'name="left"; filename="l.png"\r\n\r\n').encode()
            with socket.create_connection(("127.0.0.1", server.port)) as sock:
                sock.sendall(head + _png()[:50])
                time.sleep(0.3)
            # Stalled connections: idle, half-sent headers, half-sent body.
            started = time.monotonic()
            for payload in (
                b"",
                b"GET /healthz HTTP/1.1\r\nHost: x\r\n",
                (f"POST /v1/sessions HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {KEY}\r\n"
                 "Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{").encode(),
            ):
                answer = _closed_within(server.port, payload, 10 * TIMEOUT_S)
                assert answer.startswith(b"HTTP/1.1 408"), answer
            assert time.monotonic() - started < 3 * (TIMEOUT_S + 1)
            time.sleep(0.5)
            errors = dict(re.findall(r'^swarmvo_errors_total\{kind="([^"]+)"\} (\S+)$',
                                     http.get("/metrics").text, re.M))
        assert server.stop()
    finally:
        if server.process.poll() is None:
            server.kill()
    text = log.read_text()
    assert KEY not in text and OTHER_KEY not in text
    assert "token=[redacted]" in text  # the paths are still logged, without the secret
    assert "without completing handshake" not in text and "Traceback" not in text
    refused = [line for line in text.splitlines() if re.search(r'"WebSocket .*" 40[14]', line)]
    assert len(refused) == 3, refused
    assert not any("connection rejected" in line for line in text.splitlines())
    assert len(re.findall(r"disconnected during POST", text)) == 1
    assert "internal" not in errors
    assert errors["client_disconnect"] == "1.0" and errors["timeout"] == "1.0"
