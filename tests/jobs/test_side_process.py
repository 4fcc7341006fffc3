"""The consumer's side processes (webhook deliveries, schedule ticker): started, replaced when
they die, stopped by SIGTERM after the step in flight."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

from app.config import Settings
from app.jobs.consumer import schedule_loop
from app.jobs.side_process import SideProcess
from app.testing.waiting import wait_until


def test_a_side_process_that_dies_is_replaced_and_stops_on_sigterm(
    job_settings: Settings, tmp_path: Path
) -> None:
    marks = tmp_path / "ticks"
    marks.mkdir()

    def tick(settings: Settings) -> None:
        (marks / f"{os.getpid()}-{time.monotonic_ns()}").touch()

    settings = job_settings.model_copy(update={"schedule_tick_seconds": 0.05})
    ticker = SideProcess(settings, "schedule-ticker", schedule_loop(tick))
    ticker.ensure_running()
    first = ticker.process
    assert first is not None
    wait_until(lambda: len(list(marks.iterdir())) >= 3, 30, "three ticks")
    ticker.ensure_running()  # alive: left alone
    assert ticker.process is first
    first.kill()
    first.join(10)
    ticker.ensure_running()
    second = ticker.process
    assert second is not None and second.pid != first.pid
    wait_until(
        lambda: any(path.name.startswith(f"{second.pid}-") for path in marks.iterdir()),
        30,
        "a tick of the replacement",
    )
    ticker.stop(timeout=10)
    assert not second.is_alive()
    assert second.exitcode == 0  # SIGTERM ends the loop, not the process mid-step


def test_a_failing_tick_is_logged_and_the_loop_goes_on(job_settings: Settings) -> None:
    calls: list[int] = []
    stop = threading.Event()

    def tick(settings: Settings) -> None:
        calls.append(1)
        if len(calls) >= 3:
            stop.set()
        raise RuntimeError("database away")

    settings = job_settings.model_copy(update={"schedule_tick_seconds": 0.01})
    schedule_loop(tick)(settings, stop)
    assert len(calls) == 3
