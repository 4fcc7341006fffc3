"""How many threads the numeric core may use: one definition for every stage.

``OMP_NUM_THREADS`` is the budget a caller gives a process (the service sets it per job worker,
the benchmarks per configuration); without it, every CPU the process may run on.
"""

from __future__ import annotations

import os

__all__ = ["available_threads", "configured_threads", "usable_cpus"]


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity mask on Linux)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def configured_threads() -> int | None:
    """``OMP_NUM_THREADS`` when it is a positive integer, else None."""
    configured = os.environ.get("OMP_NUM_THREADS", "").strip()
    return int(configured) if configured.isdigit() and int(configured) > 0 else None


def available_threads() -> int:
    """Threads a stage may keep busy: ``OMP_NUM_THREADS`` if set, else :func:`usable_cpus`."""
    configured = configured_threads()
    return configured if configured is not None else usable_cpus()
