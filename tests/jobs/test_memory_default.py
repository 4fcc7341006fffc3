"""The worker's default memory cap: derived from the machine, overridable, 0 / "none" disable it."""

from __future__ import annotations

import os
import resource

import pytest

from app.config import GIB, Settings, get_settings
from app.jobs.consumer import MEMORY_LIMIT_ENV, fix_job_memory_limit
from app.jobs.limits import (
    MEMORY_LIMIT_CEILING_BYTES,
    MEMORY_LIMIT_FLOOR_BYTES,
    default_memory_limit,
    job_memory_limit,
    machine_memory_bytes,
    memory_limit,
)


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
    memory = machine_memory_bytes()
    assert memory is not None and 0 < memory <= os.sysconf("SC_PAGE_SIZE") * os.sysconf(
        "SC_PHYS_PAGES"
    )
    expected = max(MEMORY_LIMIT_FLOOR_BYTES, min(MEMORY_LIMIT_CEILING_BYTES, memory * 3 // 4 // 3))
    limit = job_memory_limit(settings)
    assert limit is not None and abs(limit - expected) <= 1
    assert job_memory_limit(settings, workers=1) == default_memory_limit(1)


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


def test_the_consumer_fixes_the_cap_once_for_its_workers(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(MEMORY_LIMIT_ENV, raising=False)
    fixed = fix_job_memory_limit(Settings(workers=2), workers=4)
    assert fixed.job_memory_limit_bytes == default_memory_limit(4)
    assert os.environ[MEMORY_LIMIT_ENV] == str(default_memory_limit(4))
    assert get_settings().job_memory_limit_bytes == default_memory_limit(4)  # what workers read

    monkeypatch.setenv(MEMORY_LIMIT_ENV, "none")
    get_settings.cache_clear()
    fixed = fix_job_memory_limit(get_settings(), workers=4)
    assert fixed.job_memory_limit_bytes is None
    assert os.environ[MEMORY_LIMIT_ENV] == "0"
    assert get_settings().job_memory_limit_bytes is None
    get_settings.cache_clear()
