"""API-key authentication: ``Authorization: Bearer KEY`` (or ``?token=KEY`` on WebSockets).

Sessions are owned by the SHA-256 of the key that created them; the key itself is never
stored. In open mode (local development) no key is needed; a key that is sent still separates
its sessions from everybody else's.
"""

from __future__ import annotations

import hmac

from service.settings import ServiceSettings, hash_key

ANONYMOUS_OWNER = hash_key("")


class AuthError(Exception):
    """Missing or unknown credentials (answered 401, or a refused WebSocket handshake)."""


def bearer_token(authorization: str | None) -> str | None:
    if not authorization:
        return None
    scheme, _, token = authorization.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        raise AuthError("malformed Authorization header: expected 'Bearer <API key>'")
    return token.strip()


def owner_for(token: str | None, settings: ServiceSettings) -> str:
    """The owner digest for a presented key, or AuthError."""
    if token is None:
        if settings.open:
            return ANONYMOUS_OWNER
        raise AuthError("missing API key: send 'Authorization: Bearer <API key>'")
    digest = hash_key(token)
    if settings.open and not settings.key_hashes:
        return digest
    # Constant-time comparison against every configured key.
    known = False
    for candidate in settings.key_hashes:
        known |= hmac.compare_digest(candidate, digest)
    if not known:
        raise AuthError("unknown API key")
    return digest
