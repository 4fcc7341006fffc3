"""A private ``redis-server``: own port, no persistence, stopped and restarted at will.

Never the shared server on 6379: tests stop their own server to play a Redis outage.
:class:`RedisServer` runs ``redis-server --port P --save '' --appendonly no`` in its own process
group; ``stop()`` (SIGTERM) / ``kill()`` (SIGKILL) and ``start()`` again on the same port model an
outage and the return.  The binary is ``$SCANDIFF_TEST_REDIS_SERVER`` or ``redis-server`` on the
PATH; :func:`redis_server_binary` is None when neither exists (tests ``require`` it).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

from app.testing.network import free_port

REDIS_SERVER_ENV = "SCANDIFF_TEST_REDIS_SERVER"
"""Path of the redis-server binary (.ci/run exports it); default: ``redis-server`` on PATH."""


def redis_server_binary() -> str | None:
    """The redis-server to run, or None when there is none."""
    configured = os.environ.get(REDIS_SERVER_ENV)
    if configured:
        return configured if Path(configured).is_file() else None
    return shutil.which("redis-server")


def redis_ping(port: int, host: str = "127.0.0.1", timeout: float = 0.5) -> bool:
    """Whether a Redis server answers PING on ``host:port`` (raw RESP, no client library)."""
    try:
        with socket.create_connection((host, port), timeout=timeout) as connection:
            connection.sendall(b"PING\r\n")
            return connection.recv(64).startswith(b"+PONG")
    except OSError:
        return False


class RedisServer:
    """One private redis-server on a free loopback port."""

    def __init__(self, binary: str, directory: Path, port: int | None = None) -> None:
        self.binary = binary
        self.directory = directory
        self.port = port or free_port()
        self.process: subprocess.Popen[bytes] | None = None
        self.log_path = directory / f"redis-{self.port}.log"

    @property
    def url(self) -> str:
        """``redis://127.0.0.1:<port>/0``, for ``SCANDIFF_QUEUE_URL``."""
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self, timeout: float = 10.0) -> RedisServer:
        """Start the server (on the same port as before, if restarting); wait until it answers."""
        if self.is_running():
            raise RuntimeError("redis-server already running")
        self.directory.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "ab") as log_file:
            self.process = subprocess.Popen(
                [
                    self.binary,
                    "--port",
                    str(self.port),
                    "--bind",
                    "127.0.0.1",
                    "--save",
                    "",
                    "--appendonly",
                    "no",
                    "--daemonize",
                    "no",
                    "--dir",
                    str(self.directory),
                ],
                stdin=subprocess.DEVNULL,
                stdout=log_file,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        deadline = time.monotonic() + timeout
        while not redis_ping(self.port):
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"redis-server did not start:\n{self.log()[-2000:]}")
            time.sleep(0.05)
        return self

    def is_running(self) -> bool:
        """Whether this server's process is alive."""
        return self.process is not None and self.process.poll() is None

    def stop(self, timeout: float = 10.0) -> None:
        """SIGTERM the server and wait until it is gone (a clean outage)."""
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.kill()

    def kill(self) -> None:
        """SIGKILL the server (a crash: the queued messages are lost with it)."""
        if self.process is None:
            return
        with contextlib.suppress(ProcessLookupError):
            self.process.kill()
        self.process.wait(10)

    def log(self) -> str:
        """What the server printed."""
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""
