"""``scandiff worker`` and ``scandiff serve --workers 0`` as subprocesses for tests.

:class:`WorkerProcess` runs ``python -m app worker`` (by default with the fake pipeline of
:mod:`tests.helpers.fake_pipeline` installed first) in its own process group on the settings of
a job test, plus ``env`` (say ``SCANDIFF_QUEUE_URL``).  Its worker pids come from the pid files
the workers write, as for :class:`tests.helpers.service.ConsumerProcess`.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

from app.config import Settings
from tests.helpers.environment import PROJECT_ROOT
from tests.helpers.service import live_worker_pids, settings_environment

FAKE_PIPELINE_WORKER = (
    "import sys, tests.helpers.fake_pipeline as fake; fake.install(); "
    "from app.cli import main; sys.exit(main(['worker', *sys.argv[1:]]))"
)
"""``python -c`` code running ``scandiff worker`` with the fast pipeline stand-in."""


class WorkerProcess:
    """One ``scandiff worker`` subprocess in its own process group."""

    def __init__(
        self,
        settings: Settings,
        *,
        log_path: Path,
        concurrency: int = 1,
        arguments: Sequence[str] = (),
        env: Mapping[str, str] | None = None,
        fake_pipeline: bool = True,
    ) -> None:
        self.settings = settings
        self.concurrency = concurrency
        self.log_path = log_path
        environment = dict(os.environ)
        environment.update(settings_environment(settings))
        if settings.database_url:
            environment["SCANDIFF_DATABASE_URL"] = settings.database_url
        if settings.queue_url:
            environment["SCANDIFF_QUEUE_URL"] = settings.queue_url
        environment.update({"SCANDIFF_TESTING": "1", "OMP_NUM_THREADS": "1"})
        environment.update(env or {})
        prefix = ["-c", FAKE_PIPELINE_WORKER] if fake_pipeline else ["-m", "app", "worker"]
        with open(log_path, "ab") as log_file:
            self.process = subprocess.Popen(
                [sys.executable, *prefix, "--concurrency", str(concurrency), *arguments],
                cwd=PROJECT_ROOT,
                env=environment,
                stdin=subprocess.DEVNULL,
                stdout=log_file,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

    def worker_pids(self) -> list[int]:
        """Live job worker processes of this ``scandiff worker``."""
        return live_worker_pids(self.settings.data_dir, self.process.pid)

    def wait_for_workers(self, timeout: float = 30.0) -> list[int]:
        """Wait until all ``concurrency`` workers are up; their pids."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            pids = self.worker_pids()
            if len(pids) >= self.concurrency:
                return pids
            if self.process.poll() is not None:
                raise RuntimeError(f"scandiff worker exited:\n{self.log()}")
            time.sleep(0.05)
        raise TimeoutError(f"workers not up:\n{self.log()}")

    def log(self) -> str:
        """Everything the process printed."""
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def terminate(self, timeout: float = 30.0) -> int | None:
        """SIGTERM (graceful stop) and wait; the exit status (None if still running)."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(timeout)
        return self.process.poll()

    def stop(self, timeout: float = 30.0) -> int | None:
        """SIGTERM, wait, then SIGKILL whatever of the group is left; the exit status."""
        status = self.terminate(timeout)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait(5)
        return status if status is not None else self.process.returncode
