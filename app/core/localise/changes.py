"""The public entry point: :func:`localise_changes` and its result, :class:`Localisation`.

The steps, each in its own module (imports go one way: changes -> visibility -> rays / regions
/ distance -> surface -> neighbourhoods -> settings; method and measured numbers in
``docs/localisation.md``):

1. **Local geometry of each cloud** (:mod:`~app.core.localise.surface`, on the k nearest
   neighbours of :mod:`~app.core.localise.neighbourhoods`): a plane, spacing ``s`` and
   residual per point; the median residual is the cloud's noise ``sigma``.
2. **Distance to the other cloud's surface** (:mod:`~app.core.localise.distance`).
3. **Change candidates.**  ``p`` is a candidate when that distance exceeds the change
   threshold ``max(tau, min_change_distance)``, with
   ``tau = threshold_factor * sqrt(sigma_ref^2 + sigma_scan^2 + registration_rmse^2)``, AND
   it is not on the other cloud's surface (its nearest point there within the support radius
   and it within the change threshold of that point's plane): the threshold along the normal
   follows the measured noise and the smallest change asked for, the one across the surface
   the other cloud's local spacing.
4. **Visibility: unobserved is never change** (:mod:`~app.core.localise.visibility`): ray
   tests from the other sensor's origin (:mod:`~app.core.localise.rays`), or a coverage test
   without one.
5. **Regions** (:mod:`~app.core.localise.regions`): connected changed points; clusters below
   ``min_region_points`` are noise and relabelled unchanged.

Everything is vectorised numpy with pykdtree's k-NN; the reference and scan sides run on two
threads when available, which roughly halves the time (figures in ``docs/performance.md``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import as_points
from app.core.errors import InputError
from app.core.localise.distance import (
    SUPPORT_FACTOR_QUANTILE,
    Side,
    alignment_residual,
    nearest_in,
    support_factor,
    surface_distance,
)
from app.core.localise.neighbourhoods import Neighbourhoods, NeighbourhoodSearch
from app.core.localise.regions import ChangedRegion, find_regions, mark_moved_surfaces
from app.core.localise.settings import (
    DEFAULT_PARAMETERS,
    as_origins,
    as_station_index,
    resolve_parameters,
)
from app.core.localise.station_assignment import assign_stations
from app.core.localise.surface import local_geometry
from app.core.localise.visibility import (
    LABEL_CHANGED,
    LABEL_UNCHANGED,
    LABEL_UNOBSERVED,
    Labelled,
    find_candidates,
    label_candidates,
)
from app.core.threads import available_threads

__all__ = ["Localisation", "localise_changes"]

MIN_REGION_POINTS_FLOOR = 4
"""Smallest default minimum region size: 1-3 point clusters are noise."""
MIN_REGION_POINTS_PER_SQRT = 0.08
"""Default minimum region size = max(4, 0.08 sqrt(min(n, m))): 4 for the 300-point corridor,
11 at 20k, 18 at 50k, 36 at 200k points.  Spurious clusters come from one-dimensional features
at the resolution limit (an edge, a thin strip seen at a grazing angle) whose point count grows
like sqrt(n); an object's grows like n, so it stays far above this."""
RESOLUTION_THRESHOLD_FRACTION = 0.05
"""``tau`` is at least this fraction of the median spacing (noise-free data has sigma = 0)."""

First = TypeVar("First")
Second = TypeVar("Second")


@dataclass(frozen=True)
class Localisation:
    """Per-point labels, distances and regions of one comparison.

    Attributes
    ----------
    reference_label : ndarray, shape (n,), int8
        0 unchanged, 1 changed ("removed"), -1 unobserved (the scan could not see it).
    scan_label : ndarray, shape (m,), int8
        0 unchanged, 1 changed ("added"), -1 unobserved (the reference could not see it).
    reference_distance : ndarray, shape (n,), float32
        Distance (metres) to the scan's surface; NaN where unobserved.
    scan_distance : ndarray, shape (m,), float32
        Distance to the reference's surface; NaN where unobserved.
    reference_region : ndarray, shape (n,), int32
        Index into ``regions`` of each reference point's region, -1 if none.
    scan_region : ndarray, shape (m,), int32
        Likewise for scan points.
    regions : list of ChangedRegion
        Sorted by ``n_points``, largest first.  Each says its ``evidence`` (seen_empty or
        surface_moved) and ``confidence``.
    uncertain_regions : list of ChangedRegion
        Clusters of candidates the other epoch did not cover (``evidence="no_coverage"``):
        listed, never counted as change; their points are unobserved.
    parameters : dict
        JSON-serialisable effective parameters and estimates (noise, spacing, thresholds,
        support and cluster radii, minimum region size, visibility mode, counts).
    """

    reference_label: NDArray[np.int8]
    scan_label: NDArray[np.int8]
    reference_distance: NDArray[np.float32]
    scan_distance: NDArray[np.float32]
    reference_region: NDArray[np.int32]
    scan_region: NDArray[np.int32]
    regions: list[ChangedRegion]
    parameters: dict[str, Any]
    uncertain_regions: list[ChangedRegion] = dataclasses.field(default_factory=list)


def _in_parallel(
    threads: int, first: Callable[[], First], second: Callable[[], Second]
) -> tuple[First, Second]:
    """``first()`` and ``second()``, concurrently if threads >= 2.

    The reference's and the scan's step of a comparison are independent (numpy and the
    KD-tree release the GIL), so with two threads the localiser takes about half the time;
    the results are the same.
    """
    if threads < 2:
        return first(), second()
    with ThreadPoolExecutor(max_workers=1) as pool:
        future = pool.submit(first)
        second_result = second()
        return future.result(), second_result


def _default_min_region_points(n_reference: int, n_scan: int) -> int:
    """``max(4, round(0.08 * sqrt(min(n, m))))``: see :data:`MIN_REGION_POINTS_PER_SQRT`."""
    return max(
        MIN_REGION_POINTS_FLOOR,
        round(MIN_REGION_POINTS_PER_SQRT * math.sqrt(min(n_reference, n_scan))),
    )


def localise_changes(
    reference: NDArray,
    scan: NDArray,
    *,
    reference_origin: NDArray | None = None,
    scan_origin: NDArray | None = None,
    registration_rmse: float = 0.0,
    min_region_points: int | None = None,
    threads: int | None = None,
    reference_neighbourhoods: Neighbourhoods | NeighbourhoodSearch | None = None,
    scan_neighbourhoods: Neighbourhoods | NeighbourhoodSearch | None = None,
    reference_station: NDArray | None = None,
    scan_station: NDArray | None = None,
    reference_stations_unknown: bool = False,
    scan_stations_unknown: bool = False,
    reference_trajectory_rays: tuple[NDArray, NDArray] | None = None,
    scan_trajectory_rays: tuple[NDArray, NDArray] | None = None,
    **params: Any,
) -> Localisation:
    """Label each point unchanged, changed or unobserved and group changes into regions.

    Parameters
    ----------
    reference : array_like, shape (n, 3)
        The reference scan.
    scan : array_like, shape (m, 3)
        The new scan, already aligned into the reference frame.
    reference_origin : array_like, shape (3,) or (k, 3), optional
        The reference sensor's position (reference frame), or one per station of a cloud
        merged from k stations.  Enables the ray visibility test for scan points (observed =
        observed by any station); without it they get the coverage test.
    scan_origin : array_like, shape (3,) or (k, 3), optional
        The scan sensor's position(s), already in the reference frame.  Enables the ray
        visibility test for reference points.
    registration_rmse : float
        Residual of the alignment (metres); widens the distance threshold.
    min_region_points : int, optional
        Smaller clusters of changed points are noise and relabelled unchanged.  Default:
        ``max(4, round(0.08 * sqrt(min(n, m))))``.
    threads : int, optional
        Threads to use (the reference and scan sides run concurrently from 2; the KD-tree
        queries use OpenMP's setting).  Default: :func:`available_threads`.  The result does
        not depend on it.
    reference_neighbourhoods : Neighbourhoods or NeighbourhoodSearch, optional
        :func:`~app.core.localise.neighbourhoods.nearest_neighbourhoods` of ``reference``
        with :func:`~app.core.localise.neighbourhoods.neighbourhood_size` neighbours,
        computed ahead (the pipeline starts one with
        :func:`~app.core.localise.neighbourhoods.start_neighbourhood_search` while the scan
        is aligned).  The result is the same as without it.
    scan_neighbourhoods : Neighbourhoods or NeighbourhoodSearch, optional
        The same for ``scan`` (the pipeline searches them while the scan's origin is
        resolved).
    reference_station, scan_station : array_like, shape (n,) / (m,), int, optional
        Index into the cloud's origins of the station that took each point.  Without it a
        cloud with several origins has its points assigned to stations
        (:func:`~app.core.localise.station_assignment.assign_stations`).
    reference_stations_unknown, scan_stations_unknown : bool
        The cloud was sampled by lidars from several stations that are not known (nor
        recovered): the other cloud's candidates get the origin-free surface test
        (``origin_free_test="auto"``, :func:`~app.core.localise.visibility.label_candidates`).
    reference_trajectory_rays, scan_trajectory_rays : (ndarray, ndarray), optional
        The cloud was taken along a trajectory: its origins are its pseudo-stations' sensor
        positions, its station index each point's pseudo-station, and these ``(returns,
        bounds)`` the points each pseudo-station's rays end on
        (:class:`app.core.trajectory_poses.SensorGroups`); the other cloud's candidates get the
        trajectory test (:mod:`~app.core.localise.trajectory_visibility`).
    **params
        See :data:`~app.core.localise.settings.DEFAULT_PARAMETERS`.

    Returns
    -------
    Localisation

    Raises
    ------
    PointCloudError
        A cloud is not (n, 3), has non-finite values or fewer than 10 points.
    InputError
        An unknown or invalid parameter or origin.
    """
    settings = resolve_parameters(params)
    threads = available_threads() if threads is None else max(1, int(threads))
    reference_points = as_points(reference, "reference")
    scan_points = as_points(scan, "scan")
    reference_origins = as_origins(reference_origin, "reference_origin")
    scan_origins = as_origins(scan_origin, "scan_origin")
    reference_station, reference_assignment = _stations_of(
        reference_points, reference_origins, reference_station, "reference_station"
    )
    scan_station, scan_assignment = _stations_of(
        scan_points, scan_origins, scan_station, "scan_station"
    )
    if not (math.isfinite(registration_rmse) and registration_rmse >= 0):
        raise InputError(f"registration_rmse must be >= 0, got {registration_rmse}")
    if min_region_points is None:
        min_region_points = _default_min_region_points(len(reference_points), len(scan_points))
    elif min_region_points < 1:
        raise InputError(f"min_region_points must be >= 1, got {min_region_points}")

    n_neighbors = settings["n_neighbors"]
    reference_geometry, scan_geometry = _in_parallel(
        threads,
        lambda: local_geometry(
            reference_points, n_neighbors, neighbourhoods=reference_neighbourhoods
        ),
        lambda: local_geometry(scan_points, n_neighbors, neighbourhoods=scan_neighbourhoods),
    )
    (reference_nn_distance, reference_nn_index), (scan_nn_distance, scan_nn_index) = _in_parallel(
        threads,
        partial(nearest_in, reference_points, scan_geometry, reference_geometry.order),
        partial(nearest_in, scan_points, reference_geometry, scan_geometry.order),
    )
    reference_side = Side(
        name="reference",
        region_kind="removed",
        points=reference_points,
        origins=reference_origins,
        station=reference_station,
        stations_unknown=reference_stations_unknown and reference_origins is None,
        trajectory_rays=reference_trajectory_rays if reference_station is not None else None,
        geometry=reference_geometry,
        nearest_distance=reference_nn_distance,
        nearest_index=reference_nn_index,
    )
    scan_side = Side(
        name="scan",
        region_kind="added",
        points=scan_points,
        origins=scan_origins,
        station=scan_station,
        stations_unknown=scan_stations_unknown and scan_origins is None,
        trajectory_rays=scan_trajectory_rays if scan_station is not None else None,
        geometry=scan_geometry,
        nearest_distance=scan_nn_distance,
        nearest_index=scan_nn_index,
    )
    del reference_geometry, scan_geometry  # the sides hold them (and release their indices)

    # both clouds' values in one array, partitioned in place (no copy: 80 MB at 5M + 5M)
    both_spacings = np.concatenate([reference_side.geometry.spacing, scan_side.geometry.spacing])
    median_spacing = float(np.median(both_spacings, overwrite_input=True))
    del both_spacings
    relative_nn_distance = np.empty(len(reference_points) + len(scan_points))
    np.divide(
        reference_nn_distance,
        scan_side.geometry.spacing[reference_nn_index],
        out=relative_nn_distance[: len(reference_points)],
    )
    np.divide(
        scan_nn_distance,
        reference_side.geometry.spacing[scan_nn_index],
        out=relative_nn_distance[len(reference_points) :],
    )
    support = support_factor(relative_nn_distance, settings["support_factor"])
    nn_distance_quartile = float(
        np.quantile(relative_nn_distance, SUPPORT_FACTOR_QUANTILE, overwrite_input=True)
    )
    del relative_nn_distance  # 8 bytes a point of both clouds
    noises = (reference_side.geometry.noise, scan_side.geometry.noise)
    resolution_floor = RESOLUTION_THRESHOLD_FRACTION * median_spacing
    noise_only_threshold = max(
        settings["threshold_factor"] * math.hypot(*noises, registration_rmse),
        resolution_floor,
    )
    residual = alignment_residual(
        reference_side, scan_side, threshold=noise_only_threshold, support_factor=support
    )
    threshold = max(
        settings["threshold_factor"] * math.hypot(*noises, registration_rmse, residual),
        resolution_floor,
    )
    change_threshold = max(threshold, settings["min_change_distance"])

    def distance_to(own: Side, other: Side) -> tuple[NDArray, NDArray]:
        distance, candidate, _ = surface_distance(
            own.points,
            own.nearest_distance,
            own.nearest_index,
            other=other.geometry,
            threshold=threshold,
            support_factor=support,
            change_threshold=change_threshold,
        )
        return distance, candidate

    (reference_distance, reference_candidate), (scan_distance, scan_candidate) = _in_parallel(
        threads,
        lambda: distance_to(reference_side, scan_side),
        lambda: distance_to(scan_side, reference_side),
    )
    # From here on the neighbour index (4 (k + 1) bytes a point) is needed only for the
    # candidates' flattest neighbours: take those and release it before the visibility test.
    reference_candidates = find_candidates(
        reference_side, distance=reference_distance, candidate=reference_candidate
    )
    scan_candidates = find_candidates(scan_side, distance=scan_distance, candidate=scan_candidate)
    del reference_candidate, scan_candidate
    reference_side = _released(reference_side)
    scan_side = _released(scan_side)
    misalignment = math.hypot(registration_rmse, residual)
    reference_labelled, scan_labelled = _in_parallel(
        threads,
        lambda: label_candidates(
            reference_side,
            scan_side,
            candidates=reference_candidates,
            misalignment=misalignment,
            threshold=threshold,
            settings=settings,
            change_threshold=change_threshold,
        ),
        lambda: label_candidates(
            scan_side,
            reference_side,
            candidates=scan_candidates,
            misalignment=misalignment,
            threshold=threshold,
            settings=settings,
            change_threshold=change_threshold,
        ),
    )
    reference_label, reference_report = reference_labelled.label, reference_labelled.report
    scan_label, scan_report = scan_labelled.label, scan_labelled.report

    def regions_of(side: Side, labelled: Labelled, distance: NDArray, wanted: int) -> Any:
        return find_regions(
            side.points,
            kind=side.region_kind,
            changed=labelled.label == wanted,
            spacing=side.geometry.spacing,
            distance=distance,
            cluster_factor=settings["cluster_factor"],
            min_region_points=min_region_points,
            evidence=labelled.evidence,
            confidence=labelled.confidence,
        )

    (removed, dropped_removed), (added, dropped_added) = _in_parallel(
        threads,
        lambda: regions_of(reference_side, reference_labelled, reference_distance, LABEL_CHANGED),
        lambda: regions_of(scan_side, scan_labelled, scan_distance, LABEL_CHANGED),
    )
    regions: list[ChangedRegion] = [*removed, *added]
    regions.sort(key=lambda region: (-region.n_points, region.kind, int(region.point_indices[0])))
    regions = mark_moved_surfaces(regions)
    uncertain_regions = [
        region
        for side, labelled, distance in (
            (reference_side, reference_labelled, reference_distance),
            (scan_side, scan_labelled, scan_distance),
        )
        for region in regions_of(side, labelled, distance, LABEL_UNOBSERVED)[0]
        if region.evidence == "no_coverage"
    ]
    uncertain_regions.sort(key=lambda region: (-region.n_points, region.kind))

    reference_region = np.full(len(reference_points), -1, dtype=np.int32)
    scan_region = np.full(len(scan_points), -1, dtype=np.int32)
    for number, region in enumerate(regions):
        target = reference_region if region.kind == "removed" else scan_region
        target[region.point_indices] = number
    # changed points outside any kept region were in clusters too small to be a change
    reference_label[(reference_label == LABEL_CHANGED) & (reference_region < 0)] = LABEL_UNCHANGED
    scan_label[(scan_label == LABEL_CHANGED) & (scan_region < 0)] = LABEL_UNCHANGED

    reference_distance_out = reference_distance.astype(np.float32)
    reference_distance_out[reference_label == LABEL_UNOBSERVED] = np.nan
    scan_distance_out = scan_distance.astype(np.float32)
    scan_distance_out[scan_label == LABEL_UNOBSERVED] = np.nan

    parameters: dict[str, Any] = {
        **{name: settings[name] for name in DEFAULT_PARAMETERS if name != "support_factor"},
        "support_factor": support,
        "support_factor_calibrated": settings["support_factor"] is None,
        "min_region_points": int(min_region_points),
        "registration_rmse": float(registration_rmse),
        "reference_noise": reference_side.geometry.noise,
        "scan_noise": scan_side.geometry.noise,
        "alignment_residual": residual,
        "threshold": threshold,
        "change_threshold": change_threshold,
        "reference_spacing_median": float(np.median(reference_side.geometry.spacing)),
        "scan_spacing_median": float(np.median(scan_side.geometry.spacing)),
        "nn_distance_over_spacing_quartile": nn_distance_quartile,
        "support_radius_median": max(support * median_spacing, threshold),
        "cluster_radius_median": settings["cluster_factor"] * median_spacing,
        "reference_stations": 0 if reference_origins is None else len(reference_origins),
        "scan_stations": 0 if scan_origins is None else len(scan_origins),
        "reference_station_assignment": reference_assignment,
        "scan_station_assignment": scan_assignment,
        **reference_report,
        **scan_report,
        "n_reference_changed": int((reference_label == LABEL_CHANGED).sum()),
        "n_reference_unobserved": int((reference_label == LABEL_UNOBSERVED).sum()),
        "n_scan_changed": int((scan_label == LABEL_CHANGED).sum()),
        "n_scan_unobserved": int((scan_label == LABEL_UNOBSERVED).sum()),
        "n_dropped_clusters": int(dropped_removed + dropped_added),
        "n_uncertain_regions": len(uncertain_regions),
    }
    return Localisation(
        reference_label=reference_label,
        scan_label=scan_label,
        reference_distance=reference_distance_out,
        scan_distance=scan_distance_out,
        reference_region=reference_region,
        scan_region=scan_region,
        regions=regions,
        parameters=parameters,
        uncertain_regions=uncertain_regions,
    )


def _stations_of(
    points: NDArray[np.float64],
    origins: NDArray[np.float64] | None,
    station: NDArray | None,
    name: str,
) -> tuple[NDArray[np.int64] | None, str]:
    """The checked per-point station index of one cloud, and where it came from.

    Returns
    -------
    station : ndarray, shape (n,), int64, or None
        None without origins or with one origin and no index (every point is its).
    source : {"none", "single", "given", "assigned"}
    """
    checked = as_station_index(
        station, points.shape[0], None if origins is None else len(origins), name
    )
    if checked is not None:
        return checked, "given"
    if origins is None:
        return None, "none"
    if len(origins) == 1:
        return None, "single"
    return assign_stations(points, origins), "assigned"


def _released(side: Side) -> Side:
    """``side`` with its geometry's neighbour index released."""
    return dataclasses.replace(side, geometry=side.geometry.without_neighbour_index())
