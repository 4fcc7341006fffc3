"""How many threads the numeric core may use: one definition for every stage.

``OMP_NUM_THREADS`` is the budget a caller gives a process (the service sets it per job worker,
the benchmarks per configuration); without it, every CPU the process may run on.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

__all__ = [
    "OPENMP_WAIT_POLICY",
    "available_threads",
    "concurrently",
    "configured_threads",
    "for_each_chunk",
    "prefer_passive_openmp_waits",
    "usable_cpus",
]

Rows = TypeVar("Rows")
First = TypeVar("First")
Second = TypeVar("Second")

OPENMP_WAIT_POLICY = "PASSIVE"
"""What ``OMP_WAIT_POLICY`` defaults to in a process that imports the core (see below)."""


def prefer_passive_openmp_waits() -> None:
    """Default ``OMP_WAIT_POLICY`` to ``PASSIVE`` (a caller's own setting is kept).

    The localiser runs the reference's and the scan's KD-tree queries on two threads, each
    query an OpenMP loop, while alignment or numpy work runs beside them: more threads than
    cores.  With the default (active) policy a thread that finishes its share of a loop spins
    for its team-mates, burning the core another thread needs.  Passive waits let it sleep,
    which saves wall and CPU time on the 1M-point pair (figures in docs/performance.md).
    OpenMP runtimes read the
    variable when they load, so this runs when ``app.core`` is imported, before pykdtree,
    small_gicp or scikit-learn load theirs; child processes inherit it.
    """
    os.environ.setdefault("OMP_WAIT_POLICY", OPENMP_WAIT_POLICY)


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


def for_each_chunk(work: Callable[[Rows], object], chunks: Iterable[Rows], threads: int) -> None:
    """Call ``work(rows)`` for every chunk of one pass, on up to ``threads`` threads.

    numpy releases the GIL in its array loops (gathers, ufuncs, ``einsum``), so the chunks of a
    pass over a cloud overlap on two cores; each ``work`` call must write only its own rows, so
    the result is the same on any number of threads.  The first exception of a chunk is raised
    here once the chunks running with it have finished (the others are not started).  At most
    ``2 * threads`` chunks are taken from ``chunks`` ahead of the ones finished: a generator of
    large chunks (the detector's calibration resamples) holds a few, never all of them.
    """
    if threads < 2:
        for rows in chunks:
            work(rows)
        return
    pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="chunks")
    pending: deque[Future[object]] = deque()
    try:
        for rows in chunks:
            pending.append(pool.submit(work, rows))
            if len(pending) > 2 * threads:
                pending.popleft().result()
        while pending:
            pending.popleft().result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def concurrently(
    threads: int, first: Callable[[], First], second: Callable[[], Second]
) -> tuple[First, Second]:
    """``first()`` and ``second()``, the first on a helper thread when ``threads`` >= 2.

    For two independent steps (e.g. one per cloud of a pair) whose work is mostly numpy array
    loops or KD-tree queries, which release the GIL; the results are the same either way.
    """
    if threads < 2:
        return first(), second()
    with ThreadPoolExecutor(max_workers=1) as pool:
        future = pool.submit(first)
        second_result = second()
        return future.result(), second_result
