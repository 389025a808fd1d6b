"""The FastAPI application: state, middleware, error handlers and the routers of each resource.

Routes validate, authenticate, queue and persist; the odometry itself runs in
:mod:`service.sessions` workers behind a :class:`~service.estimator_adapter.PipelineFactory`.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from starlette.concurrency import run_in_threadpool

from service.body_limit import BodyLimit
from service.dependencies import ServiceState
from service.errors import install_error_handlers
from service.estimator_adapter import EstimatorFactory, PipelineFactory
from service.metrics import Metrics
from service.routes import frames, operations, sessions, stream, trajectories
from service.sessions import SessionManager
from service.settings import ServiceSettings
from service.storage import Store
from service.web import install_web_view


def create_app(
    settings: ServiceSettings,
    factory: PipelineFactory | None = None,
    store: Store | None = None,
) -> FastAPI:
    """The service app; ``factory`` defaults to the real odometry, ``store`` to settings' DB."""
    settings.check_startable()
    metrics = Metrics()
    pipeline_factory = factory or EstimatorFactory()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        own_store = store is None
        database = store or await run_in_threadpool(
            Store.open, settings.resolved_database_url(), settings.sqlite_synchronous
        )
        manager = SessionManager(settings, database, pipeline_factory, metrics)
        try:
            await manager.start()
        except BaseException:
            if own_store:
                database.close()
            raise
        app.state.swarmvo = ServiceState(settings, database, manager, metrics, pipeline_factory)
        try:
            yield
        finally:
            await manager.shutdown()
            if own_store:
                database.close()

    app = FastAPI(
        title="swarmvo odometry service",
        version="1",
        description="Stereo visual odometry over HTTP and WebSocket. Every answered pose is "
        "stored before the answer is sent.",
        lifespan=lifespan,
        # Served offline by service.web (the defaults load Swagger UI / ReDoc from a CDN).
        docs_url=None,
        redoc_url=None,
    )
    app.add_middleware(BodyLimit, max_bytes=settings.max_request_bytes,
                       timeout_s=settings.request_body_timeout_s, metrics=metrics)
    install_error_handlers(app, metrics)
    for module in (operations, sessions, frames, trajectories, stream):
        app.include_router(module.router)
    install_web_view(app)
    return app
