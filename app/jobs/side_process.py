"""A long-running helper process of a job consumer, started beside its job workers and replaced
when it dies: the webhook deliveries (:mod:`app.jobs.alerts.deliveries`) and the schedule ticker.

Each runs a loop until its stop event is set; SIGTERM sets it (the loop finishes the step in
flight), SIGINT is ignored (the consumer decides when to stop).  Forked, so the loop may be any
callable; the child never uses the parent's database connections.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import signal
import threading
from collections.abc import Callable
from multiprocessing.process import BaseProcess

from app.config import Settings
from app.db.session import get_engine

logger = logging.getLogger("scandiff.jobs")

Loop = Callable[[Settings, threading.Event], None]
"""A side process's body: runs until the event is set."""


def _side_process_main(settings: Settings, loop: Loop) -> None:
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    get_engine(settings.sqlalchemy_url).dispose(close=False)  # never the parent's connections
    loop(settings, stop)


class SideProcess:
    """One named helper process running ``loop``, started again when it died."""

    def __init__(self, settings: Settings, name: str, loop: Loop) -> None:
        self.settings = settings
        self.name = name
        self.loop = loop
        self.process: BaseProcess | None = None

    def ensure_running(self) -> None:
        """Start the process, or a new one if it died."""
        if self.process is not None and self.process.is_alive():
            return
        if self.process is not None:
            logger.warning(
                "%s process died; starting another",
                self.name,
                extra={"exitcode": self.process.exitcode},
            )
        self.process = multiprocessing.get_context("fork").Process(
            target=_side_process_main,
            args=(self.settings, self.loop),
            name=f"scandiff-{self.name}",
            daemon=True,
        )
        self.process.start()

    def stop(self, timeout: float) -> None:
        """SIGTERM, then SIGKILL after ``timeout`` seconds."""
        process = self.process
        if process is None or not process.is_alive():
            return
        process.terminate()
        process.join(timeout)
        if process.is_alive():
            with contextlib.suppress(OSError):
                process.kill()
            process.join(1.0)
