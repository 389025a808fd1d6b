"""The pages: the sessions list at ``/``, one session at ``/sessions/{id}``, and ``/docs``.

Everything a page loads is served from this package (robots and labs are often offline): the
view's own JavaScript and CSS, and Swagger UI's files from the ``fastapi-offline`` wheel.
"""

from __future__ import annotations

from pathlib import Path

import fastapi_offline
from fastapi import APIRouter, FastAPI, Request
from fastapi.openapi.docs import get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles

STATIC_DIR = Path(__file__).resolve().parent / "static"
SWAGGER_DIR = Path(fastapi_offline.__file__).resolve().parent / "static"
STATIC_URL = "/web/static"
SWAGGER_URL = "/web/swagger"
DOCS_URL = "/docs"
OAUTH2_REDIRECT_URL = "/docs/oauth2-redirect"
# The pages never change per request; the browser may keep them briefly.
_HEADERS = {"cache-control": "no-cache", "x-content-type-options": "nosniff"}

router = APIRouter(include_in_schema=False)


def _page() -> FileResponse:
    return FileResponse(STATIC_DIR / "index.html", media_type="text/html", headers=_HEADERS)


@router.get("/")
def sessions_page() -> FileResponse:
    """The sessions of the key entered in the page (the page asks for it)."""
    return _page()


@router.get("/sessions/{session_id}")
def session_page(session_id: str) -> FileResponse:
    """One session, live or finished; the page checks the id with the key."""
    return _page()


@router.get(DOCS_URL)
def swagger_ui(request: Request) -> HTMLResponse:
    """FastAPI's Swagger UI page, pointed at files served here instead of a CDN."""
    root = request.scope.get("root_path", "")
    app: FastAPI = request.app
    return get_swagger_ui_html(
        openapi_url=f"{root}{app.openapi_url}",
        title=f"{app.title} - API",
        oauth2_redirect_url=f"{root}{OAUTH2_REDIRECT_URL}",
        swagger_js_url=f"{root}{SWAGGER_URL}/swagger-ui-bundle.js",
        swagger_css_url=f"{root}{SWAGGER_URL}/swagger-ui.css",
        swagger_favicon_url=f"{root}{SWAGGER_URL}/favicon.png",
        # Swagger UI would otherwise send the schema to an online validator for its badge.
        swagger_ui_parameters={"validatorUrl": None},
    )


@router.get(OAUTH2_REDIRECT_URL)
def swagger_ui_redirect() -> HTMLResponse:
    return get_swagger_ui_oauth2_redirect_html()


def install_pages(app: FastAPI) -> None:
    """The pages, the view's static files and Swagger UI's."""
    app.include_router(router)
    app.mount(STATIC_URL, StaticFiles(directory=STATIC_DIR), name="web-static")
    app.mount(SWAGGER_URL, StaticFiles(directory=SWAGGER_DIR), name="swagger-static")
