"""Request bodies bounded in size and in time, before any route reads them."""

from __future__ import annotations

import asyncio
import json

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import Refusal
from service.metrics import Metrics


class BodyLimit:
    """Refuse oversized or stalled request bodies: by Content-Length, and while streaming in.

    A body larger than ``max_bytes`` gets a 413; a client that stops sending its body for
    ``timeout_s`` gets a 408, so half-sent requests do not hold connections forever.
    """

    def __init__(self, app: ASGIApp, max_bytes: int, timeout_s: float, metrics: Metrics) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.timeout_s = timeout_s
        self.metrics = metrics

    async def _refuse(self, send: Send, refusal: Refusal) -> None:
        self.metrics.errors.labels(refusal.kind or "too_large").inc()
        body = json.dumps({"detail": refusal.detail}).encode()
        await send(
            {
                "type": "http.response.start",
                "status": refusal.status_code,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = -1
                if declared < 0 or declared > self.max_bytes:
                    await self._refuse(send, _TooLarge(self.max_bytes))
                    return
        received = 0
        body_done = False
        started = False

        async def limited_receive() -> Message:
            nonlocal received, body_done
            if body_done:  # afterwards only a disconnect can come: no time limit
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), self.timeout_s)
            except TimeoutError:
                raise _BodyTimeout(self.timeout_s) from None
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                body_done = not message.get("more_body", False)
                if received > self.max_bytes:
                    raise _TooLarge(self.max_bytes)
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except _BodyRefusal as refusal:
            if not started:
                await self._refuse(send, refusal)


class _BodyRefusal(Refusal):
    """Raised from ``receive``; an HTTPException, so body parsers pass it through."""


class _TooLarge(_BodyRefusal):
    def __init__(self, max_bytes: int) -> None:
        super().__init__(413, f"request body exceeds the limit of {max_bytes} bytes", "too_large")


class _BodyTimeout(_BodyRefusal):
    def __init__(self, seconds: float) -> None:
        super().__init__(
            408, f"request body not received: nothing arrived for {seconds:g} s", "timeout"
        )
