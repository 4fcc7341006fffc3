"""The real service (``python -m app serve``) or a job consumer as subprocesses.

:class:`ServiceProcess` starts ``scandiff serve`` in its own process group on a free port, waits
for ``GET /api/v1/health`` to answer 200, and offers the handles tests need: ``base_url``,
``admin_token`` (read from ``<data_dir>/admin-token``), ``client()``, ``stop()`` (SIGTERM,
graceful), ``kill()`` (SIGKILL to the whole group, as a power cut would), ``kill_parent()``
(SIGKILL to ``serve`` only: its children must follow), ``restart()`` and ``worker_pids()`` (job
worker processes, from the pid files the workers write in ``<data_dir>/run``).

Use it through the ``service_factory`` fixture (in ``tests/conftest.py``)::

    def test_flow(service_factory):
        service = service_factory(workers=2, env={"SCANDIFF_JOB_LEASE_SECONDS": "3"})
        with service.client() as client:
            assert client.get("/api/v1/sites").status_code == 200

The child environment gets ``SCANDIFF_TESTING=1`` (enables the documented job test hooks),
``OMP_NUM_THREADS=1`` and ``PYTHONUNBUFFERED=1``; ``env`` adds or overrides variables.  Output of
the service goes to ``log_path`` (default ``<data_dir>.service.log``), shown when start-up fails.

:class:`ConsumerProcess` runs ``python -m app.jobs.consumer`` alone (by default with the fake
pipeline of :mod:`app.testing.fake_pipeline`) on the settings of a job test.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx

from app.config import Settings
from app.kit.data_layout import DataLayout
from app.testing.fake_pipeline import CONSUMER_BOOTSTRAP
from app.testing.network import free_port, local_tls_context, token_status
from app.testing.paths import PROJECT_ROOT

HEALTH_PATH = "/api/v1/health"


def process_group_members(pgid: int) -> list[int]:
    """Live (non-zombie) processes whose process group is ``pgid`` (Linux /proc)."""
    members = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        # Fields after the command name (which may contain spaces) in parentheses.
        fields = stat[stat.rindex(")") + 2 :].split()
        state, process_group = fields[0], int(fields[2])
        if process_group == pgid and state not in ("Z", "X"):
            members.append(int(entry.name))
    return sorted(members)


def kill_process_group(process: subprocess.Popen[Any], timeout: float = 10.0) -> bool:
    """``kill -9`` the process group led by ``process``; whether none of it is left after
    ``timeout`` (stragglers of the group are killed again while waiting)."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGKILL)
    process.wait(timeout)
    deadline = time.monotonic() + timeout
    while process_group_members(process.pid) and time.monotonic() < deadline:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
        time.sleep(0.05)
    return not process_group_members(process.pid)


def pid_is_alive(pid: int) -> bool:
    """Whether ``pid`` is a running, non-zombie process."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2 :].split()[0] not in ("Z", "X")


def live_worker_pids(data_dir: Path, process_group: int) -> list[int]:
    """Live job workers of ``process_group`` (each writes ``<data_dir>/run/worker-<pid>``)."""
    members = set(process_group_members(process_group))
    pids = []
    for pid_text in DataLayout(data_dir).worker_pid_files():
        if not pid_text.isdigit():
            continue
        pid = int(pid_text)
        if pid in members and pid_is_alive(pid):
            pids.append(pid)
    return sorted(pids)


class ServiceStartError(RuntimeError):
    """The service exited or did not become healthy in time."""


class PortTakenError(ServiceStartError):
    """Another server holds the service's port (a free port taken between choosing and binding)."""


PORT_ATTEMPTS = 3
"""Ports a service with a chosen-for-it port tries before its start fails."""


class ServiceProcess:
    """One ``scandiff serve`` subprocess (API + job consumer) on a free port."""

    started_line: str | None = "scandiff serving at"
    """What the process prints once its token file is written (None: its health is not checked
    against its token)."""

    def __init__(
        self,
        data_dir: str | Path,
        *,
        workers: int = 1,
        env: Mapping[str, str] | None = None,
        port: int | None = None,
        host: str = "127.0.0.1",
        startup_timeout: float = 60.0,
        log_path: str | Path | None = None,
    ) -> None:
        self.data_dir = Path(data_dir).resolve()
        self.workers = workers
        self.host = host
        self.port = port or free_port(host)
        self._port_given = port is not None
        self.startup_timeout = startup_timeout
        self.log_path = Path(log_path) if log_path else self.data_dir.with_suffix(".service.log")
        self.extra_env = dict(env or {})
        self.process: subprocess.Popen[bytes] | None = None
        self._log_offset = 0

    # -- lifecycle ---------------------------------------------------------------------------

    @property
    def base_url(self) -> str:
        """``http://host:port`` of the API."""
        return f"http://{self.host}:{self.port}"

    @property
    def pid(self) -> int:
        """Process id of ``scandiff serve`` (also its process group id)."""
        if self.process is None:
            raise RuntimeError("service not started")
        return self.process.pid

    def command(self) -> list[str]:
        """The command line that starts the service."""
        return [
            sys.executable,
            "-m",
            "app",
            "serve",
            "--data-dir",
            str(self.data_dir),
            "--host",
            self.host,
            "--port",
            str(self.port),
            "--workers",
            str(self.workers),
        ]

    def environment(self) -> dict[str, str]:
        """The child's environment: ours plus the test defaults plus ``env``."""
        environment = dict(os.environ)
        environment.pop("SCANDIFF_DATA_DIR", None)
        environment.update(
            {
                "SCANDIFF_TESTING": "1",
                "OMP_NUM_THREADS": "1",
                "OPENBLAS_NUM_THREADS": "1",
                "MKL_NUM_THREADS": "1",
                "PYTHONUNBUFFERED": "1",
            }
        )
        environment.update(self.extra_env)
        return environment

    def start(self) -> ServiceProcess:
        """Start the service and wait until its health endpoint answers 200."""
        if self.is_running():
            raise RuntimeError("service already running")
        self.data_dir.parent.mkdir(parents=True, exist_ok=True)
        for attempt in range(1, PORT_ATTEMPTS + 1):
            self._launch()
            try:
                self.wait_healthy()
            except PortTakenError:
                self.kill()
                if self._port_given or attempt == PORT_ATTEMPTS:
                    raise
                self.port = free_port(self.host)
            else:
                break
        return self

    def _launch(self) -> None:
        """Start ``scandiff serve`` with its output appended to the log."""
        self._log_offset = self.log_path.stat().st_size if self.log_path.exists() else 0
        with open(self.log_path, "ab") as log_file:
            self.process = subprocess.Popen(
                self.command(),
                cwd=PROJECT_ROOT,
                env=self.environment(),
                stdin=subprocess.DEVNULL,
                stdout=log_file,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # own session and process group: kill() reaches all
            )

    def wait_healthy(self, timeout: float | None = None) -> None:
        """Poll the health endpoint until 200; raise with the log if the service dies first."""
        deadline = time.monotonic() + (timeout or self.startup_timeout)
        last_error = "no answer yet"
        while time.monotonic() < deadline:
            if self.process is None or self.process.poll() is not None:
                error = PortTakenError if "address already in use" in self.log_text() else None
                raise (error or ServiceStartError)(
                    f"scandiff serve exited with {self.process and self.process.returncode}:\n"
                    f"{self.log_text()[-4000:]}"
                )
            try:
                response = httpx.get(
                    self.base_url + HEALTH_PATH, timeout=2.0, verify=local_tls_context()
                )
                if response.status_code == 200 and self._answers_to_its_token():
                    return
                last_error = (
                    "healthy, but this service has not started yet"
                    if response.status_code == 200
                    else f"{response.status_code} {response.text[:200]}"
                )
            except httpx.HTTPError as exc:
                last_error = repr(exc)
            time.sleep(0.1)
        raise ServiceStartError(
            f"service not healthy after {timeout or self.startup_timeout}s ({last_error}):\n"
            f"{self.log_text()[-4000:]}"
        )

    def _answers_to_its_token(self) -> bool:
        """Whether the server on the port knows this service's admin token (raises
        :class:`PortTakenError` when it refuses it: another server answered the health check).

        False until the process printed :attr:`started_line` (its token file is written by
        then); a data directory without a token file (a shared database), or a process without
        such a line, cannot be checked: True.
        """
        if self.started_line is None:
            return True
        if self.started_line not in self.log_text():
            return False
        path = DataLayout(self.data_dir).admin_token_file
        if not path.exists():
            return True
        if token_status(self.base_url, path.read_text().strip()) in (401, 403, 404):
            raise PortTakenError(f"another server answers on port {self.port}")
        return True

    def is_running(self) -> bool:
        """Whether the ``serve`` process is alive."""
        return self.process is not None and self.process.poll() is None

    def stop(self, timeout: float = 30.0) -> int | None:
        """SIGTERM ``serve`` (graceful); SIGKILL the group after ``timeout``; the exit status."""
        if self.process is None:
            return None
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()
        self.wait_group_gone(timeout=10.0, force=True)
        return self.process.returncode

    def kill(self) -> None:
        """SIGKILL every process of the service at once (API, consumer, workers)."""
        if self.process is None:
            return
        kill_process_group(self.process)

    def kill_parent(self) -> None:
        """SIGKILL ``serve`` alone; its children are expected to exit by themselves."""
        if self.process is None:
            return
        self.process.kill()
        self.process.wait(10)

    def wait_group_gone(self, timeout: float = 10.0, force: bool = False) -> bool:
        """Wait until no process of the group is left; SIGKILL leftovers when ``force``."""
        if self.process is None:
            return True
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if not process_group_members(self.process.pid):
                return True
            time.sleep(0.05)
        if force:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.process.pid, signal.SIGKILL)
            time.sleep(0.2)
        return not process_group_members(self.process.pid)

    def restart(self, *, kill: bool = False) -> ServiceProcess:
        """Stop (or kill) the service and start it again on the same data dir and port."""
        if kill:
            self.kill()
        else:
            self.stop()
        return self.start()

    def __enter__(self) -> ServiceProcess:
        return self if self.is_running() else self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    # -- introspection -----------------------------------------------------------------------

    @property
    def admin_token(self) -> str:
        """The admin token written by ``serve`` on its database's first start.

        A database an earlier service already started (the PostgreSQL pass of ``.ci/run``
        shares one) gets no such token: then an admin of a new organisation, from ``scandiff
        token create``, kept in the same file.
        """
        path = DataLayout(self.data_dir).admin_token_file
        if not path.exists():
            organisation = f"service-{uuid.uuid4().hex[:12]}"
            command = [sys.executable, "-m", "app", "token", "create", "--role", "admin"]
            created = subprocess.run(
                [*command, "--org", organisation, "--data-dir", str(self.data_dir)],
                cwd=PROJECT_ROOT,
                env=self.environment(),
                stdin=subprocess.DEVNULL,
                capture_output=True,
                text=True,
                timeout=120,
                check=True,
            )
            path.write_text(created.stdout.strip() + "\n")
        return path.read_text().strip()

    def client(self, token: str | None = None, **kwargs: Any) -> httpx.Client:
        """An ``httpx.Client`` on ``base_url`` sending ``token`` (default: the admin token)."""
        headers = dict(kwargs.pop("headers", {}))
        headers.setdefault("Authorization", f"Bearer {token or self.admin_token}")
        kwargs.setdefault("timeout", 30.0)
        kwargs.setdefault("verify", local_tls_context())
        return httpx.Client(base_url=self.base_url, headers=headers, **kwargs)

    def group_pids(self) -> list[int]:
        """Every live process of the service (``serve`` and its descendants)."""
        return process_group_members(self.pid) if self.process is not None else []

    def worker_pids(self) -> list[int]:
        """Live job-worker processes (each writes ``<data_dir>/run/worker-<pid>`` on start)."""
        if self.process is None:
            return []
        return live_worker_pids(self.data_dir, self.pid)

    def wait_for_workers(self, count: int | None = None, timeout: float = 30.0) -> list[int]:
        """Wait until ``count`` (default: ``workers``) job workers are up; their pids."""
        wanted = self.workers if count is None else count
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            pids = self.worker_pids()
            if len(pids) >= wanted:
                return pids
            time.sleep(0.05)
        raise TimeoutError(f"{wanted} workers not up after {timeout}s: {self.worker_pids()}")

    def wait_for_job(
        self,
        client: httpx.Client,
        job_id: str,
        *,
        statuses: tuple[str, ...] = ("succeeded", "failed"),
        timeout: float = 60.0,
    ) -> dict[str, Any]:
        """Poll ``GET /api/v1/jobs/{job_id}`` until its status is one of ``statuses``."""
        deadline = time.monotonic() + timeout
        job: dict[str, Any] = {}
        while time.monotonic() < deadline:
            response = client.get(f"/api/v1/jobs/{job_id}")
            response.raise_for_status()
            job = response.json()
            if job["status"] in statuses:
                return job
            time.sleep(0.1)
        raise TimeoutError(f"job {job_id} not in {statuses} after {timeout}s: {job}")

    def log_text(self) -> str:
        """What the service printed since the last ``start()``."""
        if not self.log_path.exists():
            return ""
        with open(self.log_path, "rb") as log_file:
            log_file.seek(self._log_offset)
            return log_file.read().decode(errors="replace")


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
        return live_worker_pids(self.settings.data_dir, self.process.pid)

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

    def kill(self) -> None:
        """SIGKILL the whole group at once (fixture clean-up: no graceful stop to wait for)."""
        kill_process_group(self.process)


class ApiProcess(ServiceProcess):
    """The API alone, ``uvicorn --factory app.main:create_app`` (no migrations, no consumer).

    One of several API processes sharing a data directory and database (run the migrations
    first); it writes no admin token, so tests make their own tokens.
    """

    started_line = None

    def __init__(self, data_dir: str | Path, *, log_path: str | Path, **kwargs: Any) -> None:
        super().__init__(data_dir, log_path=log_path, **kwargs)
        self.extra_env.setdefault("SCANDIFF_DATA_DIR", str(self.data_dir))

    def command(self) -> list[str]:
        """The uvicorn command line of this API process."""
        return [
            sys.executable,
            *("-m", "uvicorn", "--factory", "app.main:create_app"),
            *("--host", self.host, "--port", str(self.port), "--no-access-log"),
        ]


@contextmanager
def api_process(
    settings: Settings, log_path: Path, env: Mapping[str, str] | None = None
) -> Iterator[str]:
    """An :class:`ApiProcess` on ``settings``' data directory for the ``with`` block; its URL."""
    api = ApiProcess(settings.data_dir, log_path=log_path, env=env, startup_timeout=90.0).start()
    try:
        yield api.base_url
    finally:
        api.stop()
