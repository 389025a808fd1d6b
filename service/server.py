"""Run the app under uvicorn (what ``swarmvo serve`` calls)."""

from __future__ import annotations

import logging

import uvicorn

from service.app import create_app
from service.redact import redact_logs
from service.settings import ServiceSettings


def serve(settings: ServiceSettings, log_level: str = "info") -> int:
    """Serve until interrupted; a configuration problem raises ValueError before binding."""
    settings.check_startable()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(level=log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    if settings.open:
        logging.getLogger("swarmvo.service").warning(
            "open mode: no API key is required; anyone who can reach %s:%d can use the service",
            settings.host,
            settings.port,
        )
    config = uvicorn.Config(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=log_level,
        ws_max_size=settings.ws_max_message_bytes,
        # Frames are PNG/JPEG already: deflating them again costs CPU on the event loop for
        # nothing (about 0.2 s per EuRoC pair on a busy core).
        ws_per_message_deflate=False,
        # Queued frames get this long to be processed and stored on SIGTERM/SIGINT.
        timeout_graceful_shutdown=15,
        access_log=log_level == "debug",
    )
    # After uvicorn.Config: it installs the handlers the filter goes on.
    redact_logs(k.strip() for k in settings.api_keys.split(","))
    uvicorn.Server(config).run()
    return 0
