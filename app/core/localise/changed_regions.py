"""Step 5 of :func:`~app.core.localise.changes.localise_changes`: each cloud's changed points
grouped into regions.

Connected changed points form regions of at least ``min_region_points``
(:func:`~app.core.localise.regions.find_regions`); smaller clusters are noise, unless one of
the small-cluster rules keeps them (:func:`~app.core.localise.protruding_faces.with_small_faces`:
faces turned in place, standing out past the other epoch's face, or far from everything it
sampled), which filter the same clustering of each cloud (clustered once,
:class:`~app.core.localise.regions.Clustering`).  The changed points outside every kept region
are relabelled unchanged.  Clusters of unobserved points the other epoch did not cover are
the uncertain regions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED, LABEL_UNOBSERVED
from app.core.localise.distance import Side
from app.core.localise.protruding_faces import with_small_faces
from app.core.localise.regions import (
    ChangedRegion,
    Clustering,
    cluster_changed,
    find_regions,
    mark_moved_surfaces,
)
from app.core.localise.turned_faces import changed_points
from app.core.localise.visibility import Labelled
from app.core.threads import concurrently

__all__ = ["Found", "Regions", "changed_regions"]


@dataclass(frozen=True)
class Found:
    """One cloud's side, distances to the other's surface and labels.

    Attributes
    ----------
    side : Side
    distance : ndarray, shape (n,), float64
        Each point's distance to the other cloud's surface (metres).
    labelled : Labelled
        Its labels, evidence and confidence (the labels are changed in place by
        :func:`changed_regions`).
    """

    side: Side
    distance: NDArray[np.float64]
    labelled: Labelled

    def output_distance(self) -> NDArray[np.float32]:
        """The distances as float32, NaN where unobserved, shape (n,)."""
        distance = self.distance.astype(np.float32)
        distance[self.labelled.label == LABEL_UNOBSERVED] = np.nan
        return distance


@dataclass(frozen=True)
class Regions:
    """The regions of one comparison (:func:`changed_regions`).

    Attributes
    ----------
    regions : list of ChangedRegion
        Largest first.
    uncertain : list of ChangedRegion
        Clusters of unobserved points the other epoch did not cover, largest first.
    dropped : int
        Clusters of changed points too small to be a change.
    reference_region, scan_region : ndarray, shapes (n,) and (m,), int32
        Each point's index in ``regions``, -1 if none.
    """

    regions: list[ChangedRegion]
    uncertain: list[ChangedRegion]
    dropped: int
    reference_region: NDArray[np.int32]
    scan_region: NDArray[np.int32]


def changed_regions(
    reference: Found,
    scan: Found,
    *,
    cluster_factor: float,
    min_region_points: int,
    change_threshold: float,
    threads: int,
) -> Regions:
    """The regions of both clouds' changed points, the small clusters the small-cluster rules
    keep among them, the uncertain regions; the changed points outside every region relabelled
    unchanged (in ``reference.labelled.label`` and ``scan.labelled.label``).

    Parameters
    ----------
    reference, scan : Found
    cluster_factor : float
        Points closer than this many local spacings are one cluster.
    min_region_points : int
    change_threshold : float
        ``c`` (metres), for the small-cluster rules.
    threads : int
        The two clouds are clustered concurrently from 2.

    Returns
    -------
    Regions
    """
    regions, uncertain, dropped, clusterings = _regions(
        reference, scan, cluster_factor, min_region_points, threads
    )
    regions, kept_small = with_small_faces(
        regions,
        (
            changed_points(reference.side, reference.labelled, reference.distance),
            changed_points(scan.side, scan.labelled, scan.distance),
        ),
        cluster_factor=cluster_factor,
        min_region_points=min_region_points,
        change_threshold=change_threshold,
        clusterings=clusterings,
    )
    reference_region, scan_region = _region_indices(regions, reference, scan)
    # changed points outside any kept region were in clusters too small to be a change
    for found, region in ((reference, reference_region), (scan, scan_region)):
        found.labelled.label[(found.labelled.label == LABEL_CHANGED) & (region < 0)] = (
            LABEL_UNCHANGED
        )
    return Regions(regions, uncertain, dropped - kept_small, reference_region, scan_region)


def _regions(
    reference: Found,
    scan: Found,
    cluster_factor: float,
    min_region_points: int,
    threads: int,
) -> tuple[list[ChangedRegion], list[ChangedRegion], int, dict[tuple[str, float], Clustering]]:
    """Regions of changed points, largest first, the uncertain ones (not covered by the other
    epoch), how many clusters were too small, and each cloud's clustering of its changed
    points (by region kind and ``cluster_factor``, for the small-cluster rules)."""

    def regions_of(found: Found, wanted: int) -> tuple[list[ChangedRegion], int, Clustering]:
        side = found.side
        changed = found.labelled.label == wanted
        clustering = cluster_changed(
            side.points, changed, side.geometry.spacing, cluster_factor, threads
        )
        regions, dropped = find_regions(
            side.points,
            kind=side.region_kind,
            changed=changed,
            spacing=side.geometry.spacing,
            distance=found.distance,
            cluster_factor=cluster_factor,
            min_region_points=min_region_points,
            evidence=found.labelled.evidence,
            confidence=found.labelled.confidence,
            clustering=clustering,
        )
        return regions, dropped, clustering

    (removed, dropped_removed, reference_clusters), (added, dropped_added, scan_clusters) = (
        concurrently(
            threads,
            lambda: regions_of(reference, LABEL_CHANGED),
            lambda: regions_of(scan, LABEL_CHANGED),
        )
    )
    regions: list[ChangedRegion] = [*removed, *added]
    regions.sort(key=lambda region: (-region.n_points, region.kind, int(region.point_indices[0])))
    regions = mark_moved_surfaces(regions)
    # the unobserved points of both clouds clustered concurrently too (the reference's first,
    # as the stable sort below expects): a serial stretch of ~0.3 CPU s at 1M + 1M otherwise
    (reference_unobserved, _, _), (scan_unobserved, _, _) = concurrently(
        threads,
        lambda: regions_of(reference, LABEL_UNOBSERVED),
        lambda: regions_of(scan, LABEL_UNOBSERVED),
    )
    uncertain = [
        region
        for region in (*reference_unobserved, *scan_unobserved)
        if region.evidence == "no_coverage"
    ]
    uncertain.sort(key=lambda region: (-region.n_points, region.kind))
    clusterings = {
        (found.side.region_kind, cluster_factor): clustering
        for found, clustering in ((reference, reference_clusters), (scan, scan_clusters))
    }
    return regions, uncertain, int(dropped_removed + dropped_added), clusterings


def _region_indices(
    regions: list[ChangedRegion], reference: Found, scan: Found
) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """Each point's index in ``regions`` (removed ones: reference points; the others: scan
    points), -1 if none; shapes (n_reference,) and (n_scan,) of the clouds compared."""
    n_reference, n_scan = len(reference.side.points), len(scan.side.points)
    reference_region = np.full(n_reference, -1, dtype=np.int32)
    scan_region = np.full(n_scan, -1, dtype=np.int32)
    for number, region in enumerate(regions):
        target = reference_region if region.kind == "removed" else scan_region
        target[region.point_indices] = number
    return reference_region, scan_region
