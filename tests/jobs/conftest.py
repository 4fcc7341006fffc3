"""Fixtures for job tests: a migrated SQLite database, job consumers, ``scandiff worker``
processes and a private Redis server."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from app.config import Settings
from app.db.session import get_engine
from app.jobs.consumer import JOB_THREADS_ENV, MEMORY_LIMIT_ENV
from app.testing.redis import REDIS_SERVER_ENV, RedisServer, redis_server_binary
from app.testing.service import ConsumerProcess
from tests.helpers.environment import require
from tests.helpers.jobs import FAST_LEASES
from tests.helpers.migrated_database import install_migrated_database
from tests.helpers.worker import WorkerProcess


@pytest.fixture
def job_settings(tmp_path: Path) -> Settings:
    """Settings on a fresh data dir whose database was migrated with Alembic (a copy of the
    session's migrated file); fast leases."""
    settings = Settings(data_dir=tmp_path / "data", **FAST_LEASES)
    settings.data_dir.mkdir(parents=True)
    install_migrated_database(settings.sqlalchemy_url)
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


@pytest.fixture
def consumer_factory(
    job_settings: Settings, tmp_path: Path
) -> Iterator[Callable[..., ConsumerProcess]]:
    """Start consumers on ``job_settings`` (killed after the test: the tests that check a
    graceful stop call ``stop()`` themselves)."""
    started: list[ConsumerProcess] = []

    def make(**kwargs: Any) -> ConsumerProcess:
        consumer = ConsumerProcess(
            job_settings, log_path=tmp_path / f"consumer{len(started)}.log", **kwargs
        )
        started.append(consumer)
        return consumer

    yield make
    for consumer in started:
        consumer.kill()


@pytest.fixture
def worker_factory(tmp_path: Path) -> Iterator[Callable[..., WorkerProcess]]:
    """Start ``scandiff worker`` processes: ``worker_factory(settings, concurrency=1, ...)``;
    killed after the test (the tests that check a graceful stop call ``terminate()``)."""
    started: list[WorkerProcess] = []

    def make(settings: Settings, **kwargs: Any) -> WorkerProcess:
        worker = WorkerProcess(settings, log_path=tmp_path / f"worker{len(started)}.log", **kwargs)
        started.append(worker)
        return worker

    yield make
    for worker in started:
        worker.kill()


@pytest.fixture
def redis_server(tmp_path: Path) -> Iterator[RedisServer]:
    """A private redis-server on a free port (never the shared one), stopped after the test."""
    binary = redis_server_binary()
    if binary is None and os.environ.get("CI") == "true":
        pytest.fail(f"redis-server is required in CI (PATH or ${REDIS_SERVER_ENV})")
    require(binary is not None, f"redis-server not found (PATH or ${REDIS_SERVER_ENV})")
    assert binary is not None
    server = RedisServer(binary, tmp_path / "redis").start()
    yield server
    server.kill()


@pytest.fixture
def redis_settings(job_settings: Settings, redis_server: RedisServer) -> Settings:
    """``job_settings`` with the private Redis as the queue (``SCANDIFF_QUEUE_URL``)."""
    return job_settings.model_copy(update={"queue_url": redis_server.url})
