"""glibc's mmap threshold is fixed, so freed large temporaries leave the resident set."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from app.kit.allocator import release_freed_memory_promptly

PROGRAM = textwrap.dedent(
    """
    import sys
    import numpy as np
    from app.kit.allocator import release_freed_memory_promptly

    if sys.argv[1] == "fixed":
        assert release_freed_memory_promptly()

    def resident_mb():
        for line in open("/proc/self/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024

    # free one 8 MB array (glibc then raises its threshold to 8 MB), then allocate 50 arrays
    # of 4 MB with a small array after each (so the heap cannot shrink), and free the big ones
    np.ones(1_000_000).sum()
    start = resident_mb()
    blocks, keep = [], []
    for _ in range(50):
        blocks.append(np.ones(500_000))
        keep.append(np.ones(1_000))  # 8 kB: from malloc, not a small-object pool
    del blocks
    if sys.argv[1] == "trimmed":
        from app.kit.allocator import return_free_heap

        return_free_heap()
    print(resident_mb() - start)
    """
)


def retained_megabytes(mode: str) -> float:
    completed = subprocess.run(
        [sys.executable, "-c", PROGRAM, mode], capture_output=True, text=True, check=True
    )
    return float(completed.stdout.strip())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_fixed_threshold_returns_freed_arrays_to_the_system() -> None:
    assert release_freed_memory_promptly()
    default = retained_megabytes("default")
    fixed = retained_megabytes("fixed")
    assert fixed < 20, f"{fixed:.0f} MB still resident after freeing with the fixed threshold"
    assert default > 100, f"the default kept only {default:.0f} MB: the test shows nothing"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim: Linux only")
def test_returning_the_free_heap_hands_back_what_the_default_threshold_kept() -> None:
    # a worker trims after each task: what one tile freed is not resident under the next
    default = retained_megabytes("default")
    trimmed = retained_megabytes("trimmed")
    assert default > 100, f"the default kept only {default:.0f} MB: the test shows nothing"
    assert trimmed < 20, f"{trimmed:.0f} MB still resident after returning the free heap"


HEADROOM_PROGRAM = textwrap.dedent(
    """
    import ctypes
    import sys

    import numpy as np

    from app.kit.allocator import keep_heap_headroom, release_freed_memory_promptly

    class MallocInfo(ctypes.Structure):
        _fields_ = [(name, ctypes.c_size_t) for name in (
            "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
            "fordblks", "keepcost")]

    assert release_freed_memory_promptly()
    if sys.argv[1] == "headroom":
        assert keep_heap_headroom()
    # 8 MB of 8 kB arrays (under the mmap threshold: from the heap), so the heap grows
    kept = [np.ones(1_000) for _ in range(1_000)]
    mallinfo2 = ctypes.CDLL("libc.so.6").mallinfo2
    mallinfo2.restype = MallocInfo
    print(mallinfo2().keepcost / 2**20)
    """
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_headroom_keeps_free_heap_at_the_top_for_the_next_temporaries() -> None:
    from app.kit.allocator import HEAP_TOP_PAD_BYTES

    def free_top_megabytes(mode: str) -> float:
        command = [sys.executable, "-c", HEADROOM_PROGRAM, mode]
        completed = subprocess.run(command, capture_output=True, text=True, check=True)
        return float(completed.stdout.strip())

    default, headroom = free_top_megabytes("default"), free_top_megabytes("headroom")
    assert default < 8, f"{default:.1f} MB free at the top by default: the test shows nothing"
    assert headroom >= 0.5 * HEAP_TOP_PAD_BYTES / 2**20, f"only {headroom:.1f} MB kept"
