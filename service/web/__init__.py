"""The live web view served by the service: pages, static files and the watcher channel."""

from __future__ import annotations

from fastapi import FastAPI


def install_web_view(app: FastAPI) -> None:
    """Add the pages (``/``, ``/sessions/{id}``, offline ``/docs``) and the watch routes."""
    from service.web.pages import install_pages
    from service.web.watch import router as watch_router

    app.include_router(watch_router)
    install_pages(app)
