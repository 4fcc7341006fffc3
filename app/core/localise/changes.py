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
5. **Regions** (:mod:`~app.core.localise.changed_regions`, clustering in
   :mod:`~app.core.localise.regions`): connected changed points; clusters below
   ``min_region_points`` are noise and relabelled unchanged, unless a small-cluster rule
   keeps them.

Everything is vectorised numpy with pykdtree's k-NN; the reference and scan sides run on two
threads when available, which roughly halves the time (figures in ``docs/performance.md``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import as_points
from app.core.errors import InputError
from app.core.labels import LABEL_CHANGED, LABEL_UNOBSERVED
from app.core.localise.changed_regions import Found, changed_regions
from app.core.localise.distance import (
    Side,
    alignment_residual,
    nearest_in,
    pair_median_spacing,
    pair_nn_distance_quartile,
    support_factor,
    surface_distance,
)
from app.core.localise.epoch import EpochCloud, with_checked_stations
from app.core.localise.flying_samples import restored_localisation, without_flying_samples
from app.core.localise.gaps import PLANE_RADIUS_FACTOR, on_sampled_planes
from app.core.localise.rays import Candidates
from app.core.localise.regions import ChangedRegion
from app.core.localise.settings import (
    DEFAULT_PARAMETERS,
    as_origins,
    resolve_parameters,
)
from app.core.localise.surface import LocalGeometry, local_geometry
from app.core.localise.surface_levels import crossing_candidates, surface_offset_candidates
from app.core.localise.threshold_band import carry_changes
from app.core.localise.visibility import (
    Labelled,
    agree_on_faces,
    find_candidates,
    label_candidates,
    map_test_planes,
)
from app.core.threads import available_threads, concurrently

__all__ = ["EpochCloud", "Localisation", "localise_changes"]

MIN_REGION_POINTS_FLOOR = 4
"""Smallest default minimum region size: 1-3 point clusters are noise."""
MIN_REGION_POINTS_PER_SQRT = 0.08
"""Default minimum region size = max(4, 0.08 sqrt(min(n, m))): 4 for the 300-point corridor,
11 at 20k, 18 at 50k, 36 at 200k points.  Spurious clusters come from one-dimensional features
at the resolution limit (an edge, a thin strip seen at a grazing angle) whose point count grows
like sqrt(n); an object's grows like n, so it stays far above this."""
RESOLUTION_THRESHOLD_FRACTION = 0.05
"""``tau`` is at least this fraction of the median spacing (noise-free data has sigma = 0)."""


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


def _default_min_region_points(n_reference: int, n_scan: int) -> int:
    """``max(4, round(0.08 * sqrt(min(n, m))))``: see :data:`MIN_REGION_POINTS_PER_SQRT`."""
    return max(
        MIN_REGION_POINTS_FLOOR,
        round(MIN_REGION_POINTS_PER_SQRT * math.sqrt(min(n_reference, n_scan))),
    )


def localise_changes(
    reference: EpochCloud | NDArray,
    scan: EpochCloud | NDArray,
    *,
    registration_rmse: float = 0.0,
    min_region_points: int | None = None,
    threads: int | None = None,
    **params: Any,
) -> Localisation:
    """Label each point unchanged, changed or unobserved and group changes into regions.

    Parameters
    ----------
    reference : EpochCloud or array_like, shape (n, 3)
        The reference scan, with what is known of its sensor (bare points: nothing).
    scan : EpochCloud or array_like, shape (m, 3)
        The new scan, already aligned into the reference frame (its origins too).
    registration_rmse : float
        Residual of the alignment (metres); widens the distance threshold.
    min_region_points : int, optional
        Smaller clusters of changed points are noise and relabelled unchanged.  Default:
        ``max(4, round(0.08 * sqrt(min(n, m))))``.
    threads : int, optional
        Threads to use (the reference and scan sides run concurrently from 2; the KD-tree
        queries use OpenMP's setting).  Default: :func:`available_threads`.  The result does
        not depend on it.
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
    reference, scan = EpochCloud.of(reference), EpochCloud.of(scan)
    reference = dataclasses.replace(reference, points=as_points(reference.points, "reference"))
    scan = dataclasses.replace(scan, points=as_points(scan.points, "scan"))
    reference = dataclasses.replace(
        reference, origin=as_origins(reference.origin, "reference_origin")
    )
    scan = dataclasses.replace(scan, origin=as_origins(scan.origin, "scan_origin"))
    reference, reference_assignment = with_checked_stations(reference, "reference_station")
    scan, scan_assignment = with_checked_stations(scan, "scan_station")
    if not (math.isfinite(registration_rmse) and registration_rmse >= 0):
        raise InputError(f"registration_rmse must be >= 0, got {registration_rmse}")
    n_reference, n_scan = len(reference.points), len(scan.points)  # type: ignore[arg-type]
    if min_region_points is None:
        min_region_points = _default_min_region_points(n_reference, n_scan)
    elif min_region_points < 1:
        raise InputError(f"min_region_points must be >= 1, got {min_region_points}")

    n_neighbors = settings["n_neighbors"]
    reference, scan, kept = without_flying_samples(reference, scan, n_neighbors, threads)
    reference_side, scan_side = _sides(reference, scan, n_neighbors, threads)
    del reference, scan  # the sides hold what is needed (and not the neighbourhoods ahead)
    limits = _thresholds(reference_side, scan_side, settings, registration_rmse, threads)
    reference_side, scan_side, candidates = _candidates(reference_side, scan_side, limits, threads)
    reference_found, scan_found = _labelled(
        (reference_side, scan_side), candidates, limits, settings, threads
    )
    for own, other in ((reference_found, scan_found), (scan_found, reference_found)):
        carry_changes(  # below a lifted c, beside a change (threshold_band)
            *(own.side, other.side, own.labelled, own.distance),
            limits=(settings["min_change_distance"], limits.change_threshold),
            cluster_factor=settings["cluster_factor"],
            min_region_points=min_region_points,
        )
    drawn = changed_regions(
        reference_found,
        scan_found,
        cluster_factor=settings["cluster_factor"],
        min_region_points=min_region_points,
        change_threshold=limits.change_threshold,
        threads=threads,
    )
    parameters = _parameters(
        (reference_found, scan_found),
        limits,
        settings,
        registration_rmse=registration_rmse,
        min_region_points=min_region_points,
        assignments=(reference_assignment, scan_assignment),
        dropped=drawn.dropped,
        n_uncertain=len(drawn.uncertain),
    )
    localisation = Localisation(
        reference_label=reference_found.labelled.label,
        scan_label=scan_found.labelled.label,
        reference_distance=reference_found.output_distance(),
        scan_distance=scan_found.output_distance(),
        reference_region=drawn.reference_region,
        scan_region=drawn.scan_region,
        regions=drawn.regions,
        parameters=parameters,
        uncertain_regions=drawn.uncertain,
    )
    return restored_localisation(localisation, kept, (n_reference, n_scan))


@dataclass(frozen=True)
class _Limits:
    """The distance limits of one localisation, measured from both clouds."""

    support: float
    nn_distance_quartile: float
    median_spacing: float
    residual: float
    threshold: float
    change_threshold: float
    registration_rmse: float
    crossing_threshold: float

    @property
    def misalignment(self) -> float:
        """What is left of the alignment's error (metres)."""
        return math.hypot(self.registration_rmse, self.residual)


def _side(
    name: str,
    region_kind: str,
    epoch: EpochCloud,
    geometry: LocalGeometry,
    nearest: tuple[NDArray, NDArray],
) -> Side:
    """One cloud as the localiser's steps see it."""
    origins = None if epoch.origin is None else np.asarray(epoch.origin, dtype=np.float64)
    station = None if epoch.station is None else np.asarray(epoch.station)
    return Side(
        name=name,
        region_kind=region_kind,
        points=np.asarray(epoch.points, dtype=np.float64),
        origins=origins,
        station=station,
        stations_unknown=epoch.stations_unknown and origins is None,
        trajectory_rays=epoch.trajectory_rays if station is not None else None,
        geometry=geometry,
        nearest_distance=nearest[0],
        nearest_index=nearest[1],
    )


def _sides(
    reference: EpochCloud, scan: EpochCloud, n_neighbors: int, threads: int
) -> tuple[Side, Side]:
    """Both clouds' local geometry and nearest points in the other (step 1)."""
    reference_points = np.asarray(reference.points, dtype=np.float64)
    scan_points = np.asarray(scan.points, dtype=np.float64)
    reference_geometry, scan_geometry = concurrently(
        threads,
        lambda: local_geometry(
            reference_points, n_neighbors, neighbourhoods=reference.neighbourhoods, threads=threads
        ),
        lambda: local_geometry(
            scan_points, n_neighbors, neighbourhoods=scan.neighbourhoods, threads=threads
        ),
    )
    reference_nearest, scan_nearest = concurrently(
        threads,
        lambda: nearest_in(
            reference_points,
            scan_geometry,
            reference_geometry.order,
            reference_geometry.kernel_tree,
            threads,
        ),
        lambda: nearest_in(
            scan_points, reference_geometry, scan_geometry.order, scan_geometry.kernel_tree, threads
        ),
    )
    # the kernel's trees (28 bytes a point) are not needed past the nearest points
    reference_geometry = dataclasses.replace(reference_geometry, kernel_tree=None)
    scan_geometry = dataclasses.replace(scan_geometry, kernel_tree=None)
    return (
        _side("reference", "removed", reference, reference_geometry, reference_nearest),
        _side("scan", "added", scan, scan_geometry, scan_nearest),
    )


def _thresholds(
    reference_side: Side,
    scan_side: Side,
    settings: dict[str, Any],
    registration_rmse: float,
    threads: int = 1,
) -> _Limits:
    """The support factor and the distance thresholds (steps 2 and 3's limits); the two
    partitions of both clouds' values (~0.1 CPU s at 1M + 1M) on two threads from 2."""
    median_spacing, nn_distance_quartile = concurrently(
        threads,
        lambda: pair_median_spacing(reference_side, scan_side),
        lambda: pair_nn_distance_quartile(reference_side, scan_side, threads),
    )
    support = support_factor(nn_distance_quartile, settings["support_factor"])
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
    return _Limits(
        support=support,
        nn_distance_quartile=nn_distance_quartile,
        median_spacing=median_spacing,
        residual=residual,
        threshold=threshold,
        change_threshold=max(threshold, settings["min_change_distance"]),
        registration_rmse=float(registration_rmse),
        crossing_threshold=max(noise_only_threshold, settings["min_change_distance"]),
    )


def _candidates(
    reference_side: Side, scan_side: Side, limits: _Limits, threads: int
) -> tuple[Side, Side, tuple[tuple[NDArray, Candidates], tuple[NDArray, Candidates]]]:
    """Distances to the other's surface and change candidates (step 3); the sides returned
    without their neighbour index (4 (k + 1) bytes a point), needed only until here."""

    def distance_to(own: Side, other: Side) -> tuple[NDArray, Candidates]:
        distance, candidate, _ = surface_distance(
            own.points,
            own.nearest_distance,
            own.nearest_index,
            other=other.geometry,
            threshold=limits.threshold,
            support_factor=limits.support,
            change_threshold=limits.change_threshold,
            threads=threads,
        )
        if other.origins is None or other.trajectory_rays is not None:  # a moving sensor's map
            candidate = on_sampled_planes(
                own.points,
                distance,
                candidate,
                other.geometry,
                radius=PLANE_RADIUS_FACTOR * limits.change_threshold,
                tolerance=limits.threshold,
                change_threshold=limits.change_threshold,
                nearest_distance=own.nearest_distance,
            )
        candidate = surface_offset_candidates(
            candidate,
            distance,
            own,
            other.geometry,
            threshold=limits.threshold,
            change_threshold=limits.change_threshold,
            threads=threads,
        )
        crossing = limits.crossing_threshold  # fused maps only (no origins: the map test)
        if crossing < limits.change_threshold and other.origins is None:
            candidate = crossing_candidates(candidate, distance, own, other.geometry, crossing)
        # the flattest neighbours before the neighbour index goes (~0.15 CPU s serial at 1M)
        return distance, find_candidates(
            own, distance=distance, candidate=candidate, threads=threads
        )

    (reference_distance, reference_candidates), (scan_distance, scan_candidates) = concurrently(
        threads,
        lambda: distance_to(reference_side, scan_side),
        lambda: distance_to(scan_side, reference_side),
    )
    return (
        _released(reference_side),
        _released(scan_side),
        ((reference_distance, reference_candidates), (scan_distance, scan_candidates)),
    )


def _labelled(
    sides: tuple[Side, Side],
    candidates: tuple[tuple[NDArray, Candidates], tuple[NDArray, Candidates]],
    limits: _Limits,
    settings: dict[str, Any],
    threads: int,
) -> tuple[Found, Found]:
    """Each cloud's candidates labelled changed or unobserved by the visibility test (step 4)."""
    reference_side, scan_side = sides
    shared = map_test_planes(sides, settings, threads)

    def label(own: Side, other: Side, found: Candidates) -> Labelled:
        return label_candidates(
            own,
            other,
            candidates=found,
            misalignment=limits.misalignment,
            threshold=limits.threshold,
            settings=settings,
            change_threshold=limits.change_threshold,
            threads=threads,
            shared=shared,
        )

    (reference_distance, reference_candidates), (scan_distance, scan_candidates) = candidates
    reference_labelled, scan_labelled = concurrently(
        threads,
        lambda: label(reference_side, scan_side, reference_candidates),
        lambda: label(scan_side, reference_side, scan_candidates),
    )
    reference_labelled, scan_labelled = agree_on_faces(
        sides,
        (reference_labelled, scan_labelled),
        threshold=limits.threshold,
        change_threshold=limits.change_threshold,
    )
    return (
        Found(reference_side, reference_distance, reference_labelled),
        Found(scan_side, scan_distance, scan_labelled),
    )


def _parameters(
    found: tuple[Found, Found],
    limits: _Limits,
    settings: dict[str, Any],
    *,
    registration_rmse: float,
    min_region_points: int,
    assignments: tuple[str, str],
    dropped: int,
    n_uncertain: int,
) -> dict[str, Any]:
    """The effective parameters, estimates and counts (:attr:`Localisation.parameters`)."""
    reference, scan = found
    reference_label, scan_label = reference.labelled.label, scan.labelled.label
    return {
        **{name: settings[name] for name in DEFAULT_PARAMETERS if name != "support_factor"},
        "support_factor": limits.support,
        "support_factor_calibrated": settings["support_factor"] is None,
        "min_region_points": int(min_region_points),
        "registration_rmse": float(registration_rmse),
        "reference_noise": reference.side.geometry.noise,
        "scan_noise": scan.side.geometry.noise,
        "alignment_residual": limits.residual,
        "threshold": limits.threshold,
        "change_threshold": limits.change_threshold,
        "reference_spacing_median": float(np.median(reference.side.geometry.spacing)),
        "scan_spacing_median": float(np.median(scan.side.geometry.spacing)),
        "nn_distance_over_spacing_quartile": limits.nn_distance_quartile,
        "support_radius_median": max(limits.support * limits.median_spacing, limits.threshold),
        "cluster_radius_median": settings["cluster_factor"] * limits.median_spacing,
        "reference_stations": _n_stations(reference.side),
        "scan_stations": _n_stations(scan.side),
        "reference_station_assignment": assignments[0],
        "scan_station_assignment": assignments[1],
        **reference.labelled.report,
        **scan.labelled.report,
        "n_reference_changed": int((reference_label == LABEL_CHANGED).sum()),
        "n_reference_unobserved": int((reference_label == LABEL_UNOBSERVED).sum()),
        "n_scan_changed": int((scan_label == LABEL_CHANGED).sum()),
        "n_scan_unobserved": int((scan_label == LABEL_UNOBSERVED).sum()),
        "n_dropped_clusters": dropped,
        "n_uncertain_regions": n_uncertain,
    }


def _n_stations(side: Side) -> int:
    """How many origins a side has (0: none known)."""
    return 0 if side.origins is None else len(side.origins)


def _released(side: Side) -> Side:
    """``side`` with its geometry's neighbour index released."""
    return dataclasses.replace(side, geometry=side.geometry.without_neighbour_index())
