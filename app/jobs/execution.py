"""Running one job durably: claim, heartbeat, compute outside any transaction, store once.

The ``job`` table is the truth; a queue message only says "look at job X".  A worker:

1. **claims** the job with one conditional ``UPDATE`` (``status='queued'``, or ``'running'`` with
   an expired lease, and ``attempts < max_attempts``) that increments ``attempts`` and takes a
   lease (``lease_owner``, ``lease_expires_at``).  A duplicate message for a finished job or a
   job leased by a live worker changes nothing;
2. keeps the lease alive from a **heartbeat** thread that also writes ``progress``/``stage``; if
   the lease was taken over, the job is abandoned at the next progress report and never stored;
3. reads the scans and runs ``compare`` **outside any transaction**, under an ``RLIMIT_AS``
   cap (by default derived from the machine's memory and the number of workers:
   :func:`default_memory_limit`);
4. writes ``results/<job_id>/labels.npz`` and ``details.npz`` **atomically** (temp, fsync,
   rename);
5. stores score, decision, regions, registration and timings in **one short transaction**, only
   if it still holds the lease.

Input problems (:class:`app.core.errors.InputError`) fail the job at once with the message; other
errors put it back in the queue until ``max_attempts`` is reached.  Test hooks (env
``SCANDIFF_TEST_JOB_HOOKS``) are honoured only when ``SCANDIFF_TESTING=1``; see
:func:`apply_test_hooks`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import resource
import signal
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import ColumnElement, and_, delete, or_, select, update

from app.clock import utc_now
from app.config import GIB, Settings
from app.core.errors import InputError
from app.core.jsonable import json_safe
from app.db.models import Job, JobStatus, Region, Scan
from app.db.session import transaction

logger = logging.getLogger("scandiff.jobs")

TESTING_ENV = "SCANDIFF_TESTING"
TEST_HOOKS_ENV = "SCANDIFF_TEST_JOB_HOOKS"
LABELS_FILENAME = "labels.npz"
DETAILS_FILENAME = "details.npz"
TEMP_MARKER = ".tmp"
MIN_HEARTBEAT_SPACING_SECONDS = 0.2
"""Stage changes wake the heartbeat early, but never write more often than this."""

# Share of the job's progress bar before and after ``compare``.
PROGRESS_LOADED = 0.05
PROGRESS_COMPARED = 0.95


class LeaseLostError(RuntimeError):
    """Another worker took this job over (our lease expired); abandon it without writing."""


def make_lease_owner() -> str:
    """A lease-owner name for this worker attempt: ``host:pid:random``."""
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"


def lease_owner_pid(lease_owner: str | None) -> int | None:
    """The process id inside a lease-owner name (None if not of the form ``host:pid:random``)."""
    if not lease_owner:
        return None
    parts = lease_owner.rsplit(":", 2)
    return int(parts[1]) if len(parts) == 3 and parts[1].isdigit() else None


def lease_owner_is_dead_here(lease_owner: str | None) -> bool:
    """Whether ``lease_owner`` names a process of this host that no longer runs.

    Lets the sweep recover a crashed local worker's job without waiting for its lease.  Only a
    definite "no such process" counts: a reused pid reads as alive (then the lease decides).
    """
    if not lease_owner:
        return False
    host, _, _ = lease_owner.rpartition(":")
    host, _, pid_text = host.rpartition(":")
    if host != socket.gethostname() or not pid_text.isdigit():
        return False
    pid = int(pid_text)
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    try:  # a zombie (killed, not yet reaped by its parent) is dead too
        with open(f"/proc/{pid}/stat") as stat_file:
            stat = stat_file.read()
        return stat[stat.rindex(")") + 2 :].split()[0] in ("Z", "X")
    except OSError:
        return False


def claimable(now: datetime) -> ColumnElement[bool]:
    """SQL condition: the job may be taken (queued, or running with an expired lease)."""
    return or_(
        Job.status == JobStatus.QUEUED,
        and_(
            Job.status == JobStatus.RUNNING,
            or_(Job.lease_expires_at.is_(None), Job.lease_expires_at < now),
        ),
    )


def held_by(job_id: str, owner: str) -> ColumnElement[bool]:
    """SQL condition: job ``job_id`` is running under ``owner``'s lease."""
    return and_(Job.id == job_id, Job.status == JobStatus.RUNNING, Job.lease_owner == owner)


@dataclass(frozen=True)
class ClaimedJob:
    """What a worker needs to run a job it has claimed."""

    id: str
    attempt: int
    max_attempts: int
    lease_owner: str
    method: str
    variant: str
    params: dict[str, Any]
    reference_path: Path | None
    reference_format: str | None
    scan_path: Path | None
    scan_format: str | None
    scan_filename: str | None
    reference_sensor_origin: list[float] | None = None
    scan_sensor_origin: list[float] | None = None


def job_log(message: str, job_id: str, stage: str, **fields: Any) -> None:
    """One structured log line about a job stage."""
    logger.info(message, extra={"job_id": job_id, "stage": stage, **fields})


def claim_job(
    job_id: str, settings: Settings, owner: str, now: datetime | None = None
) -> ClaimedJob | None:
    """Atomically take job ``job_id`` for ``owner``; None if it needs no run (or is used up)."""
    now = now or utc_now()
    lease_until = now + timedelta(seconds=settings.job_lease_seconds)
    with transaction(settings.sqlalchemy_url) as session:
        claimed = session.execute(
            update(Job)
            .where(Job.id == job_id, Job.attempts < Job.max_attempts, claimable(now))
            .values(
                status=JobStatus.RUNNING,
                attempts=Job.attempts + 1,
                lease_owner=owner,
                lease_expires_at=lease_until,
                started_at=now,
                finished_at=None,
                stage="claimed",
                progress=0.0,
            )
            .execution_options(synchronize_session=False)
        ).rowcount
        job = session.get(Job, job_id, populate_existing=True)
        if job is None:
            logger.warning("job not found", extra={"job_id": job_id, "stage": "skipped"})
            return None
        if not claimed:
            give_up_if_used_up(session, job, now)
            return None
        reference = session.get(Scan, job.reference_scan_id)
        scan = session.get(Scan, job.scan_id)
        claimed_job = ClaimedJob(
            id=job.id,
            attempt=job.attempts,
            max_attempts=job.max_attempts,
            lease_owner=owner,
            method=job.method,
            variant=job.variant,
            params=dict(job.params or {}),
            reference_path=settings.data_dir / reference.storage_path if reference else None,
            reference_format=reference.format if reference else None,
            scan_path=settings.data_dir / scan.storage_path if scan else None,
            scan_format=scan.format if scan else None,
            scan_filename=scan.filename if scan else None,
            reference_sensor_origin=reference.sensor_origin if reference else None,
            scan_sensor_origin=scan.sensor_origin if scan else None,
        )
    job_log(
        "job claimed",
        job_id,
        "claimed",
        attempt=claimed_job.attempt,
        max_attempts=claimed_job.max_attempts,
        lease_owner=owner,
    )
    return claimed_job


def give_up_if_used_up(session: Any, job: Job, now: datetime) -> bool:
    """Inside a claim: fail a claimable job whose attempts are used up; True if it did."""
    reason = (
        f"gave up after {job.attempts} attempts (max_attempts={job.max_attempts}): "
        f"{job.error or 'each attempt stopped without finishing (worker killed or lost)'}"
    )
    failed = session.execute(
        update(Job)
        .where(Job.id == job.id, Job.attempts >= Job.max_attempts, claimable(now))
        .values(
            status=JobStatus.FAILED,
            error=reason,
            stage="failed",
            finished_at=now,
            lease_expires_at=None,
        )
        .execution_options(synchronize_session=False)
    ).rowcount
    if failed:
        job_log("job failed", job.id, "failed", attempt=job.attempts, error=reason)
    else:
        logger.info(
            "job message ignored (duplicate, finished or leased elsewhere)",
            extra={"job_id": job.id, "stage": "skipped", "status": job.status},
        )
    return bool(failed)


class LeaseKeeper:
    """Heartbeat thread: extends the lease and writes progress/stage; notices a lost lease."""

    def __init__(self, job: ClaimedJob, settings: Settings) -> None:
        self.job = job
        self.settings = settings
        self.stage = "claimed"
        self.progress = 0.0
        self.lost = threading.Event()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"lease-{job.id[:8]}", daemon=True)

    def start(self) -> LeaseKeeper:
        """Start heart-beating."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop heart-beating (idempotent)."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()

    def check(self) -> None:
        """Raise :class:`LeaseLostError` if another worker took the job over."""
        if self.lost.is_set():
            raise LeaseLostError(f"job {self.job.id}: lease of {self.job.lease_owner} was lost")

    def report(self, stage: str, progress: float) -> None:
        """Note the job's stage and overall progress (0..1); logs each new stage once."""
        self.check()
        progress = min(max(float(progress), 0.0), 1.0)
        if stage != self.stage:
            self.stage = stage
            self.progress = progress
            job_log(
                "job stage",
                self.job.id,
                stage,
                attempt=self.job.attempt,
                progress=round(progress, 3),
            )
            self._wake.set()
        else:
            self.progress = progress

    def compare_progress(self, stage: str, fraction: float) -> None:
        """``compare``'s progress callback, mapped into the compare share of the job."""
        fraction = min(max(float(fraction), 0.0), 1.0)
        self.report(stage, PROGRESS_LOADED + (PROGRESS_COMPARED - PROGRESS_LOADED) * fraction)

    def beat(self) -> bool:
        """Extend the lease and store progress once; False if the lease is no longer ours."""
        now = utc_now()
        with transaction(self.settings.sqlalchemy_url) as session:
            updated = session.execute(
                update(Job)
                .where(held_by(self.job.id, self.job.lease_owner))
                .values(
                    lease_expires_at=now + timedelta(seconds=self.settings.job_lease_seconds),
                    progress=self.progress,
                    stage=self.stage[:32],
                )
                .execution_options(synchronize_session=False)
            ).rowcount
        return bool(updated)

    def _run(self) -> None:
        """Beat every ``job_heartbeat_seconds`` (sooner on a stage change) until stopped."""
        interval = self.settings.job_heartbeat_seconds
        while not self._stop.is_set():
            self._wake.wait(interval)
            self._wake.clear()
            if self._stop.is_set():
                return
            try:
                if not self.beat():
                    self.lost.set()
                    logger.warning(
                        "job lease lost; abandoning this attempt",
                        extra={"job_id": self.job.id, "stage": "lease-lost"},
                    )
                    return
            except Exception:  # a failed beat is retried; the lease covers several intervals
                logger.exception(
                    "job heartbeat failed", extra={"job_id": self.job.id, "stage": self.stage}
                )
            self._stop.wait(MIN_HEARTBEAT_SPACING_SECONDS)


MEMORY_SHARE = 0.75
"""Share of the machine's memory the workers' caps add up to by default (the rest: the API,
the consumer, the page cache)."""
MEMORY_LIMIT_CEILING_BYTES = 8 * GIB
"""Largest default cap: a 5M-point pair peaks at 4.1 GiB of address space (docs/jobs.md), the
rest is room for the thread stacks and malloc arenas of BLAS threads on many-core machines."""
MEMORY_LIMIT_FLOOR_BYTES = 1 * GIB
"""Smallest default cap: an idle worker with the pipeline loaded already maps ~0.35 GiB."""
_CGROUP_MEMORY_FILES = (
    Path("/sys/fs/cgroup/memory.max"),  # cgroup v2
    Path("/sys/fs/cgroup/memory/memory.limit_in_bytes"),  # cgroup v1
)


def cgroup_memory_limit() -> int | None:
    """The memory limit of this process's container (cgroup), or None when there is none."""
    for path in _CGROUP_MEMORY_FILES:
        try:
            text = path.read_text().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < 2**60:  # v1 says "no limit" with a huge number
            return int(text)
    return None


def machine_memory_bytes() -> int | None:
    """Physical memory, or the container's memory limit when lower; None if unknown."""
    try:
        physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError):
        physical = 0
    limits = [value for value in (physical, cgroup_memory_limit()) if value and value > 0]
    return min(limits) if limits else None


def default_memory_limit(workers: int, memory_bytes: int | None = None) -> int | None:
    """The default job cap: 75 % of the memory shared by ``workers``, within 1 to 8 GiB."""
    memory = machine_memory_bytes() if memory_bytes is None else memory_bytes
    if not memory:
        return None
    share = int(memory * MEMORY_SHARE / max(workers, 1))
    return max(MEMORY_LIMIT_FLOOR_BYTES, min(MEMORY_LIMIT_CEILING_BYTES, share))


def job_memory_limit(settings: Settings, workers: int | None = None) -> int | None:
    """The ``RLIMIT_AS`` of a job in bytes: the setting, or the default when it is ``auto``."""
    configured = settings.job_memory_limit_bytes
    if configured == "auto":
        return default_memory_limit(workers or settings.workers)
    return configured if isinstance(configured, int) and configured > 0 else None


def job_threads(settings: Settings, workers: int | None = None) -> int:
    """Threads a job may use: the setting, else this machine's CPUs shared by the workers."""
    if settings.job_threads:
        return settings.job_threads
    from app.core.threads import usable_cpus  # the numeric core is imported lazily here

    return max(1, usable_cpus() // max(workers or settings.workers, 1))


@contextmanager
def memory_limit(limit_bytes: int | None) -> Iterator[None]:
    """Cap this process's address space (RLIMIT_AS) at ``limit_bytes`` while inside."""
    if not limit_bytes:
        yield
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    capped = limit_bytes if hard == resource.RLIM_INFINITY else min(limit_bytes, hard)
    resource.setrlimit(resource.RLIMIT_AS, (capped, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def testing_enabled() -> bool:
    """Whether test hooks are honoured (env ``SCANDIFF_TESTING=1``; never set in production)."""
    return os.environ.get(TESTING_ENV) == "1"


def test_hooks_for(job: ClaimedJob) -> dict[str, Any]:
    """The test hooks that apply to ``job`` (empty unless ``SCANDIFF_TESTING=1``)."""
    raw = os.environ.get(TEST_HOOKS_ENV)
    if not raw:
        return {}
    if not testing_enabled():
        logger.warning(
            f"{TEST_HOOKS_ENV} is set but {TESTING_ENV} is not 1; ignoring the test hooks",
            extra={"job_id": job.id, "stage": "claimed"},
        )
        return {}
    hooks = json.loads(raw)
    if "scan_filename" in hooks and hooks["scan_filename"] != job.scan_filename:
        return {}
    on_attempts = hooks.get("on_attempts")
    if on_attempts is not None and job.attempt not in on_attempts:
        return {}
    return dict(hooks)


def apply_test_hooks(job: ClaimedJob, keeper: LeaseKeeper) -> None:
    """Test-only behaviour from the JSON object in env ``SCANDIFF_TEST_JOB_HOOKS``.

    Honoured only when ``SCANDIFF_TESTING=1`` (set by the test harness, never in production).
    Filters: ``scan_filename`` (only jobs whose scan has that filename), ``on_attempts`` (list
    of attempt numbers).  Actions, in this order: ``sleep_seconds`` (sleep while heart-beating,
    stage ``testing-sleep``), ``allocate_bytes`` (allocate that much: hits the memory cap),
    ``kill_worker`` (SIGKILL this worker process: a crash), ``raise_error`` (raise
    ``RuntimeError`` with that message: a transient failure).
    """
    hooks = test_hooks_for(job)
    if not hooks:
        return
    sleep_seconds = float(hooks.get("sleep_seconds", 0.0))
    if sleep_seconds > 0:
        deadline = time.monotonic() + sleep_seconds
        while (remaining := deadline - time.monotonic()) > 0:
            keeper.report("testing-sleep", PROGRESS_LOADED * (1 - remaining / sleep_seconds))
            time.sleep(min(0.05, remaining))
    if hooks.get("allocate_bytes"):
        ballast = np.ones(int(hooks["allocate_bytes"]), dtype=np.uint8)
        del ballast
    if hooks.get("kill_worker"):
        job_log("test hook: killing this worker", job.id, "testing-kill", attempt=job.attempt)
        logging.shutdown()
        os.kill(os.getpid(), signal.SIGKILL)
    if hooks.get("raise_error"):
        raise RuntimeError(str(hooks["raise_error"]))


def fsync_directory(directory: Path) -> None:
    """Make a rename inside ``directory`` durable."""
    descriptor = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def write_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(temp_path)`` next to ``path``, fsync it, then rename it over ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # Keep the suffix last: numpy appends ".npz" to names not ending with it.
    temp_path = path.with_name(f".{path.stem}.{uuid.uuid4().hex}{TEMP_MARKER}{path.suffix}")
    try:
        write(temp_path)
        with open(temp_path, "rb+") as written:
            os.fsync(written.fileno())
        os.replace(temp_path, path)
    finally:
        temp_path.unlink(missing_ok=True)
    fsync_directory(path.parent)


def job_results_dir(settings: Settings, job_id: str) -> Path:
    """Where the per-point files of job ``job_id`` live."""
    return settings.results_dir / job_id


def compute(
    job: ClaimedJob, settings: Settings, keeper: LeaseKeeper
) -> tuple[Any, dict[str, float]]:
    """Read both scans and run ``compare``; the result and this job's own timings."""
    from app.core.allocator import release_freed_memory_promptly
    from app.core.formats import read_point_cloud
    from app.core.pipeline import compare

    release_freed_memory_promptly()  # freed temporaries go back to the system: peak = live data
    apply_test_hooks(job, keeper)
    if job.reference_path is None or job.scan_path is None:
        raise InputError("the job's reference scan or scan no longer exists")
    keeper.report("loading", 0.0)
    started = time.perf_counter()
    threads = job_threads(settings)  # the result does not depend on it
    reference = read_point_cloud(job.reference_path, format=job.reference_format, threads=threads)
    scan = read_point_cloud(job.scan_path, format=job.scan_format, threads=threads)
    # The origin given at upload wins over the file's; a job's params override both.
    if job.reference_sensor_origin is not None:
        reference = dataclasses.replace(
            reference, sensor_origin=np.asarray(job.reference_sensor_origin, dtype=np.float64)
        )
    if job.scan_sensor_origin is not None:
        scan = dataclasses.replace(
            scan, sensor_origin=np.asarray(job.scan_sensor_origin, dtype=np.float64)
        )
    load_seconds = time.perf_counter() - started
    keeper.report("comparing", PROGRESS_LOADED)
    result = compare(
        reference,
        scan,
        method=job.method,
        variant=job.variant,
        params=job.params,  # replayable: holds align/random_state/stage parameters when given
        progress=keeper.compare_progress,
        threads=threads,
    )
    return result, {"load_inputs": load_seconds}


def write_result_files(job: ClaimedJob, settings: Settings, result: Any) -> str:
    """Write ``labels.npz`` and ``details.npz`` atomically; the labels path relative to data_dir."""
    directory = job_results_dir(settings, job.id)
    labels_path = directory / LABELS_FILENAME
    write_atomically(labels_path, result.write_labels_npz)
    write_atomically(
        directory / DETAILS_FILENAME,
        lambda path: np.savez(
            path,
            reference_distance=np.asarray(result.reference_distance, dtype=np.float32),
            scan_distance=np.asarray(result.scan_distance, dtype=np.float32),
        ),
    )
    return labels_path.relative_to(settings.data_dir).as_posix()


def store_results(
    job: ClaimedJob, settings: Settings, result: Any, labels_path: str, timings: dict[str, float]
) -> bool:
    """One short transaction: results and Region rows, only if the lease is still ours."""
    with transaction(settings.sqlalchemy_url) as session:
        row = session.execute(
            select(Job).where(held_by(job.id, job.lease_owner)).with_for_update()
        ).scalar_one_or_none()
        if row is None:
            return False
        session.execute(delete(Region).where(Region.job_id == job.id))
        session.add_all(
            Region(
                job_id=job.id,
                ordinal=ordinal,
                kind=str(region.kind),
                n_points=int(region.n_points),
                centroid=json_safe(list(region.centroid)),
                bbox_min=json_safe(list(region.bbox_min)),
                bbox_max=json_safe(list(region.bbox_max)),
                mean_distance=float(region.mean_distance),
                max_distance=float(region.max_distance),
            )
            for ordinal, region in enumerate(result.regions)
        )
        row.status = JobStatus.SUCCEEDED
        row.score = float(result.score)
        row.threshold = float(result.threshold)
        row.changed = bool(result.changed)
        row.calibration = json_safe(result.calibration)
        row.effective_params = json_safe(getattr(result, "params", None))
        row.registration = json_safe(result.registration)
        row.n_regions = len(result.regions)
        row.timings = json_safe(timings)
        row.labels_path = labels_path
        row.error = None
        row.progress = 1.0
        row.stage = "succeeded"
        row.finished_at = utc_now()
        row.lease_expires_at = None
    return True


def fail_job(job: ClaimedJob, settings: Settings, message: str) -> bool:
    """Mark the job ``failed`` with ``message`` if we still hold it; True if we did."""
    with transaction(settings.sqlalchemy_url) as session:
        failed = session.execute(
            update(Job)
            .where(held_by(job.id, job.lease_owner))
            .values(
                status=JobStatus.FAILED,
                error=message,
                stage="failed",
                finished_at=utc_now(),
                lease_expires_at=None,
            )
            .execution_options(synchronize_session=False)
        ).rowcount
    if failed:
        job_log("job failed", job.id, "failed", attempt=job.attempt, error=message)
    return bool(failed)


def release_job(job: ClaimedJob, settings: Settings, error: str, *, count_attempt: bool) -> str:
    """Give the job back (``queued``) or fail it when attempts are used up; the new status.

    ``count_attempt=False`` (shutdown interrupted the attempt) does not use up an attempt and
    leaves ``enqueued_at`` empty so the next recovery sweep sends the message again.
    """
    with transaction(settings.sqlalchemy_url) as session:
        row = session.execute(
            select(Job).where(held_by(job.id, job.lease_owner)).with_for_update()
        ).scalar_one_or_none()
        if row is None:
            return "lease-lost"
        if count_attempt and row.attempts >= row.max_attempts:
            row.status = JobStatus.FAILED
            row.error = f"failed after {row.attempts} attempts; last error: {error}"
            row.finished_at = utc_now()
            row.stage = "failed"
        else:
            row.status = JobStatus.QUEUED
            row.error = error
            row.stage = "requeued"
            row.enqueued_at = utc_now() if count_attempt else None
            if not count_attempt:
                row.attempts = max(0, row.attempts - 1)
        row.lease_owner = None
        row.lease_expires_at = None
        status = row.status
        final_error = row.error
    job_log(f"job {status}", job.id, status, attempt=job.attempt, error=final_error)
    return status


def execute_job(job_id: str, settings: Settings) -> str:
    """Run job ``job_id`` once if it needs running; the outcome.

    Outcomes: ``succeeded``, ``failed``, ``queued`` (retried later), ``skipped`` (duplicate
    message, finished or leased elsewhere), ``lease-lost`` (taken over; nothing written).
    """
    owner = make_lease_owner()
    job = claim_job(job_id, settings, owner)
    if job is None:
        return "skipped"
    keeper = LeaseKeeper(job, settings).start()
    started = time.perf_counter()
    limit_bytes = job_memory_limit(settings)
    try:
        with memory_limit(limit_bytes):
            result, job_timings = compute(job, settings, keeper)
            keeper.report("writing", PROGRESS_COMPARED)
            write_started = time.perf_counter()
            labels_path = write_result_files(job, settings, result)
            job_timings["write_outputs"] = time.perf_counter() - write_started
        keeper.report("storing", PROGRESS_COMPARED)
        keeper.stop()
        keeper.check()
        job_timings["job_total"] = time.perf_counter() - started
        timings = {**dict(result.timings), **job_timings}
        if not store_results(job, settings, result, labels_path, timings):
            job_log("job lease lost before storing; nothing stored", job.id, "lease-lost")
            return "lease-lost"
        job_log(
            "job succeeded",
            job.id,
            "succeeded",
            attempt=job.attempt,
            seconds=round(job_timings["job_total"], 3),
            n_regions=len(result.regions),
            changed=bool(result.changed),
        )
        return "succeeded"
    except LeaseLostError:
        job_log("job lease lost; nothing stored", job.id, "lease-lost", attempt=job.attempt)
        return "lease-lost"
    except InputError as exc:
        keeper.stop()
        return "failed" if fail_job(job, settings, str(exc)) else "lease-lost"
    except MemoryError:
        keeper.stop()
        message = (
            f"out of memory: the job needs more than the worker's memory cap "
            f"(SCANDIFF_JOB_MEMORY_LIMIT_BYTES={limit_bytes})"
            if limit_bytes
            else "out of memory"
        )
        return "failed" if fail_job(job, settings, message) else "lease-lost"
    except KeyboardInterrupt:
        keeper.stop()
        release_job(job, settings, "interrupted by a worker shutdown", count_attempt=False)
        raise
    except Exception as exc:
        keeper.stop()
        logger.exception("job attempt failed", extra={"job_id": job.id, "stage": keeper.stage})
        status = release_job(job, settings, f"{type(exc).__name__}: {exc}", count_attempt=True)
        if status == JobStatus.QUEUED:
            from app.jobs.queue import send_job_message

            send_job_message(job.id, settings)
        return status
    finally:
        keeper.stop()
