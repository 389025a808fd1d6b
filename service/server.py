"""Run the app under uvicorn (what ``swarmvo serve`` calls), with three adjustments.

- Logs never carry an API key (``service.redact``): uvicorn's records go to the root handler,
  whose filter redacts keys, bearer tokens and ``?token=`` query values.
- A connection that does not complete its request headers in ``request_header_timeout_s`` is
  answered 408 and closed (uvicorn only times out idle keep-alive connections).
- A WebSocket handshake is one log line (accepted, or the 401/404 of a refusal): uvicorn's
  sans-I/O protocol would add an "ASGI callable returned without completing handshake" error
  to each refusal, and the websockets library its own line to each handshake.
- On SIGTERM/SIGINT the open streams are told first (``SessionManager.stop_streams``): they
  stop reading, send what is due for a moment and close with 1012, instead of holding the
  shutdown until uvicorn cancels them with a traceback each; a socket whose client stopped
  reading is cut off shortly after.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import uvicorn
from fastapi import FastAPI
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

from service.app import create_app
from service.memory import reuse_frame_buffers
from service.preflight import check_database, check_listen, prepare_data_dir
from service.redact import redact_logs
from service.settings import ServiceSettings


class HeaderTimeoutProtocol(HttpToolsProtocol):
    """HTTP/1.1 that closes connections whose request headers do not arrive in time."""

    header_timeout_s = 10.0

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._header_timer: asyncio.TimerHandle | None = None

    def _arm(self) -> None:
        self._disarm()
        self._header_timer = self.loop.call_later(self.header_timeout_s, self._headers_late)

    def _disarm(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _headers_late(self) -> None:
        self._header_timer = None
        if self.transport.is_closing():
            return
        if self.cycle is None or self.cycle.response_complete:
            body = b'{"detail": "request headers not received in time"}'
            self.transport.write(
                b"HTTP/1.1 408 Request Timeout\r\ncontent-type: application/json\r\n"
                b"connection: close\r\ncontent-length: %d\r\n\r\n%s" % (len(body), body)
            )
        self.transport.close()

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._arm()

    def on_headers_complete(self) -> None:
        self._disarm()
        super().on_headers_complete()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)


# Seconds between the server's pings on an open stream (under the balancer's read timeout).
WS_PING_INTERVAL_S = 5.0
# The websockets library's own lines ("connection open", "connection rejected", frames at
# debug) repeat uvicorn's one line per handshake: only its warnings and errors are kept.
HANDSHAKE_LOGGER = logging.getLogger("swarmvo.websockets")


# Seconds the open streams get to close themselves once the server stops (see stream.py's
# STOPPING_DRAIN_S and CLOSE_SEND_TIMEOUT_S, which fit in it).
STREAMS_STOP_GRACE_S = 4.0
# Seconds a WebSocket's socket may still take to flush its close after shutdown; then it is
# aborted (its client stopped reading: the buffered bytes would never leave).
WS_ABORT_AFTER_S = 1.0


class DenialLoggedOnce(WebSocketsSansIOProtocol):
    """A handshake answered with an HTTP denial is complete: no extra error line for it; a
    socket that cannot flush at shutdown is aborted rather than waited for."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.conn.logger = HANDSHAKE_LOGGER
        self.lost = False

    def connection_lost(self, exc: Exception | None) -> None:
        self.lost = True
        super().connection_lost(exc)

    def shutdown(self) -> None:
        super().shutdown()
        self.loop.call_later(WS_ABORT_AFTER_S, self._abort_if_stuck)

    def _abort_if_stuck(self) -> None:
        if not self.lost:
            self.transport.abort()

    async def send(self, message: Any) -> None:
        await super().send(message)
        if message["type"] == "websocket.http.response.body" and not message.get("more_body"):
            self.handshake_complete = True


class StreamsFirstServer(uvicorn.Server):
    """uvicorn, telling the app's open streams the server stops before waiting for them."""

    def __init__(self, config: uvicorn.Config, app: FastAPI) -> None:
        super().__init__(config)
        self.service_app = app

    async def shutdown(self, sockets: list[Any] | None = None) -> None:
        for server in self.servers:
            server.close()  # no new connections while the streams close
        state = getattr(self.service_app.state, "swarmvo", None)
        if state is not None:
            await state.manager.stop_streams(STREAMS_STOP_GRACE_S)
        await super().shutdown(sockets)


def serve(settings: ServiceSettings, log_level: str = "info") -> int:
    """Serve until interrupted; a configuration problem raises ValueError before binding."""
    settings.check_startable()
    prepare_data_dir(settings.data_dir)
    check_listen(settings.host, settings.port)
    check_database(settings.resolved_database_url())
    logging.basicConfig(level=log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    if settings.open:
        logging.getLogger("swarmvo.service").warning(
            "open mode: no API key is required; anyone who can reach %s:%d can use the service",
            settings.host,
            settings.port,
        )
    protocol = type("HttpProtocol", (HeaderTimeoutProtocol,),
                    {"header_timeout_s": settings.request_header_timeout_s})
    app = create_app(settings)
    config = uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        log_level=log_level,
        # uvicorn's records go to the root handler configured above (and its redaction).
        log_config=None,
        http=protocol,
        ws=DenialLoggedOnce,
        ws_max_size=settings.ws_max_message_bytes,
        # Frames are PNG/JPEG already: deflating them again costs CPU on the event loop for
        # nothing (about 0.2 s per EuRoC pair on a busy core).
        ws_per_message_deflate=False,
        # A ping keeps a quiet stream alive behind a balancer whose read timeout finds stalled
        # replicas (docker/nginx.conf: 15 s).
        ws_ping_interval=WS_PING_INTERVAL_S,
        timeout_keep_alive=settings.timeout_keep_alive_s,
        # The last resort for connections still open after the streams were told to close
        # (StreamsFirstServer); queued frames are processed and stored after it, at lifespan
        # shutdown (SessionManager.shutdown, up to 10 s).
        timeout_graceful_shutdown=15,
        access_log=log_level == "debug",
    )
    redact_logs(k.strip() for k in settings.api_keys.split(","))
    reuse_frame_buffers()
    HANDSHAKE_LOGGER.setLevel(logging.WARNING)
    StreamsFirstServer(config, app).run()
    return 0
