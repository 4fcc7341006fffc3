"""The queue's doorbell: idle workers of the SQLite queue wake as soon as a message is sent.

Huey's workers poll an SQLite queue, backing off to one poll a second
(``QUEUE_POLL_MAX_DELAY_SECONDS``) while idle, so a job sent to an idle service waited up to a
second before a worker looked.  The doorbell is a named pipe (FIFO) beside the workers' pid
files, ``<data_dir>/run/queue-doorbell``: an idle worker sleeps in ``select`` on it instead of
a plain timer, and whoever sends a message (:func:`app.jobs.queue.send_job_message`) writes a
byte to it.  One byte wakes one idle worker, which polls the queue at once.

It is only a hint, never the record: the job row is committed and the message is in the queue
before the bell rings, and a worker still polls on its timer, so a lost ring (no worker
listening, a full pipe, another host) only costs the old poll delay.  Ringing never blocks and
never raises.  A Redis queue needs no bell (its workers block on the queue itself).
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import stat
import time
from pathlib import Path

from app.kit.data_layout import DataLayout

DOORBELL_NAME = "queue-doorbell"


def doorbell_path(data_dir: Path) -> Path:
    """Where the doorbell of the queue of the data directory ``data_dir`` lives."""
    return DataLayout(data_dir).run_dir / DOORBELL_NAME


def ring(path: Path, times: int = 1) -> bool:
    """Wake up to ``times`` idle workers listening at ``path``; whether a byte was written.

    Never blocks and never raises: nobody listening (no pipe, no reader), a full pipe or any
    other error only means the workers find the message at their next poll.
    """
    try:
        descriptor = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
    except OSError:  # ENOENT: no worker made it yet; ENXIO: nobody has it open
        return False
    try:
        if not stat.S_ISFIFO(os.fstat(descriptor).st_mode):
            return False
        return os.write(descriptor, b"\x01" * max(1, times)) > 0
    except OSError:  # EAGAIN: the pipe is full of rings nobody took yet; enough to wake all
        return False
    finally:
        os.close(descriptor)


class Doorbell:
    """The listening end, opened in a worker process (:meth:`open`), waited on while idle."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._descriptor: int | None = None

    def open(self) -> bool:
        """Create the pipe if missing and open it; whether the doorbell can be waited on.

        Opened for reading and writing: a FIFO opened only for reading reports end-of-file
        (readable) without end once its last writer closed, which would spin the ``select``.
        """
        if self._descriptor is not None:
            return True
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with contextlib.suppress(FileExistsError):
                os.mkfifo(self.path, 0o600)
            descriptor = os.open(self.path, os.O_RDWR | os.O_NONBLOCK)
        except OSError:
            return False
        if not stat.S_ISFIFO(os.fstat(descriptor).st_mode):
            os.close(descriptor)
            return False
        self._descriptor = descriptor
        return True

    def wait(self, timeout: float) -> bool:
        """Sleep until a ring (taken: this worker answers it) or ``timeout`` seconds pass;
        whether it rang.  Another worker taking the ring first does not end the wait."""
        if self._descriptor is None:
            time.sleep(max(0.0, timeout))
            return False
        deadline = time.monotonic() + max(0.0, timeout)
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            try:
                readable, _, _ = select.select([self._descriptor], [], [], remaining)
            except InterruptedError:
                continue
            if not readable:
                return False
            try:
                if os.read(self._descriptor, 1):
                    return True
            except OSError as exc:
                if exc.errno not in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EINTR):
                    raise

    def drain(self) -> int:
        """Take every ring waiting in the pipe (rings for messages already taken); how many."""
        taken = 0
        if self._descriptor is None:
            return taken
        while True:
            try:
                chunk = os.read(self._descriptor, 4096)
            except OSError:  # EAGAIN: empty
                return taken
            if not chunk:
                return taken
            taken += len(chunk)

    def close(self) -> None:
        """Stop listening (the pipe stays for the other workers)."""
        if self._descriptor is not None:
            os.close(self._descriptor)
            self._descriptor = None
