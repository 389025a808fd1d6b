"""What ``swarmvo serve`` checks before it starts: the data folder, the address and the database.

Each problem found here would otherwise surface as a traceback from inside uvicorn's start-up
(or, for a taken port, after the workers were started and warmed up for nothing). Here it is
one ``ValueError`` naming what is wrong, which the CLI prints as one line.
"""

from __future__ import annotations

import socket
from pathlib import Path

from estimator.formats.folders import writable_folder
from service.storage.engine import check_database

__all__ = ["check_database", "check_listen", "prepare_data_dir"]


def prepare_data_dir(folder: Path) -> None:
    """Make the data folder (the SQLite file lives there) or say why it cannot be."""
    try:
        writable_folder(folder)
    except ValueError as error:
        raise ValueError(f"data directory: {error}") from None


def check_listen(host: str, port: int) -> None:
    """The address can be bound now (as uvicorn binds it: SO_REUSEADDR), else why not."""
    where = f"{host}:{port}"
    try:
        family, kind, protocol, _name, address = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
    except socket.gaierror as error:
        raise ValueError(f"cannot listen on {where}: {error.strerror}") from None
    with socket.socket(family, kind, protocol) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as error:
            raise ValueError(f"cannot listen on {where}: {error.strerror}") from None
