"""SQLAlchemy 2 models: the durable state of the service.

Point clouds and per-point results live as files under the data directory (written atomically);
rows hold metadata, scores and regions.  The ``job`` table is the source of truth for background
work: the queue only carries job ids, and the recovery sweep re-enqueues what a dead worker left.
IDs are random hex UUIDs, never sequential.
"""

from __future__ import annotations

import uuid
from datetime import datetime
from enum import StrEnum
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    func,
    select,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, column_property, mapped_column, relationship

from app.clock import utc_now


def new_id() -> str:
    """A random 32-character hex id."""
    return uuid.uuid4().hex


class Base(DeclarativeBase):
    """Declarative base with a naming convention so Alembic batch migrations work on SQLite."""

    from sqlalchemy import MetaData

    metadata = MetaData(
        naming_convention={
            "ix": "ix_%(column_0_label)s",
            "uq": "uq_%(table_name)s_%(column_0_name)s",
            "ck": "ck_%(table_name)s_%(constraint_name)s",
            "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
            "pk": "pk_%(table_name)s",
        }
    )


Timestamp = DateTime(timezone=True)


class Organisation(Base):
    __tablename__ = "organisation"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)


class ApiToken(Base):
    __tablename__ = "api_token"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    organisation_id: Mapped[str] = mapped_column(ForeignKey("organisation.id", ondelete="CASCADE"))
    role: Mapped[str] = mapped_column(String(16))  # admin | writer | reader
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)  # sha256 hex of the token
    name: Mapped[str | None] = mapped_column(String(200), nullable=True)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)
    revoked_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)

    organisation: Mapped[Organisation] = relationship()


class Site(Base):
    __tablename__ = "site"
    __table_args__ = (UniqueConstraint("organisation_id", "name"),)

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    organisation_id: Mapped[str] = mapped_column(
        ForeignKey("organisation.id", ondelete="CASCADE"), index=True
    )
    name: Mapped[str] = mapped_column(String(200))
    description: Mapped[str | None] = mapped_column(Text, nullable=True)
    detector_method: Mapped[str] = mapped_column(String(16), default="gmm")
    detector_variant: Mapped[str] = mapped_column(String(16), default="improved")
    detector_params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    # No FK constraint to scan (cycle site <-> scan); the service keeps it consistent.
    reference_scan_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    # Thresholds learned from the site's reviewed jobs (app.core.site_calibration), recomputed
    # whenever a verdict changes; the worker passes them to the comparison.
    calibration: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)
    updated_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now, onupdate=utc_now)


class Scan(Base):
    __tablename__ = "scan"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    organisation_id: Mapped[str] = mapped_column(
        ForeignKey("organisation.id", ondelete="CASCADE"), index=True
    )
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id", ondelete="CASCADE"), index=True)
    filename: Mapped[str] = mapped_column(String(255))  # sanitised display name
    format: Mapped[str] = mapped_column(String(16))  # ply pcd las laz e57 xyz csv txt npy npz
    size_bytes: Mapped[int] = mapped_column(Integer)
    sha256: Mapped[str] = mapped_column(String(64))
    # bytes of the cached k-NN geometry of this scan as a reference (counted in the quota)
    geometry_cache_bytes: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    storage_path: Mapped[str] = mapped_column(String(500))  # relative to the data directory
    n_points: Mapped[int] = mapped_column(Integer)  # finite points
    n_dropped: Mapped[int] = mapped_column(Integer, default=0)  # NaN/inf rows dropped
    bbox_min: Mapped[list[float]] = mapped_column(JSON)
    bbox_max: Mapped[list[float]] = mapped_column(JSON)
    # Where the sensor was, in the file's frame: from the upload's ?sensor_origin= or the file
    # itself (a PCD VIEWPOINT, E57 scan poses). Lets localisation tell occluded (unobserved)
    # from removed. [x, y, z], or [[x, y, z], ...] for a cloud merged from several stations.
    sensor_origin: Mapped[list[float] | list[list[float]] | None] = mapped_column(
        JSON, nullable=True
    )
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now, index=True)


class ReferenceHistory(Base):
    """Every time a site's reference changed: which scan, when."""

    __tablename__ = "reference_history"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id", ondelete="CASCADE"), index=True)
    scan_id: Mapped[str] = mapped_column(ForeignKey("scan.id", ondelete="CASCADE"))
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)


class JobStatus(StrEnum):
    """Where a job is in its life: ``queued -> running -> succeeded | failed`` (a lost lease or a
    retry puts a running job back to ``queued``)."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"

    @classmethod
    def unfinished(cls) -> tuple[JobStatus, ...]:
        """The statuses of a job that still holds a place in the queue."""
        return (cls.QUEUED, cls.RUNNING)


class Job(Base):
    """A comparison of a scan against a reference scan; the source of truth for the queue."""

    __tablename__ = "job"
    __table_args__ = (
        Index("ix_job_site_created", "site_id", "created_at"),
        Index("ix_job_status_lease", "status", "lease_expires_at"),
    )

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    organisation_id: Mapped[str] = mapped_column(
        ForeignKey("organisation.id", ondelete="CASCADE"), index=True
    )
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id", ondelete="CASCADE"))
    reference_scan_id: Mapped[str] = mapped_column(ForeignKey("scan.id", ondelete="CASCADE"))
    scan_id: Mapped[str] = mapped_column(ForeignKey("scan.id", ondelete="CASCADE"))
    method: Mapped[str] = mapped_column(String(16))
    variant: Mapped[str] = mapped_column(String(16))
    params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # as requested
    # Every parameter in effect (the detector's get_params(), seed, stages, decision rule):
    # POST /jobs with these params replays the result exactly, whatever defaults change later.
    effective_params: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    status: Mapped[str] = mapped_column(String(16), default=JobStatus.QUEUED)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    stage: Mapped[str | None] = mapped_column(String(32), nullable=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer, default=3)
    lease_owner: Mapped[str | None] = mapped_column(String(64), nullable=True)
    lease_expires_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    enqueued_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    score: Mapped[float | None] = mapped_column(Float, nullable=True)
    threshold: Mapped[float | None] = mapped_column(Float, nullable=True)
    changed: Mapped[bool | None] = mapped_column(Boolean, nullable=True, index=True)
    calibration: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    registration: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    n_regions: Mapped[int | None] = mapped_column(Integer, nullable=True)
    timings: Mapped[dict[str, float] | None] = mapped_column(JSON, nullable=True)
    labels_path: Mapped[str | None] = mapped_column(String(500), nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)
    started_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    # indexed: the metrics' duration histogram reads the jobs finished in the last day
    finished_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True, index=True)
    # The X-Request-ID (or generated id) of the API request that created the job: the worker's
    # log lines about the job carry it, so one id follows an upload into its comparison.
    request_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    # The current review verdict ({"verdict", "note", "set_by", "set_at"}); history: JobVerdict.
    verdict: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    # Issue 15/19 (branch i19/explain): the sensor origins used (per side a list of {origin,
    # source, confidence}), quality warnings ([{code, message, ...}]) and the decision's
    # explanation ({..., text}); null until the job succeeded.
    sensor_origins: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    # clusters of candidates the other epoch did not cover (evidence no_coverage): listed for
    # review, never counted as change
    uncertain_regions: Mapped[list[dict[str, Any]] | None] = mapped_column(JSON, nullable=True)
    warnings: Mapped[list[dict[str, Any]] | None] = mapped_column(JSON, nullable=True)
    explanation: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)

    regions: Mapped[list[Region]] = relationship(
        back_populates="job", cascade="all, delete-orphan", order_by="Region.ordinal"
    )
    # The compared scans (their file names appear in JobRead); lists load them in one query each.
    reference_scan: Mapped[Scan] = relationship(foreign_keys=[reference_scan_id], viewonly=True)
    scan: Mapped[Scan] = relationship(foreign_keys=[scan_id], viewonly=True)


class Region(Base):
    """A connected cluster of changed points found by a job."""

    __tablename__ = "region"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    job_id: Mapped[str] = mapped_column(ForeignKey("job.id", ondelete="CASCADE"), index=True)
    ordinal: Mapped[int] = mapped_column(Integer)  # position in the job's region list
    kind: Mapped[str] = mapped_column(String(16))  # added | removed
    n_points: Mapped[int] = mapped_column(Integer)
    centroid: Mapped[list[float]] = mapped_column(JSON)
    bbox_min: Mapped[list[float]] = mapped_column(JSON)
    bbox_max: Mapped[list[float]] = mapped_column(JSON)
    mean_distance: Mapped[float] = mapped_column(Float)
    max_distance: Mapped[float] = mapped_column(Float)
    # seen_empty | surface_moved (why it is a change; no_coverage regions live on the job)
    evidence: Mapped[str] = mapped_column(String(16), default="seen_empty")
    confidence: Mapped[float | None] = mapped_column(Float, nullable=True)

    job: Mapped[Job] = relationship(back_populates="regions")


class IdempotencyRecord(Base):
    """The first response to a request carrying an ``Idempotency-Key``, replayed on retries."""

    __tablename__ = "idempotency_record"
    __table_args__ = (UniqueConstraint("organisation_id", "key"),)

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    organisation_id: Mapped[str] = mapped_column(ForeignKey("organisation.id", ondelete="CASCADE"))
    key: Mapped[str] = mapped_column(String(200))
    request_fingerprint: Mapped[str] = mapped_column(String(64))
    status_code: Mapped[int] = mapped_column(Integer)
    response_body: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)


# --- i16/verdicts: review verdicts (issue 16 part 3) ---


class JobVerdict(Base):
    """Every verdict a reviewer gave a job, oldest first; the newest is ``Job.verdict``."""

    __tablename__ = "job_verdict"
    __table_args__ = (Index("ix_job_verdict_job_created", "job_id", "created_at"),)

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    organisation_id: Mapped[str] = mapped_column(
        ForeignKey("organisation.id", ondelete="CASCADE"), index=True
    )
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id", ondelete="CASCADE"), index=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("job.id", ondelete="CASCADE"))
    verdict: Mapped[str] = mapped_column(String(16))  # confirmed | false_alarm | new_reference
    note: Mapped[str | None] = mapped_column(Text, nullable=True)
    token_id: Mapped[str | None] = mapped_column(String(32), nullable=True)  # who, by token
    token_name: Mapped[str | None] = mapped_column(String(200), nullable=True)
    role: Mapped[str] = mapped_column(String(16))
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)


# --- i16/schedules: scheduled comparisons of a site and the periods they ran -----------------


class ScheduleRunStatus(StrEnum):
    """What came of a schedule's period: ``running -> compared | missed | failed``;
    ``skipped`` (the catch-up policy) is final at once."""

    RUNNING = "running"
    COMPARED = "compared"
    MISSED = "missed"
    SKIPPED = "skipped"
    FAILED = "failed"


class Schedule(Base):
    """A rhythm (cron in a time zone, or a fixed interval) on which a site's scans are compared."""

    __tablename__ = "schedule"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    organisation_id: Mapped[str] = mapped_column(
        ForeignKey("organisation.id", ondelete="CASCADE"), index=True
    )
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id", ondelete="CASCADE"), index=True)
    cron: Mapped[str | None] = mapped_column(String(200), nullable=True)
    interval_seconds: Mapped[int | None] = mapped_column(Integer, nullable=True)
    timezone: Mapped[str] = mapped_column(String(64), default="UTC")
    # {"kind": "uploads"} | {"kind": "directory", "directory": ...} | {"kind": "url", "url": ...}
    source: Mapped[dict[str, Any]] = mapped_column(JSON)
    stale_after_seconds: Mapped[int | None] = mapped_column(Integer, nullable=True)
    detector: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    catch_up: Mapped[str] = mapped_column(String(16), default="latest")  # latest | each | none
    compare_previous: Mapped[bool] = mapped_column(Boolean, default=False)
    enabled: Mapped[bool] = mapped_column(Boolean, default=True)
    # The newest period handled (run, missed or skipped); None: none since created_at.
    last_period_start: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    # The scan the last compared run used: the next run takes a newer one.
    last_scan_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    last_scan_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    # What the source showed last (a directory's newest file, a URL's SHA-256).
    source_marker: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    # Set when site.stale was published; cleared when a scan arrives (one event per spell).
    stale_since: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    # Set when schedule.missed was published; cleared when a run compares (one event per spell).
    missed_since: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)
    updated_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now, onupdate=utc_now)


class ScheduleRun(Base):
    """One period of a schedule: at most one row per (schedule, period), whoever ticks."""

    __tablename__ = "schedule_run"
    __table_args__ = (
        UniqueConstraint("schedule_id", "period_start"),
        Index("ix_schedule_run_schedule_created", "schedule_id", "created_at"),
    )

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    organisation_id: Mapped[str] = mapped_column(
        ForeignKey("organisation.id", ondelete="CASCADE"), index=True
    )
    schedule_id: Mapped[str] = mapped_column(ForeignKey("schedule.id", ondelete="CASCADE"))
    period_start: Mapped[datetime] = mapped_column(Timestamp)  # UTC
    kind: Mapped[str] = mapped_column(String(16), default="scheduled")  # scheduled | manual
    status: Mapped[str] = mapped_column(String(16))  # a ScheduleRunStatus
    scan_id: Mapped[str | None] = mapped_column(
        ForeignKey("scan.id", ondelete="SET NULL"), nullable=True
    )
    job_id: Mapped[str | None] = mapped_column(
        ForeignKey("job.id", ondelete="SET NULL"), nullable=True
    )
    trend_job_id: Mapped[str | None] = mapped_column(
        ForeignKey("job.id", ondelete="SET NULL"), nullable=True
    )
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    # Why a missed (or skipped) run compared nothing, in a sentence that says what to do.
    reason: Mapped[str | None] = mapped_column(Text, nullable=True)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)
    finished_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)


# -- branch i16/webhooks (issue 16: alerts) ----------------------------------------------------


class Event(Base):
    """Something that happened in an organisation (a job finished, a site went stale...).

    ``id`` is the event id every delivery of it carries (``Scandiff-Event-Id``): receivers drop
    duplicates by it.  Written by :func:`app.db.events.publish_event` in the transaction of the
    state change it reports (the transactional outbox).
    """

    __tablename__ = "event"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    organisation_id: Mapped[str] = mapped_column(
        ForeignKey("organisation.id", ondelete="CASCADE"), index=True
    )
    type: Mapped[str] = mapped_column(String(32))
    payload: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)


class Webhook(Base):
    """Where an organisation wants its events POSTed, signed with ``secret``.

    The secret is stored as given (an HMAC key cannot be hashed); encryption at rest is not
    done: whoever reads the database can sign as the service.
    """

    __tablename__ = "webhook"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    organisation_id: Mapped[str] = mapped_column(
        ForeignKey("organisation.id", ondelete="CASCADE"), index=True
    )
    url: Mapped[str] = mapped_column(String(2000))
    events: Mapped[list[str]] = mapped_column(JSON, default=list)
    secret: Mapped[str] = mapped_column(String(100))
    description: Mapped[str | None] = mapped_column(String(200), nullable=True)
    # The token that created it: the view links of its payloads name it (revoking it kills them).
    created_by_token_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)


class DeliveryStatus(StrEnum):
    """``pending -> delivering -> delivered | pending (retry later) | failed`` (attempts used)."""

    PENDING = "pending"
    DELIVERING = "delivering"
    DELIVERED = "delivered"
    FAILED = "failed"


class WebhookDelivery(Base):
    """One event to one webhook: the durable outbox row a worker claims with a lease."""

    __tablename__ = "webhook_delivery"
    __table_args__ = (
        Index("ix_webhook_delivery_due", "status", "next_attempt_at"),
        Index("ix_webhook_delivery_webhook_created", "webhook_id", "created_at"),
    )

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    organisation_id: Mapped[str] = mapped_column(
        ForeignKey("organisation.id", ondelete="CASCADE"), index=True
    )
    webhook_id: Mapped[str] = mapped_column(ForeignKey("webhook.id", ondelete="CASCADE"))
    event_id: Mapped[str] = mapped_column(ForeignKey("event.id", ondelete="CASCADE"), index=True)
    event_type: Mapped[str] = mapped_column(String(32))
    status: Mapped[str] = mapped_column(String(16), default=DeliveryStatus.PENDING)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer, default=8)
    next_attempt_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    lease_owner: Mapped[str | None] = mapped_column(String(64), nullable=True)
    lease_expires_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    last_status_code: Mapped[int | None] = mapped_column(Integer, nullable=True)
    last_error: Mapped[str | None] = mapped_column(Text, nullable=True)
    last_attempt_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    delivered_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)


# --- i30/resumable uploads: tus uploads being received (app/services/resumable_uploads.py) ---


class ResumableUpload(Base):
    """A tus upload: its declared length, the bytes accepted so far (durable) and its fate."""

    __tablename__ = "resumable_upload"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    organisation_id: Mapped[str] = mapped_column(
        ForeignKey("organisation.id", ondelete="CASCADE"), index=True
    )
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id", ondelete="CASCADE"), index=True)
    length: Mapped[int] = mapped_column(BigInteger)  # Upload-Length
    offset: Mapped[int] = mapped_column(BigInteger, default=0)  # bytes fsynced and accepted
    # the upload's options as the normal upload takes them (reference, filename, method, ...),
    # the raw Upload-Metadata and the whole-file checksum the client declared
    options: Mapped[dict[str, Any]] = mapped_column(JSON)
    upload_metadata: Mapped[str] = mapped_column(Text, default="")
    # active | completed | failed | terminated (expired: active with expires_at passed)
    state: Mapped[str] = mapped_column(String(16), default="active")
    result_status: Mapped[int | None] = mapped_column(Integer, nullable=True)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    expires_at: Mapped[datetime] = mapped_column(Timestamp, index=True)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utc_now)


class TileStatus(StrEnum):
    """Where one tile of a fanned-out job is: ``queued -> running -> succeeded``, or ``cancelled``
    when its job stopped needing it (a worker killed mid-tile leaves it ``running`` with a lease
    that expires, and the next claimer takes it)."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    CANCELLED = "cancelled"


class JobTile(Base):
    """One tile of a job localised tile by tile on several workers (issue 30's fan-out).

    The row is the truth for the tile as ``job`` is for the job: a worker claims it with one
    conditional ``UPDATE`` and a lease; a succeeded tile's ``result_path`` (under the data
    directory) holds its :class:`app.core.tiling.TileResult` and is never computed again.
    """

    __tablename__ = "job_tile"
    __table_args__ = (Index("ix_job_tile_job_status", "job_id", "status"),)

    job_id: Mapped[str] = mapped_column(ForeignKey("job.id", ondelete="CASCADE"), primary_key=True)
    tile_index: Mapped[int] = mapped_column(Integer, primary_key=True)
    status: Mapped[str] = mapped_column(String(16), default=TileStatus.QUEUED)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    lease_owner: Mapped[str | None] = mapped_column(String(64), nullable=True)
    lease_expires_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    result_path: Mapped[str | None] = mapped_column(String(500), nullable=True)
    points: Mapped[int] = mapped_column(Integer, default=0)  # both clouds' points in its crop
    seconds: Mapped[float | None] = mapped_column(Float, nullable=True)
    started_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)


class JobCropPass(Base):
    """One cloud's pass writing its share of every tile's crop in a streamed tiled job.

    The parent's crops pass split by cloud (:mod:`app.jobs.crop_passes`): claimed, leased,
    retried and cancelled as a :class:`JobTile` is; ``pass_index`` numbers the clouds
    (0 the reference, 1 the scan).
    """

    __tablename__ = "job_crop_pass"
    __table_args__ = (Index("ix_job_crop_pass_job_status", "job_id", "status"),)

    job_id: Mapped[str] = mapped_column(ForeignKey("job.id", ondelete="CASCADE"), primary_key=True)
    pass_index: Mapped[int] = mapped_column(Integer, primary_key=True)
    status: Mapped[str] = mapped_column(String(16), default=TileStatus.QUEUED)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    lease_owner: Mapped[str | None] = mapped_column(String(64), nullable=True)
    lease_expires_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    points: Mapped[int] = mapped_column(Integer, default=0)  # points written into the crops
    seconds: Mapped[float | None] = mapped_column(Float, nullable=True)
    started_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(Timestamp, nullable=True)


# A fanned-out job's tiles, counted where the job is read (``JobRead.tiles``): no counter to keep
# in step, the rows are the truth.
Job.tiles_total = column_property(
    select(func.count(JobTile.tile_index))
    .where(JobTile.job_id == Job.id)
    .correlate_except(JobTile)
    .scalar_subquery()
)
Job.tiles_done = column_property(
    select(func.count(JobTile.tile_index))
    .where(JobTile.job_id == Job.id, JobTile.status == TileStatus.SUCCEEDED)
    .correlate_except(JobTile)
    .scalar_subquery()
)
