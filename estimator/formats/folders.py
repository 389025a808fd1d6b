"""Output folders made before the work that fills them: a mistyped, read-only or blocked path
is one clear error at the start, not a traceback after minutes of computing."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["writable_folder"]


def writable_folder(folder: Path) -> Path:
    """``folder``, made with its parents if needed; ValueError when it cannot take files."""
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"cannot write into {folder}: it is a file, not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ValueError(f"cannot write into {folder}: {error.strerror}") from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write into {folder}: permission denied")
    return folder
