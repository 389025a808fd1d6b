"""What routes share, as FastAPI dependencies: the service state, the caller's key, the session.

A session of another key is indistinguishable from no session: both are 404.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.concurrency import run_in_threadpool
from starlette.requests import HTTPConnection

from service.auth import AuthError, bearer_token, owner_for
from service.errors import Refusal, unknown_session
from service.estimator_adapter import PipelineFactory
from service.metrics import Metrics
from service.sessions import LiveSession, SessionGone, SessionManager
from service.settings import ServiceSettings
from service.storage import SessionRecord, Store

SESSION_ID = re.compile(r"^[0-9a-f]{32}$")


@dataclass
class ServiceState:
    settings: ServiceSettings
    store: Store
    manager: SessionManager
    metrics: Metrics
    factory: PipelineFactory


def service_state(connection: HTTPConnection) -> ServiceState:
    """The running app's state (set by its lifespan), for HTTP and WebSocket routes alike."""
    return connection.app.state.swarmvo


bearer_scheme = HTTPBearer(auto_error=False, description="API key: 'Authorization: Bearer KEY'")


def current_owner(
    request: Request,
    _credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)],
) -> str:
    state = service_state(request)
    try:
        return owner_for(bearer_token(request.headers.get("authorization")), state.settings)
    except AuthError as error:
        raise Refusal(401, str(error), "auth", headers={"WWW-Authenticate": "Bearer"}) from error


Owner = Annotated[str, Depends(current_owner)]
State = Annotated[ServiceState, Depends(service_state)]


def lookup(state: ServiceState, session_id: str, owner: str) -> SessionRecord:
    """The owner's stored session or 404."""
    if session_id in state.manager.deleted:
        raise unknown_session(session_id)
    record = state.store.get_session(session_id, owner) if SESSION_ID.match(session_id) else None
    if record is None:
        raise unknown_session(session_id)
    return record


async def lookup_live_first(state: ServiceState, session_id: str, owner: str) -> SessionRecord:
    """The session's record, from its live session when it has one (no database round trip)."""
    live = state.manager.live.get(session_id)
    if live is not None and live.owner == owner:
        return live.record
    return await run_in_threadpool(lookup, state, session_id, owner)


def live_session(state: ServiceState, record: SessionRecord) -> LiveSession:
    """The live session (started on first use), or 404 when it was deleted meanwhile.

    Called right before a frame is submitted, not as a dependency: a live session fetched before a
    slow upload could be unloaded as idle while the body arrives.
    """
    try:
        return state.manager.live_session(record)
    except SessionGone as error:
        raise unknown_session(record.id) from error


def stored_session(session_id: str, owner: Owner, state: State) -> SessionRecord:
    """Path dependency: the session as stored (fresh counts), for reads and deletion."""
    return lookup(state, session_id, owner)


async def active_session(session_id: str, owner: Owner, state: State) -> SessionRecord:
    """Path dependency: the session for sending data, from its live session when it has one."""
    return await lookup_live_first(state, session_id, owner)


StoredSession = Annotated[SessionRecord, Depends(stored_session)]
ActiveSession = Annotated[SessionRecord, Depends(active_session)]
