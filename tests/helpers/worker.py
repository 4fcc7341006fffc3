"""``scandiff worker`` and ``scandiff serve --workers 0`` as subprocesses for tests.

:class:`WorkerProcess` runs ``python -m app worker`` (by default with the fake pipeline of
:mod:`app.testing.fake_pipeline` installed first) in its own process group on the settings of
a job test, plus ``env`` (say ``SCANDIFF_QUEUE_URL``).  Its worker pids come from the pid files
the workers write, as for :class:`app.testing.service.ConsumerProcess`, whose handles it has.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

from app.config import Settings
from app.testing.paths import PROJECT_ROOT
from app.testing.service import ConsumerProcess, settings_environment

FAKE_PIPELINE_WORKER = (
    "import sys, app.testing.fake_pipeline as fake; fake.install(); "
    "from app.cli import main; sys.exit(main(['worker', *sys.argv[1:]]))"
)
"""``python -c`` code running ``scandiff worker`` with the fast pipeline stand-in."""


class WorkerProcess(ConsumerProcess):
    """One ``scandiff worker`` subprocess in its own process group (the handles of
    :class:`ConsumerProcess`: ``worker_pids``, ``wait_for_workers``, ``log``, ``stop``)."""

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
        self.workers = concurrency
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

    def terminate(self, timeout: float = 30.0) -> int | None:
        """SIGTERM (graceful stop) and wait; the exit status (None if still running)."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(timeout)
        return self.process.poll()
