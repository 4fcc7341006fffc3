"""``scandiff worker``: a standalone job consumer (no API) for scaled-out deployments.

``scandiff worker [--concurrency N] [--data-dir DIR] [--shutdown-grace S] [--wait-for-database S]``
runs ``N`` job worker processes (default ``SCANDIFF_WORKERS``) and the periodic recovery sweep
(:mod:`app.jobs.consumer`) on the ``SCANDIFF_*`` settings every process of the deployment shares
(``DATABASE_URL``, ``QUEUE_URL``, ``DATA_DIR``).  It never migrates the database: it waits, saying
what it waits for, until the database is reachable and at the code's revision (the API
processes, ``scandiff serve --workers 0``, migrate), and exits with status 1 and one line on
stderr if that takes longer than ``--wait-for-database`` seconds.

SIGTERM or SIGINT: no new job is taken, a running job gets ``--shutdown-grace`` seconds
(``SCANDIFF_SHUTDOWN_GRACE_SECONDS``, default 10) to finish, else it is handed back to the queue
without using an attempt; the exit status is 0.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pydantic-settings is imported when the command runs
    from app.config import Settings


DATABASE_WAIT_SECONDS = 120.0
"""Default of ``--wait-for-database``: how long to wait for a reachable, migrated database."""
EXIT_DATABASE_NOT_READY = 1
"""Exit status when the database was not reachable and migrated within the wait."""


def non_negative_seconds(text: str) -> float:
    """An argparse type: a finite number of seconds >= 0."""
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"{text!r}: give a number of seconds >= 0")
    return value


def positive_count(text: str) -> int:
    """An argparse type: an integer >= 1."""
    if not text.strip().isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: give a whole number of processes >= 1")
    return int(text)


def add_parser(subparsers: Any) -> None:
    """Register ``scandiff worker``."""
    parser = subparsers.add_parser(
        "worker",
        help="run job workers only (no API), for scaled-out deployments",
        description="Run a standalone job consumer: N worker processes and the recovery sweep. "
        "It does not migrate the database; it waits until the database is at head.",
    )
    parser.add_argument(
        "--concurrency",
        type=positive_count,
        default=None,
        help="job worker processes (default: SCANDIFF_WORKERS)",
    )
    parser.add_argument("--data-dir", type=Path, default=None, help="data directory (shared)")
    parser.add_argument(
        "--shutdown-grace",
        type=non_negative_seconds,
        default=None,
        help="seconds a running job may take to finish on SIGTERM before it is handed back "
        "(default: SCANDIFF_SHUTDOWN_GRACE_SECONDS, else 10)",
    )
    parser.add_argument(
        "--wait-for-database",
        type=non_negative_seconds,
        default=DATABASE_WAIT_SECONDS,
        help="seconds to wait for a reachable, migrated database "
        f"(default {DATABASE_WAIT_SECONDS:g})",
    )
    parser.set_defaults(handler=handle_worker)


def build_settings(args: argparse.Namespace) -> Settings:
    """Settings from the environment, overridden by the options given."""
    overrides: dict[str, Any] = {}
    if args.data_dir is not None:
        overrides["data_dir"] = args.data_dir
    if args.concurrency is not None:
        overrides["workers"] = args.concurrency
    if args.shutdown_grace is not None:
        overrides["shutdown_grace_seconds"] = args.shutdown_grace
    from app.config import Settings

    return Settings(**overrides)


def handle_worker(args: argparse.Namespace) -> int:
    """Entry of ``scandiff worker``."""
    from app.jobs.consumer import DatabaseNotReadyError, run_consumer
    from app.services.schedules.runs import tick

    settings = build_settings(args)
    try:
        return run_consumer(
            settings,
            settings.workers,
            settings.shutdown_grace_seconds,
            wait_for_database_seconds=args.wait_for_database,
            schedule_tick=tick,
        )
    except DatabaseNotReadyError as exc:
        print(f"scandiff worker: error: {exc}", file=sys.stderr)
        return EXIT_DATABASE_NOT_READY
