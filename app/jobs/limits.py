"""How much of the machine one job may use: its address-space cap and its thread budget.

The consumer fixes both once for its workers (:func:`app.jobs.consumer.fix_job_memory_limit`);
a worker applies the cap (``RLIMIT_AS``) around each job with :func:`memory_limit`, so a file that
parses but needs more memory than the machine can give fails its job with a message instead of
taking the machine down.
"""

from __future__ import annotations

import os
import resource
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from app.config import GIB, Settings
from app.core.threads import usable_cpus

MEMORY_SHARE = 0.75
"""Share of the machine's memory the workers' caps add up to by default (the rest: the API,
the consumer, the page cache)."""
MEMORY_LIMIT_CEILING_BYTES = 8 * GIB
"""Largest default cap: about twice the peak address space of a 5M-point pair (figures in
docs/performance.md); the rest is room for the thread stacks and malloc arenas of BLAS threads
on many-core machines."""
MEMORY_LIMIT_FLOOR_BYTES = 1 * GIB
"""Smallest default cap: an idle worker with the pipeline loaded already maps a good part of it
(figure in docs/performance.md)."""
_CGROUP_MEMORY_FILES = (
    Path("/sys/fs/cgroup/memory.max"),  # cgroup v2
    Path("/sys/fs/cgroup/memory/memory.limit_in_bytes"),  # cgroup v1
)


def cgroup_memory_limit() -> int | None:
    """The memory limit of this process's container (cgroup), or None when there is none."""
    for path in _CGROUP_MEMORY_FILES:
        try:
            text = path.read_text().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < 2**60:  # v1 says "no limit" with a huge number
            return int(text)
    return None


def machine_memory_bytes() -> int | None:
    """Physical memory, or the container's memory limit when lower; None if unknown."""
    try:
        physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError):
        physical = 0
    limits = [value for value in (physical, cgroup_memory_limit()) if value and value > 0]
    return min(limits) if limits else None


def default_memory_limit(workers: int, memory_bytes: int | None = None) -> int | None:
    """The default job cap: 75 % of the memory shared by ``workers``, within 1 to 8 GiB."""
    memory = machine_memory_bytes() if memory_bytes is None else memory_bytes
    if not memory:
        return None
    share = int(memory * MEMORY_SHARE / max(workers, 1))
    return max(MEMORY_LIMIT_FLOOR_BYTES, min(MEMORY_LIMIT_CEILING_BYTES, share))


def job_memory_limit(settings: Settings, workers: int | None = None) -> int | None:
    """The ``RLIMIT_AS`` of a job in bytes: the setting, or the default when it is ``auto``."""
    configured = settings.job_memory_limit_bytes
    if configured == "auto":
        return default_memory_limit(workers or settings.workers)
    return configured if isinstance(configured, int) and configured > 0 else None


def job_threads(settings: Settings, workers: int | None = None) -> int:
    """Threads a job may use: the setting, else this machine's CPUs shared by the workers."""
    if settings.job_threads:
        return settings.job_threads
    return max(1, usable_cpus() // max(workers or settings.workers, 1))


@contextmanager
def memory_limit(limit_bytes: int | None) -> Iterator[None]:
    """Cap this process's address space (RLIMIT_AS) at ``limit_bytes`` while inside."""
    if not limit_bytes:
        yield
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    capped = limit_bytes if hard == resource.RLIM_INFINITY else min(limit_bytes, hard)
    resource.setrlimit(resource.RLIMIT_AS, (capped, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
