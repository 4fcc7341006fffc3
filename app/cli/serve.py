"""``scandiff serve``: one command that runs the whole service.

It creates the data directory, applies the migrations, removes leftover temporary files, runs
the job recovery sweep, on first start creates organisation ``default`` with an admin token
(printed, and stored in ``<data_dir>/admin-token`` with mode 0600), then starts two children:
uvicorn (``app.main:create_app``) and the job consumer (``--workers`` processes).  Settings reach
the children through ``SCANDIFF_*`` environment variables.  SIGTERM/SIGINT stop both gracefully;
if ``serve`` itself is killed, the children notice (``PR_SET_PDEATHSIG`` and a ``getppid``
watchdog) and stop too.  If a child exits on its own, ``serve`` stops the other and exits 1.

``--workers 0`` runs the API alone (migrations, recovery sweep at start, uvicorn, no consumer):
the API process of a scaled-out deployment whose jobs run in ``scandiff worker`` processes.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

from app.kit.files import write_private_file

if TYPE_CHECKING:  # pydantic-settings is imported when the command runs
    from app.config import Settings

logger = logging.getLogger("scandiff.serve")

DEFAULT_ORGANISATION = "default"
CHILD_STOP_TIMEOUT_SECONDS = 30.0
"""How long the children get to stop after SIGTERM before SIGKILL (jobs get 10 s of it)."""
API_GRACEFUL_SHUTDOWN_SECONDS = 10
CHILD_ROLES = ("api", "consumer")


def add_parser(subparsers: Any) -> None:
    """Register ``scandiff serve``."""
    parser = subparsers.add_parser(
        "serve",
        help="run the HTTP API and the job workers",
        description="Run the scandiff service: migrations, recovery, API and job workers.",
    )
    parser.add_argument("--data-dir", type=Path, default=None, help="data directory")
    parser.add_argument("--host", default=None, help="address to bind (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None, help="port to bind (default 8000)")
    parser.add_argument(
        "--workers",
        type=worker_count,
        default=None,
        help="job worker processes; 0 runs the API only (jobs run in `scandiff worker`)",
    )
    parser.add_argument("--child", choices=CHILD_ROLES, default=None, help=argparse.SUPPRESS)
    parser.set_defaults(handler=handle_serve)


def worker_count(text: str) -> int:
    """An argparse type: a whole number >= 0."""
    if not text.strip().isdigit():
        raise argparse.ArgumentTypeError(
            f"{text!r}: give a whole number of worker processes >= 0 (0: API only)"
        )
    return int(text)


def build_settings(args: argparse.Namespace) -> Settings:
    """Settings from the environment, overridden by the command-line options given.

    ``--workers 0`` (API only) is not a setting: :func:`child_roles` reads it from ``args``.
    """
    overrides = {
        name: value
        for name, value in (
            ("data_dir", args.data_dir),
            ("host", args.host),
            ("port", args.port),
            ("workers", args.workers or None),
        )
        if value is not None
    }
    from app.config import Settings

    return Settings(**overrides)


def child_roles(args: argparse.Namespace) -> tuple[str, ...]:
    """The children to start: the API, and the consumer unless ``--workers 0``."""
    return ("api",) if args.workers == 0 else CHILD_ROLES


def child_stop_timeout(settings: Settings) -> float:
    """How long the children get to stop: the jobs' shutdown grace plus time to hand back."""
    return max(CHILD_STOP_TIMEOUT_SECONDS, settings.shutdown_grace_seconds + 20.0)


def child_environment(settings: Settings) -> dict[str, str]:
    """Our environment plus the settings the command line overrode, as ``SCANDIFF_*``."""
    from app.jobs.lifecycle import SUPERVISOR_PID_ENV

    environment = dict(os.environ)
    environment.update(
        {
            "SCANDIFF_DATA_DIR": str(settings.data_dir),
            "SCANDIFF_HOST": settings.host,
            "SCANDIFF_PORT": str(settings.port),
            "SCANDIFF_WORKERS": str(settings.workers),
            SUPERVISOR_PID_ENV: str(os.getpid()),
        }
    )
    return environment


def ensure_admin_token(settings: Settings) -> str | None:
    """On first start, create organisation ``default`` and an admin token; the new token."""
    from app.db.session import transaction
    from app.services.auth import create_token, insert_organisation_if_absent

    token_path = settings.data_layout.admin_token_file
    with transaction(settings.sqlalchemy_url) as session:
        # Replicas starting together: one inserts the organisation, the others find it (their
        # insert does nothing) and leave the token to it.
        _organisation, created = insert_organisation_if_absent(session, DEFAULT_ORGANISATION)
        if not created:
            return None  # not the first start, or another replica's
        token = create_token(session, DEFAULT_ORGANISATION, "admin", name="admin (first start)")
        # Written before the commit: a crash in between leaves no organisation, so the next
        # start creates a new token and overwrites this file.
        write_private_file(token_path, token + "\n", overwrite=True)
    return token


SHARED_DATA_SWEEP_MIN_AGE_SECONDS = 3600.0
"""Start-up sweep of an API-only process (``--workers 0``): other processes share the data
directory and may be mid-upload or mid-write, so only files this old are leftovers."""


def prepare(settings: Settings, *, data_dir_shared: bool = False) -> str | None:
    """Everything before the children start; the admin token on first start.

    ``data_dir_shared``: other API or worker processes use the data directory now (an API-only
    process of a scaled-out deployment), so the sweep spares recent temporary and unreferenced
    files: an upload in flight elsewhere is not a leftover.
    """
    from app.db.migrate import upgrade_to_head
    from app.db.session import get_engine
    from app.jobs.queue import close_queue_connections
    from app.jobs.recovery import recovery_sweep
    from app.services.storage import sweep_temporary_files

    settings.data_dir.mkdir(parents=True, exist_ok=True)
    upgrade_to_head(settings.sqlalchemy_url)
    sweep_temporary_files(
        settings, min_age_seconds=SHARED_DATA_SWEEP_MIN_AGE_SECONDS if data_dir_shared else 0.0
    )
    report = recovery_sweep(settings)
    if report.enqueued or report.failed_expired:
        logger.info(
            "recovered jobs at start-up",
            extra={"enqueued": len(report.enqueued), "failed": len(report.failed_expired)},
        )
    token = ensure_admin_token(settings)
    get_engine(settings.sqlalchemy_url).dispose()
    close_queue_connections()
    return token


class Supervisor:
    """Starts the API and consumer children, forwards stop signals, stops both together."""

    def __init__(self, settings: Settings, roles: tuple[str, ...] = CHILD_ROLES) -> None:
        self.settings = settings
        self.roles = roles
        self.stop_timeout = child_stop_timeout(settings)
        self.children: dict[str, subprocess.Popen[bytes]] = {}
        self.stop_requested: int | None = None

    def start_children(self) -> None:
        """Start ``python -m app.cli.serve --child api|consumer`` with the settings in the env."""
        environment = child_environment(self.settings)
        for role in self.roles:
            self.children[role] = subprocess.Popen(
                [sys.executable, "-m", "app.cli.serve", "--child", role],
                env=environment,
                stdin=subprocess.DEVNULL,
            )

    def request_stop(self, signum: int, _frame: FrameType | None) -> None:
        """Signal handler: remember that we must stop."""
        self.stop_requested = signum

    def wait(self) -> int:
        """Block until a stop signal or a child's exit; stop everything; the exit status."""
        while self.stop_requested is None:
            for role, child in self.children.items():
                if child.poll() is not None:
                    logger.error(
                        "child exited unexpectedly; stopping the service",
                        extra={"child": role, "returncode": child.returncode},
                    )
                    self.stop_children()
                    return 1
            time.sleep(0.2)
        logger.info("stopping", extra={"signal": signal.Signals(self.stop_requested).name})
        self.stop_children()
        return 0

    def stop_children(self) -> None:
        """SIGTERM every child, wait, SIGKILL whatever is left after the timeout."""
        for child in self.children.values():
            if child.poll() is None:
                child.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + self.stop_timeout
        for role, child in self.children.items():
            try:
                child.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                logger.warning("child did not stop in time; killing it", extra={"child": role})
                child.kill()
                child.wait()


def serve(settings: Settings, roles: tuple[str, ...] = CHILD_ROLES) -> int:
    """Prepare, start the children, and supervise them until stopped; the exit status."""
    token = prepare(settings, data_dir_shared="consumer" not in roles)
    url = f"http://{settings.host}:{settings.port}"
    print(f"scandiff serving at {url}  (API docs: {url}/docs)", flush=True)
    print(f"data directory: {settings.data_dir}", flush=True)
    if "consumer" not in roles:
        print("no job workers here (--workers 0): run `scandiff worker` for the jobs", flush=True)
    if token:
        print(
            f"admin token (first start; also in {settings.data_layout.admin_token_file}):\n{token}",
            flush=True,
        )
    supervisor = Supervisor(settings, roles)
    signal.signal(signal.SIGTERM, supervisor.request_stop)
    signal.signal(signal.SIGINT, supervisor.request_stop)
    supervisor.start_children()
    return supervisor.wait()


def run_api_child(settings: Settings) -> int:
    """The API child: uvicorn serving ``app.main:create_app``."""
    import uvicorn

    uvicorn.run(
        "app.main:create_app",
        factory=True,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level.lower(),
        timeout_graceful_shutdown=API_GRACEFUL_SHUTDOWN_SECONDS,
        access_log=False,  # the app logs one JSON line per request itself
    )
    return 0


def run_child(role: str) -> int:
    """Run one child of ``serve`` (settings from ``SCANDIFF_*``), dying with its parent."""
    from app.jobs.consumer import run_consumer
    from app.jobs.lifecycle import die_with_supervisor
    from app.services.schedules.runs import tick

    die_with_supervisor()
    from app.config import Settings

    settings = Settings()
    if role == "api":
        return run_api_child(settings)
    return run_consumer(settings, settings.workers, schedule_tick=tick)


def handle_serve(args: argparse.Namespace) -> int:
    """Entry of ``scandiff serve``."""
    if args.child:
        return run_child(args.child)
    from app.log import configure_process_logging

    settings = build_settings(args)
    configure_process_logging(settings.log_level, settings.log_format)
    logging.getLogger("alembic.runtime.plugins").setLevel(logging.WARNING)
    return serve(settings, child_roles(args))


if __name__ == "__main__":  # the children: python -m app.cli.serve --child api|consumer
    child_parser = argparse.ArgumentParser(prog="scandiff serve (child)")
    child_parser.add_argument("--child", choices=CHILD_ROLES, required=True)
    sys.exit(run_child(child_parser.parse_args().child))
