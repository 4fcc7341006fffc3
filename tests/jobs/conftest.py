"""Fixtures for job tests: a migrated SQLite database, scans on disk, job rows, consumers."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sqlalchemy import func, select

from app.config import Settings
from app.db.migrate import upgrade_to_head
from app.db.models import Job, Organisation, Region, Scan, Site
from app.db.session import get_engine, transaction
from app.jobs.consumer import JOB_THREADS_ENV, MEMORY_LIMIT_ENV
from tests.jobs.fake_pipeline import CONSUMER_BOOTSTRAP
from tests.service_harness import PROJECT_ROOT, pid_is_alive, process_group_members

FAST_LEASES = {
    "job_lease_seconds": 2.0,
    "job_heartbeat_seconds": 0.25,
    "recovery_interval_seconds": 0.5,
    "job_max_attempts": 3,
}
"""Short leases so that recovery after a kill takes seconds in tests."""


def settings_environment(settings: Settings) -> dict[str, str]:
    """``SCANDIFF_*`` variables reproducing ``settings`` in a child process."""
    environment = {
        "SCANDIFF_DATA_DIR": str(settings.data_dir),
        "SCANDIFF_JOB_LEASE_SECONDS": str(settings.job_lease_seconds),
        "SCANDIFF_JOB_HEARTBEAT_SECONDS": str(settings.job_heartbeat_seconds),
        "SCANDIFF_RECOVERY_INTERVAL_SECONDS": str(settings.recovery_interval_seconds),
        "SCANDIFF_JOB_MAX_ATTEMPTS": str(settings.job_max_attempts),
    }
    if settings.job_memory_limit_bytes:
        environment["SCANDIFF_JOB_MEMORY_LIMIT_BYTES"] = str(settings.job_memory_limit_bytes)
    return environment


@pytest.fixture
def job_settings(tmp_path: Path) -> Settings:
    """Settings on a fresh data dir whose database was migrated with Alembic; fast leases."""
    settings = Settings(data_dir=tmp_path / "data", **FAST_LEASES)
    settings.data_dir.mkdir(parents=True)
    upgrade_to_head(settings.sqlalchemy_url)
    yield settings
    get_engine(settings.sqlalchemy_url).dispose()


@pytest.fixture
def without_consumer_exports(monkeypatch: pytest.MonkeyPatch) -> None:
    """Neither the memory cap nor the thread count in the environment, and none left after.

    ``fix_job_memory_limit`` exports both; ``monkeypatch.delenv`` of an absent variable records
    nothing to undo, so each is set first and the teardown restores the original state.
    """
    for name in (MEMORY_LIMIT_ENV, JOB_THREADS_ENV):
        monkeypatch.setenv(name, "")
        monkeypatch.delenv(name)


def corridor_points(n_points: int, *, added_box: bool, seed: int) -> np.ndarray:
    """Points on two walls and a ceiling; with ``added_box``, a box near x = 1.5."""
    rng = np.random.default_rng(seed)
    y = rng.uniform(-2, 2, n_points)
    z = rng.uniform(0, 2, n_points)
    x = np.where(rng.random(n_points) < 0.5, -1.0, 1.0) + rng.normal(0, 0.005, n_points)
    points = np.column_stack([x, y, z])
    if added_box:
        box = rng.uniform([1.2, -0.3, 0.0], [1.8, 0.3, 0.6], (n_points // 10, 3))
        points = np.vstack([points, box])
    return points


def write_scan_file(settings: Settings, name: str, points: np.ndarray) -> str:
    """Store ``points`` as an NPY scan file; its path relative to the data dir."""
    relative = f"scans/{name}"
    path = settings.data_dir / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, points)
    return relative


def create_job(
    settings: Settings,
    *,
    scan_filename: str = "scan.npy",
    n_points: int = 2000,
    params: dict[str, Any] | None = None,
    max_attempts: int | None = None,
    scan_bytes: bytes | None = None,
) -> str:
    """Insert organisation, site, reference and scan (files on disk) and a queued job; its id."""
    with transaction(settings.sqlalchemy_url) as session:
        organisation = session.scalar(select(Organisation).where(Organisation.name == "tests"))
        if organisation is None:
            organisation = Organisation(name="tests")
            session.add(organisation)
            session.flush()
        site = Site(organisation_id=organisation.id, name=f"site-{os.urandom(4).hex()}")
        session.add(site)
        session.flush()
        scans = []
        for role, added in (("reference", False), ("scan", True)):
            points = corridor_points(n_points, added_box=added, seed=len(role))
            scan = Scan(
                organisation_id=organisation.id,
                site_id=site.id,
                filename=scan_filename if role == "scan" else "reference.npy",
                format="npy",
                size_bytes=int(points.nbytes),
                sha256="0" * 64,
                storage_path="",
                n_points=len(points),
                bbox_min=points.min(axis=0).tolist(),
                bbox_max=points.max(axis=0).tolist(),
            )
            session.add(scan)
            session.flush()
            scan.storage_path = write_scan_file(settings, f"{scan.id}.npy", points)
            if role == "scan" and scan_bytes is not None:
                (settings.data_dir / scan.storage_path).write_bytes(scan_bytes)
            scans.append(scan)
        job = Job(
            organisation_id=organisation.id,
            site_id=site.id,
            reference_scan_id=scans[0].id,
            scan_id=scans[1].id,
            method="gmm",
            variant="improved",
            params=params or {},
            status="queued",
            max_attempts=max_attempts or settings.job_max_attempts,
        )
        session.add(job)
        session.flush()
        return job.id


def load_job(settings: Settings, job_id: str) -> Job:
    """The job row as stored now."""
    with transaction(settings.sqlalchemy_url) as session:
        job = session.get(Job, job_id)
        assert job is not None
        session.expunge(job)
        return job


def count_regions(settings: Settings, job_id: str) -> int:
    """How many Region rows job ``job_id`` has."""
    with transaction(settings.sqlalchemy_url) as session:
        return int(session.scalar(select(func.count()).where(Region.job_id == job_id)) or 0)


def wait_for_status(
    settings: Settings, job_id: str, statuses: tuple[str, ...], timeout: float = 30.0
) -> Job:
    """Poll the job row until its status is one of ``statuses``."""
    deadline = time.monotonic() + timeout
    job = load_job(settings, job_id)
    while time.monotonic() < deadline:
        job = load_job(settings, job_id)
        if job.status in statuses:
            return job
        time.sleep(0.05)
    raise TimeoutError(
        f"job {job_id} still {job.status} ({job.stage}, {job.error}) after {timeout}s"
    )


class ConsumerProcess:
    """``python -m app.jobs.consumer`` (optionally with the fake pipeline) in its own group."""

    def __init__(
        self,
        settings: Settings,
        *,
        workers: int = 1,
        env: dict[str, str] | None = None,
        fake_pipeline: bool = True,
        shutdown_grace_seconds: float = 10.0,
        log_path: Path,
    ) -> None:
        self.settings = settings
        self.workers = workers
        self.log_path = log_path
        environment = dict(os.environ)
        environment.update(settings_environment(settings))
        environment.update({"SCANDIFF_TESTING": "1", "OMP_NUM_THREADS": "1"})
        environment.update(env or {})
        code = (
            CONSUMER_BOOTSTRAP
            if fake_pipeline
            else "import sys; from app.jobs.consumer import main; sys.exit(main())"
        )
        with open(log_path, "ab") as log_file:
            self.process = subprocess.Popen(
                [
                    sys.executable,
                    "-c",
                    code,
                    "--workers",
                    str(workers),
                    "--shutdown-grace",
                    str(shutdown_grace_seconds),
                ],
                cwd=PROJECT_ROOT,
                env=environment,
                stdout=log_file,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

    def worker_pids(self) -> list[int]:
        """Live worker processes of this consumer."""
        members = set(process_group_members(self.process.pid))
        run_dir = self.settings.data_dir / "run"
        pids = (
            [int(path.name.split("-")[1]) for path in run_dir.glob("worker-*")]
            if run_dir.is_dir()
            else []
        )
        return sorted(pid for pid in pids if pid in members and pid_is_alive(pid))

    def wait_for_workers(self, timeout: float = 20.0) -> list[int]:
        """Wait until all workers are up."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            pids = self.worker_pids()
            if len(pids) >= self.workers:
                return pids
            if self.process.poll() is not None:
                raise RuntimeError(f"consumer exited:\n{self.log()}")
            time.sleep(0.05)
        raise TimeoutError(f"workers not up:\n{self.log()}")

    def log(self) -> str:
        """Everything the consumer printed."""
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def stop(self, timeout: float = 20.0) -> int | None:
        """SIGTERM, wait, then SIGKILL the group."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(timeout)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait(5)
        return self.process.returncode


@pytest.fixture
def consumer_factory(
    job_settings: Settings, tmp_path: Path
) -> Iterator[Callable[..., ConsumerProcess]]:
    """Start consumers on ``job_settings`` (stopped after the test)."""
    started: list[ConsumerProcess] = []

    def make(**kwargs: Any) -> ConsumerProcess:
        consumer = ConsumerProcess(
            job_settings, log_path=tmp_path / f"consumer{len(started)}.log", **kwargs
        )
        started.append(consumer)
        return consumer

    yield make
    for consumer in started:
        consumer.stop()
