"""Thinned crops: a tile too dense for the budget even at the smallest tile (issue 30).

A terrestrial station's near field is far denser than change detection needs: round a lidar
1 m above the floor the returns are a millimetre apart, so at 100M + 100M points a 3.5 x 3.3 m
crop (the smallest tile, 1.5 x 1.3 m, plus 1 m margins) holds 25M points, and the planner
cannot cut a tile narrower than two margins.  Such a tile is localised on a *thinned* crop:

- each cloud of the crop is cut into cubes of side ``cell`` (the thinning cell); a cube's
  first point in crop order represents it, a cube holding one point keeps it, so only
  places denser than the cell lose points;
- the cell follows from the budget and the crop's extent (:func:`thinning_cell`): the
  localisation points the budget leaves once the whole crop is held
  (:func:`~app.core.tiling.plan.thinned_point_limit`) spread over
  :data:`SURFACE_AREA_FACTOR` times the crop's area, clamped to
  ``[MIN_THINNING_CELL_METRES, MAX_THINNING_CELL_METRES]``; the tile counts its thinned
  crop and, while it is over that limit, coarsens the cell by the square root of the excess
  (at least :data:`THINNING_CELL_STEP`) up to the ceiling;
- a budget that cannot hold the whole crop beside a thinned copy is refused by the planner,
  one whose thinned crop is still over the limit at the ceiling cell by the tile
  (:class:`~app.core.tiling.plan.TileBudgetError`, naming the budget to set);
- every point of the crop then takes its representative's label, distance and region
  (:func:`representatives`).

The cell's bounds keep it far below the detection scales: the truth threshold of the
synthetic surveys is 10 cm and the localiser's k-NN neighbourhoods (k = 11) span about two
cells, so the ceiling of 2 cm keeps a neighbourhood within 4-5 cm; the floor of 2 mm is the
ranging noise of a terrestrial scanner, below which thinning removes nothing a surface test
could use and a finer cell only costs sorting.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import column_extreme

if TYPE_CHECKING:  # the planner imports this module: numpy only, not the localiser
    from app.core.localise import Localisation

__all__ = [
    "HELD_CROP_BYTES_PER_POINT",
    "MAX_THINNING_CELL_METRES",
    "MIN_THINNING_CELL_METRES",
    "SURFACE_AREA_FACTOR",
    "THINNING_CELL_STEP",
    "carried_back",
    "representatives",
    "thinning_cell",
]

MIN_THINNING_CELL_METRES = 0.002
"""Finest thinning cell: a terrestrial scanner's ranging noise."""
MAX_THINNING_CELL_METRES = 0.02
"""Coarsest thinning cell: a fifth of the 10 cm truth threshold; k-NN neighbourhoods of
about two cells stay within 4-5 cm."""
SURFACE_AREA_FACTOR = 1.0
"""Surface a crop holds per square metre of its xy box where it is dense (the floor round a
station): a surface thinned at cell ``c`` keeps about ``area / c**2`` points.  A model for
the first cell only, on the fine side: the tile counts its thinned crop and coarsens the cell
while it is over its limit.  The densest 3.5 x 3.3 m crop of the 100M + 100M survey keeps
19-25 times its area over ``c**2`` at 4-16 mm (racks, walls and the noise's thickness;
``python -m bench.thinned_tile --densest DIR``, bench/results/tiled_100m.md)."""
THINNING_CELL_STEP = 2**0.5
"""Least factor by which a tile coarsens the cell when its thinned crop is still over its
limit."""
HELD_CROP_BYTES_PER_POINT = 80
"""Bytes a point of a thinned tile's whole crop costs while its thinned copy is localised:
its index (8), float64 coordinates (24) and station (8) as the crop hands them over, and the
thinning's voxel keys, sort order and representative map (32), plus spare.  Estimated from
the arrays held, not measured."""


def thinning_cell(crop_area: float, limit_points: int) -> float:
    """The thinning cell a tile starts from: ``sqrt(SURFACE_AREA_FACTOR * crop_area /
    limit_points)`` for a crop of ``crop_area`` square metres (its xy box) allowed
    ``limit_points`` (> 0) points, clamped to ``[MIN_THINNING_CELL_METRES,
    MAX_THINNING_CELL_METRES]``."""
    cell = float(np.sqrt(SURFACE_AREA_FACTOR * crop_area / max(1, limit_points)))
    return min(MAX_THINNING_CELL_METRES, max(MIN_THINNING_CELL_METRES, cell))


def representatives(
    points: NDArray[np.floating], cell: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Thin ``points`` on cubes of side ``cell``: each occupied cube's first point.

    Parameters
    ----------
    points : ndarray, shape (p, 3)
    cell : float
        Metres.

    Returns
    -------
    kept : ndarray, shape (q,), int64
        Rows of ``points`` kept, increasing.
    representative : ndarray, shape (p,), int64
        For each point, the position in ``kept`` of its cube's representative (a kept point
        is its own).
    """
    if len(points) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    from app.core.detectors.voxel_grid import voxel_ids  # here: the planner imports numpy only

    low = column_extreme(points, np.minimum).astype(np.float64)  # the grid starts at the crop
    key, n_cells = voxel_ids(points, cell, low)
    if n_cells >= 1 << 62:  # ids in int64: a crop 2 km across at 2 mm is 2**60 cells
        raise ValueError(f"a crop too wide to thin at {cell} m")
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    del key
    order = np.argsort(first, kind="stable")
    kept = first[order].astype(np.int64)
    rank = np.empty(len(first), dtype=np.int64)
    rank[order] = np.arange(len(first), dtype=np.int64)
    return kept, rank[inverse.reshape(-1)]


def carried_back(
    localisation: Localisation,
    reference_representative: NDArray[np.int64],
    scan_representative: NDArray[np.int64],
) -> Localisation:
    """A thinned crop's localisation for every point of the whole crop: each point takes its
    representative's label, distance and region, and a region holds every point whose
    representative it holds (see :func:`~app.core.tiling.tile.thin_crop`)."""
    members = {
        "removed": _members_by_representative(reference_representative),
        "added": _members_by_representative(scan_representative),
    }

    def widened(region: Any) -> Any:
        order, bounds = members[region.kind]
        local = region.point_indices
        lengths = bounds[local + 1] - bounds[local]
        starts = np.repeat(bounds[local] - np.cumsum(lengths) + lengths, lengths)
        rows = order[starts + np.arange(int(lengths.sum()))]
        return dataclasses.replace(region, point_indices=np.sort(rows).astype(np.int64))

    return dataclasses.replace(
        localisation,
        reference_label=localisation.reference_label[reference_representative],
        scan_label=localisation.scan_label[scan_representative],
        reference_distance=localisation.reference_distance[reference_representative],
        scan_distance=localisation.scan_distance[scan_representative],
        reference_region=localisation.reference_region[reference_representative],
        scan_region=localisation.scan_region[scan_representative],
        regions=[widened(region) for region in localisation.regions],
        uncertain_regions=[widened(region) for region in localisation.uncertain_regions],
    )


def _members_by_representative(
    representative: NDArray[np.int64],
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The crop's rows grouped by representative: ``order[bounds[r]:bounds[r + 1]]``."""
    order = np.argsort(representative, kind="stable")
    counts = np.bincount(representative, minlength=int(representative.max(initial=-1)) + 1)
    return order, np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
