"""``swarmvo serve``: the HTTP/WebSocket odometry service under uvicorn."""

from __future__ import annotations

import argparse
from typing import get_args

from service.settings import Executor


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default=None, help="bind address (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None, help="TCP port (default 8000)")
    parser.add_argument("--data-dir", default=None, help="where the SQLite database lives")
    parser.add_argument(
        "--database-url", default=None, help="SQLAlchemy URL (e.g. postgresql+psycopg://...)"
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="worker processes (or threads) running the odometry (default: cores)",
    )
    parser.add_argument(
        "--executor",
        choices=get_args(Executor),
        default=None,
        help="where the odometry runs: worker processes with session affinity (default) or "
        "threads of the server process",
    )
    parser.add_argument(
        "--open",
        action="store_true",
        default=None,
        help="no API keys: anyone reaching the port may use it (local development only)",
    )
    parser.add_argument("--log-level", default="info", help="uvicorn log level")


def run(args: argparse.Namespace) -> int:
    # Imported here so `swarmvo --help` does not pay for FastAPI and SQLAlchemy.
    from pydantic import ValidationError

    from estimator.config import explain_validation_error
    from service.server import serve
    from service.settings import SECRET_SETTINGS, ServiceSettings

    overrides = {
        "host": args.host,
        "port": args.port,
        "data_dir": args.data_dir,
        "database_url": args.database_url,
        "workers": args.workers,
        "executor": args.executor,
        "open": args.open,
    }
    try:
        settings = ServiceSettings(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as error:
        problems = explain_validation_error(error, ServiceSettings, SECRET_SETTINGS)
        raise ValueError(f"invalid settings: {problems}") from None
    return serve(settings, log_level=args.log_level)
