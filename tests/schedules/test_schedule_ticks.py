"""The tick at chosen times: catch-up policies, missed and stale events, trend comparisons, and
two tickers racing for the same periods (each period runs once)."""

from __future__ import annotations

import subprocess
import sys
import threading
from collections import Counter
from datetime import datetime, timedelta
from typing import Any

import httpx

from app.clock import utc_now
from app.db.models import Job, ScheduleRun, ScheduleRunStatus
from app.db.session import transaction
from app.services.schedules.runs import TickReport, abandoned_after, claim_period, tick
from app.testing.files import room_ply
from app.testing.paths import PROJECT_ROOT
from tests.helpers.database import count_rows
from tests.helpers.http import site_with_reference, upload_accepted
from tests.helpers.schedules import created, new_schedule, runs_of
from tests.helpers.server import ApiServer


def test_catch_up_each_runs_every_missed_period(
    api: ApiServer, writer: httpx.Client, events: list[dict[str, Any]]
) -> None:
    site, _reference = site_with_reference(writer)
    # the detector of the upload's own job (PCA): the run reuses that job
    schedule = new_schedule(
        writer, site["id"], interval_seconds=600, catch_up="each", detector={"method": "pca"}
    )
    scan = upload_accepted(writer, site["id"], "night.ply", room_ply(5, with_box=True))
    start = created(schedule)
    # the scan arrived within the first period (seconds after creation); periods 2 and 3 had none
    report = tick(api.settings, start + timedelta(seconds=1805))
    runs = runs_of(writer, schedule["id"])
    assert [run["status"] for run in runs] == ["compared", "missed", "missed"]
    assert runs[0]["scan_id"] == scan["scan"]["id"]
    assert runs[0]["job_id"] == scan["job"]["id"]  # the upload's own comparison, not a copy
    assert sorted(report.runs) == ["compared", "missed"]
    missed = [event for event in events if event["type"] == "schedule.missed"]
    # one event for the spell of two missed periods (throttled as site.stale is)
    assert [event["run_id"] for event in missed] == [runs[1]["id"]]
    assert all(event["schedule_id"] == schedule["id"] for event in missed)
    # the same tick again (a restart) runs nothing twice
    assert tick(api.settings, start + timedelta(seconds=1805)).runs == {}
    assert count_rows(api, ScheduleRun, schedule_id=schedule["id"]) == 3


def test_catch_up_latest_runs_only_the_newest_period(
    api: ApiServer, writer: httpx.Client, events: list[dict[str, Any]]
) -> None:
    site, _reference = site_with_reference(writer)
    schedule = new_schedule(writer, site["id"], interval_seconds=600, catch_up="latest")
    scan = upload_accepted(writer, site["id"], "night.ply", room_ply(5, with_box=True))
    report = tick(api.settings, created(schedule) + timedelta(seconds=3 * 600 + 5))
    runs = runs_of(writer, schedule["id"])
    assert [run["status"] for run in runs] == ["skipped", "skipped", "compared"]
    assert runs[-1]["scan_id"] == scan["scan"]["id"]
    assert report.skipped == 2
    assert not [event for event in events if event["type"] == "schedule.missed"]


def test_catch_up_none_skips_late_periods_and_runs_one_on_time(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, _reference = site_with_reference(writer)
    schedule = new_schedule(writer, site["id"], interval_seconds=600, catch_up="none")
    upload_accepted(writer, site["id"], "night.ply", room_ply(5, with_box=True))
    start = created(schedule)
    tick(api.settings, start + timedelta(seconds=3 * 600 + 400))  # all three are late
    assert [run["status"] for run in runs_of(writer, schedule["id"])] == ["skipped"] * 3
    tick(api.settings, start + timedelta(seconds=4 * 600 + 10))  # period 4, ticked on time
    runs = runs_of(writer, schedule["id"])
    assert [run["status"] for run in runs] == ["skipped"] * 3 + ["compared"]


def test_compare_previous_adds_a_trend_job(api: ApiServer, writer: httpx.Client) -> None:
    site, reference = site_with_reference(writer)
    schedule = new_schedule(
        writer, site["id"], interval_seconds=600, compare_previous=True, detector={"method": "pca"}
    )
    first = upload_accepted(writer, site["id"], "first.ply", room_ply(5))
    second = upload_accepted(writer, site["id"], "second.ply", room_ply(6, with_box=True))
    tick(api.settings, created(schedule) + timedelta(seconds=605))
    (run,) = runs_of(writer, schedule["id"])
    assert run["status"] == "compared"
    assert run["scan_id"] == second["scan"]["id"]
    assert run["job_id"] == second["job"]["id"]
    trend = writer.get(f"/api/v1/jobs/{run['trend_job_id']}").json()
    assert (trend["reference_scan_id"], trend["scan_id"]) == (
        first["scan"]["id"],
        second["scan"]["id"],
    )
    assert reference["id"] not in (trend["reference_scan_id"],)


def test_a_site_without_new_scans_goes_stale_once_per_spell(
    api: ApiServer, writer: httpx.Client, events: list[dict[str, Any]]
) -> None:
    site, _reference = site_with_reference(writer)
    schedule = new_schedule(writer, site["id"], interval_seconds=3600, stale_after_seconds=7200)
    start = created(schedule)

    def stale_events() -> list[dict[str, Any]]:
        return [event for event in events if event["type"] == "site.stale"]

    tick(api.settings, start + timedelta(seconds=3605))
    assert stale_events() == []
    assert [run["status"] for run in runs_of(writer, schedule["id"])] == ["missed"]
    tick(api.settings, start + timedelta(hours=2, seconds=5))
    tick(api.settings, start + timedelta(hours=3, seconds=5))
    assert [event["site_id"] for event in stale_events()] == [site["id"]]
    assert writer.get(f"/api/v1/schedules/{schedule['id']}").json()["stale_since"] is not None
    # a scan arrives: the spell ends; two hours without one start a new spell
    upload_accepted(writer, site["id"], "back.ply", room_ply(7))
    tick(api.settings, datetime.now().astimezone() + timedelta(seconds=60))
    assert writer.get(f"/api/v1/schedules/{schedule['id']}").json()["stale_since"] is None
    tick(api.settings, datetime.now().astimezone() + timedelta(hours=2, seconds=60))
    assert len(stale_events()) == 2


def test_two_tickers_racing_run_each_period_once(api: ApiServer, writer: httpx.Client) -> None:
    site, _reference = site_with_reference(writer)
    schedules = [
        new_schedule(
            writer,
            site["id"],
            interval_seconds=60,
            catch_up="each",
            compare_previous=True,
            detector={"method": "pca"},  # the upload's detector: its job is reused
        )
        for _ in range(3)
    ]
    upload_accepted(writer, site["id"], "night.ply", room_ply(5, with_box=True))
    now = max(created(schedule) for schedule in schedules) + timedelta(seconds=20 * 60 + 5)
    barrier = threading.Barrier(4)
    reports: list[TickReport] = []

    def ticker() -> None:
        barrier.wait()
        reports.append(tick(api.settings, now))

    threads = [threading.Thread(target=ticker) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert len(reports) == 4
    jobs_before = count_rows(api, Job, site_id=site["id"])
    for schedule in schedules:
        runs = runs_of(writer, schedule["id"])
        periods = Counter(run["period_start"] for run in runs)
        assert len(runs) >= 20
        assert max(periods.values()) == 1  # 0 duplicate runs
        assert Counter(run["status"] for run in runs)["compared"] == 1
    claimed = [run_id for report in reports for ids in report.runs.values() for run_id in ids]
    assert (
        len(claimed)
        == len(set(claimed))
        == sum(len(runs_of(writer, schedule["id"])) for schedule in schedules)
    )
    # the three schedules compared the same scan: one comparison job, the upload's
    assert jobs_before == 1


TICKER_SCRIPT = """
import sys
from datetime import datetime
from app.config import Settings
from app.services.schedules.runs import tick
settings = Settings(data_dir=sys.argv[1])
report = tick(settings, datetime.fromisoformat(sys.argv[2]))
print(sum(len(ids) for ids in report.runs.values()))
"""


def test_two_ticker_processes_run_each_period_once(api: ApiServer, writer: httpx.Client) -> None:
    site, _reference = site_with_reference(writer)
    schedule = new_schedule(writer, site["id"], interval_seconds=60, catch_up="each")
    upload_accepted(writer, site["id"], "night.ply", room_ply(5, with_box=True))
    now = created(schedule) + timedelta(seconds=30 * 60 + 5)
    tickers = [
        subprocess.Popen(
            [sys.executable, "-c", TICKER_SCRIPT, str(api.data_dir), now.isoformat()],
            cwd=PROJECT_ROOT,
            stdout=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    handled = [int(ticker.communicate(timeout=180)[0].strip()) for ticker in tickers]
    runs = runs_of(writer, schedule["id"])
    assert len(runs) == 30 == sum(handled)
    assert len({run["period_start"] for run in runs}) == 30
    assert Counter(run["status"] for run in runs) == {"compared": 1, "missed": 29}


def test_a_paused_schedule_does_not_catch_up_when_enabled_again(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, _reference = site_with_reference(writer)
    schedule = new_schedule(writer, site["id"], interval_seconds=60, catch_up="each", enabled=False)
    assert writer.get(f"/api/v1/schedules/{schedule['id']}").json()["next_run_at"] is None
    assert tick(api.settings, created(schedule) + timedelta(minutes=10)).runs == {}
    enabled = writer.patch(f"/api/v1/schedules/{schedule['id']}", json={"enabled": True}).json()
    assert enabled["next_run_at"] is not None
    # the periods of the pause are not run, the next one after enabling is
    next_run = datetime.fromisoformat(enabled["next_run_at"].replace("Z", "+00:00"))
    tick(api.settings, next_run + timedelta(seconds=1))
    assert [run["status"] for run in runs_of(writer, schedule["id"])] == ["missed"]


def test_a_period_claimed_by_a_process_that_died_is_not_run_again(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, _reference = site_with_reference(writer)
    schedule = new_schedule(
        writer, site["id"], interval_seconds=600, catch_up="each", detector={"method": "pca"}
    )
    upload_accepted(writer, site["id"], "night.ply", room_ply(5, with_box=True))
    first_period = created(schedule) + timedelta(seconds=600)
    # a ticker claimed the first period, then was killed before running it
    abandoned = claim_period(
        api.settings, schedule["id"], first_period, "scheduled", ScheduleRunStatus.RUNNING
    )
    assert abandoned
    # soon after the claim, the run may still be live: left alone
    early = tick(api.settings, first_period + timedelta(seconds=5))
    assert "failed" not in early.runs
    # long after it (on the wall clock), the run is marked failed, saying why, and its period
    # is not run again
    with transaction(api.settings.sqlalchemy_url) as session:
        run = session.get_one(ScheduleRun, abandoned)
        run.created_at = utc_now() - abandoned_after(api.settings) - timedelta(seconds=5)
    report = tick(api.settings, first_period + timedelta(seconds=605))
    runs = runs_of(writer, schedule["id"])
    assert runs[0]["id"] == abandoned
    assert runs[0]["status"] == "failed"
    assert "interrupted" in runs[0]["error"]
    assert report.runs["failed"] == [abandoned]
    assert all(run["status"] != "running" for run in runs)
    assert count_rows(api, ScheduleRun, schedule_id=schedule["id"], status="running") == 0
    assert count_rows(api, Job, site_id=site["id"]) == 1
