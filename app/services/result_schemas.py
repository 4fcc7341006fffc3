"""The JSON a job's result stores, described field by field for the API (OpenAPI).

Pydantic mirrors of the core's reports (:mod:`app.core.comparison`, :mod:`app.core.quality`,
:mod:`app.core.explanation`): the alignment's report, the calibration with its decision and
visibility, the sensor origins, the quality warnings and the explanation.  Each is a
:class:`StoredJson`: it reads the stored object, accepts keys it does not name (a detector's
own calibration figures, a trajectory's summary), and answers with exactly the keys stored, in
their order, so responses are the stored JSON while OpenAPI names and types every field.
"""

from __future__ import annotations

from typing import Any

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    SerializerFunctionWrapHandler,
    ValidatorFunctionWrapHandler,
    model_serializer,
    model_validator,
)

Number = float | int
"""A JSON number as stored (an integer stays one)."""


class StoredJson(BaseModel):
    """A stored JSON object: its named fields typed, others kept; answered as stored."""

    model_config = ConfigDict(extra="allow")
    _stored_keys: list[str] = PrivateAttr(default_factory=list)

    @model_validator(mode="wrap")
    @classmethod
    def _remember_keys(cls, data: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        """Validate, remembering which keys were stored and in which order."""
        model = handler(data)
        if isinstance(data, dict):
            model._stored_keys = list(data)
        elif isinstance(data, StoredJson):
            model._stored_keys = list(data._stored_keys)
        return model

    @model_serializer(mode="wrap")
    def _as_stored(self, handler: SerializerFunctionWrapHandler):
        """The stored keys only (no null for a field never stored), in their stored order.

        Not annotated on purpose: so the schema (OpenAPI) is the model's, not a plain object.
        """
        data = handler(self)
        return {key: data[key] for key in self._stored_keys if key in data}


class RegistrationRead(StoredJson):
    """How the scan was aligned onto the reference (``app.core.comparison.align``)."""

    transform: list[list[Number]] | None = Field(
        default=None, description="4 x 4 matrix taking the scan file's coordinates to the "
        "reference file's."
    )  # fmt: skip
    fitness: Number | None = Field(
        default=None, description="Share of the scan's points near the reference once aligned."
    )
    rmse: Number | None = Field(default=None, description="Their RMS distance (metres).")
    converged: bool | None = None
    iterations: int | None = None
    method: str | None = Field(default=None, description="small_gicp, or identity.")
    max_correspondence_distance: Number | None = Field(
        default=None, description="Farthest pairing distance (metres)."
    )
    voxel_size: Number | None = Field(default=None, description="Downsampling voxel (metres).")
    rotation_degrees: Number | None = Field(default=None, description="The turn applied.")
    enabled: bool | None = Field(default=None, description="False: compared without aligning.")
    sample_points: int | None = Field(
        default=None,
        description="The points of each cloud it was estimated on, when a sample (a pair "
        "compared in tiles).",
    )
    translation_m: Number | None = Field(
        default=None, description="How far the scan's centre moved (metres)."
    )


class DecisionTestRead(StoredJson):
    """One test of the decision rule (``app.core.site_calibration.decide``)."""

    statistic: str | None = Field(default=None, description="largest_region_extent_m or score.")
    value: Number | None = None
    comparison: str | None = None
    threshold: Number | None = None
    source: str | None = Field(default=None, description="default, or site (learned).")
    fires: bool | None = None
    n_regions: int | None = None
    min_region_points: int | None = None


class DecisionRead(StoredJson):
    """The decision rule in effect and its tests."""

    rule: str | None = Field(default=None, description="regions, detector or either.")
    detector_changed: bool | None = Field(
        default=None, description="The detector's own verdict (score above its threshold)."
    )
    n_regions: int | None = None
    tests: list[DecisionTestRead] | None = None


class TrajectorySummaryRead(StoredJson):
    """A cloud's trajectory as the comparison used it (``app.core.origins.trajectory_origin``)."""

    source: str | None = Field(default=None, description="trajectory.")
    poses: int | None = None
    time_span: list[Number] | None = Field(
        default=None, description="[first, last] pose time (seconds)."
    )
    path_length_m: Number | None = None
    assignment: str | None = Field(
        default=None, description="How points were given their pose: times, or nearest."
    )
    points_outside: int | None = Field(
        default=None, description="Points whose times lie outside the poses' span."
    )
    groups: int | None = Field(default=None, description="Pseudo-stations along the path.")
    group_length_m: Number | None = None
    rays: int | None = None


class SideVisibilityRead(StoredJson):
    """What was found out about one cloud's sensors, and the visibility test it got."""

    origins: str | None = Field(
        default=None,
        description="given, file, estimated, recovered, trajectory or none.",
    )
    lidar_like: bool | None = Field(
        default=None, description="Its sampling was measured to be a lidar's."
    )
    lidar_twin_share: Number | None = None
    lidar_spacing_spread: Number | None = None
    lidar_noise_ratio: Number | None = Field(
        default=None, description="The points' noise against their spacing."
    )
    stations_recovered: int | None = None
    stations_unknown: bool | None = Field(
        default=None, description="A merged lidar cloud whose stations are not known."
    )
    trajectory: TrajectorySummaryRead | None = Field(
        default=None, description="A trajectory's summary (poses, groups, assignment...)."
    )
    test: str | None = Field(
        default=None,
        description="The visibility test its change candidates got (ray, trajectory, maps, "
        "surfaces, coverage, gaps).",
    )


class VisibilityRead(StoredJson):
    """Per side, its sensors and visibility test."""

    reference: SideVisibilityRead | None = None
    scan: SideVisibilityRead | None = None


class SiteProvenanceRead(StoredJson):
    """Whether the site's learned thresholds applied (its calibration's fields besides)."""

    applied: bool | None = None
    reason: str | None = Field(default=None, description="Why not, when not applied.")


class CalibrationRead(StoredJson):
    """How the threshold was calibrated (the detector's own figures besides these fields)."""

    compared_points: str | None = Field(default=None, description="mutually observed, or all.")
    site: SiteProvenanceRead | None = None
    visibility: VisibilityRead | None = None
    decision: DecisionRead | None = None


class SensorOriginRead(TrajectorySummaryRead):
    """One sensor origin used (a trajectory's entry holds its summary and path instead)."""

    origin: list[Number] | None = Field(default=None, description="[x, y, z] in that file's frame.")
    source: str | None = Field(
        default=None, description="given, file, estimated, recovered or trajectory."
    )
    confidence: Number | None = None
    path: list[list[Number]] | None = Field(
        default=None, description="A trajectory's poses, [x, y, z] each, in that file's frame."
    )


class WarningDetailRead(StoredJson):
    """A warning's measured value, the limit it crossed and what it means."""

    value: Number | None = None
    limit: Number | None = None
    unit: str | None = None
    side: str | None = None
    median: Number | None = Field(
        default=None, description="The site's usual region count (region_count_above_history)."
    )
    history_jobs: int | None = Field(
        default=None, description="How many of the site's previous jobs make that usual."
    )
    explanation: str | None = None


class HowToFixRead(StoredJson):
    """What to do about a warning."""

    action: str | None = None
    summary: str | None = None
    text: str | None = Field(default=None, description="The API's knob for it.")
    parameters: list[str] | None = None


class QualityWarningRead(StoredJson):
    """One quality warning (``app.core.quality``, or the site's region count history)."""

    code: str | None = None
    message: str | None = Field(default=None, description="One sentence, with units.")
    value: Number | None = None
    limit: Number | None = None
    unit: str | None = None
    side: str | None = None
    median: Number | None = Field(
        default=None, description="The site's usual region count (region_count_above_history)."
    )
    history_jobs: int | None = Field(
        default=None, description="How many of the site's previous jobs make that usual."
    )
    detail: WarningDetailRead | None = None
    how_to_fix: HowToFixRead | None = None


class LargestRegionRead(StoredJson):
    """The largest region of a decision."""

    index: int | None = None
    kind: str | None = None
    n_points: int | None = None
    size_m: list[Number] | None = Field(default=None, description="Extents in metres.")


class ExplanationRead(StoredJson):
    """Why the job decided what it did (``app.core.explanation``)."""

    decision: str | None = Field(default=None, description="changed or unchanged.")
    rule: str | None = None
    decided_by: str | None = None
    n_regions: int | None = None
    n_region_points: int | None = None
    min_region_points: int | None = None
    dropped_clusters: int | None = None
    largest_region: LargestRegionRead | None = None
    score: Number | None = None
    threshold: Number | None = None
    detector_changed: bool | None = None
    agrees: bool | None = Field(
        default=None, description="Whether the regions and the detector say the same."
    )
    site_test: DecisionTestRead | None = None
    text: str | None = Field(default=None, description="The explanation in one line.")


Setting = Number | str | bool
"""A parameter's value as given (a number, ``"auto"``, a flag): the stage checks it."""


class RegistrationParamsRead(StoredJson):
    """The registration stage's keyword parameters (``app.core.registration.register_scan``)."""

    voxel_size: Setting | None = Field(default=None, description="Metres.")
    max_correspondence_distance: Setting | None = Field(default=None, description="Metres.")
    initial_transform: list[list[Number]] | None = Field(
        default=None, description="4 x 4 starting guess."
    )
    min_fitness: Setting | None = None
    num_threads: Setting | None = None


class LocalisationParamsRead(StoredJson):
    """The localisation stage's keyword parameters (``app.core.localise.DEFAULT_PARAMETERS``)."""

    n_neighbors: Setting | None = None
    threshold_factor: Setting | None = None
    support_factor: Setting | None = None
    cluster_factor: Setting | None = None
    coverage_factor: Setting | None = None
    visibility_margin_factor: Setting | None = None
    visibility_angle_factor: Setting | None = None
    visibility_beyond_fraction: Setting | None = None
    visibility_miss_factor: Setting | None = None
    origin_free_test: Setting | None = None
    min_change_distance: Setting | None = Field(default=None, description="Metres.")
    min_region_points: Setting | None = None


Origins = list[Number] | list[list[Number]]
"""One origin [x, y, z], or one per station."""


class ComparisonParamsRead(StoredJson):
    """A comparison's parameters: the detector's (those named here and its own), and the
    reserved keys of ``app.core.pipeline.compare``."""

    variant: str | None = None
    random_state: int | None = None
    false_alarm_rate: Setting | None = None
    n_resamples: Setting | None = None
    calibration: Setting | None = Field(default=None, description="auto, permutation or paired.")
    max_points: Setting | None = None
    voxel_size: Setting | None = Field(default=None, description="Metres, or auto.")
    align: bool | None = None
    registration: RegistrationParamsRead | None = None
    localisation: LocalisationParamsRead | None = None
    decision: str | None = Field(default=None, description="regions, detector or either.")
    memory_budget_bytes: int | None = Field(
        default=None, description="The memory budget of a pair compared in tiles."
    )
    reference_origin: Origins | None = Field(
        default=None, description="Sensor position(s) in the reference file's frame."
    )
    scan_origin: Origins | None = Field(
        default=None, description="Sensor position(s) in the scan file's frame."
    )
    estimate_origins: bool | None = None
    recover_stations: bool | str | None = Field(default=None, description="auto, true or false.")


class TimingsRead(StoredJson):
    """Seconds per stage of the comparison and of the job around it."""

    load_inputs: Number | None = None
    origins: Number | None = None
    align: Number | None = None
    plan: Number | None = Field(default=None, description="Tile planning (a pair in tiles).")
    localise: Number | None = None
    detect: Number | None = None
    write_outputs: Number | None = None
    job_total: Number | None = None
