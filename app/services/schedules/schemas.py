"""Request and response bodies of schedules and their runs."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, Field, StringConstraints

from app.db.models import ScheduleRunStatus
from app.services.schemas import DetectorConfig, RowRead, StrictBody, UtcDatetime

CatchUp = Literal["latest", "each", "none"]
Cron = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=200)]
TimeZoneName = Annotated[str, StringConstraints(min_length=1, max_length=64)]
Seconds = Annotated[int, Field(ge=1, le=366 * 24 * 3600)]


class DirectorySource(StrictBody):
    """Scans dropped in a server-side directory (under a root the operator allowed)."""

    directory: Annotated[str, StringConstraints(min_length=1, max_length=4096)]


class UrlSource(StrictBody):
    """A scan fetched from an HTTP(S) URL at each run."""

    url: Annotated[str, StringConstraints(min_length=1, max_length=2000)]


Source = Literal["uploads"] | DirectorySource | UrlSource


class ScheduleCreate(StrictBody):
    """A new schedule: ``cron`` (in ``timezone``) or ``interval_seconds``, exactly one."""

    cron: Cron | None = None
    interval_seconds: Seconds | None = None
    timezone: TimeZoneName = "UTC"
    source: Source | None = "uploads"
    stale_after_seconds: Seconds | None = None
    detector: DetectorConfig | None = None
    catch_up: CatchUp = "latest"
    compare_previous: bool = False
    enabled: bool = True


class ScheduleUpdate(StrictBody):
    """Fields of a schedule to change; absent fields are kept."""

    cron: Cron | None = None
    interval_seconds: Seconds | None = None
    timezone: TimeZoneName | None = None
    source: Source | None = None
    stale_after_seconds: Seconds | None = None
    detector: DetectorConfig | None = None
    catch_up: CatchUp | None = None
    compare_previous: bool | None = None
    enabled: bool | None = None


class ScheduleRead(BaseModel):
    """A schedule as the API shows it, with when it runs next."""

    id: str
    site_id: str
    cron: str | None
    interval_seconds: int | None
    timezone: str
    source: Any
    stale_after_seconds: int | None
    detector: DetectorConfig | None
    catch_up: CatchUp
    compare_previous: bool
    enabled: bool
    last_period_start: UtcDatetime | None
    next_run_at: UtcDatetime | None
    stale_since: UtcDatetime | None
    missed_since: UtcDatetime | None = Field(
        default=None,
        description="Start of the current spell of missed periods (schedule.missed was sent "
        "for it); null once a run compares.",
    )
    created_at: UtcDatetime


class ScheduleRunRead(RowRead):
    """One period of a schedule and what came of it."""

    id: str
    schedule_id: str
    period_start: UtcDatetime
    kind: Literal["scheduled", "manual"]
    status: ScheduleRunStatus
    scan_id: str | None
    job_id: str | None
    trend_job_id: str | None
    error: str | None
    reason: str | None = Field(
        default=None,
        description="Why a missed or skipped run compared nothing, and what to do about it.",
    )
    created_at: UtcDatetime
    finished_at: UtcDatetime | None
