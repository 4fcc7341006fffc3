"""The Huey instance for the configured backend, its two tasks, enqueueing and health.

The queue only carries job ids; the ``job`` table is the truth (see ``docs/jobs.md``).  By default
the queue is a SQLite file in the data directory (``SqliteHuey``, no server); a ``redis://`` (or
``rediss://``, ``unix://``) ``SCANDIFF_QUEUE_URL`` selects ``RedisHuey`` so consumers can run on
many hosts.  One Huey instance per backend per process, each with the ``run_job``, ``run_tile``
and ``run_crop_pass`` tasks registered (no Huey retries: attempts live in the job, job_tile and
job_crop_pass tables).

The queue knows nothing of what runs on it: the task calls the runner a worker process installs
with :func:`install_job_runner` (:mod:`app.jobs.runner`); a process that only enqueues (the API)
installs none, and a message that reached such a process would fail loudly.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

from huey import Huey, RedisHuey, SqliteHuey
from sqlalchemy import update

from app.clock import utc_now
from app.config import Settings
from app.db.models import Job, JobStatus
from app.db.session import transaction
from app.jobs.doorbell import doorbell_path, ring

logger = logging.getLogger("scandiff.jobs.queue")

QUEUE_NAME = "scandiff"
JOB_TASK_NAME = "run_job"
TILE_TASK_NAME = "run_tile"
"""The second task: one tile of a job localised tile by tile (:mod:`app.jobs.tiles`)."""
CROP_PASS_TASK_NAME = "run_crop_pass"
"""The third task: one cloud's crop pass of a streamed tiled job (:mod:`app.jobs.crop_passes`)."""
SQLITE_QUEUE_TIMEOUT_SECONDS = 60.0
"""Busy timeout of the Huey SQLite queue file (Huey's default of 5 s is too short under load)."""
REDIS_URL_SCHEMES = ("redis://", "rediss://", "unix://")
REDIS_CONNECT_TIMEOUT_SECONDS = 5.0
"""How long connecting to Redis may take: an unreachable host fails an enqueue in bounded time."""
REDIS_SOCKET_TIMEOUT_SECONDS = 10.0
"""How long one Redis reply may take (longer than Huey's 1 s blocking read of an idle worker)."""
CONSUMER_HEARTBEAT_KEY = "consumer-heartbeat"
"""Huey key-value entry where consumers note they are alive (read by :func:`queue_health`)."""

_hueys: dict[tuple[str, str], Huey] = {}
_job_tasks: dict[int, Callable[..., Any]] = {}
_tile_tasks: dict[int, Callable[..., Any]] = {}
_crop_pass_tasks: dict[int, Callable[..., Any]] = {}
_hueys_lock = threading.Lock()
_job_runner: Callable[[str], object] | None = None
_tile_runner: Callable[[str, int], object] | None = None
_crop_pass_runner: Callable[[str, int], object] | None = None


def install_job_runner(runner: Callable[[str], object]) -> None:
    """Make this process's ``run_job`` messages call ``runner(job_id)`` (a worker does this)."""
    global _job_runner
    _job_runner = runner


def run_job(job_id: str) -> None:
    """The Huey task: hand job ``job_id`` to the runner this process installed."""
    if _job_runner is None:
        raise RuntimeError(
            f"job {job_id}: no job runner in this process (start a worker: scandiff worker)"
        )
    _job_runner(job_id)


def install_tile_runner(runner: Callable[[str, int], object]) -> None:
    """Make this process's ``run_tile`` messages call ``runner(job_id, tile_index)``."""
    global _tile_runner
    _tile_runner = runner


def run_tile(job_id: str, tile_index: int) -> None:
    """The Huey task: hand tile ``tile_index`` of job ``job_id`` to this process's tile runner."""
    _hand_part_to(_tile_runner, "tile", job_id, tile_index)


def install_crop_pass_runner(runner: Callable[[str, int], object]) -> None:
    """Make this process's ``run_crop_pass`` messages call ``runner(job_id, pass_index)``."""
    global _crop_pass_runner
    _crop_pass_runner = runner


def run_crop_pass(job_id: str, pass_index: int) -> None:
    """The Huey task: hand crop pass ``pass_index`` of job ``job_id`` to this process's runner."""
    _hand_part_to(_crop_pass_runner, "crop pass", job_id, pass_index)


def _hand_part_to(
    runner: Callable[[str, int], object] | None, part: str, job_id: str, index: int
) -> None:
    """Call ``runner(job_id, index)``, or say that this process installed no runner for ``part``."""
    if runner is None:
        raise RuntimeError(
            f"job {job_id} {part} {index}: no {part} runner in this process "
            "(start a worker: scandiff worker)"
        )
    runner(job_id, int(index))


def queue_backend(settings: Settings) -> str:
    """``"sqlite"`` or ``"redis"``: which Huey backend ``settings`` select."""
    url = settings.queue_url
    if not url:
        return "sqlite"
    if url.startswith(REDIS_URL_SCHEMES):
        return "redis"
    raise ValueError(
        f"unsupported SCANDIFF_QUEUE_URL {url!r}: leave it unset for the SQLite queue file in the "
        "data directory, or give redis://host:port/db"
    )


def create_huey(settings: Settings) -> Huey:
    """A new Huey instance for ``settings`` with the job task registered."""
    backend = queue_backend(settings)
    if backend == "sqlite":
        settings.queue_path.parent.mkdir(parents=True, exist_ok=True)
        huey: Huey = SqliteHuey(
            name=QUEUE_NAME,
            filename=str(settings.queue_path),
            results=False,
            utc=True,
            timeout=SQLITE_QUEUE_TIMEOUT_SECONDS,
        )
    else:
        from redis import ConnectionPool  # the optional "redis" extra, needed only here

        pool = ConnectionPool.from_url(
            settings.queue_url,
            socket_connect_timeout=REDIS_CONNECT_TIMEOUT_SECONDS,
            socket_timeout=REDIS_SOCKET_TIMEOUT_SECONDS,
        )
        huey = RedisHuey(name=QUEUE_NAME, connection_pool=pool, results=False, utc=True)
    _job_tasks[id(huey)] = huey.task(name=JOB_TASK_NAME, retries=0)(run_job)
    _tile_tasks[id(huey)] = huey.task(name=TILE_TASK_NAME, retries=0)(run_tile)
    _crop_pass_tasks[id(huey)] = huey.task(name=CROP_PASS_TASK_NAME, retries=0)(run_crop_pass)
    return huey


def _cache_key(settings: Settings) -> tuple[str, str]:
    """Identifies the queue ``settings`` point at."""
    return (settings.queue_url or "", str(settings.queue_path))


def get_huey(settings: Settings) -> Huey:
    """The process-wide Huey instance for ``settings`` (created on first use)."""
    key = _cache_key(settings)
    with _hueys_lock:
        huey = _hueys.get(key)
        if huey is None:
            huey = _hueys[key] = create_huey(settings)
        return huey


def job_task(huey: Huey) -> Callable[..., Any]:
    """The registered ``run_job`` task wrapper of ``huey``."""
    return _job_tasks[id(huey)]


def send_job_message(job_id: str, settings: Settings) -> None:
    """Put one ``run_job(job_id)`` message on the queue (no database write), then wake an idle
    worker of an SQLite queue (:mod:`app.jobs.doorbell`; a hint, the message is the record)."""
    job_task(get_huey(settings))(job_id)
    if queue_backend(settings) == "sqlite":
        ring(doorbell_path(settings.data_dir))


def send_tile_messages(job_id: str, tile_indices: list[int], settings: Settings) -> None:
    """Put one ``run_tile(job_id, i)`` message on the queue per tile, then wake idle workers of
    an SQLite queue.  A lost message costs nothing: the job's own worker takes every tile no
    other worker took (:mod:`app.jobs.tiles`)."""
    _send_part_messages(_tile_tasks, job_id, tile_indices, settings)


def send_crop_pass_messages(job_id: str, pass_indices: list[int], settings: Settings) -> None:
    """Put one ``run_crop_pass(job_id, i)`` message on the queue per pass, then wake idle
    workers of an SQLite queue.  A lost message costs nothing: the job's own worker runs every
    pass no other worker took (:mod:`app.jobs.crop_passes`)."""
    _send_part_messages(_crop_pass_tasks, job_id, pass_indices, settings)


def _send_part_messages(
    tasks: dict[int, Callable[..., Any]], job_id: str, indices: list[int], settings: Settings
) -> None:
    """Send ``task(job_id, i)`` for each index with this queue's task of ``tasks``; ring once."""
    task = tasks[id(get_huey(settings))]
    for index in indices:
        task(job_id, int(index))
    if indices and queue_backend(settings) == "sqlite":
        ring(doorbell_path(settings.data_dir))


def mark_not_enqueued(job_ids: list[str], settings: Settings) -> None:
    """Clear ``enqueued_at`` of those jobs still ``queued``: the next recovery sweep sends them
    at once instead of after its grace period (their message never reached the queue)."""
    if not job_ids:
        return
    with transaction(settings.sqlalchemy_url) as session:
        session.execute(
            update(Job)
            .where(Job.id.in_(job_ids), Job.status == JobStatus.QUEUED)
            .values(enqueued_at=None)
        )


def enqueue_job(job_id: str, settings: Settings) -> bool:
    """Queue a committed job: note ``enqueued_at`` then send its message; whether it was sent.

    Call after the transaction that created the job has committed.  If the queue cannot be
    reached (Redis down) the failure is logged, never raised: the job stays ``queued`` with
    ``enqueued_at`` cleared, and the recovery sweep of any running consumer sends it once the
    queue is back.  Duplicates are harmless because the worker's claim is idempotent.
    """
    with transaction(settings.sqlalchemy_url) as session:
        session.execute(
            update(Job)
            .where(Job.id == job_id, Job.status == JobStatus.QUEUED)
            .values(enqueued_at=utc_now())
        )
    try:
        send_job_message(job_id, settings)
    except Exception as exc:
        logger.warning(
            "job not enqueued: the queue is unreachable (%s: %s); it stays queued and the "
            "recovery sweep sends it when the queue is back",
            type(exc).__name__,
            exc,
            extra={"job_id": job_id, "stage": "enqueue-failed"},
        )
        try:
            mark_not_enqueued([job_id], settings)
        except Exception:  # the sweep still sends it, after its grace period
            logger.exception("cannot clear enqueued_at", extra={"job_id": job_id})
        return False
    logger.info("job enqueued", extra={"job_id": job_id, "stage": "enqueued"})
    return True


def pending_job_ids(settings: Settings) -> set[str]:
    """Job ids with a message waiting in the queue or its schedule."""
    huey = get_huey(settings)
    job_ids: set[str] = set()
    for task in [*huey.pending(), *huey.scheduled()]:
        if task.args and task.name.endswith(JOB_TASK_NAME):
            job_ids.add(str(task.args[0]))
    return job_ids


def note_consumer_alive(settings: Settings, workers: int) -> None:
    """Record in the queue that a consumer on this host is alive (for ``queue_health``)."""
    get_huey(settings).put(
        CONSUMER_HEARTBEAT_KEY,
        {"host": socket.gethostname(), "pid": os.getpid(), "workers": workers, "at": time.time()},
    )


def queue_health(settings: Settings) -> dict[str, Any]:
    """The queue's state for ``/health``: backend, reachability, waiting messages, consumer."""
    health: dict[str, Any] = {"backend": queue_backend(settings)}
    try:
        huey = get_huey(settings)
        health["pending"] = huey.pending_count()
        health["scheduled"] = huey.scheduled_count()
        consumer = huey.get(CONSUMER_HEARTBEAT_KEY, peek=True)
    except Exception as exc:  # health must report, never raise
        health.update(status="error", error=f"{type(exc).__name__}: {exc}")
        return health
    health["status"] = "ok"
    if consumer:
        health["consumer_last_seen_seconds"] = round(max(0.0, time.time() - consumer["at"]), 1)
        health["consumer_workers"] = consumer.get("workers")
    else:
        health["consumer_last_seen_seconds"] = None
    return health


def forget_queue_connections() -> None:
    """Drop (without closing) queue connections inherited over ``fork``."""
    for huey in list(_hueys.values()):
        storage = huey.storage
        if hasattr(storage, "_conn"):
            storage._conn = None
            storage.lock = threading.Lock()


def close_queue_connections() -> None:
    """Close this process's queue connections (before forking workers)."""
    for huey in list(_hueys.values()):
        close = getattr(huey.storage, "close", None)
        if close is not None:
            close()
