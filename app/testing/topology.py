"""The scaled-out deployment shape as real processes on this machine (issue 17, item 1).

:func:`scaled_out` starts, on one data directory:

* a private ``redis-server`` on a free port (no persistence: a restart comes back empty, as a
  Redis without a volume would; the shared one on 6379 is never touched);
* a fresh PostgreSQL database on the shared server (``SCANDIFF_TEST_POSTGRES_ADMIN_URL``, default
  ``postgresql://postgres@127.0.0.1:5432/postgres``), migrated with ``upgrade_to_head`` and
  dropped at the end;
* ``n_api`` API processes (``python -m uvicorn --factory app.main:create_app``, the API of
  ``scandiff serve --workers 0``) on free ports;
* ``n_workers`` job consumers (``python -m app.jobs.consumer --workers 1``, the future
  ``scandiff worker``), each with one Huey worker process;

all with the same ``SCANDIFF_DATA_DIR``, ``SCANDIFF_DATABASE_URL`` (``postgresql+psycopg://``) and
``SCANDIFF_QUEUE_URL`` (``redis://127.0.0.1:<port>/0``).  Every process runs in its own process
group (``kill()`` is a ``kill -9`` of that group: a container dying); teardown kills whatever is
left even when the test failed, then drops the database.  ``cpus`` pins a process with
``taskset -c`` (used by ``bench/perf_scaling.py``).

:func:`scaled_out` raises :class:`TopologyUnavailableError` when PostgreSQL, the redis client
library or ``/usr/bin/redis-server`` is missing (:func:`missing_topology_services` says which);
tests call ``tests.helpers.topology.require_topology`` first, which skips then (fails in CI).
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from app.config import Settings
from app.db.migrate import upgrade_to_head
from app.db.session import get_engine, transaction
from app.services.auth import create_token
from app.testing.fake_pipeline import CONSUMER_BOOTSTRAP
from app.testing.network import free_port, local_tls_context, token_status
from app.testing.paths import PROJECT_ROOT
from app.testing.redis import redis_ping, redis_server_binary
from app.testing.service import (
    PORT_ATTEMPTS,
    kill_process_group,
    live_worker_pids,
    process_group_members,
)

REDIS_SERVER = redis_server_binary() or "/usr/bin/redis-server"
"""The redis-server the topology runs (``SCANDIFF_TEST_REDIS_SERVER``, else on the PATH)."""
POSTGRES_ADMIN_URL = os.environ.get(
    "SCANDIFF_TEST_POSTGRES_ADMIN_URL", "postgresql://postgres@127.0.0.1:5432/postgres"
)
HEALTH_PATH = "/api/v1/health"
START_TIMEOUT_SECONDS = 180.0
"""How long a process may take to serve (a loaded 2-core machine imports slowly)."""
WORKER_COMMAND = (sys.executable, "-m", "app", "worker", "--concurrency", "1")
"""A standalone worker (``scandiff worker``)."""
REDIS_OPTIONS = ("--bind", "127.0.0.1", "--save", "", "--appendonly", "no")
"""No persistence: a restarted Redis comes back empty."""
API_COMMAND = (sys.executable, "-m", "app", "serve", "--workers", "0", "--host", "127.0.0.1")
"""An API process without a consumer (``scandiff serve --workers 0``; port appended)."""
TOPOLOGY_ENV = {
    "SCANDIFF_TESTING": "1",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "PYTHONUNBUFFERED": "1",
}
"""Every process of the topology gets these (test hooks on, one BLAS/OpenMP thread)."""


def postgres_reachable(admin_url: str = POSTGRES_ADMIN_URL) -> bool:
    """Whether the PostgreSQL server of ``admin_url`` answers."""
    try:
        import psycopg
    except ImportError:
        return False
    try:
        with psycopg.connect(admin_url, connect_timeout=3):
            return True
    except psycopg.Error:
        return False


class TopologyUnavailableError(RuntimeError):
    """PostgreSQL, redis-server or redis-py is missing: the topology cannot start."""


def missing_topology_services() -> list[str]:
    """What the topology needs and this machine lacks (PostgreSQL, redis-server, redis-py)."""
    missing = []
    if not postgres_reachable():
        missing.append(f"PostgreSQL not reachable at {POSTGRES_ADMIN_URL}")
    if not Path(REDIS_SERVER).is_file():
        missing.append(f"{REDIS_SERVER} not installed")
    if importlib.util.find_spec("redis") is None:
        missing.append("redis-py missing (pip install redis)")
    return missing


def wait_for(condition: Any, timeout: float, what: str, process: ManagedProcess) -> None:
    """Poll ``condition()`` until true; raise with ``process``'s log if it dies or times out."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not process.is_running():
            raise RuntimeError(f"{process.name} exited ({what}):\n{process.log_text()[-4000:]}")
        if condition():
            return
        time.sleep(0.05)
    log = process.log_text()[-4000:]
    raise TimeoutError(f"{process.name}: not {what} after {timeout}s:\n{log}")


@dataclass
class ManagedProcess:
    """One process of the topology in its own process group, logging to ``log_path``."""

    name: str
    command: list[str]
    environment: dict[str, str]
    log_path: Path
    cpus: str | None = None
    process: subprocess.Popen[bytes] | None = None
    starts: int = 0

    def start(self) -> ManagedProcess:
        """Start it (pinned with ``taskset -c cpus`` when given) and wait until it is ready."""
        self.spawn()
        self.wait_ready()
        return self

    def spawn(self) -> ManagedProcess:
        """Start it without waiting (pinned with ``taskset -c cpus`` when given)."""
        if self.is_running():
            raise RuntimeError(f"{self.name} already running")
        prefix = ["taskset", "-c", self.cpus] if self.cpus else []
        with open(self.log_path, "ab") as log_file:
            log_file.write(f"--- start {self.starts + 1}: {' '.join(self.command)}\n".encode())
            log_file.flush()
            self.process = subprocess.Popen(
                prefix + self.command,
                cwd=PROJECT_ROOT,
                env=self.environment,
                stdin=subprocess.DEVNULL,
                stdout=log_file,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # own process group: kill() reaches every child
            )
        self.starts += 1
        return self

    def wait_ready(self) -> None:
        """Block until the process serves (subclasses); by default, until it is running."""

    @property
    def pid(self) -> int:
        """The process id (also its process group id)."""
        if self.process is None:
            raise RuntimeError(f"{self.name} not started")
        return self.process.pid

    def is_running(self) -> bool:
        """Whether the main process is alive."""
        return self.process is not None and self.process.poll() is None

    def group_pids(self) -> list[int]:
        """Live processes of its process group."""
        return process_group_members(self.pid) if self.process is not None else []

    def kill(self) -> None:
        """``kill -9`` the whole process group and wait until none of it is left."""
        if self.process is None:
            return
        kill_process_group(self.process)

    def stop(self, timeout: float = 15.0) -> None:
        """SIGTERM (graceful), then :meth:`kill` after ``timeout``."""
        if self.is_running():
            assert self.process is not None
            self.process.send_signal(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(timeout)
        self.kill()

    def restart(self) -> ManagedProcess:
        """``kill -9`` and start again with the same command (same port)."""
        self.kill()
        return self.start()

    def log_text(self) -> str:
        """Everything it printed (all starts)."""
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""


@dataclass
class RedisProcess(ManagedProcess):
    """A private ``redis-server`` without persistence."""

    port: int = 0

    def ping(self) -> bool:
        """Whether it answers ``PING``."""
        return redis_ping(self.port)

    def wait_ready(self) -> None:
        wait_for(self.ping, 20, "answering PING", self)

    @property
    def url(self) -> str:
        """``redis://127.0.0.1:<port>/0``."""
        return f"redis://127.0.0.1:{self.port}/0"


@dataclass
class ApiProcess(ManagedProcess):
    """One API process (uvicorn, no job consumer)."""

    port: int = 0
    admin_token: str = ""

    @property
    def base_url(self) -> str:
        """``http://127.0.0.1:<port>``."""
        return f"http://127.0.0.1:{self.port}"

    def healthy(self) -> bool:
        """Whether ``GET /api/v1/health`` answers 200 and, given :attr:`admin_token`, the server
        on the port knows it (another test's server that took the port first does not)."""
        try:
            answer = httpx.get(self.base_url + HEALTH_PATH, timeout=2.0, verify=local_tls_context())
            if answer.status_code != 200 or not self.admin_token:
                return answer.status_code == 200
            return token_status(self.base_url, self.admin_token) == 200
        except httpx.HTTPError:
            return False

    def wait_ready(self) -> None:
        """Wait until healthy; when the port was taken before it bound, move to a fresh port."""
        for attempt in range(PORT_ATTEMPTS):
            try:
                wait_for(self.healthy, START_TIMEOUT_SECONDS, "healthy", self)
                return
            except RuntimeError:
                last_start = self.log_text().rsplit("--- start ", 1)[-1]
                if attempt == PORT_ATTEMPTS - 1 or "address already in use" not in last_start:
                    raise
            self.kill()
            self.port = free_port()
            self.command = [*self.command[: self.command.index("--port") + 1], str(self.port)]
            self.spawn()


@dataclass
class WorkerProcess(ManagedProcess):
    """One job consumer with ``workers`` Huey worker processes."""

    data_dir: Path = Path()
    workers: int = 1

    def worker_pids(self) -> list[int]:
        """Its live Huey worker processes (from the pid files in ``<data_dir>/run``)."""
        return live_worker_pids(self.data_dir, self.pid) if self.process is not None else []

    def wait_ready(self) -> None:
        wait_for(
            lambda: len(self.worker_pids()) >= self.workers,
            START_TIMEOUT_SECONDS,
            "with its workers",
            self,
        )


@dataclass
class Topology:
    """A running scaled-out deployment and handles on its state."""

    data_dir: Path
    database_name: str
    settings: Settings
    redis: RedisProcess
    apis: list[ApiProcess]
    workers: list[WorkerProcess]
    admin_token: str
    processes: list[ManagedProcess] = field(default_factory=list)

    @property
    def libpq_url(self) -> str:
        """The database for psycopg (``postgresql://``), read outside the services' engines."""
        return admin_url_for(self.database_name)

    def rows(self, table: str) -> list[dict[str, Any]]:
        """Every row of ``table`` (read with psycopg, autocommit: never blocks a writer)."""
        import psycopg
        from psycopg.rows import dict_row

        with psycopg.connect(self.libpq_url, autocommit=True, row_factory=dict_row) as connection:
            return list(connection.execute(f'SELECT * FROM "{table}"').fetchall())

    def job_status_counts(self) -> Counter[str]:
        """How many jobs are in each status."""
        return Counter(job["status"] for job in self.rows("job"))

    def client(self, index: int = 0, **kwargs: Any) -> httpx.Client:
        """An admin ``httpx.Client`` on API process ``index``."""
        headers = {"Authorization": f"Bearer {self.admin_token}", **kwargs.pop("headers", {})}
        kwargs.setdefault("timeout", 60.0)
        kwargs.setdefault("verify", local_tls_context())
        return httpx.Client(base_url=self.apis[index].base_url, headers=headers, **kwargs)

    def worker_logs(self) -> str:
        """Everything the job consumers printed."""
        return "".join(worker.log_text() for worker in self.workers)

    def all_logs(self) -> str:
        """Everything every process printed."""
        return "".join(process.log_text() for process in self.processes)

    def kill_all(self) -> None:
        """``kill -9`` every process group (workers first, Redis last)."""
        for process in reversed(self.processes):
            process.kill()


def admin_url_for(database_name: str) -> str:
    """``POSTGRES_ADMIN_URL`` with its database replaced by ``database_name``."""
    return POSTGRES_ADMIN_URL.rsplit("/", 1)[0] + f"/{database_name}"


def create_database() -> str:
    """A new empty database on the shared server; its name."""
    import psycopg

    name = f"scandiff_topology_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(POSTGRES_ADMIN_URL, autocommit=True) as connection:
        connection.execute(f'CREATE DATABASE "{name}"')
    return name


def drop_database(name: str) -> None:
    """Drop ``name``, disconnecting whoever is still connected."""
    import psycopg

    with psycopg.connect(POSTGRES_ADMIN_URL, autocommit=True) as connection:
        connection.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def process_environment(
    data_dir: Path, database_url: str, queue_url: str, extra: Mapping[str, str]
) -> dict[str, str]:
    """The environment of every API and worker process."""
    environment = {
        key: value for key, value in os.environ.items() if not key.startswith("SCANDIFF_")
    }
    environment.update(TOPOLOGY_ENV)
    environment.update(
        {
            "SCANDIFF_DATA_DIR": str(data_dir),
            "SCANDIFF_DATABASE_URL": database_url,
            "SCANDIFF_QUEUE_URL": queue_url,
        }
    )
    environment.update(extra)
    return environment


def pick(cpus: Sequence[str | None] | None, index: int) -> str | None:
    """The ``taskset`` CPU list of process ``index`` (round robin), or None."""
    return cpus[index % len(cpus)] if cpus else None


@contextlib.contextmanager
def scaled_out(
    base_dir: Path,
    *,
    n_api: int = 2,
    n_workers: int = 3,
    env: Mapping[str, str] | None = None,
    fake_pipeline: bool = False,
    api_cpus: Sequence[str | None] | None = None,
    worker_cpus: Sequence[str | None] | None = None,
) -> Iterator[Topology]:
    """Start the deployment shape (see the module docstring) under ``base_dir``; tear it down.

    ``env`` is added to every API and worker process (leases, test hooks, thread counts);
    ``fake_pipeline`` makes the workers use :mod:`app.testing.fake_pipeline`;
    ``api_cpus``/``worker_cpus`` pin process ``i`` to ``cpus[i % len(cpus)]`` (``taskset -c``).
    """
    missing = missing_topology_services()
    if missing:
        raise TopologyUnavailableError("; ".join(missing))
    data_dir = (base_dir / "data").resolve()
    logs = (base_dir / "logs").resolve()
    data_dir.mkdir(parents=True, exist_ok=True)
    logs.mkdir(parents=True, exist_ok=True)
    database_name = create_database()
    database_url = "postgresql+psycopg" + admin_url_for(database_name).removeprefix("postgresql")
    processes: list[ManagedProcess] = []
    settings = Settings(data_dir=data_dir, database_url=database_url)
    try:
        upgrade_to_head(settings.sqlalchemy_url)
        with transaction(settings.sqlalchemy_url) as session:
            admin_token = create_token(session, "default", "admin", name="topology admin")
        get_engine(settings.sqlalchemy_url).dispose()

        redis_port = free_port()
        redis = RedisProcess(
            "redis",
            [REDIS_SERVER, "--port", str(redis_port), *REDIS_OPTIONS],
            dict(os.environ),
            logs / "redis.log",
            port=redis_port,
        )
        processes.append(redis.start())
        environment = process_environment(data_dir, database_url, redis.url, env or {})
        settings = settings.model_copy(update={"queue_url": redis.url})

        apis = []
        for index in range(n_api):
            port = free_port()
            api = ApiProcess(
                f"api-{index}",
                [*API_COMMAND, "--port", str(port)],
                environment,
                logs / f"api-{index}.log",
                cpus=pick(api_cpus, index),
                port=port,
                admin_token=admin_token,
            )
            processes.append(api)
            apis.append(api)
        workers = []
        worker_command = (
            [sys.executable, "-c", CONSUMER_BOOTSTRAP, "--workers", "1"]
            if fake_pipeline
            else list(WORKER_COMMAND)
        )
        for index in range(n_workers):
            worker = WorkerProcess(
                f"worker-{index}",
                worker_command,
                environment,
                logs / f"worker-{index}.log",
                cpus=pick(worker_cpus, index),
                data_dir=data_dir,
            )
            processes.append(worker)
            workers.append(worker)
        for process in [*apis, *workers]:
            process.spawn()
        for process in [*apis, *workers]:
            process.wait_ready()
        yield Topology(
            data_dir, database_name, settings, redis, apis, workers, admin_token, processes
        )
    finally:
        for process in reversed(processes):
            process.kill()
        get_engine(settings.sqlalchemy_url).dispose()
        drop_database(database_name)


def copy_logs(topology: Topology, destination: Path) -> None:
    """Keep the processes' logs (e.g. under test-artifacts) after the base dir goes away."""
    destination.mkdir(parents=True, exist_ok=True)
    for process in topology.processes:
        if process.log_path.exists():
            shutil.copy(process.log_path, destination / process.log_path.name)
