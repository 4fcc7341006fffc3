"""The worker's default memory cap: derived from the machine, overridable, 0 / "none" disable it."""

from __future__ import annotations

import contextlib
import os
import resource
from pathlib import Path

import pytest

from app.config import GIB, Settings, get_settings
from app.jobs import limits
from app.jobs.consumer import MEMORY_LIMIT_ENV, fix_job_memory_limit
from app.jobs.limits import (
    default_memory_limit,
    job_memory_limit,
    machine_memory_bytes,
    memory_limit,
)

CGROUP_MEMORY_FILES = ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes")


def memory_of_this_machine() -> int:
    """``MemTotal`` of ``/proc/meminfo``, or the container's memory limit when lower."""
    with open("/proc/meminfo") as meminfo:
        memory = next(
            int(line.split()[1]) * 1024 for line in meminfo if line.startswith("MemTotal:")
        )
    for path in CGROUP_MEMORY_FILES:
        with contextlib.suppress(OSError), open(path) as limit_file:
            text = limit_file.read().strip()
            if text.isdigit():  # cgroup v1 says "no limit" with a huge number: min() drops it
                memory = min(memory, int(text))
    return memory


def expected_cap(memory: int, workers: int) -> int:
    """The documented default: 75 % of ``memory`` shared by ``workers``, within 1 to 8 GiB."""
    return max(1 * GIB, min(8 * GIB, memory * 3 // 4 // workers))


@pytest.mark.parametrize(
    ("memory", "workers", "expected"),
    [
        (16 * GIB, 2, 6 * GIB),  # 75 % of 16 GiB shared by 2 workers
        (16 * GIB, 4, 3 * GIB),
        (64 * GIB, 2, 8 * GIB),  # never above the ceiling
        (4 * GIB, 8, 1 * GIB),  # never below the floor
        (0, 2, None),  # memory unknown: no cap
    ],
)
def test_the_default_is_three_quarters_of_memory_per_worker_within_bounds(
    memory: int, workers: int, expected: int | None
) -> None:
    assert default_memory_limit(workers, memory_bytes=memory) == expected


def test_auto_is_the_default_and_derives_from_this_machine(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv(MEMORY_LIMIT_ENV, raising=False)
    settings = Settings(workers=3)
    assert settings.job_memory_limit_bytes == "auto"
    memory = memory_of_this_machine()
    assert machine_memory_bytes() == memory
    for workers, limit in ((3, job_memory_limit(settings)), (1, job_memory_limit(settings, 1))):
        assert limit is not None and abs(limit - expected_cap(memory, workers)) <= 1, workers


def test_a_container_limit_below_the_machine_s_memory_wins(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv(MEMORY_LIMIT_ENV, raising=False)
    version_2, version_1 = tmp_path / "memory.max", tmp_path / "memory.limit_in_bytes"
    monkeypatch.setattr(limits, "_CGROUP_MEMORY_FILES", (version_2, version_1))
    version_2.write_text("max\n")  # cgroup v2 without a limit: the v1 file is read next
    version_1.write_text(f"{4 * GIB}\n")
    container = min(4 * GIB, memory_of_this_machine())

    assert machine_memory_bytes() == container
    assert job_memory_limit(Settings(workers=2)) == expected_cap(container, 2)

    version_1.write_text(f"{2**63 - 4096}\n")  # cgroup v1's "no limit"
    assert machine_memory_bytes() == memory_of_this_machine()


@pytest.mark.parametrize("value", ["0", "none", "None", "off", "unlimited"])
def test_zero_or_none_disables_the_cap(monkeypatch: pytest.MonkeyPatch, value: str) -> None:
    monkeypatch.setenv(MEMORY_LIMIT_ENV, value)
    settings = Settings()
    assert settings.job_memory_limit_bytes is None
    assert job_memory_limit(settings) is None
    before = resource.getrlimit(resource.RLIMIT_AS)
    with memory_limit(job_memory_limit(settings)):
        assert resource.getrlimit(resource.RLIMIT_AS) == before


def test_an_explicit_cap_overrides_the_default(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(MEMORY_LIMIT_ENV, str(3 * GIB))
    settings = Settings()
    assert job_memory_limit(settings) == 3 * GIB
    assert job_memory_limit(settings.model_copy(update={"job_memory_limit_bytes": 0})) is None
    before = resource.getrlimit(resource.RLIMIT_AS)
    with memory_limit(job_memory_limit(settings)):
        assert resource.getrlimit(resource.RLIMIT_AS)[0] == min(
            3 * GIB, before[1] if before[1] != resource.RLIM_INFINITY else 3 * GIB
        )
    assert resource.getrlimit(resource.RLIMIT_AS) == before
    with pytest.raises(ValueError):
        Settings(job_memory_limit_bytes=-1)


@pytest.mark.usefixtures("without_consumer_exports")
def test_the_consumer_fixes_the_cap_once_for_its_workers(monkeypatch: pytest.MonkeyPatch) -> None:
    expected = expected_cap(memory_of_this_machine(), 4)
    fixed = fix_job_memory_limit(Settings(workers=2), workers=4)
    assert isinstance(fixed.job_memory_limit_bytes, int)
    assert abs(fixed.job_memory_limit_bytes - expected) <= 1
    assert os.environ[MEMORY_LIMIT_ENV] == str(fixed.job_memory_limit_bytes)
    assert get_settings().job_memory_limit_bytes == fixed.job_memory_limit_bytes  # workers read

    monkeypatch.setenv(MEMORY_LIMIT_ENV, "none")
    get_settings.cache_clear()
    fixed = fix_job_memory_limit(get_settings(), workers=4)
    assert fixed.job_memory_limit_bytes is None
    assert os.environ[MEMORY_LIMIT_ENV] == "0"
    assert get_settings().job_memory_limit_bytes is None
    get_settings.cache_clear()
