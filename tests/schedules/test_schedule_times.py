"""Periods of cron schedules in a real time zone across DST, and of interval schedules."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from itertools import pairwise
from zoneinfo import ZoneInfo

from app.services.schedules.times import Rhythm

LISBON = ZoneInfo("Europe/Lisbon")
ANCHOR = datetime(2026, 1, 1, tzinfo=UTC)


def lisbon(*fields: int) -> datetime:
    """A Lisbon wall-clock time."""
    return datetime(*fields, tzinfo=LISBON)


def test_a_daily_cron_keeps_its_wall_clock_time_across_both_transitions() -> None:
    nightly = Rhythm("0 2 * * *", None, "Europe/Lisbon", ANCHOR)
    starts = nightly.starts_between(
        datetime(2026, 3, 27, tzinfo=UTC), datetime(2026, 10, 27, tzinfo=UTC), 1000
    )
    local = [start.astimezone(LISBON) for start in starts]
    assert len(starts) == (datetime(2026, 10, 27) - datetime(2026, 3, 27)).days
    assert all((moment.hour, moment.minute) == (2, 0) for moment in local)
    # 02:00 is 02:00 UTC in winter (WET) and 01:00 UTC in summer (WEST)
    assert starts[0] == datetime(2026, 3, 27, 2, tzinfo=UTC)
    assert starts[3] == datetime(2026, 3, 30, 1, tzinfo=UTC)
    assert starts[-1] == datetime(2026, 10, 26, 2, tzinfo=UTC)
    assert len(set(starts)) == len(starts)


def test_spring_forward_a_time_in_the_gap_runs_once_at_the_end_of_the_gap() -> None:
    # 2026-03-29: Lisbon jumps from 01:00 WET to 02:00 WEST; 01:30 does not exist that night
    rhythm = Rhythm("30 1 * * *", None, "Europe/Lisbon", ANCHOR)
    starts = rhythm.starts_between(lisbon(2026, 3, 28, 0, 0), lisbon(2026, 3, 30, 23, 0), 1000)
    assert [start.astimezone(LISBON) for start in starts] == [
        lisbon(2026, 3, 28, 1, 30),
        lisbon(2026, 3, 29, 2, 0),  # the gap's end, 01:00 UTC
        lisbon(2026, 3, 30, 1, 30),
    ]
    assert starts[1] == datetime(2026, 3, 29, 1, 0, tzinfo=UTC)


def test_fall_back_a_repeated_time_runs_once() -> None:
    # 2026-10-25: Lisbon goes back from 02:00 WEST to 01:00 WET; 01:30 happens twice
    rhythm = Rhythm("30 1 * * *", None, "Europe/Lisbon", ANCHOR)
    starts = rhythm.starts_between(lisbon(2026, 10, 24, 0, 0), lisbon(2026, 10, 26, 23, 0), 1000)
    assert starts == [
        datetime(2026, 10, 24, 0, 30, tzinfo=UTC),
        datetime(2026, 10, 25, 0, 30, tzinfo=UTC),  # the first 01:30 (WEST) only
        datetime(2026, 10, 26, 1, 30, tzinfo=UTC),
    ]


def test_an_hourly_cron_over_the_fall_back_night_has_no_duplicate_period() -> None:
    rhythm = Rhythm("0 * * * *", None, "Europe/Lisbon", ANCHOR)
    starts = rhythm.starts_between(
        datetime(2026, 10, 24, 22, tzinfo=UTC), datetime(2026, 10, 25, 4, tzinfo=UTC), 1000
    )
    assert len(starts) == len(set(starts))
    assert starts == sorted(starts)
    gaps = {later - earlier for earlier, later in pairwise(starts)}
    assert max(gaps) <= timedelta(hours=2)


def test_next_after_matches_the_periods() -> None:
    rhythm = Rhythm("30 1 * * *", None, "Europe/Lisbon", ANCHOR)
    assert rhythm.next_after(datetime(2026, 3, 28, 23, tzinfo=UTC)) == datetime(
        2026, 3, 29, 1, 0, tzinfo=UTC
    )


def test_interval_periods_count_from_the_anchor_and_keep_the_newest() -> None:
    anchor = datetime(2026, 1, 1, 0, 0, 30, tzinfo=UTC)
    rhythm = Rhythm(None, 3600, "Europe/Lisbon", anchor)
    until = anchor + timedelta(hours=5, minutes=10)
    assert rhythm.starts_between(anchor, until, 1000) == [
        anchor + timedelta(hours=hours) for hours in range(1, 6)
    ]
    assert rhythm.starts_between(anchor, until, 2) == [
        anchor + timedelta(hours=4),
        anchor + timedelta(hours=5),
    ]
    assert rhythm.next_after(until) == anchor + timedelta(hours=6)
    assert rhythm.starts_between(until, anchor, 10) == []
