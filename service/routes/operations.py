"""Operations: the health check and Prometheus metrics."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Response
from fastapi.responses import PlainTextResponse
from starlette.concurrency import run_in_threadpool

from service.dependencies import State
from service.errors import Refusal
from service.schemas import Health

logger = logging.getLogger("swarmvo.service")
router = APIRouter(tags=["operations"])


@router.get("/healthz", response_model=Health)
async def healthz(state: State) -> Health:
    try:
        await run_in_threadpool(state.store.ping)
    except Exception as error:
        logger.error("health check: database unavailable: %s", str(error).splitlines()[:1])
        raise Refusal(503, "database unavailable", "storage") from error
    return Health(status="ok", sessions_active=len(state.manager.live), database="ok",
                  executor=state.manager.runner.mode, workers=state.settings.workers)


@router.get("/metrics", response_class=PlainTextResponse)
async def prometheus_metrics(state: State) -> Response:
    return Response(state.metrics.render(), media_type="text/plain; version=0.0.4; charset=utf-8")
