"""Keep API keys out of the logs, whatever the log level.

At ``debug`` uvicorn logs every request line and its WebSocket library logs handshake headers
and message text, which is where keys travel (``Authorization: Bearer KEY``, the watcher's
``{"type": "auth", "token": KEY}``, a ``?token=KEY`` query). A filter on every handler rewrites
such records before they are written.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable

MASK = "[redacted]"
_PATTERNS = (
    re.compile(r"(?i)(bearer\s+)[^\s'\",]+"),
    re.compile(r"""(["']token["']\s*:\s*["'])[^"']*"""),
    re.compile(r"([?&]token=)[^&\s'\"]+"),
)


class SecretFilter(logging.Filter):
    """Replaces configured keys, bearer tokens and auth-message tokens in log records."""

    def __init__(self, secrets: Iterable[str] = ()) -> None:
        super().__init__()
        self.secrets = sorted({s for s in secrets if s}, key=len, reverse=True)

    def redact(self, text: str) -> str:
        for secret in self.secrets:
            text = text.replace(secret, MASK)
        for pattern in _PATTERNS:
            text = pattern.sub(lambda m: m.group(1) + MASK, text)
        return text

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        cleaned = self.redact(message)
        if cleaned != message:
            record.msg, record.args = cleaned, ()
        return True


def redact_logs(secrets: Iterable[str], loggers: Iterable[str] = ("", "uvicorn",
                "uvicorn.error", "uvicorn.access")) -> SecretFilter:
    """Put one filter on every handler of ``loggers`` (the root and uvicorn's by default)."""
    secret_filter = SecretFilter(secrets)
    for name in loggers:
        for handler in logging.getLogger(name).handlers:
            handler.addFilter(secret_filter)
    return secret_filter
