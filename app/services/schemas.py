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
    computed_field,
)

from app.clock import as_utc
from app.db.models import JobStatus, Site
from app.services.messages import api_warnings
from app.services.result_schemas import (
    CalibrationRead,
    ComparisonParamsRead,
    ExplanationRead,
    QualityWarningRead,
    RegistrationRead,
    SensorOriginRead,
    TimingsRead,
)

UtcDatetime = Annotated[datetime, AfterValidator(as_utc)]
Name = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=200)]
Identifier = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=64)]

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


def tile_progress_of(job: object) -> TileProgressRead | None:
    """A job row's tiles done / total, or None when it is not tiled."""
    total = getattr(job, "tiles_total", None) or 0
    return TileProgressRead(done=getattr(job, "tiles_done", 0) or 0, total=total) if total else None


DEFAULT_DETECTOR_VARIANT = "improved"
"""The variant a detector given by its method alone gets (``{"method": "pe"}``)."""


class DetectorConfig(StrictBody):
    """A detector: method (``pca``, ``gmm``, ``planes``...), variant (default ``improved``) and
    keyword parameters."""

    method: Identifier
    variant: Identifier = DEFAULT_DETECTOR_VARIANT
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
    calibration: dict[str, Any] | None = Field(
        default=None,
        description="Thresholds the site learned from its reviewed jobs (rule, samples, "
        "rank, values, source job ids); null until a job of the site got a verdict.",
    )
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
            calibration=site.calibration,
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


class VerdictCreate(StrictBody):
    """A reviewer's verdict on a succeeded job."""

    verdict: Literal["confirmed", "false_alarm", "new_reference"] = Field(
        description="confirmed: the decision was right; false_alarm: it said changed but "
        "nothing that matters changed; new_reference: the job's scan becomes the site's reference."
    )
    note: Annotated[str, StringConstraints(strip_whitespace=True, max_length=2000)] | None = None


class VerdictSetBy(BaseModel):
    """Who gave a verdict: the API token (its id, name and role)."""

    token_id: str | None
    name: str | None
    role: str


class VerdictRead(BaseModel):
    """A verdict: what, the reviewer's note, who and when."""

    verdict: str
    note: str | None
    set_by: VerdictSetBy
    set_at: UtcDatetime


class TileProgressRead(BaseModel):
    """How far a job compared tile by tile on several workers has got."""

    done: int = Field(description="Tiles localised and stored.")
    total: int = Field(description="Tiles in the job's plan.")


class JobRead(RowRead):
    """A comparison job: its inputs, state and results."""

    id: str
    site_id: str
    reference_scan_id: str
    scan_id: str
    status: JobStatus
    progress: float
    stage: str | None
    tiles: TileProgressRead | None = Field(
        default=None,
        description="A pair too large for one worker's memory budget is localised in tiles "
        "that any worker takes from the queue: tiles done / total; null for a job in one piece.",
    )
    attempts: int
    max_attempts: int
    method: str
    variant: str
    params: Annotated[ComparisonParamsRead, BeforeValidator(lambda value: value or {})]
    effective_params: ComparisonParamsRead | None = Field(
        default=None,
        description="Every parameter in effect once the job ran; POST /jobs with these params "
        "replays the result exactly.",
    )
    score: float | None
    threshold: float | None
    changed: bool | None
    calibration: CalibrationRead | None = Field(
        description="How the threshold was calibrated, the decision rule's tests and what was "
        "found out about each cloud's sensors."
    )
    registration: RegistrationRead | None = Field(description="How the scan was aligned.")
    n_regions: int | None
    error: str | None
    timings: TimingsRead | None
    created_at: UtcDatetime
    started_at: UtcDatetime | None
    finished_at: UtcDatetime | None
    request_id: str | None = Field(
        default=None,
        description="The id of the request that created the job (its X-Request-ID, or the id "
        "generated for it); every log line about the job carries it.",
    )
    verdict: VerdictRead | None = Field(
        default=None, description="The current review verdict (POST /jobs/{id}/verdict)."
    )
    sensor_origins: dict[str, list[SensorOriginRead]] | None = Field(
        default=None,
        description="The sensor origins the comparison used, per side (reference, scan) a list "
        "of {origin: [x, y, z] in that file's frame, source: given | file | estimated | "
        "recovered, confidence}; an empty list: unknown.",
    )
    warnings: Annotated[list[QualityWarningRead] | None, BeforeValidator(api_warnings)] = Field(
        default=None,
        description="Quality warnings on the result, each {code, message (one sentence), "
        "detail, how_to_fix: {action, text, parameters}, ...}: "
        "low_registration_fitness, large_rotation, large_translation, low_overlap, "
        "sensor_origin, sensor_origin_unknown, region_count_above_history.",
    )
    explanation: ExplanationRead | None = Field(
        default=None,
        description="Why the job decided what it did: the decision rule, the regions' and the "
        "detector's evidence, and a one-line text.",
    )
    uncertain_regions: list[UncertainRegionRead] | None = Field(
        default=None,
        description="Clusters of points the other epoch did not cover (evidence no_coverage: "
        "a patch of a surface that continues unmoved in the other epoch, or a place it never "
        "came near). Listed for review; they never count as change and their points are "
        "unobserved.",
    )

    @computed_field  # type: ignore[prop-decorator]
    @property
    def will_retry(self) -> bool:
        """Whether the worker will try the job again (an attempt failed, attempts are left)."""
        return (
            self.status == JobStatus.QUEUED
            and self.error is not None
            and self.attempts < self.max_attempts
        )

    reference_filename: str | None = Field(
        default=None, description="File name of the reference scan as uploaded."
    )
    scan_filename: str | None = Field(
        default=None, description="File name of the compared scan as uploaded."
    )

    @classmethod
    def from_model(cls, row: object) -> Self:
        """Build from a ``Job`` row, with the file names of its two scans and its tiles."""
        read = cls.model_validate(row)
        reference_scan = getattr(row, "reference_scan", None)
        scan = getattr(row, "scan", None)
        read.reference_filename = reference_scan.filename if reference_scan else None
        read.scan_filename = scan.filename if scan else None
        read.tiles = tile_progress_of(row)
        return read


class JobRerun(StrictBody):
    """A re-run of a job on the same reference and scan; absent fields keep the job's.

    Without ``params``, the job's parameters are kept when method and variant are the job's
    (another detector takes its own defaults).
    """

    method: Identifier | None = None
    variant: Identifier | None = None
    params: dict[str, Any] | None = None


class UncertainRegionRead(BaseModel):
    """A cluster the other epoch did not cover: reported, not counted as change."""

    kind: str = Field(description="removed (a reference part) or added (a scan part).")
    n_points: int
    centroid: list[float]
    bbox_min: list[float]
    bbox_max: list[float]
    mean_distance: float
    max_distance: float
    evidence: str = Field(default="no_coverage")
    confidence: float | None = None


class RegionRead(RowRead):
    """A connected cluster of changed points (``added``: new in the scan; ``removed``: gone)."""

    id: str
    ordinal: int = Field(description="Position in the job's region list (0 first).")
    kind: str
    n_points: int
    centroid: list[float]
    bbox_min: list[float]
    bbox_max: list[float]
    mean_distance: float
    max_distance: float
    evidence: str = Field(
        default="seen_empty",
        description="Why it is a change: seen_empty (the other epoch saw its place empty: "
        "through, behind or beneath it) or surface_moved (the surface is found again, "
        "displaced, within a metre: a removed and an added region side by side).",
    )
    confidence: float | None = Field(
        default=None,
        description="Mean confidence of its points' labels, 0-1 (direct evidence: 1); "
        "null for regions stored before it was measured.",
    )


class CapabilitiesRead(BaseModel):
    """What this server reads and runs: the dashboard builds its file picker and forms from it."""

    upload_formats: list[str] = Field(description="Formats an upload may be in.")
    upload_extensions: list[str] = Field(description="File name suffixes of those formats.")
    detector_methods: list[str]
    detector_variants: list[str]
    default_detector: DetectorConfig


class UploadRead(BaseModel):
    """Answer to an upload: the stored scan and, unless it became the reference, its job."""

    scan: ScanRead
    job: JobRead | None


class Page(BaseModel, Generic[ItemT]):
    """One page of a list, newest first; pass ``next_cursor`` as ``cursor`` for the next one."""

    items: list[ItemT]
    next_cursor: str | None


class SiteAwaitingReview(BaseModel):
    """A site's succeeded jobs that await a verdict: how many, and the newest one's time."""

    site_id: str
    site_name: str | None
    count: int
    newest_at: UtcDatetime


class AwaitingReviewCounts(BaseModel):
    """The review inbox's counts: all jobs awaiting a verdict, and per site (newest first)."""

    total: int
    sites: list[SiteAwaitingReview]


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
