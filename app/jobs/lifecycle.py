"""Child processes that die with their parent: ``PR_SET_PDEATHSIG`` plus a ``getppid`` watchdog.

``scandiff serve`` starts the API and the job consumer as children; if ``serve`` is killed (even
with SIGKILL) they must not linger.  On Linux the kernel sends the child a signal when its parent
dies (``prctl(PR_SET_PDEATHSIG)``); everywhere, a watchdog thread polls ``getppid()`` as well
(it also covers a parent that died before ``prctl`` ran).
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
import threading
import time

logger = logging.getLogger("scandiff.lifecycle")

PR_SET_PDEATHSIG = 1
SUPERVISOR_PID_ENV = "SCANDIFF_SUPERVISOR_PID"
"""Set by ``scandiff serve`` in its children's environment: the pid they must outlive not."""
WATCHDOG_INTERVAL_SECONDS = 0.5
FORCED_EXIT_AFTER_SECONDS = 15.0
"""After asking itself to stop (SIGTERM), an orphaned child SIGKILLs itself this much later."""


def set_parent_death_signal(signum: int) -> bool:
    """Ask the kernel to send ``signum`` to this process when its parent dies (Linux only)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return int(libc.prctl(PR_SET_PDEATHSIG, int(signum), 0, 0, 0)) == 0
    except (OSError, AttributeError):
        return False


def _watch(parent_pid: int, signum: int, kernel_signals: bool) -> None:
    """Poll ``getppid``; when the parent is gone, signal ourselves (unless the kernel did)."""
    while os.getppid() == parent_pid:
        time.sleep(WATCHDOG_INTERVAL_SECONDS)
    logger.warning("parent process %s is gone; stopping", parent_pid)
    if not kernel_signals:  # a second signal would mean "stop now" to the consumer
        os.kill(os.getpid(), signum)
    time.sleep(FORCED_EXIT_AFTER_SECONDS)
    logger.error("still running %ss after the parent died; killing", FORCED_EXIT_AFTER_SECONDS)
    os.kill(os.getpid(), signal.SIGKILL)


def die_with_parent(parent_pid: int | None = None, signum: int = signal.SIGTERM) -> None:
    """Make this process receive ``signum`` when ``parent_pid`` (default: our parent) exits."""
    if parent_pid is None:
        parent_pid = os.getppid()
    kernel_signals = set_parent_death_signal(signum)
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os.kill(os.getpid(), signum)
        kernel_signals = True  # already signalled
    threading.Thread(
        target=_watch,
        args=(parent_pid, signum, kernel_signals),
        name="parent-watchdog",
        daemon=True,
    ).start()


def die_with_supervisor() -> None:
    """If started by ``scandiff serve`` (``SCANDIFF_SUPERVISOR_PID`` set), die with it."""
    value = os.environ.get(SUPERVISOR_PID_ENV)
    if value and value.isdigit():
        die_with_parent(int(value))
