"""One comparison from end to end: align, localise, detect, decide.

This is the function the CLI (``scandiff compare``) and the service's worker both call, so a
result over HTTP is identical to the CLI's on the same inputs and parameters.

Stages
------
1. **Local origin.** Both clouds are shifted by one rounded origin taken from the reference
   (:func:`app.core.cloud.choose_local_origin`) so georeferenced coordinates keep their
   millimetres in float arithmetic; every coordinate reported is shifted back.
2. **Registration** of the scan onto the reference (GICP via small_gicp), or the identity with
   its fit measured when ``align=False``.
3. **Localisation**: per-point labels (changed / unchanged / unobserved) for both clouds and
   connected regions (:mod:`app.core.localise`).
4. **Detection**: the paper's global EMD score between the parts of the two clouds that both
   sensors observed (points the other scan could not see are not evidence of change), with a
   threshold calibrated from the clouds' own resampling noise (:mod:`app.core.detectors`).
"""

from __future__ import annotations

import time
import zipfile
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from app.core.cache.geometry import GeometryCache, reference_neighbourhoods
from app.core.cache.reference_alignment import ReferenceAlignmentCache
from app.core.cache.reference_origin import ReferenceOriginCache
from app.core.cloud import MIN_POINTS, PointCloud, choose_local_origin
from app.core.comparison_settings import (
    parse_comparison_params,
)
from app.core.detectors import canonical_method, warm_up
from app.core.explanation import explain_comparison
from app.core.jsonable import json_safe
from app.core.localise import (
    LABEL_CHANGED,
    LABEL_UNCHANGED,
    LABEL_UNOBSERVED,
    Neighbourhoods,
    NeighbourhoodSearch,
    localise_changes,
    start_neighbourhood_search,
)
from app.core.origins.known_stations import origins_in_local_frame
from app.core.origins.own_frame import resolve_moved_cloud
from app.core.origins.resolve import ResolvedOrigin
from app.core.origins.station_recovery import resolve_stations
from app.core.origins.trajectory_origin import station_index, trajectory_origin, trajectory_rays
from app.core.quality import quality_warnings
from app.core.registration import (
    apply_transform,
    identity_registration,
    register_scan,
)
from app.core.site_calibration import DecisionInputs, decide, largest_extent
from app.core.threads import available_threads

ProgressCallback = Callable[[str, float], None]
"""Called as ``progress(stage, fraction_done)`` with fraction in [0, 1]."""


@dataclass(frozen=True)
class RegionSummary:
    """One connected cluster of changed points, in file coordinates of the reference frame."""

    kind: str  # "added" (in the scan, not in the reference) or "removed"
    n_points: int
    centroid: list[float]
    bbox_min: list[float]
    bbox_max: list[float]
    mean_distance: float
    max_distance: float
    evidence: str = "seen_empty"  # seen_empty | surface_moved | no_coverage
    confidence: float = 1.0

    def to_json_dict(self) -> dict[str, Any]:
        """Plain JSON types."""
        return {
            "kind": self.kind,
            "n_points": self.n_points,
            "centroid": self.centroid,
            "bbox_min": self.bbox_min,
            "bbox_max": self.bbox_max,
            "mean_distance": self.mean_distance,
            "max_distance": self.max_distance,
            "evidence": self.evidence,
            "confidence": self.confidence,
        }


@dataclass(frozen=True)
class ComparisonResult:
    """Everything one comparison produced.

    Per-point arrays have one entry per row of the source file (points dropped on load keep
    their place): labels are 0 unchanged, 1 changed, -1 unobserved or dropped; distances are
    NaN there.  ``reference_region``/``scan_region`` index ``regions`` (-1: none).
    ``visibility`` says per cloud where its origins came from (``"origins"``: given, file,
    estimated, recovered or none), whether its sampling was measured to be a lidar's
    (``lidar_like``, with its figures) and stations searched (``stations_recovered``), whether
    it is a merged lidar cloud whose stations are unknown (``stations_unknown``), and the
    visibility test its change candidates got (``test``: ray, coverage or surfaces).
    """

    method: str
    variant: str
    params: dict[str, Any]
    score: float
    threshold: float
    changed: bool
    calibration: dict[str, Any]
    registration: dict[str, Any]
    regions: list[RegionSummary]
    n_reference: int
    n_scan: int
    reference_label: NDArray[np.int8]
    scan_label: NDArray[np.int8]
    reference_distance: NDArray[np.float32]
    scan_distance: NDArray[np.float32]
    reference_region: NDArray[np.int32]
    scan_region: NDArray[np.int32]
    localisation: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    sensor_origins: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    visibility: dict[str, dict[str, Any]] = field(default_factory=dict)
    uncertain_regions: list[RegionSummary] = field(default_factory=list)

    def label_counts(self) -> dict[str, dict[str, int]]:
        """How many points of each cloud are unchanged, changed and unobserved."""

        def counts(labels: NDArray[np.int8]) -> dict[str, int]:
            return {
                "unchanged": int(np.count_nonzero(labels == LABEL_UNCHANGED)),
                "changed": int(np.count_nonzero(labels == LABEL_CHANGED)),
                "unobserved": int(np.count_nonzero(labels == LABEL_UNOBSERVED)),
            }

        return {"reference": counts(self.reference_label), "scan": counts(self.scan_label)}

    def to_json_dict(self) -> dict[str, Any]:
        """The JSON object printed by ``scandiff compare --json`` (non-finite numbers: null)."""
        return json_safe(
            {
                "method": self.method,
                "variant": self.variant,
                "params": self.params,
                "score": self.score,
                "threshold": self.threshold,
                "changed": self.changed,
                "calibration": self.calibration,
                "registration": self.registration,
                "regions": [region.to_json_dict() for region in self.regions],
                "n_regions": len(self.regions),
                "uncertain_regions": [region.to_json_dict() for region in self.uncertain_regions],
                "n_reference": self.n_reference,
                "n_scan": self.n_scan,
                "label_counts": self.label_counts(),
                "localisation": self.localisation,
                "timings": self.timings,
                "sensor_origins": self.sensor_origins,
                "warnings": self.warnings,
                "visibility": self.visibility,
                "quality_warnings": quality_warnings(self),  # structured, with the above
                "explanation": explain_comparison(self),
            }
        )

    def write_labels_npz(self, path: str | Path) -> None:
        """Write ``reference_changed``, ``scan_changed``, ``reference_label``, ``scan_label``.

        A ``numpy.savez_compressed`` file (``numpy.load`` reads it), deflated at level 1: a
        third of the time of its default level for 1.5x the bytes (labels compress well
        either way).
        """
        arrays = {
            "reference_changed": self.reference_label == LABEL_CHANGED,
            "scan_changed": self.scan_label == LABEL_CHANGED,
            "reference_label": self.reference_label.astype(np.int8),
            "scan_label": self.scan_label.astype(np.int8),
        }
        with zipfile.ZipFile(
            path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=LABELS_COMPRESS_LEVEL
        ) as archive:
            for name, array in arrays.items():
                with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, array, allow_pickle=False)


LABELS_COMPRESS_LEVEL = 1
"""zlib level of the labels file (:meth:`ComparisonResult.write_labels_npz`)."""


def _region_summary(region: Any, local_origin: NDArray[np.float64]) -> RegionSummary:
    """A localised region in file coordinates (the local origin added back)."""
    return RegionSummary(
        kind=region.kind,
        n_points=int(region.n_points),
        centroid=(np.asarray(region.centroid) + local_origin).tolist(),
        bbox_min=(np.asarray(region.bbox_min) + local_origin).tolist(),
        bbox_max=(np.asarray(region.bbox_max) + local_origin).tolist(),
        mean_distance=float(region.mean_distance),
        max_distance=float(region.max_distance),
        evidence=str(region.evidence),
        confidence=round(float(region.confidence), 3),
    )


def _file_frame_transform(
    local_transform: NDArray[np.float64], local_origin: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Express a transform estimated in local coordinates in the files' coordinates."""
    shift = np.eye(4)
    shift[:3, 3] = local_origin
    unshift = np.eye(4)
    unshift[:3, 3] = -local_origin
    return shift @ local_transform @ unshift


REFERENCE_AHEAD_MIN_POINTS = 50_000
"""From this many reference points (and with >= 2 threads) the reference's nearest-neighbour
search starts on a second thread while the scan is aligned: alignment uses one core, and the
search is the largest single cost of localisation (gain in ``docs/performance.md``)."""


@contextmanager
def _reference_neighbourhoods_ahead(
    reference_points: NDArray[np.float64],
    localisation_params: Mapping[str, Any],
    enabled: bool,
    cache: GeometryCache | None = None,
    facts: Mapping[str, tuple[str, Any]] | None = None,
) -> Iterator[Neighbourhoods | NeighbourhoodSearch | None]:
    """The reference's neighbourhood search running on a second thread, or None (not
    ``enabled``, a small cloud, or see :func:`start_neighbourhood_search`).  On leaving, a
    search still running is stopped at its next chunk and waited for, so no thread outlives
    the comparison.  With a ``cache``, from it when it holds them, else written to it (with
    ``facts``)."""
    ahead = enabled and len(reference_points) >= REFERENCE_AHEAD_MIN_POINTS
    search = reference_neighbourhoods(
        reference_points, localisation_params, cache=cache, ahead=ahead, facts=facts
    )
    try:
        yield search
    finally:
        if isinstance(search, NeighbourhoodSearch):
            search.cancel()


def compare(
    reference: PointCloud,
    scan: PointCloud,
    *,
    method: str = "gmm",
    variant: str = "improved",
    align: bool = True,
    random_state: int = 0,
    params: Mapping[str, Any] | None = None,
    progress: ProgressCallback | None = None,
    threads: int | None = None,
    site_calibration: Mapping[str, Any] | None = None,
    geometry_cache: GeometryCache | None = None,
) -> ComparisonResult:
    """Compare ``scan`` against ``reference``; see the module docstring.

    Parameters
    ----------
    reference, scan : PointCloud
        The clouds as read from their files.
    method : {"gmm", "pca", "planes"}
        Or one of the paper's names (``"pe"``, ``"PE-EMD"``...); the result carries the
        canonical name.
    variant : {"improved", "paper"}
    align : bool
        Register the scan onto the reference first (recommended for robot scans).
    random_state : int
        Seeds every random choice, so a result can be replayed exactly.
    params : mapping, optional
        Detector keyword parameters, plus the reserved keys ``"registration"`` and
        ``"localisation"`` (dicts of keyword parameters for those stages), ``"decision"``
        (one of :data:`app.core.comparison_settings.DECISION_RULES`) and
        ``"reference_origin"`` / ``"scan_origin"`` (sensor positions in each file's frame,
        overriding what the file says: 3 numbers, or a list of them for a cloud merged from
        several stations, whose ``station_index`` attribute, if any, says which took each
        point), ``"estimate_origins"`` (default true: estimate a missing or contradicted
        origin from the points, :mod:`app.core.origins.resolve`) and ``"recover_stations"``
        (``"auto"``, default: a cloud left without an origin whose sampling is a lidar's,
        :func:`app.core.origins.sampling.lidar_sampling`, gets its stations recovered,
        :func:`app.core.origins.station_recovery.recover_stations`, a second or two per cloud; when
        none are, it is a merged lidar cloud with unknown stations and the other cloud's
        candidates get the origin-free surface test; ``true``: recover whatever the sampling;
        ``false``: never).
        The origins used are reported in ``sensor_origins``, contradicted ones in ``warnings``.
    progress : callable, optional
        ``progress(stage, fraction)`` after each stage.
    threads : int, optional
        Threads the localiser may use (default: ``OMP_NUM_THREADS`` if set, else every CPU
        this process may run on).  Detectors run their BLAS calls on one thread (small
        matrices: more threads only contend).  Results do not depend on it.
    site_calibration : mapping, optional
        A site's thresholds learned from its reviewed jobs
        (:func:`app.core.site_calibration.learn_site_calibration`); applied when learned for
        this method and variant.  Its provenance is in ``calibration["site"]`` either way.
    geometry_cache : GeometryCache, optional
        Where the reference's k-NN geometry, resolved origin and alignment arrays are kept
        between comparisons (read when valid, written otherwise, :mod:`app.core.cache.geometry`,
        :mod:`app.core.cache.reference_origin`, :mod:`app.core.cache.reference_alignment`).
        Results do not depend on it.

    Returns
    -------
    ComparisonResult

    Raises
    ------
    InputError
        Unknown method, variant or parameter; clouds that cannot be aligned.
    """
    method = canonical_method(method)
    settings = parse_comparison_params(
        method, variant, params, random_state=random_state, align=align
    )
    warm_up()  # the detector's libraries load on a thread while the clouds are aligned
    align = settings.align
    registration_params = settings.registration
    localisation_params = settings.localisation
    explicit_reference_origin = settings.reference_origin
    explicit_scan_origin = settings.scan_origin
    detector = settings.detector

    def report(stage: str, fraction: float) -> None:
        if progress is not None:
            progress(stage, fraction)

    timings: dict[str, float] = {}
    local_origin = choose_local_origin(reference.points)
    # no copy when the data is already local (1M points: 24 MB a cloud); nothing below
    # modifies these arrays in place
    reference_points = reference.points - local_origin if local_origin.any() else reference.points
    scan_points = scan.points - local_origin if local_origin.any() else scan.points
    threads = available_threads() if threads is None else max(1, int(threads))
    ahead = align and threads >= 2 and len(reference_points) >= REFERENCE_AHEAD_MIN_POINTS
    origin_cache = ReferenceOriginCache.of(
        geometry_cache,
        reference,
        local_origin,
        given=explicit_reference_origin,
        estimate=settings.estimate_origins,
        recover=settings.recover_stations,
    )
    facts: dict[str, tuple[str, Any]] = {}
    alignment_cache = ReferenceAlignmentCache.of(geometry_cache, facts)

    def resolve_reference() -> ResolvedOrigin:
        started = time.perf_counter()
        resolved = origin_cache.load(facts) if origin_cache is not None else None
        if reference.trajectory is not None:  # its pseudo-stations along the path
            resolved = trajectory_origin(reference, reference_points, local_origin)
        elif resolved is None:
            resolved = resolve_stations(
                "reference",
                reference_points,
                given=origins_in_local_frame(
                    explicit_reference_origin, None, local_origin, "reference_origin"
                ),
                from_file=origins_in_local_frame(None, reference.sensor_origin, local_origin),
                estimate=settings.estimate_origins,
                recover=settings.recover_stations,
                station_of=reference,
            )
            if origin_cache is not None:
                origin_cache.remember(resolved, facts)
        timings["origins"] = timings.get("origins", 0.0) + time.perf_counter() - started
        return resolved

    # With a second thread the reference's neighbour search starts first and runs while the
    # reference's origin is resolved and the scan aligned (none of which needs it); on one
    # thread the origin comes first, so that a cache written by the search holds it.
    resolved_reference = None if ahead else resolve_reference()
    report("align", 0.05)
    with _reference_neighbourhoods_ahead(
        reference_points, localisation_params, ahead, geometry_cache, facts
    ) as reference_neighbourhoods:
        if resolved_reference is None:
            resolved_reference = resolve_reference()
        reference_origin = resolved_reference.origin
        reference_station = station_index(reference, resolved_reference, "reference")
        started = time.perf_counter()
        if align:
            registration = register_scan(
                reference_points,
                scan_points,
                reference_memory=alignment_cache,
                **registration_params,
            )
        else:
            registration = identity_registration(
                reference_points, scan_points, reference_memory=alignment_cache
            )
        aligned_scan = apply_transform(scan_points, registration.transform)
        timings["align"] = time.perf_counter() - started
        # the scan's own neighbour search runs while its origin is resolved
        scan_neighbourhoods = (
            start_neighbourhood_search(aligned_scan, openmp_threads=threads, **localisation_params)
            if ahead and len(aligned_scan) >= REFERENCE_AHEAD_MIN_POINTS
            else None
        )
        try:
            started = time.perf_counter()
            resolved_scan = (
                trajectory_origin(
                    scan,
                    aligned_scan,
                    local_origin,
                    lambda origins: apply_transform(origins, registration.transform),
                )
                if scan.trajectory is not None
                else resolve_moved_cloud(
                    "scan",
                    scan_points,
                    registration.transform,
                    aligned_points=aligned_scan,
                    given=origins_in_local_frame(
                        settings.scan_origin, None, local_origin, "scan_origin"
                    ),
                    from_file=origins_in_local_frame(None, scan.sensor_origin, local_origin),
                    estimate=settings.estimate_origins,
                    recover=settings.recover_stations,
                    station_of=scan,
                    # a reference surveyed from several stations: the scan's are searched first
                    stations_first=resolved_reference.source == "recovered",
                )
            )
            scan_origin = resolved_scan.origin
            scan_station = station_index(scan, resolved_scan, "scan")
            timings["origins"] += time.perf_counter() - started
            registration_report = registration.to_json_dict()
            registration_report["transform"] = _file_frame_transform(
                registration.transform, local_origin
            ).tolist()
            registration_report["enabled"] = align
            centre = scan_points.mean(axis=0)  # how far the alignment moved the scan (metres)
            moved = apply_transform(centre[None], registration.transform)[0] - centre
            registration_report["translation_m"] = float(np.linalg.norm(moved))
            del scan_points  # a shifted copy (24 bytes a point) when the files are georeferenced

            report("localise", 0.35)
            started = time.perf_counter()
            with threadpool_limits(limits=threads, user_api="openmp"):
                localisation = localise_changes(
                    reference_points,
                    aligned_scan,
                    reference_origin=reference_origin,
                    scan_origin=scan_origin,
                    reference_station=reference_station,
                    scan_station=scan_station,
                    reference_stations_unknown=resolved_reference.stations_unknown,
                    scan_stations_unknown=resolved_scan.stations_unknown,
                    reference_trajectory_rays=trajectory_rays(resolved_reference),
                    scan_trajectory_rays=trajectory_rays(resolved_scan),
                    # Not registration.rmse: that includes sampling distance and real change
                    # (0.15 m on KITTI); localise measures the remaining misalignment itself
                    # from local surfaces.
                    registration_rmse=0.0,
                    threads=threads,
                    reference_neighbourhoods=reference_neighbourhoods,
                    scan_neighbourhoods=scan_neighbourhoods,
                    **localisation_params,
                )
        finally:
            if isinstance(scan_neighbourhoods, NeighbourhoodSearch):
                scan_neighbourhoods.cancel()
    timings["localise"] = time.perf_counter() - started
    if origin_cache is not None:
        origin_cache.keep()
    if alignment_cache is not None:
        alignment_cache.keep()

    report("detect", 0.65)
    started = time.perf_counter()
    reference_observed = localisation.reference_label != LABEL_UNOBSERVED
    scan_observed = localisation.scan_label != LABEL_UNOBSERVED
    use_observed = (
        np.count_nonzero(reference_observed) >= MIN_POINTS
        and np.count_nonzero(scan_observed) >= MIN_POINTS
    )
    with threadpool_limits(limits=1, user_api="blas"):
        if use_observed:
            detection = detector.detect(
                reference_points[reference_observed], aligned_scan[scan_observed]
            )
        else:
            detection = detector.detect(reference_points, aligned_scan)
    timings["detect"] = time.perf_counter() - started

    calibration = dict(detection.calibration)
    calibration["compared_points"] = "mutually observed" if use_observed else "all"
    changed, tests, calibration["site"] = decide(
        DecisionInputs(
            rule=settings.decision,
            method=method,
            variant=variant,
            score=float(detection.score),
            detector_threshold=float(detection.threshold),
            n_regions=len(localisation.regions),
            largest_region_extent_m=largest_extent(localisation.regions),
            min_region_points=int(localisation.parameters.get("min_region_points", 1)),
        ),
        site_calibration,
    )
    visibility = {  # what was found out about each cloud's sensors, and the test it got
        side: {
            **resolved.visibility_report(),
            "test": localisation.parameters.get(f"{side}_visibility"),
        }
        for side, resolved in (("reference", resolved_reference), ("scan", resolved_scan))
    }
    calibration["visibility"] = visibility  # stored with a job's result (the API shows it)
    calibration["decision"] = {
        "rule": settings.decision,
        "detector_changed": bool(detection.changed),
        "n_regions": len(localisation.regions),
        "tests": tests,
    }
    regions = [_region_summary(region, local_origin) for region in localisation.regions]
    uncertain_regions = [
        _region_summary(region, local_origin) for region in localisation.uncertain_regions
    ]
    effective_params: dict[str, Any] = {
        **detector.get_params(),
        "align": align,
        "registration": registration_params,
        "localisation": localisation_params,
        "decision": settings.decision,
    }
    for key, explicit in (
        ("reference_origin", explicit_reference_origin),
        ("scan_origin", explicit_scan_origin),
    ):
        if explicit is not None:  # as given: one origin, or a list of them
            effective_params[key] = np.asarray(explicit, dtype=np.float64).tolist()
    if settings.recover_stations != "auto":
        effective_params["recover_stations"] = settings.recover_stations
    if not settings.estimate_origins:
        effective_params["estimate_origins"] = False
    report("done", 1.0)
    return ComparisonResult(
        method=method,
        variant=variant,
        params=effective_params,
        score=float(detection.score),
        threshold=float(detection.threshold),
        changed=changed,
        calibration=calibration,
        registration=registration_report,
        regions=regions,
        uncertain_regions=uncertain_regions,
        n_reference=len(reference),
        n_scan=len(scan),
        reference_label=reference.to_source_order(
            localisation.reference_label.astype(np.int8), LABEL_UNOBSERVED
        ),
        scan_label=scan.to_source_order(localisation.scan_label.astype(np.int8), LABEL_UNOBSERVED),
        reference_distance=reference.to_source_order(
            localisation.reference_distance.astype(np.float32), np.nan
        ),
        scan_distance=scan.to_source_order(localisation.scan_distance.astype(np.float32), np.nan),
        reference_region=reference.to_source_order(
            localisation.reference_region.astype(np.int32), -1
        ),
        scan_region=scan.to_source_order(localisation.scan_region.astype(np.int32), -1),
        localisation=dict(localisation.parameters),
        timings=timings,
        sensor_origins={
            "reference": resolved_reference.report(lambda origin: origin + local_origin),
            "scan": resolved_scan.report(
                lambda origin: _to_scan_file(origin, registration.transform, local_origin)
            ),
        },
        warnings=[*resolved_reference.warnings, *resolved_scan.warnings],
        visibility=visibility,
    )


def _to_scan_file(
    origin: NDArray[np.float64], transform: NDArray[np.float64], local_origin: NDArray
) -> NDArray[np.float64]:
    """Positions in the aligned local frame, in the scan file's coordinates, shape (3,)/(k, 3)."""
    moved = apply_transform(origin.reshape(-1, 3), np.linalg.inv(transform)) + local_origin
    return moved.reshape(origin.shape)
