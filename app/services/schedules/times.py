"""When a schedule's periods start: cron expressions in a time zone, or fixed intervals.

A *period* starts at each fire time of the schedule and lasts until the next one; it is keyed by
its start in UTC.  Cron expressions are evaluated by :mod:`cronsim` on the wall clock of the
schedule's IANA zone (:mod:`zoneinfo`), with daylight-saving time handled as Debian's cron does:
a time that does not exist on a spring-forward day fires at the end of the gap (``30 1 * * *``
in Europe/Lisbon fires at 02:00 WEST on the last Sunday of March), and a time that happens
twice on a fall-back day fires once, at its first occurrence.  An interval schedule fires every
``interval_seconds`` from its anchor (its creation), whatever the zone.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from cronsim import CronSim, CronSimError

from app.clock import as_utc
from app.services.errors import ValidationFailedError

ONE_SECOND = timedelta(seconds=1)


def parse_timezone(name: str) -> ZoneInfo:
    """The IANA zone ``name``; 422 saying what to give otherwise."""
    try:
        if not name or name != name.strip() or name.startswith(("/", ".")) or ".." in name:
            raise ValueError(name)
        return ZoneInfo(name)
    except (ZoneInfoNotFoundError, ValueError, OSError) as exc:
        raise ValidationFailedError(
            f"unknown time zone {name!r}: give an IANA zone name such as 'Europe/Lisbon' or 'UTC'",
            code="invalid_timezone",
        ) from exc


def check_cron(expression: str) -> None:
    """422 with cronsim's reason when ``expression`` is not a five-field cron expression."""
    try:
        if len(expression.split()) != 5:
            raise CronSimError("it needs exactly five fields (no seconds field)")
        next(CronSim(expression, datetime.now(UTC)))
    except (CronSimError, StopIteration) as exc:
        raise ValidationFailedError(
            f"invalid cron expression {expression!r} ({exc}): give five fields "
            "'minute hour day-of-month month day-of-week', e.g. '0 2 * * *' for 02:00 daily",
            code="invalid_cron",
        ) from exc


@dataclass(frozen=True)
class Rhythm:
    """When a schedule fires: ``cron`` in ``timezone``, or every ``interval_seconds`` from
    ``anchor``."""

    cron: str | None
    interval_seconds: int | None
    timezone: str
    anchor: datetime

    def _zone(self) -> ZoneInfo:
        return parse_timezone(self.timezone)

    def next_after(self, moment: datetime) -> datetime:
        """The first fire time strictly after ``moment`` (UTC)."""
        moment = as_utc(moment)
        if self.cron is not None:
            return as_utc(next(CronSim(self.cron, moment.astimezone(self._zone()))))
        step = timedelta(seconds=self._interval())
        anchor = as_utc(self.anchor)
        if moment < anchor:
            return anchor + step
        elapsed = int((moment - anchor) / step)
        return anchor + step * (elapsed + 1)

    def starts_between(self, after: datetime, until: datetime, limit: int) -> list[datetime]:
        """Fire times ``t`` with ``after < t <= until`` (UTC, oldest first): the newest
        ``limit`` of them when there are more."""
        after, until = as_utc(after), as_utc(until)
        starts: list[datetime] = []
        if until <= after:
            return starts
        if self.cron is not None:
            backwards = CronSim(self.cron, (until + ONE_SECOND).astimezone(self._zone()), True)
            for local_start in backwards:
                start = as_utc(local_start)
                if start <= after or len(starts) >= limit:
                    break
                if start <= until:
                    starts.append(start)
        else:
            step = timedelta(seconds=self._interval())
            anchor = as_utc(self.anchor)
            newest = int((until - anchor) / step)
            while newest >= 1 and len(starts) < limit:
                start = anchor + step * newest
                if start <= after:
                    break
                starts.append(start)
                newest -= 1
        starts.reverse()
        return starts

    def _interval(self) -> int:
        if self.interval_seconds is None:
            raise ValueError("a rhythm has a cron expression or an interval")
        return self.interval_seconds
