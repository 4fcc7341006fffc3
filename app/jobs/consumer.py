"""The job consumer process: Huey process workers plus the periodic recovery sweep.

Run by ``scandiff serve`` as a child, or alone on another host for scale-out
(``scandiff worker --concurrency 4`` with the same ``SCANDIFF_*`` settings, see
:mod:`app.cli.worker`; ``python -m app.jobs.consumer --workers 4`` is the same without the wait
for a migrated database)::

    consumer (this process: supervises workers, runs the recovery sweep every
    │         recovery_interval_seconds, notes it is alive in the queue for /health)
    ├── Huey scheduler (process)
    ├── Huey worker 1..N (processes; each runs one job at a time)
    ├── webhook deliveries (process: :mod:`app.jobs.alerts.deliveries`, replaced when it dies)
    └── schedule ticker (process, when given a tick: every schedule_tick_seconds; replaced
                         when it dies, so a slow URL fetch never delays supervision)

SIGTERM or SIGINT stop it gracefully: idle workers exit at once (no new job is taken), running
jobs get the shutdown grace (``SCANDIFF_SHUTDOWN_GRACE_SECONDS``, default 10 s) to finish,
then are interrupted and handed back to the queue without using up an attempt (``enqueued_at``
cleared: the next sweep of any consumer sends them again at once); the exit status is 0.  A
worker that dies is replaced within a second; its job is recovered by the sweep once its lease
expires.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from huey import Huey
from huey.consumer import Consumer, ConsumerStopped, Worker

from app.config import Settings, get_settings
from app.db.migrate import current_revision, head_revision
from app.db.session import get_engine
from app.jobs import queue, runner
from app.jobs.alerts.deliveries import delivery_process
from app.jobs.doorbell import Doorbell, doorbell_path, ring
from app.jobs.hooks import job_hooks
from app.jobs.lifecycle import die_with_supervisor, set_parent_death_signal
from app.jobs.limits import job_memory_limit, job_threads
from app.jobs.recovery import recovery_sweep
from app.jobs.side_process import Loop, SideProcess
from app.kit.allocator import release_freed_memory_promptly, return_free_heap
from app.log import bind_job, configure_process_logging

logger = logging.getLogger("scandiff.jobs.consumer")

DATABASE_WAIT_LOG_SECONDS = 10.0
"""How often the wait says what it is waiting for."""
WORKER_HEALTH_CHECK_SECONDS = 1.0
"""How often dead workers are replaced."""
QUEUE_POLL_MAX_DELAY_SECONDS = 1.0
"""Longest pause between two polls of an empty SQLite queue by an idle worker."""
CONSUMER_HEARTBEAT_SECONDS = 5.0
MEMORY_LIMIT_ENV = "SCANDIFF_JOB_MEMORY_LIMIT_BYTES"
JOB_THREADS_ENV = "SCANDIFF_JOB_THREADS"


class DatabaseNotReadyError(RuntimeError):
    """The database was not reachable and migrated to head within the wait."""


def database_state(url: str) -> str | None:
    """None when the database at ``url`` is reachable and at head; else what is wrong."""
    head = head_revision()
    try:
        revision = current_revision(url)
    except Exception as exc:
        return f"the database cannot be reached ({type(exc).__name__}: {str(exc).strip()[:200]})"
    if revision != head:
        return (
            f"the database is at revision {revision or 'none (never migrated)'}, this code needs "
            f"{head}: start `scandiff serve` (it migrates) or run `alembic upgrade head`"
        )
    return None


def wait_for_database_at_head(
    settings: Settings,
    timeout: float,
    *,
    poll_seconds: float = 0.5,
) -> None:
    """Block until the database is reachable and migrated to head; raise
    :class:`DatabaseNotReadyError` saying why after ``timeout`` seconds.

    A standalone consumer never migrates (the API processes do): started with them, it waits.
    """
    deadline = time.monotonic() + timeout
    next_note = time.monotonic()
    while (problem := database_state(settings.sqlalchemy_url)) is not None:
        now = time.monotonic()
        if now >= deadline:
            raise DatabaseNotReadyError(f"gave up after waiting {timeout:g} s: {problem}")
        if now >= next_note:
            next_note = now + DATABASE_WAIT_LOG_SECONDS
            logger.warning(
                "waiting for the database: %s", problem, extra={"stage": "waiting-for-database"}
            )
        time.sleep(min(poll_seconds, max(0.0, deadline - now)))


def worker_pid_dir(settings: Settings) -> Path:
    """Where workers note their pid (``worker-<pid>``) while alive (used by tests and ops)."""
    return settings.data_layout.run_dir


def release_inherited_connections(settings: Settings) -> None:
    """In a forked child: drop the parent's database and queue connections without closing."""
    get_engine(settings.sqlalchemy_url).dispose(close=False)
    queue.forget_queue_connections()


def install_worker_hooks(huey: Huey, settings: Settings) -> None:
    """Register start/stop hooks run inside each Huey worker process."""
    pid_dir = worker_pid_dir(settings)

    @huey.on_startup(name="scandiff_worker_started")
    def worker_started() -> None:
        # a worker may run tiles and crop passes before any job: freed temporaries leave it
        release_freed_memory_promptly()
        pid_dir.mkdir(parents=True, exist_ok=True)
        settings.data_layout.worker_pid_file(os.getpid()).touch()
        logger.info("job worker started", extra={"stage": "worker-started"})

    @huey.pre_execute(name="scandiff_bind_job")
    def bind_running_job(task: Any) -> None:
        bind_job(str(task.args[0]) if task.args else None)  # Huey's lines carry the job id

    @huey.post_execute(name="scandiff_unbind_job")
    def unbind_running_job(task: Any, task_value: Any, exception: BaseException | None) -> None:
        bind_job(None)
        return_free_heap()  # the next task (a tile sized by the budget) starts from live data

    @huey.on_shutdown(name="scandiff_worker_stopped")
    def worker_stopped() -> None:
        settings.data_layout.worker_pid_file(os.getpid()).unlink(missing_ok=True)


def remove_stale_worker_pid_files(settings: Settings) -> None:
    """Delete pid files of workers that are no longer running."""
    for pid_text, path in settings.data_layout.worker_pid_files().items():
        if not pid_text.isdigit() or not Path(f"/proc/{pid_text}").exists():
            path.unlink(missing_ok=True)


def schedule_loop(schedule_tick: Callable[[Settings], object]) -> Loop:
    """The schedule ticker's body: ``schedule_tick`` every ``schedule_tick_seconds`` until
    stopped; a failed tick is logged, never fatal."""

    def run_schedule_ticks(settings: Settings, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                schedule_tick(settings)
            except Exception:
                logger.exception("schedule tick failed", extra={"stage": "schedules"})
            stop.wait(settings.schedule_tick_seconds)

    return run_schedule_ticks


class DoorbellWorker(Worker):  # type: ignore[misc]
    """Huey's worker that sleeps on the queue's doorbell (:mod:`app.jobs.doorbell`) while idle.

    Between two empty polls it waits for a ring or its back-off delay, whichever comes first:
    a job sent to an idle worker is taken at once instead of at the next poll (up to
    ``QUEUE_POLL_MAX_DELAY_SECONDS`` later).  Without a doorbell it is Huey's worker.
    """

    def __init__(self, *args: Any, doorbell: Doorbell | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.doorbell = doorbell  # opened in the worker process, at its first sleep

    def sleep(self) -> None:
        """Wait for a ring or the back-off delay after an empty poll."""
        if self.doorbell is None or not self.doorbell.open():
            super().sleep()
            return
        # The poll just found nothing: rings waiting now were for messages already taken,
        # unless one came in since; poll once more rather than risk sleeping through it.
        if self.doorbell.drain():
            return
        self.delay = min(self.delay, self.max_delay)
        if self.stop_flag.is_set():
            return
        if self.doorbell.wait(self.delay):
            self.delay = self.default_delay
        else:
            self.delay *= self.backoff


class ScandiffConsumer(Consumer):  # type: ignore[misc]
    """Huey's consumer with process workers, SIGTERM as a graceful stop and the recovery sweep."""

    def __init__(
        self,
        huey: Huey,
        settings: Settings,
        workers: int,
        shutdown_grace_seconds: float,
        schedule_tick: Callable[[Settings], object] | None = None,
    ) -> None:
        self.settings = settings  # before Huey's __init__: it creates the workers
        super().__init__(
            huey,
            workers=workers,
            worker_type="process",
            periodic=False,
            initial_delay=0.1,
            backoff=1.15,
            max_delay=QUEUE_POLL_MAX_DELAY_SECONDS,
            scheduler_interval=1,
            check_worker_health=True,
            health_check_interval=WORKER_HEALTH_CHECK_SECONDS,
            shutdown_timeout=shutdown_grace_seconds,
        )
        # SIGTERM (what `scandiff serve` and service managers send) stops gracefully, like SIGINT;
        # a second signal interrupts at once.  Workers still treat SIGTERM as "interrupt now".
        self._signal_actions[signal.SIGTERM] = (False, True)
        self.settings = settings
        self.deliveries = delivery_process(settings)  # webhook deliveries beside the job workers
        # The schedule tick in a process of its own: a slow URL fetch never delays supervision.
        self.schedule_ticker = (
            None
            if schedule_tick is None
            else SideProcess(settings, "schedule-ticker", schedule_loop(schedule_tick))
        )
        self._next_sweep = 0.0
        self._next_alive_note = 0.0

    def _create_worker(self) -> Worker:
        """A :class:`DoorbellWorker` (listening when the queue is the SQLite file)."""
        doorbell = None
        if queue.queue_backend(self.settings) == "sqlite":
            doorbell = Doorbell(doorbell_path(self.settings.data_dir))
        return DoorbellWorker(
            huey=self.huey,
            stop_flag=self.stop_flag,
            default_delay=self.default_delay,
            max_delay=self.max_delay,
            backoff=self.backoff,
            max_tasks=self.max_tasks,
            doorbell=doorbell,
        )

    def stop(self, graceful: bool = False) -> None:
        """Huey's stop, with every idle worker woken to see the stop flag at once."""
        self.stop_flag.set()
        if queue.queue_backend(self.settings) == "sqlite":
            ring(doorbell_path(self.settings.data_dir), times=self.workers)
        super().stop(graceful)

    def loop(self, health_check_ts: float | None = None) -> float | None:
        """Huey's supervision loop, plus the recovery sweep and the liveness note when due."""
        health_check_ts = super().loop(health_check_ts)
        now = time.monotonic()
        if not self.stop_flag.is_set():
            self.deliveries.ensure_running()
            if self.schedule_ticker is not None:
                self.schedule_ticker.ensure_running()
        try:
            if now >= self._next_sweep:
                self._next_sweep = now + self.settings.recovery_interval_seconds
                self.sweep()
            if now >= self._next_alive_note:
                self._next_alive_note = now + CONSUMER_HEARTBEAT_SECONDS
                self.note_alive()
        except KeyboardInterrupt:  # a second stop signal while sweeping: stop now
            logger.info("stop requested during the recovery sweep; stopping now")
            self.stop(graceful=False)
            raise ConsumerStopped from None
        return health_check_ts

    def sweep(self) -> None:
        """Run the recovery sweep; errors are logged, never fatal."""
        try:
            recovery_sweep(self.settings)
        except Exception:
            logger.exception("recovery sweep failed", extra={"stage": "recovery"})
        finally:
            self.close_connections()

    def note_alive(self) -> None:
        """Tell ``/health`` this consumer is alive."""
        try:
            queue.note_consumer_alive(self.settings, self.workers)
        except Exception:
            logger.exception("cannot note consumer liveness in the queue")
        finally:
            self.close_connections()

    def close_connections(self) -> None:
        """Close this process's connections so workers forked later inherit none."""
        get_engine(self.settings.sqlalchemy_url).dispose()
        queue.close_queue_connections()


REGISTRATION_LIBRARIES = ("small_gicp",)
"""What the registration imports on first use (:mod:`app.core.registration`)."""


def first_use_libraries() -> tuple[str, ...]:
    """The libraries the comparison imports on its first run, not with its modules.

    The detectors' and the region clustering's (scipy.optimize, scipy.sparse.csgraph:
    :data:`app.core.detectors.LIBRARIES`) and the registration's.  The command line keeps them
    lazy, loading them on a thread while it aligns; a worker loaded them in its first job, on
    the cores the job needs.
    """
    from app.core.detectors import LIBRARIES  # loaded with the pipeline already

    return (*LIBRARIES, *REGISTRATION_LIBRARIES)


def preload_pipeline() -> None:
    """Load the comparison here once, with the libraries it would import in a worker's first
    job, so forked workers start ready (copy-on-write).  Importing starts no thread, so
    forking stays safe.  A test's stand-in comparison (:data:`app.jobs.hooks.job_hooks`) needs
    none of the libraries."""
    started = time.perf_counter()
    job_hooks.comparison()
    if job_hooks.compare is None:
        for name in first_use_libraries():
            try:
                importlib.import_module(name)
            except ImportError:  # the job that needs it reports it
                logger.warning("library not preloaded", extra={"library": name})
    logger.info("pipeline preloaded", extra={"seconds": round(time.perf_counter() - started, 2)})


def fix_job_memory_limit(settings: Settings, workers: int) -> Settings:
    """Resolve an ``auto`` memory cap and the job thread count for ``workers`` here, once.

    The values are exported as ``SCANDIFF_JOB_MEMORY_LIMIT_BYTES`` (0 = no cap) and
    ``SCANDIFF_JOB_THREADS`` before any worker is forked, since workers read their settings
    from the environment.
    """
    limit = job_memory_limit(settings, workers)
    os.environ[MEMORY_LIMIT_ENV] = str(limit or 0)
    threads = job_threads(settings, workers)  # the CPUs shared among this many workers
    os.environ[JOB_THREADS_ENV] = str(threads)
    get_settings.cache_clear()
    return settings.model_copy(update={"job_memory_limit_bytes": limit, "job_threads": threads})


def run_consumer(
    settings: Settings,
    workers: int | None = None,
    shutdown_grace_seconds: float | None = None,
    *,
    wait_for_database_seconds: float | None = None,
    schedule_tick: Callable[[Settings], object] | None = None,
) -> int:
    """Run the consumer until SIGTERM/SIGINT; the exit status.

    ``shutdown_grace_seconds`` None takes ``settings.shutdown_grace_seconds``.  With
    ``wait_for_database_seconds`` it first waits that long for a migrated database.
    ``schedule_tick`` (the service layer's :func:`app.services.schedules.runs.tick`, passed by
    the commands that start consumers) runs every ``schedule_tick_seconds`` in this process.
    """
    configure_process_logging(settings.log_level, settings.log_format)
    if shutdown_grace_seconds is None:
        shutdown_grace_seconds = settings.shutdown_grace_seconds
    if wait_for_database_seconds is not None:
        wait_for_database_at_head(settings, wait_for_database_seconds)
    preload_pipeline()
    workers = workers or settings.workers
    settings = fix_job_memory_limit(settings, workers)
    runner.install()  # this process's run_job messages run jobs (inherited by forked workers)
    huey = queue.get_huey(settings)
    install_worker_hooks(huey, settings)
    remove_stale_worker_pid_files(settings)

    def after_fork_in_child() -> None:
        set_parent_death_signal(signal.SIGKILL)  # workers and scheduler never outlive us
        release_inherited_connections(settings)

    os.register_at_fork(after_in_child=after_fork_in_child)
    logger.info(
        "job consumer starting",
        extra={
            "workers": workers,
            "queue": queue.queue_backend(settings),
            "job_memory_limit_bytes": settings.job_memory_limit_bytes,
            "job_threads": settings.job_threads,
            "shutdown_grace_seconds": shutdown_grace_seconds,
        },
    )
    consumer = ScandiffConsumer(
        huey, settings, workers, shutdown_grace_seconds, schedule_tick=schedule_tick
    )
    try:
        consumer.run()
    finally:
        consumer.stop_flag.set()  # idle workers exit by themselves even if run() failed
        consumer.deliveries.stop(timeout=settings.webhook_timeout_seconds + 1.0)
        if consumer.schedule_ticker is not None:
            consumer.schedule_ticker.stop(timeout=settings.schedule_fetch_timeout_seconds + 1.0)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m app.jobs.consumer [--workers N]``: settings from ``SCANDIFF_*``."""
    parser = argparse.ArgumentParser(description="Run scandiff job workers.")
    parser.add_argument("--workers", type=int, default=None, help="worker processes")
    parser.add_argument(
        "--shutdown-grace",
        type=float,
        default=None,
        help="seconds running jobs may take to finish on SIGTERM/SIGINT before being handed back",
    )
    args = parser.parse_args(argv)
    die_with_supervisor()
    return run_consumer(get_settings(), args.workers, args.shutdown_grace)


if __name__ == "__main__":
    sys.exit(main())
