"""Make glibc return freed large arrays to the system at once, so peak memory is live data.

glibc serves allocations above ``M_MMAP_THRESHOLD`` (128 KiB) with their own mappings and
unmaps them on free, but each time such a block is freed it raises the threshold (up to
32 MiB), after which equally large arrays come from the heap, whose freed space is kept.  A
comparison allocates and frees many 1-30 MB temporaries (chunked neighbour gathers, KD-tree
query results), so the heap grows by hundreds of MB that no array uses.  Setting the threshold
explicitly turns the dynamic adjustment off.

It is fixed at 1 MiB rather than glibc's initial 128 KiB: every block above the threshold is
a fresh mapping whose pages fault (and are zeroed) on first touch, and the localiser and the
detectors allocate thousands of 0.1-1 MB chunk temporaries.

Fixing the mmap threshold also freezes glibc's trim threshold at 128 KiB: whenever more than
that is free at the top of the heap it is handed back, and the next chunk temporary faults
the same pages in again.  It is fixed at 32 MiB (at most that much freed heap stays
resident).  The measurements behind all three choices are in docs/performance.md.

A one-off comparison (the CLI) also keeps :data:`HEAP_TOP_PAD_BYTES` of free space at the top
of the heap (:func:`keep_heap_headroom`): glibc grows the heap by that much more each time and
trims it back no further, so the comparison's temporaries reuse pages already faulted in (the
1M class: about 40 % fewer minor faults, 0.2-0.3 s less system CPU, the same peak resident set).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
from collections.abc import Callable

__all__ = [
    "HEAP_TOP_PAD_BYTES",
    "MMAP_THRESHOLD_BYTES",
    "TRIM_THRESHOLD_BYTES",
    "keep_heap_headroom",
    "release_freed_memory_promptly",
    "return_free_heap",
]

MMAP_THRESHOLD_BYTES = 1024 * 1024
"""Fixed here instead of growing with each large free (glibc starts at 128 KiB)."""
TRIM_THRESHOLD_BYTES = 32 * 1024 * 1024
"""Free space kept at the top of the heap before glibc gives it back (default 128 KiB)."""
HEAP_TOP_PAD_BYTES = 64 * 1024 * 1024
"""Free space glibc adds when it grows the heap and keeps when it trims it (default 128 KiB)."""
_M_TRIM_THRESHOLD = -1  # from <malloc.h>
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3


def _libc() -> ctypes.CDLL | None:
    """glibc, or None elsewhere (not Linux, or a C library without mallopt)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt, libc.malloc_trim  # noqa: B018 (glibc's, not musl's)
    except (OSError, AttributeError):
        return None
    return libc


def _mallopt() -> Callable[[int, int], int] | None:
    """glibc's ``mallopt(param, value)``, typed; None where there is no glibc."""
    libc = _libc()
    if libc is None:
        return None
    mallopt = libc.mallopt
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return mallopt


def release_freed_memory_promptly() -> bool:
    """Fix glibc's mmap and trim thresholds for this process (a no-op elsewhere).

    Returns
    -------
    bool
        True when the settings were applied (Linux with glibc).
    """
    mallopt = _mallopt()
    if mallopt is None:
        return False
    trimmed = mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(trimmed)


def keep_heap_headroom() -> bool:
    """Keep :data:`HEAP_TOP_PAD_BYTES` of free heap for reuse in this process (glibc's
    ``M_TOP_PAD``; a no-op elsewhere).

    For a process that runs one comparison and exits (the CLI): at most that much freed memory
    stays resident, and the comparison's temporaries fault fewer fresh pages in.  The job
    workers, which run task after task, keep glibc's default.

    Returns
    -------
    bool
        True when the setting was applied (Linux with glibc).
    """
    mallopt = _mallopt()
    if mallopt is None:
        return False
    return bool(mallopt(_M_TOP_PAD, HEAP_TOP_PAD_BYTES))


def return_free_heap() -> bool:
    """Hand the heap's free pages back to the system now (glibc's ``malloc_trim(0)``), so
    that the next task starts from live data only; whether any went back (False elsewhere)."""
    libc = _libc()
    if libc is None:
        return False
    libc.malloc_trim.argtypes = [ctypes.c_size_t]
    libc.malloc_trim.restype = ctypes.c_int
    return bool(libc.malloc_trim(0))
