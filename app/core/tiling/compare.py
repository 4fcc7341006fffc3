"""A whole comparison in tiles, in one process: what ``scandiff compare`` runs when a pair does
not fit the memory budget (and the job runner, until tiles fan out to the workers).

The stages around localisation are those of :func:`app.core.pipeline.compare`, with three
differences that bound memory:

- **Registration** runs on at most :data:`REGISTRATION_SAMPLE` points of each cloud (evenly
  strided: GICP thins both clouds on a voxel grid anyway); each tile then measures the
  alignment residual left on its own crop, reported per tile (``localisation.tiles``) with
  the largest of them.
- **Localisation** runs tile by tile (:mod:`app.core.tiling`), with the sensor origins and
  stations resolved once on the whole clouds and each point's station assigned once.
- **Detection**: the EMD detectors score at most :data:`DETECTION_SAMPLE` mutually observed
  points of each cloud, a uniform random subsample (seeded by ``random_state``) of the
  points the one-process comparison scores.  The detectors thin their input on a voxel grid
  to a few thousand working points (``max_points``), so at most a subsample of 2M points
  changes which point represents a voxel, not which voxels are occupied: the score and its
  threshold are those of the whole observed parts to within their resampling noise.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from app.core.cloud import MIN_POINTS, PointCloud, choose_local_origin
from app.core.comparison.align import file_frame_transform as _file_frame_transform
from app.core.comparison.assemble import to_scan_file as _to_scan_file
from app.core.comparison.result import region_summary as _region_summary
from app.core.comparison_settings import parse_comparison_params
from app.core.detectors import canonical_method
from app.core.localise import LABEL_UNOBSERVED, Localisation
from app.core.localise.changes import _default_min_region_points
from app.core.localise.station_assignment import assign_stations
from app.core.origins.known_stations import origins_in_local_frame
from app.core.origins.own_frame import resolve_moved_cloud
from app.core.origins.resolve import ResolvedOrigin
from app.core.origins.station_recovery import resolve_stations
from app.core.origins.trajectory_origin import station_index, trajectory_origin, trajectory_rays
from app.core.pipeline import ComparisonResult, ProgressCallback
from app.core.registration import apply_transform, identity_registration, register_scan
from app.core.site_calibration import DecisionInputs, decide, largest_extent
from app.core.threads import available_threads
from app.core.tiling.merge import merge_tiles
from app.core.tiling.plan import (
    DEFAULT_MARGIN_METRES,
    DEFAULT_RAY_REACH_METRES,
    TilePlan,
    crop_point_limit,
    plan_tiles,
)
from app.core.tiling.tile import TileContext, TileResult, TileSource, compute_tile

__all__ = [
    "DETECTION_SAMPLE",
    "REGISTRATION_SAMPLE",
    "compare_tiled",
    "compare_within_budget",
    "fits_budget",
]

REGISTRATION_SAMPLE = 2_000_000
DETECTION_SAMPLE = 2_000_000


def fits_budget(n_reference: int, n_scan: int, budget_bytes: int) -> bool:
    """Whether the one-process comparison of a pair this size fits ``budget_bytes``."""
    return crop_point_limit(budget_bytes, n_reference + n_scan) >= n_reference + n_scan


def _strided(points: NDArray[np.float64], most: int) -> NDArray[np.float64]:
    return points[:: max(1, len(points) // most)]


def _stations(
    points: NDArray[np.float64], origins: NDArray | None, station: NDArray | None
) -> NDArray | None:
    """Each point's station: given, or assigned once for the whole cloud (several origins)."""
    if station is not None or origins is None or len(np.atleast_2d(origins)) < 2:
        return station
    return assign_stations(points, np.atleast_2d(origins))


def compare_tiled(
    reference: PointCloud,
    scan: PointCloud,
    *,
    budget_bytes: int,
    method: str = "gmm",
    variant: str = "improved",
    align: bool = True,
    random_state: int = 0,
    params: Mapping[str, Any] | None = None,
    progress: ProgressCallback | None = None,
    threads: int | None = None,
    site_calibration: Mapping[str, Any] | None = None,
    max_crop_points: int | None = None,
    margin: float = DEFAULT_MARGIN_METRES,
    ray_reach: float = DEFAULT_RAY_REACH_METRES,
    run_tiles: TileRunner | None = None,
) -> ComparisonResult:
    """:func:`app.core.pipeline.compare` localised tile by tile within ``budget_bytes``.

    Parameters
    ----------
    reference, scan, method, variant, align, random_state, params, progress, threads,
    site_calibration
        As :func:`app.core.pipeline.compare`.
    budget_bytes : int
        Memory this process may use; tile sizes follow from it (:mod:`app.core.tiling.plan`).
    max_crop_points : int, optional
        Points of both clouds a tile's crop may have, instead of the budget's figure (tests
        force small tiles with it).
    margin : float
        Metres a tile's crop extends beyond its core.
    ray_reach : float
        Metres beyond a crop that the other sensor's returns through it are kept
        (:class:`~app.core.tiling.tile.TileContext`).
    run_tiles : callable, optional
        ``run_tiles(plan, source, context, threads, report) -> list[TileResult]`` (in tile
        order): who computes the tiles.  Default: each in turn in this process
        (:func:`compute_tiles_here`); a job worker passes one that fans them out on the queue
        (:mod:`app.jobs.tiles`).

    Returns
    -------
    ComparisonResult
        With ``localisation["tiles"]``: the plan and each tile's figures.

    Raises
    ------
    TileBudgetError
        Not even one tile fits the budget.
    InputError
        As :func:`app.core.pipeline.compare`.
    """
    method = canonical_method(method)
    settings = parse_comparison_params(
        method, variant, params, random_state=random_state, align=align
    )

    def report(stage: str, fraction: float) -> None:
        if progress is not None:
            progress(stage, fraction)

    threads = available_threads() if threads is None else max(1, int(threads))
    aligned = _align(reference, scan, settings, report)
    report("localise", 0.35)
    started = time.perf_counter()
    context, source = _tile_inputs(reference, scan, aligned, settings, ray_reach)
    limit = (
        max_crop_points
        if max_crop_points is not None
        else crop_point_limit(budget_bytes, len(source.reference_points) + len(source.scan_points))
    )
    plan = plan_tiles(
        source.reference_points[:, :2],
        source.scan_points[:, :2],
        max_crop_points=limit,
        count_crop=lambda low, high: source.count_crop(low, high, margin, context),
        margin=margin,
        budget_bytes=budget_bytes,
    )
    aligned.timings["plan"] = time.perf_counter() - started
    results = (run_tiles or compute_tiles_here)(plan, source, context, threads, report)
    localisation = merge_tiles(
        plan,
        results,
        len(source.reference_points),
        len(source.scan_points),
        context.min_region_points,
    )
    aligned.timings["localise"] = time.perf_counter() - started
    report("detect", 0.85)
    result = _assemble(
        reference,
        scan,
        aligned,
        localisation,
        settings,
        method=method,
        variant=variant,
        random_state=random_state,
        site_calibration=site_calibration,
        min_region_points=context.min_region_points,
        budget_bytes=budget_bytes,
    )
    report("done", 1.0)
    return result


@dataclass
class _Aligned:
    """The pair in the local frame, the scan aligned, both clouds' origins resolved."""

    local_origin: NDArray[np.float64]
    reference_points: NDArray[np.float64]
    aligned_scan: NDArray[np.float64]
    transform: NDArray[np.float64]
    registration_report: dict[str, Any]
    resolved_reference: ResolvedOrigin
    resolved_scan: ResolvedOrigin
    timings: dict[str, float]


def _align(
    reference: PointCloud, scan: PointCloud, settings: Any, report: ProgressCallback
) -> _Aligned:
    """Origins of the reference, registration on a subsample, origins of the aligned scan."""
    timings: dict[str, float] = {}
    local_origin = choose_local_origin(reference.points)
    reference_points = reference.points - local_origin if local_origin.any() else reference.points
    scan_points = scan.points - local_origin if local_origin.any() else scan.points
    started = time.perf_counter()
    resolved_reference: ResolvedOrigin = (
        trajectory_origin(reference, reference_points, local_origin)
        if reference.trajectory is not None
        else resolve_stations(
            "reference",
            reference_points,
            given=origins_in_local_frame(
                settings.reference_origin, None, local_origin, "reference_origin"
            ),
            from_file=origins_in_local_frame(None, reference.sensor_origin, local_origin),
            estimate=settings.estimate_origins,
            recover=settings.recover_stations,
            station_of=reference,
        )
    )
    timings["origins"] = time.perf_counter() - started
    report("align", 0.05)
    started = time.perf_counter()
    reference_sample = _strided(reference_points, REGISTRATION_SAMPLE)
    scan_sample = _strided(scan_points, REGISTRATION_SAMPLE)
    registration = (
        register_scan(reference_sample, scan_sample, **settings.registration)
        if settings.align
        else identity_registration(reference_sample, scan_sample)
    )
    del reference_sample, scan_sample
    aligned_scan = apply_transform(scan_points, registration.transform)
    timings["align"] = time.perf_counter() - started
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
            given=origins_in_local_frame(settings.scan_origin, None, local_origin, "scan_origin"),
            from_file=origins_in_local_frame(None, scan.sensor_origin, local_origin),
            estimate=settings.estimate_origins,
            recover=settings.recover_stations,
            station_of=scan,
            stations_first=resolved_reference.source == "recovered",
        )
    )
    timings["origins"] += time.perf_counter() - started
    registration_report = registration.to_json_dict()
    registration_report["transform"] = _file_frame_transform(
        registration.transform, local_origin
    ).tolist()
    registration_report["enabled"] = settings.align
    registration_report["sample_points"] = min(len(reference_points), REGISTRATION_SAMPLE)
    centre = scan_points.mean(axis=0)
    moved = apply_transform(centre[None], registration.transform)[0] - centre
    registration_report["translation_m"] = float(np.linalg.norm(moved))
    return _Aligned(
        local_origin=local_origin,
        reference_points=reference_points,
        aligned_scan=aligned_scan,
        transform=registration.transform,
        registration_report=registration_report,
        resolved_reference=resolved_reference,
        resolved_scan=resolved_scan,
        timings=timings,
    )


def _tile_inputs(
    reference: PointCloud, scan: PointCloud, aligned: _Aligned, settings: Any, ray_reach: float
) -> tuple[TileContext, TileSource]:
    """What every tile shares, and the points with each one's station."""
    localisation_params = dict(settings.localisation)
    min_region_points = localisation_params.get("min_region_points") or (
        _default_min_region_points(len(aligned.reference_points), len(aligned.aligned_scan))
    )
    context = TileContext(
        reference_origins=_origins(aligned.resolved_reference),
        scan_origins=_origins(aligned.resolved_scan),
        reference_stations_unknown=aligned.resolved_reference.stations_unknown,
        scan_stations_unknown=aligned.resolved_scan.stations_unknown,
        min_region_points=int(min_region_points),
        localisation_params=localisation_params,
        ray_reach=ray_reach,
    )
    source = TileSource(
        reference_points=aligned.reference_points,
        scan_points=aligned.aligned_scan,
        reference_station=_stations(
            aligned.reference_points,
            context.reference_origins,
            station_index(reference, aligned.resolved_reference, "reference"),
        ),
        scan_station=_stations(
            aligned.aligned_scan,
            context.scan_origins,
            station_index(scan, aligned.resolved_scan, "scan"),
        ),
        reference_rays=trajectory_rays(aligned.resolved_reference),
        scan_rays=trajectory_rays(aligned.resolved_scan),
    )
    return context, source


def _assemble(
    reference: PointCloud,
    scan: PointCloud,
    aligned: _Aligned,
    localisation: Localisation,
    settings: Any,
    **facts: Any,
) -> ComparisonResult:
    """Detection on a subsample, the decision, and the result in the files' frame and order."""
    started = time.perf_counter()
    detection, compared = _detect(
        settings.detector,
        aligned.reference_points,
        aligned.aligned_scan,
        localisation,
        facts["random_state"],
    )
    aligned.timings["detect"] = time.perf_counter() - started
    calibration = dict(detection.calibration)
    calibration["compared_points"] = compared
    changed, tests, calibration["site"] = decide(
        DecisionInputs(
            rule=settings.decision,
            method=facts["method"],
            variant=facts["variant"],
            score=float(detection.score),
            detector_threshold=float(detection.threshold),
            n_regions=len(localisation.regions),
            largest_region_extent_m=largest_extent(localisation.regions),
            min_region_points=int(facts["min_region_points"]),
        ),
        facts["site_calibration"],
    )
    sides = (("reference", aligned.resolved_reference), ("scan", aligned.resolved_scan))
    visibility = {
        side: {
            **resolved.visibility_report(),
            "test": localisation.parameters.get(f"{side}_visibility"),
        }
        for side, resolved in sides
    }
    calibration["visibility"] = visibility
    calibration["decision"] = {
        "rule": settings.decision,
        "detector_changed": bool(detection.changed),
        "n_regions": len(localisation.regions),
        "tests": tests,
    }
    local_origin, transform = aligned.local_origin, aligned.transform
    return ComparisonResult(
        method=facts["method"],
        variant=facts["variant"],
        params=_effective_params(settings, facts["budget_bytes"]),
        score=float(detection.score),
        threshold=float(detection.threshold),
        changed=changed,
        calibration=calibration,
        registration=aligned.registration_report,
        regions=[_region_summary(region, local_origin) for region in localisation.regions],
        uncertain_regions=[
            _region_summary(region, local_origin) for region in localisation.uncertain_regions
        ],
        n_reference=len(reference),
        n_scan=len(scan),
        reference_label=reference.to_source_order(localisation.reference_label, -1),
        scan_label=scan.to_source_order(localisation.scan_label, -1),
        reference_distance=reference.to_source_order(localisation.reference_distance, np.nan),
        scan_distance=scan.to_source_order(localisation.scan_distance, np.nan),
        reference_region=reference.to_source_order(localisation.reference_region, -1),
        scan_region=scan.to_source_order(localisation.scan_region, -1),
        localisation=dict(localisation.parameters),
        timings=aligned.timings,
        sensor_origins={
            "reference": aligned.resolved_reference.report(lambda origin: origin + local_origin),
            "scan": aligned.resolved_scan.report(
                lambda origin: _to_scan_file(origin, transform, local_origin)
            ),
        },
        warnings=[*aligned.resolved_reference.warnings, *aligned.resolved_scan.warnings],
        visibility=visibility,
    )


def _effective_params(settings: Any, budget_bytes: int) -> dict[str, Any]:
    """The parameters the comparison ran with, as :func:`app.core.pipeline.compare` reports."""
    effective: dict[str, Any] = {
        **settings.detector.get_params(),
        "align": settings.align,
        "registration": settings.registration,
        "localisation": dict(settings.localisation),
        "decision": settings.decision,
        "memory_budget_bytes": int(budget_bytes),
    }
    for key, explicit in (
        ("reference_origin", settings.reference_origin),
        ("scan_origin", settings.scan_origin),
    ):
        if explicit is not None:  # as given
            effective[key] = np.asarray(explicit, dtype=np.float64).tolist()
    if settings.recover_stations != "auto":
        effective["recover_stations"] = settings.recover_stations
    if not settings.estimate_origins:
        effective["estimate_origins"] = False
    return effective


def _origins(resolved: ResolvedOrigin) -> NDArray[np.float64] | None:
    """A resolution's origins as a (k, 3) array, or None."""
    return None if resolved.origin is None else np.atleast_2d(resolved.origin).astype(np.float64)


TileRunner = Callable[[TilePlan, TileSource, TileContext, int, ProgressCallback], list[TileResult]]
"""Who computes a plan's tiles: ``run_tiles(plan, source, context, threads, report)``."""


def compute_tiles_here(
    plan: TilePlan,
    source: TileSource,
    context: TileContext,
    threads: int,
    report: ProgressCallback,
) -> list[TileResult]:
    """Every tile in turn in this process (the default :data:`TileRunner`)."""
    results = []
    for tile_index in range(plan.n_tiles):
        results.append(compute_tile(plan, tile_index, source, context, threads=threads))
        report("localise", 0.35 + 0.5 * (tile_index + 1) / plan.n_tiles)
    return results


def _detect(
    detector: Any,
    reference_points: NDArray[np.float64],
    aligned_scan: NDArray[np.float64],
    localisation: Localisation,
    random_state: int,
) -> tuple[Any, str]:
    """The detector on (at most :data:`DETECTION_SAMPLE` of) the mutually observed points."""
    reference_observed = np.flatnonzero(localisation.reference_label != LABEL_UNOBSERVED)
    scan_observed = np.flatnonzero(localisation.scan_label != LABEL_UNOBSERVED)
    use_observed = len(reference_observed) >= MIN_POINTS and len(scan_observed) >= MIN_POINTS
    if not use_observed:
        reference_observed = np.arange(len(reference_points))
        scan_observed = np.arange(len(aligned_scan))
    rng = np.random.default_rng(random_state)
    sampled = False
    chosen = []
    for observed in (reference_observed, scan_observed):
        if len(observed) > DETECTION_SAMPLE:
            observed = np.sort(rng.choice(observed, DETECTION_SAMPLE, replace=False))
            sampled = True
        chosen.append(observed)
    with threadpool_limits(limits=1, user_api="blas"):
        detection = detector.detect(reference_points[chosen[0]], aligned_scan[chosen[1]])
    compared = "mutually observed" if use_observed else "all"
    if sampled:
        compared += f" (a random {DETECTION_SAMPLE:,} of each cloud at most)"
    return detection, compared


def compare_within_budget(
    reference: PointCloud,
    scan: PointCloud,
    *,
    budget_bytes: int | None,
    **options: Any,
) -> ComparisonResult:
    """:func:`app.core.pipeline.compare` when the pair fits ``budget_bytes`` (or no budget),
    else :func:`compare_tiled` (the ``geometry_cache`` option applies to the former only).

    Parameters
    ----------
    reference, scan : PointCloud
    budget_bytes : int or None
        Memory the comparison may use; None: no limit (always one process).
    **options
        Keyword arguments of :func:`app.core.pipeline.compare`.

    Returns
    -------
    ComparisonResult

    Raises
    ------
    TileBudgetError
        Not even one tile fits.
    """
    from app.core.pipeline import compare

    if budget_bytes is None or fits_budget(len(reference), len(scan), budget_bytes):
        return compare(reference, scan, **options)
    options.pop("geometry_cache", None)
    return compare_tiled(reference, scan, budget_bytes=budget_bytes, **options)
