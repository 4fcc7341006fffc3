"""An API-only process (uvicorn with ``app.main:create_app``, no job consumer) for tests.

What a scaled-out deployment runs next to other API processes and workers on one database:
``python -m uvicorn --factory app.main:create_app`` with ``SCANDIFF_*`` settings from the
environment.  The database must already be migrated (the app does not migrate).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import httpx

from app.config import Settings
from tests.helpers.environment import PROJECT_ROOT
from tests.helpers.network import free_port

STARTUP_TIMEOUT_SECONDS = 90.0
"""Importing the app takes seconds, far more on a loaded machine."""


@contextmanager
def api_process(
    settings: Settings, log_path: Path, env: Mapping[str, str] | None = None
) -> Iterator[str]:
    """Run an API process on ``settings``' data directory until exit; yields its base URL.

    Its stdout and stderr go to ``log_path``; ``env`` adds variables (``SCANDIFF_*``).
    """
    port = free_port()
    environment = {**os.environ, "SCANDIFF_DATA_DIR": str(settings.data_dir), **(env or {})}
    command = [sys.executable, "-m", "uvicorn", "--factory", "app.main:create_app"]
    with open(log_path, "ab") as log_file:
        process = subprocess.Popen(
            [*command, "--host", "127.0.0.1", "--port", str(port), "--no-access-log"],
            cwd=PROJECT_ROOT,
            env=environment,
            stdout=log_file,
            stderr=subprocess.STDOUT,
        )
    base_url = f"http://127.0.0.1:{port}"
    try:
        wait_healthy(base_url, process, log_path)
        yield base_url
    finally:
        process.terminate()
        try:
            process.wait(15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)


def wait_healthy(base_url: str, process: subprocess.Popen[bytes], log_path: Path) -> None:
    """Wait until ``GET /api/v1/health`` answers 200; fail with the log if the process exits."""
    deadline = time.monotonic() + STARTUP_TIMEOUT_SECONDS
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"API process exited:\n{log_path.read_text()[-3000:]}")
        try:
            if httpx.get(f"{base_url}/api/v1/health", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise TimeoutError(f"API process not healthy:\n{log_path.read_text()[-3000:]}")
