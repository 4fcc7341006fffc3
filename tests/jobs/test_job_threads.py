"""Threads a job may use: the CPUs shared among the workers unless set; workers inherit it."""

from __future__ import annotations

import os

import pytest

from app.config import Settings, get_settings
from app.core.threads import usable_cpus
from app.jobs.consumer import JOB_THREADS_ENV, fix_job_memory_limit
from app.jobs.limits import job_threads


def cores() -> int:
    return usable_cpus()


def test_the_default_shares_the_cpus_among_the_workers() -> None:
    assert job_threads(Settings(workers=1)) == cores()
    assert job_threads(Settings(workers=1), workers=cores()) == 1
    assert job_threads(Settings(workers=cores() * 4)) == 1  # never below one


def test_a_configured_thread_count_wins() -> None:
    assert job_threads(Settings(workers=8, job_threads=3)) == 3


def test_the_setting_rejects_zero() -> None:
    with pytest.raises(ValueError, match="job_threads"):
        Settings(job_threads=0)


@pytest.mark.usefixtures("without_consumer_exports")
def test_the_consumer_exports_the_count_its_workers_read() -> None:
    get_settings.cache_clear()
    fixed = fix_job_memory_limit(Settings(workers=1), workers=cores())
    assert fixed.job_threads == 1
    assert os.environ[JOB_THREADS_ENV] == "1"
    assert get_settings().job_threads == 1  # what a forked worker reads
    get_settings.cache_clear()
