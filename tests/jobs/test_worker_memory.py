"""Each job worker fixes its allocator when it starts and hands its free heap back after each
task: a worker that runs tiles and crop passes before any job of its own (so never set up by
the job's own start) holds only live data when the next tile, sized by the budget, begins."""

from __future__ import annotations

import pytest
from huey import MemoryHuey

import app.jobs.consumer as consumer
from app.config import Settings


def test_a_worker_fixes_its_allocator_on_start_and_trims_after_each_task(
    job_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[str] = []
    monkeypatch.setattr(
        consumer, "release_freed_memory_promptly", lambda: calls.append("thresholds") or True
    )
    monkeypatch.setattr(consumer, "return_free_heap", lambda: calls.append("trim") or True)
    huey = MemoryHuey("worker-memory", immediate=False)
    consumer.install_worker_hooks(huey, job_settings)

    @huey.task()
    def a_tile(job_id: str) -> str:
        calls.append("task")
        return job_id

    for hook in huey._startup.values():  # what Huey's worker runs as it starts
        hook()
    assert calls == ["thresholds"]
    huey.execute(a_tile.s("job-1"))
    huey.execute(a_tile.s("job-2"))
    assert calls == ["thresholds", "task", "trim", "task", "trim"]
