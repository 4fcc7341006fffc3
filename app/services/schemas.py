"""Request and response bodies of the API (``XCreate`` / ``XUpdate`` / ``XRead``).

Read models are built from ORM rows by ``from_model``; datetimes are rendered as UTC with an
offset (SQLite hands them back naive).
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Generic, Literal, Self, TypeVar

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StringConstraints,
)

from app.clock import as_utc
from app.db.models import JobStatus, Site

UtcDatetime = Annotated[datetime, AfterValidator(as_utc)]
Name = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=200)]
Identifier = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=64)]
JsonObject = Annotated[dict[str, Any], BeforeValidator(lambda value: value or {})]
"""A JSON object column that reads as ``{}`` when it is empty or null."""

ItemT = TypeVar("ItemT")


class StrictBody(BaseModel):
    """A request body that rejects unknown fields (a typo is a 422, not silently ignored)."""

    model_config = ConfigDict(extra="forbid")


class RowRead(BaseModel):
    """A response body whose fields are the attributes of the same names of a row."""

    model_config = ConfigDict(from_attributes=True)

    @classmethod
    def from_model(cls, row: object) -> Self:
        """Build from a row (a ``Scan``, ``Job``, quota ``Usage``...) by attribute name."""
        return cls.model_validate(row)


class DetectorConfig(StrictBody):
    """A detector: method (``pca``, ``gmm``, ``planes``...), variant and keyword parameters."""

    method: Identifier
    variant: Identifier
    params: dict[str, Any] = Field(default_factory=dict)


class SiteCreate(StrictBody):
    """A new site; the detector defaults to the service's default (GMM-EMD, improved)."""

    name: Name
    description: Annotated[str, StringConstraints(max_length=10_000)] | None = None
    detector: DetectorConfig | None = None


class SiteUpdate(StrictBody):
    """Fields of a site to change; absent fields are kept."""

    name: Name | None = None
    description: Annotated[str, StringConstraints(max_length=10_000)] | None = None
    detector: DetectorConfig | None = None


class SiteRead(BaseModel):
    """A site as the API shows it."""

    id: str
    name: str
    description: str | None
    detector: DetectorConfig
    reference_scan_id: str | None
    created_at: UtcDatetime
    updated_at: UtcDatetime

    @classmethod
    def from_model(cls, site: Site) -> SiteRead:
        """Build from a ``Site`` row."""
        return cls(
            id=site.id,
            name=site.name,
            description=site.description,
            detector=DetectorConfig(
                method=site.detector_method,
                variant=site.detector_variant,
                params=dict(site.detector_params or {}),
            ),
            reference_scan_id=site.reference_scan_id,
            created_at=site.created_at,
            updated_at=site.updated_at,
        )


class ReferencePromote(StrictBody):
    """Make an existing scan of the site its reference."""

    scan_id: Identifier


class ScanRead(RowRead):
    """An uploaded scan: metadata of the stored original file."""

    id: str
    site_id: str
    filename: str
    format: str
    size_bytes: int
    sha256: str
    n_points: int
    n_dropped: int
    bbox_min: list[float]
    bbox_max: list[float]
    sensor_origin: list[float] | list[list[float]] | None = Field(
        default=None,
        description="Where the sensor was, in the file's frame: [x, y, z], or one per station "
        "[[x, y, z], ...] for a cloud merged from several stations (an E57 file's scans).",
    )
    created_at: UtcDatetime


class JobCreate(StrictBody):
    """Any comparison of two scans of one site; method/variant/params default to the site's."""

    reference_scan_id: Identifier
    scan_id: Identifier
    method: Identifier | None = None
    variant: Identifier | None = None
    params: dict[str, Any] | None = None


class JobRead(RowRead):
    """A comparison job: its inputs, state and results."""

    id: str
    site_id: str
    reference_scan_id: str
    scan_id: str
    status: JobStatus
    progress: float
    stage: str | None
    attempts: int
    max_attempts: int
    method: str
    variant: str
    params: JsonObject
    effective_params: dict[str, Any] | None = Field(
        default=None,
        description="Every parameter in effect once the job ran; POST /jobs with these params "
        "replays the result exactly.",
    )
    score: float | None
    threshold: float | None
    changed: bool | None
    calibration: dict[str, Any] | None
    registration: dict[str, Any] | None
    n_regions: int | None
    error: str | None
    timings: dict[str, Any] | None
    created_at: UtcDatetime
    started_at: UtcDatetime | None
    finished_at: UtcDatetime | None
    request_id: str | None = Field(
        default=None,
        description="The id of the request that created the job (its X-Request-ID, or the id "
        "generated for it); every log line about the job carries it.",
    )


class RegionRead(RowRead):
    """A connected cluster of changed points (``added``: new in the scan; ``removed``: gone)."""

    id: str
    kind: str
    n_points: int
    centroid: list[float]
    bbox_min: list[float]
    bbox_max: list[float]
    mean_distance: float
    max_distance: float


class UploadRead(BaseModel):
    """Answer to an upload: the stored scan and, unless it became the reference, its job."""

    scan: ScanRead
    job: JobRead | None


class Page(BaseModel, Generic[ItemT]):
    """One page of a list, newest first; pass ``next_cursor`` as ``cursor`` for the next one."""

    items: list[ItemT]
    next_cursor: str | None


class ErrorRead(BaseModel):
    """Every error: a stable code and a human-readable message."""

    error: str
    detail: str


class HealthRead(BaseModel):
    """Whether the database and the queue work."""

    status: Literal["ok", "degraded", "unavailable"]
    version: str
    database: dict[str, Any]
    queue: dict[str, Any]


class OrganisationRead(RowRead):
    """The caller's organisation, its usage and its quotas (a null cap is unlimited)."""

    id: str
    name: str
    queued_jobs: int = Field(description="Jobs not finished yet (queued or running).")
    max_queued_jobs: int | None = Field(description="Cap on queued_jobs; more is a 429.")
    stored_bytes: int = Field(description="Bytes of the organisation's scan files.")
    max_stored_bytes: int | None = Field(description="Cap on stored_bytes; more is a 507.")
