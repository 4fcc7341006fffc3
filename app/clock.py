"""Time in one place: the current UTC time and how stored times are read and written.

SQLite hands datetimes back naive (they are UTC); PostgreSQL hands them back aware.  Every
layer reads a stored time through :func:`as_utc` and renders one through :func:`iso_utc`.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import overload


def utc_now() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(UTC)


@overload
def as_utc(moment: datetime) -> datetime: ...
@overload
def as_utc(moment: None) -> None: ...
def as_utc(moment: datetime | None) -> datetime | None:
    """``moment`` as aware UTC (naive values, as SQLite returns them, are taken to be UTC)."""
    if moment is None:
        return None
    return moment.replace(tzinfo=UTC) if moment.tzinfo is None else moment.astimezone(UTC)


def iso_utc(moment: datetime) -> str:
    """``moment`` as ISO 8601 in UTC to the second, with a ``Z`` suffix."""
    return as_utc(moment).isoformat(timespec="seconds").replace("+00:00", "Z")
