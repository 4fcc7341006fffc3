"""The Huey task: it takes a job id only; everything else is read from the ``job`` table."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from huey import Huey

JOB_TASK_NAME = "run_job"


def run_job(job_id: str) -> None:
    """Run job ``job_id`` if it still needs running (claim, compare, store; idempotent)."""
    from app.config import get_settings
    from app.jobs.execution import execute_job

    execute_job(job_id, get_settings())


def register_tasks(huey: Huey) -> Callable[..., Any]:
    """Register :func:`run_job` on ``huey`` (no Huey retries: attempts live in the job table)."""
    return huey.task(name=JOB_TASK_NAME, retries=0)(run_job)  # type: ignore[no-any-return]
