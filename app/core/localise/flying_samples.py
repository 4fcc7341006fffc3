"""Flying samples of a dense fused map, left out of the comparison.

A depth camera's pixel on a depth edge (its footprint half on a near surface, half on one
behind it) returns a depth between the two: a point in the air along its line of sight.  A
fused RGB-D map gathers them from every frame that saw the edge, a sparse scatter round each
silhouette (about 2 % of a map's points).  Each epoch has its own, in other places: they are
more than the change distance from every surface of the other epoch, they cluster into
regions (their spacing is wide, so is the linking distance), and as the other epoch's samples
they stand in the air where the map test looks for surface: over a changed chair (its points
within the change distance of them: no candidates) and in front of a part one path never saw
(surface seen through it).  Removing the flying samples the synthetic rooms' truth knows
(drifting RGB-D rooms 004/104/304: 464/907/1,006 false points -> 54/66/31; rotated chairs
503/303: 15/36 % -> 77/93 %) showed they were the cause.

A flying sample is told from the map's own k nearest neighbours (searched once, reused):
on a dense map (median spacing under :data:`DENSE_SPACING`) a
point whose k-th neighbour is :data:`SPARSE_FACTOR` times farther than the cloud's median, and
whose neighbourhood is no surface (surface variation, smallest eigenvalue over the trace, at
least :data:`SCATTER`), that is isolated (:data:`ISOLATION`) and that has no sample of the other
epoch next to it (:data:`OTHER_NEAR`; the other epoch's own flying candidates do not count,
:func:`_standing`).  Density and shape alone do not tell a flying scatter
from a thin solid part seen sparsely (a chair leg: sparse and not flat at k neighbours too);
its own next samples along it, or the other epoch's samples on it, do.  A sparse surface of a
dense map (a far wall band under the ceiling) is planar at that scale.  A sparse map (a robot
map, a lidar scan) is left as it is.
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.labels import LABEL_UNOBSERVED
from app.core.localise.epoch import EpochCloud
from app.core.localise.flying_sight import on_sight_lines
from app.core.localise.neighbourhoods import Neighbourhoods, nearest_neighbourhoods
from app.core.localise.surface import neighbourhood_planes
from app.core.threads import concurrently

__all__ = [
    "DENSE_SPACING",
    "HOLDING",
    "ISOLATED_NEIGHBOURS",
    "ISOLATION",
    "OTHER_NEAR",
    "PASSES",
    "SCATTER",
    "SPARSE_FACTOR",
    "flying_samples",
    "restored_localisation",
    "without_flying_samples",
]

DENSE_SPACING = 0.025
"""Metres: a map whose median spacing (``r_k sqrt(pi / k)``, as the local geometry's) is under
this is dense enough for flying samples to stand out: a handheld RGB-D map thinned to 5-10 mm
voxels has 2.2 cm (its far walls and ceiling sparser than its near surfaces); a robot map
voxel-filtered at 2-5 cm has 3-5 cm, and its sparse samples are ring arcs, not flying."""
SPARSE_FACTOR = 2.5
"""A flying sample's k-th neighbour is at least this many times the cloud's median k-th
neighbour distance away."""
SCATTER = 0.08
"""Smallest surface variation (smallest eigenvalue over the trace; 1/3 for an isotropic
scatter, 0 on a plane) of a flying sample's neighbourhood."""
ISOLATION = 4.0
"""A flying sample has at most :data:`ISOLATED_NEIGHBOURS` own points within this many of the
cloud's median spacings (about 7 cm on a 1.8 cm map): a scatter in the air.  A thin solid part
(a chair leg) sparse and not flat at k neighbours still holds its surface's samples at its own
spacing there (5-9 of them on the RGB-D rooms' legs, 1-3 round most flying pixels)."""
ISOLATED_NEIGHBOURS = 2
"""Own points (the point not counted) a flying sample may have within :data:`ISOLATION`
median spacings."""
OTHER_NEAR = 1.0
"""A point with a sample of the other epoch within this many of its cloud's median spacings
(about 1.8 cm on the RGB-D rooms) is no flying sample: a thin part both epochs saw stays in
both (unchanged RGB-D room 104's scan saw a chair leg in 4 samples, the reference in 169: the
4 taken out, 84 of the reference's were called removed).  A flying pixel stands where the other
epoch saw air: its nearest sample there is 4-5 spacings away at the median, under one spacing
for fewer than 10 % of them."""
HOLDING = 6.0
"""Median spacings: an isolated flat sample that no sample of the other epoch holds
(:data:`OTHER_NEAR`) is tried on lines of sight only when one lies within this many (about
11 cm on the RGB-D rooms, the change distance): a flying pixel matters where it holds the other
epoch's points (drifting RGB-D room 503's reference pixels over the scan's turned chair); a
sparse band of a far wall the other path never filmed is left whole (drifting room 403's
scan lost a wall band's samples near the ceiling and its turned chair's parts fell apart with
every flat isolated sample tried: 73 -> 57 %, 1,073 -> 2,009 changed points)."""
PASSES = 3
"""Passes of the test: a flying sample whose neighbours were flying samples taken out is
sparser without them (the scatter thins from its edges inwards)."""


def flying_samples(
    points: NDArray[np.float64],
    neighbourhoods: Neighbourhoods,
    typical: float | None = None,
    other: tuple[KDTree, NDArray[np.float64]] | None = None,
    sighted_only: bool = False,
) -> NDArray[np.bool_]:
    """Which of a cloud's points are flying samples (module docstring), shape (n,).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    neighbourhoods : Neighbourhoods
        Of ``points`` (k + 1 columns, the point first).
    typical : float, optional
        The cloud's median k-th neighbour distance (default: measured on ``points``; a pass
        after the first keeps the whole cloud's).
    other : (pykdtree.kdtree.KDTree, ndarray of shape (p, 3)), optional
        The other epoch's points (aligned) and their tree: a point with one of them within
        :data:`OTHER_NEAR` median spacings is no flying sample.
    sighted_only : bool
        Only the isolated points the passes keep (scatters ``other`` holds; flat ones it does
        not hold but has a sample within :data:`HOLDING` median spacings of) that lie on lines
        of sight past an own edge (:func:`~app.core.localise.flying_sight.on_sight_lines`):
        flying all the same.

    Returns
    -------
    ndarray, shape (n,), bool
        All False on a cloud that is not dense.
    """
    n, columns = neighbourhoods.neighbor_index.shape
    flying = np.zeros(n, dtype=bool)
    k = columns - 1
    if n <= columns or k < 3:
        return flying
    kth = neighbourhoods.kth_distance
    typical = float(np.median(kth)) if typical is None else typical
    if typical * math.sqrt(math.pi / k) >= DENSE_SPACING or typical <= 0:
        return flying
    sparse = np.flatnonzero(kth >= SPARSE_FACTOR * typical)
    if sparse.size == 0:
        return flying
    index = neighbourhoods.neighbor_index[sparse]
    variation = neighbourhood_planes(points, index)[4]
    nearest = index[:, ISOLATED_NEIGHBOURS + 1].astype(np.intp)  # sorted nearest first
    spread = np.linalg.norm(points[nearest] - points[sparse], axis=1)
    spacing = typical * math.sqrt(math.pi / k)
    isolated = spread > ISOLATION * spacing
    sparse, scattered = sparse[isolated], variation[isolated] >= SCATTER
    if other is None:
        if sighted_only:
            return flying
        sparse = sparse[scattered]
    elif sparse.size:
        near = other[0].query(points[sparse], k=1, distance_upper_bound=HOLDING * spacing)
        held = near[0] <= OTHER_NEAR * spacing
        holding = np.isfinite(near[0])
        if not sighted_only:
            sparse = sparse[scattered & ~held]
        else:  # the isolated samples the passes kept: held scatters, flat ones holding others
            solid = np.ones(n, dtype=bool)
            solid[sparse] = False
            sparse = sparse[scattered & held | ~scattered & ~held & holding]
            sparse = sparse[on_sight_lines(points, sparse, solid, other[1], spacing)]
    flying[sparse] = True
    return flying


def _kept_neighbourhoods(
    points: NDArray[np.float64], neighbourhoods: Neighbourhoods, flying: NDArray[np.bool_]
) -> Neighbourhoods:
    """The neighbourhoods of the points that are not ``flying`` (shape (n,)), in their own
    indices: a row without a flying neighbour is the same neighbours; the rows with one are
    searched again among the kept points."""
    keep = ~flying
    kept_points = np.ascontiguousarray(points[keep])
    renumbered = np.full(points.shape[0], -1, dtype=np.int32)  # int32: the index's size
    renumbered[keep] = np.arange(kept_points.shape[0], dtype=np.int32)
    index = renumbered[neighbourhoods.neighbor_index[keep]]
    k = index.shape[1] - 1
    kth_distance = neighbourhoods.kth_distance[keep].copy()
    tree = KDTree(kept_points)
    again = np.flatnonzero((index < 0).any(axis=1))
    if again.size:
        squared, found = tree.query(kept_points[again], k=k + 1, sqr_dists=True)
        index[again] = found
        kth_distance[again] = np.sqrt(squared[:, k])
    order = neighbourhoods.order
    if order is not None:
        order = renumbered[order[keep[order]]].astype(np.intp)
    return Neighbourhoods(tree, index.view(np.uint32), kth_distance, order)


def _searched(
    epoch: EpochCloud, n_neighbors: int, threads: int
) -> tuple[NDArray[np.float64], Neighbourhoods] | None:
    """A cloud without origins (a fused map as exported): its points and k nearest neighbours
    (searched ahead or now); None for a cloud taken from known sensor positions, which gets the
    ray tests (they judge each ray's sample)."""
    if epoch.origin is not None or epoch.trajectory_rays is not None:
        return None
    points = np.asarray(epoch.points, dtype=np.float64)
    k = min(n_neighbors, points.shape[0] - 1)
    found = epoch.neighbourhoods
    if found is not None and not isinstance(found, Neighbourhoods):
        found = found.take()
    if found is None or found.neighbor_index.shape != (points.shape[0], k + 1):
        found = nearest_neighbourhoods(points, k, threads=threads)
    assert found is not None  # not cancelled: no event was given
    return points, found


def _without_flying_samples(
    epoch: EpochCloud,
    searched: tuple[NDArray[np.float64], Neighbourhoods] | None,
    other_tree: tuple[KDTree, NDArray[np.float64]] | None,
) -> tuple[EpochCloud, NDArray[np.intp] | None]:
    """``epoch`` without its flying samples, and the indices of the points kept (None: all
    kept, ``epoch`` as it is, its neighbourhoods found).  ``searched``: its points and
    neighbourhoods (:func:`_searched`; None: a cloud with origins, left as it is);
    ``other_tree``: the other cloud's samples that keep a point near them and their tree
    (:data:`OTHER_NEAR`, :func:`_standing`)."""
    if searched is None:
        return epoch, None
    points, found = searched
    typical = float(np.median(found.kth_distance))
    kept, neighbourhoods = np.arange(points.shape[0]), found
    for _ in range(PASSES):
        flying = flying_samples(points[kept], neighbourhoods, typical, other_tree)
        if not flying.any():
            break
        neighbourhoods = _kept_neighbourhoods(points[kept], neighbourhoods, flying)
        kept = kept[~flying]
    sighted = flying_samples(points[kept], neighbourhoods, typical, other_tree, True)
    if sighted.any():  # after the passes: their neighbours are not judged again without them
        neighbourhoods = _kept_neighbourhoods(points[kept], neighbourhoods, sighted)
        kept = kept[~sighted]
    if kept.size == points.shape[0]:
        return dataclasses.replace(epoch, neighbourhoods=found), None
    return dataclasses.replace(epoch.subset(kept), neighbourhoods=neighbourhoods), kept


def _standing(
    searched: tuple[NDArray[np.float64], Neighbourhoods] | None,
) -> tuple[KDTree, NDArray[np.float64]] | None:
    """A cloud's samples that can keep the other epoch's points (:data:`OTHER_NEAR`) and their
    tree: all but its own flying candidates (the test without the other epoch).  Round a silhouette
    both epochs' cameras saw, each has its flying pixels in the same air: a flying pixel next
    to another is no surface both saw (drifting RGB-D room 503: such scan pixels kept the
    turned chair's reference points unchanged, recall 43 % with them, 47 % without).  None
    for a cloud with origins."""
    if searched is None:
        return None
    points, found = searched
    candidates = flying_samples(points, found)
    if not candidates.any():
        return found.tree, points
    standing = np.ascontiguousarray(points[~candidates])
    return KDTree(standing), standing


def restored(values: NDArray, kept: NDArray[np.intp] | None, n: int, fill: float) -> NDArray:
    """Per-point ``values`` (shape (len(kept),)) of the kept points back in the whole cloud's
    indices, shape (n,): ``fill`` for the flying samples (``values`` as they are when
    ``kept`` is None)."""
    if kept is None:
        return values
    whole = np.full(n, fill, dtype=values.dtype)
    whole[kept] = values
    return whole


def _restored_regions(
    regions: list[Any], kept: tuple[NDArray[np.intp] | None, NDArray[np.intp] | None]
) -> list[Any]:
    """``regions`` (:class:`~app.core.localise.regions.ChangedRegion`; ``removed`` ones of the
    reference, the others of the scan) with their point indices in the whole clouds'."""
    restored_ones = []
    for region in regions:
        indices = kept[0] if region.kind == "removed" else kept[1]
        if indices is not None:
            region = dataclasses.replace(
                region, point_indices=indices[region.point_indices].astype(np.int64)
            )
        restored_ones.append(region)
    return restored_ones


def restored_localisation(
    localisation: Any,
    kept: tuple[NDArray[np.intp] | None, NDArray[np.intp] | None],
    sizes: tuple[int, int],
) -> Any:
    """A :class:`~app.core.localise.changes.Localisation` of the clouds without their flying
    samples (``kept``: the indices of each cloud's points kept, None: all) in the whole
    clouds' indices (``sizes``: their point counts): the flying samples unobserved, with no
    distance and no region; ``parameters["flying_samples"]`` counts them per cloud."""
    (reference_kept, scan_kept), (n_reference, n_scan) = kept, sizes
    localisation.parameters["flying_samples"] = [
        0 if indices is None else n - len(indices)
        for indices, n in ((reference_kept, n_reference), (scan_kept, n_scan))
    ]
    if reference_kept is None and scan_kept is None:
        return localisation
    return dataclasses.replace(
        localisation,
        reference_label=restored(
            localisation.reference_label, reference_kept, n_reference, LABEL_UNOBSERVED
        ),
        scan_label=restored(localisation.scan_label, scan_kept, n_scan, LABEL_UNOBSERVED),
        reference_distance=restored(
            localisation.reference_distance, reference_kept, n_reference, np.nan
        ),
        scan_distance=restored(localisation.scan_distance, scan_kept, n_scan, np.nan),
        reference_region=restored(localisation.reference_region, reference_kept, n_reference, -1),
        scan_region=restored(localisation.scan_region, scan_kept, n_scan, -1),
        regions=_restored_regions(localisation.regions, kept),
        uncertain_regions=_restored_regions(localisation.uncertain_regions, kept),
    )


def without_flying_samples(
    reference: EpochCloud, scan: EpochCloud, n_neighbors: int, threads: int
) -> tuple[EpochCloud, EpochCloud, tuple[NDArray[np.intp] | None, NDArray[np.intp] | None]]:
    """Both clouds without their flying samples (concurrently), and the indices of each
    cloud's points kept (None: all kept, the cloud as it is, its neighbourhoods found).

    Only a cloud without origins (a fused map as exported) is looked at; a cloud taken from
    known sensor positions gets the ray tests, which judge each ray's sample.
    """
    searched = concurrently(
        threads,
        partial(_searched, reference, n_neighbors, threads),
        partial(_searched, scan, n_neighbors, threads),
    )
    standing = concurrently(
        threads, partial(_standing, searched[0]), partial(_standing, searched[1])
    )
    (reference, reference_kept), (scan, scan_kept) = concurrently(
        threads,
        partial(_without_flying_samples, reference, searched[0], standing[1]),
        partial(_without_flying_samples, scan, searched[1], standing[0]),
    )
    return reference, scan, (reference_kept, scan_kept)
