"""One tile: crop both clouds, localise the crop, keep its core points' labels.

:func:`compute_tile` is a pure function of the plan, the tile's number, the points
(:class:`TileSource`) and what every tile shares (:class:`TileContext`); its
:class:`TileResult` is saved and loaded as ``.npz`` so tiles can run as separate tasks.
Localisation is called in one place, :func:`localise_crop`.  A tile the plan thins
(:mod:`app.core.tiling.thinning`) is localised on its thinned crop and every crop point takes
its representative's label, distance and region (:func:`thin_crop`,
:func:`~app.core.tiling.thinning.carried_back`).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.jsonable import json_safe
from app.core.labels import LABEL_UNOBSERVED
from app.core.localise import EpochCloud, Localisation, localise_changes
from app.core.localise.regions import EVIDENCE_NAMES
from app.core.tiling.plan import (
    LOCALISATION_BYTES_PER_POINT,
    TileBudgetError,
    TilePlan,
    thinned_point_limit,
)
from app.core.tiling.rays import crop_mask, crop_masks
from app.core.tiling.thinning import (
    HELD_CROP_BYTES_PER_POINT,
    MAX_THINNING_CELL_METRES,
    THINNING_CELL_STEP,
    carried_back,
    representatives,
)

__all__ = [
    "EVIDENCE_CODES",
    "MIN_CROP_POINTS",
    "TileContext",
    "TileCrop",
    "TileResult",
    "TileSource",
    "compute_tile",
    "crop_mask",
    "localise_crop",
    "thin_crop",
]

EVIDENCE_CODES = {name: code for code, name in EVIDENCE_NAMES.items()}
MIN_CROP_POINTS = 32
"""A crop with fewer points of either cloud is not localised: its core points are unobserved."""
COUNT_CELL_SCALE = 2.0
"""The planner counts crops on a subsample, whose sparser points mark fewer direction cells
(:mod:`app.core.tiling.rays`): it counts with cells this much coarser, so that it
over-estimates a crop (by 15-25 % on the warehouse pair at 1 point in 50) rather than
under-estimates it (by 7-14 % with the crop's own cells)."""


@dataclass(frozen=True)
class TileContext:
    """What every tile of one comparison shares besides the points.

    Attributes
    ----------
    reference_origins, scan_origins : ndarray, shape (k, 3), or None
        Sensor positions (stations, pseudo-stations of a trajectory) in the local frame, the
        scan's aligned.
    reference_stations_unknown, scan_stations_unknown : bool
        A merged lidar cloud whose stations were not found (the other's candidates get the
        origin-free tests).
    min_region_points : int
        The whole pair's minimum region size.
    localisation_params : dict
        Keyword parameters of :func:`~app.core.localise.localise_changes`.
    ray_reach : float
        Metres beyond a tile's crop box that the returns whose ray crossed it are kept
        (:func:`~app.core.tiling.rays.crop_mask`): the ray test's evidence behind a candidate.
    reference_ray_cells, scan_ray_cells : ndarray, shape (k,), or None
        The direction cell of each origin's returns (:func:`~app.core.tiling.rays.ray_cell_sizes`):
        a crop keeps the returns whose direction the other cloud's points in its box need.
        None: every return whose ray crosses the box in the top view.
    """

    reference_origins: NDArray[np.float64] | None
    scan_origins: NDArray[np.float64] | None
    reference_stations_unknown: bool
    scan_stations_unknown: bool
    min_region_points: int
    localisation_params: Mapping[str, Any] = field(default_factory=dict)
    ray_reach: float = 8.0
    reference_ray_cells: NDArray[np.float64] | None = None
    scan_ray_cells: NDArray[np.float64] | None = None

    def save(self, path: str | Path) -> None:
        """Write the context as a small ``.npz``."""
        arrays = {
            name: value
            for name, value in (
                ("reference_origins", self.reference_origins),
                ("scan_origins", self.scan_origins),
                ("reference_ray_cells", self.reference_ray_cells),
                ("scan_ray_cells", self.scan_ray_cells),
            )
            if value is not None
        }
        meta = {
            "reference_stations_unknown": self.reference_stations_unknown,
            "scan_stations_unknown": self.scan_stations_unknown,
            "min_region_points": self.min_region_points,
            "localisation_params": dict(self.localisation_params),
            "ray_reach": self.ray_reach,
        }
        np.savez(path, meta=np.array(json.dumps(meta)), **arrays)

    @classmethod
    def load(cls, path: str | Path) -> TileContext:
        """Read a context written by :meth:`save`."""
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            return cls(
                reference_origins=data.get("reference_origins", None),
                scan_origins=data.get("scan_origins", None),
                reference_stations_unknown=bool(meta["reference_stations_unknown"]),
                scan_stations_unknown=bool(meta["scan_stations_unknown"]),
                min_region_points=int(meta["min_region_points"]),
                localisation_params=meta["localisation_params"],
                ray_reach=float(meta["ray_reach"]),
                reference_ray_cells=data.get("reference_ray_cells", None),
                scan_ray_cells=data.get("scan_ray_cells", None),
            )


@dataclass(frozen=True)
class TileCrop:
    """Both clouds' points in one tile's crop (indices sorted, into the whole clouds)."""

    reference_index: NDArray[np.int64]
    scan_index: NDArray[np.int64]
    reference_points: NDArray[np.float64]
    scan_points: NDArray[np.float64]
    reference_station: NDArray[np.int64] | None
    scan_station: NDArray[np.int64] | None
    reference_rays: tuple[NDArray[np.int64], NDArray[np.int64]] | None
    scan_rays: tuple[NDArray[np.int64], NDArray[np.int64]] | None


@dataclass(frozen=True)
class TileSource:
    """The whole pair as tiles read it: arrays or ``.npy`` memory maps, local frame.

    Attributes
    ----------
    reference_points : ndarray, shape (n, 3)
    scan_points : ndarray, shape (m, 3)
        Aligned onto the reference.
    reference_station, scan_station : ndarray, shape (n,) / (m,), int, or None
        Index into the context's origins of the station (or pseudo-station) of each point;
        None: one origin (or none).
    reference_rays, scan_rays : (ndarray, ndarray) or None
        A trajectory's ``(returns, bounds)`` (:class:`app.core.trajectory_poses.SensorGroups`).
    """

    reference_points: NDArray[np.float64]
    scan_points: NDArray[np.float64]
    reference_station: NDArray[np.integer] | None = None
    scan_station: NDArray[np.integer] | None = None
    reference_rays: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None
    scan_rays: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None

    def _sides(self, context: TileContext) -> tuple[tuple, tuple]:
        return (
            (self.reference_points, self.reference_station, context.reference_origins),
            (self.scan_points, self.scan_station, context.scan_origins),
        )

    def count_crop(
        self,
        low: NDArray[np.float64],
        high: NDArray[np.float64],
        margin: float,
        context: TileContext,
        sample: int = 400_000,
    ) -> int:
        """Points of both clouds in the crop of the core box ``[low, high)``, counted on at most
        ``sample`` points of each cloud (with :data:`COUNT_CELL_SCALE` coarser direction cells
        when that is a subsample) and scaled up."""
        sides, cells, scale = [], [], []
        for (points, station, origins), cell in zip(
            self._sides(context), (context.reference_ray_cells, context.scan_ray_cells), strict=True
        ):
            step = max(1, len(points) // sample)
            sides.append((points[::step], None if station is None else station[::step], origins))
            cells.append(None if cell is None else cell * (COUNT_CELL_SCALE if step > 1 else 1.0))
            scale.append(len(points) / max(1, len(sides[-1][0])))
        masks = crop_masks(sides, cells, low - margin, high + margin, context.ray_reach)
        total = sum(
            np.count_nonzero(mask) * factor for mask, factor in zip(masks, scale, strict=True)
        )
        return int(np.ceil(total))

    def crop(self, plan: TilePlan, tile_index: int, context: TileContext) -> TileCrop:
        """Both clouds' points in tile ``tile_index``'s crop."""
        low, high = plan.crop_box(tile_index)
        masks = crop_masks(
            self._sides(context),
            (context.reference_ray_cells, context.scan_ray_cells),
            low,
            high,
            context.ray_reach,
        )
        reference, scan = (np.flatnonzero(mask) for mask in masks)
        return TileCrop(
            reference_index=reference,
            scan_index=scan,
            reference_points=np.asarray(self.reference_points[reference], dtype=np.float64),
            scan_points=np.asarray(self.scan_points[scan], dtype=np.float64),
            reference_station=_taken(self.reference_station, reference),
            scan_station=_taken(self.scan_station, scan),
            reference_rays=_cropped_rays(self.reference_rays, reference),
            scan_rays=_cropped_rays(self.scan_rays, scan),
        )


def _taken(station: NDArray | None, index: NDArray[np.int64]) -> NDArray[np.int64] | None:
    return None if station is None else np.asarray(station[index], dtype=np.int64)


def _cropped_rays(
    rays: tuple[NDArray[np.int64], NDArray[np.int64]] | None, index: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
    """A trajectory's ``(returns, bounds)`` restricted to the crop, renumbered into it."""
    if rays is None:
        return None
    returns, bounds = rays
    group = np.repeat(np.arange(len(bounds) - 1), np.diff(bounds))
    if len(index) == 0:
        position = np.zeros(len(returns), dtype=np.int64)
        kept = np.zeros(len(returns), dtype=bool)
    else:
        position = np.minimum(np.searchsorted(index, returns), len(index) - 1)
        kept = index[position] == returns
    counts = np.bincount(group[kept], minlength=len(bounds) - 1)
    new_bounds = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return position[kept].astype(np.int64), new_bounds


def localise_crop(crop: TileCrop, context: TileContext, threads: int | None = None) -> Localisation:
    """Localise one crop: the single call of :func:`~app.core.localise.localise_changes`."""
    params = {
        key: value
        for key, value in context.localisation_params.items()
        if key != "min_region_points"
    }
    reference = EpochCloud(
        crop.reference_points,
        origin=context.reference_origins,
        station=crop.reference_station,
        stations_unknown=context.reference_stations_unknown,
        trajectory_rays=crop.reference_rays,
    )
    scan = EpochCloud(
        crop.scan_points,
        origin=context.scan_origins,
        station=crop.scan_station,
        stations_unknown=context.scan_stations_unknown,
        trajectory_rays=crop.scan_rays,
    )
    return localise_changes(
        reference,
        scan,
        registration_rmse=0.0,
        min_region_points=context.min_region_points,
        threads=threads,
        **params,
    )


REGION_FIELDS = (
    "cloud",
    "uncertain",
    "evidence",
    "confidence",
    "core_count",
    "core_sum",
    "core_min",
    "core_max",
    "distance_sum",
    "distance_max",
    "member_bounds",
    "members",
    "member_in_core",
)


@dataclass(frozen=True)
class TileResult:
    """What one tile found, for its core points (indices into the whole clouds).

    Attributes
    ----------
    tile_index : int
    reference_index, scan_index : ndarray, shape (a,) / (b,), int64
        The core points of each cloud, sorted.
    reference_label, scan_label : ndarray, int8
        Their labels (0 unchanged, 1 changed, -1 unobserved).
    reference_distance, scan_distance : ndarray, float32
        Their distances to the other cloud's surface (NaN where unobserved).
    regions : dict of ndarray
        One row per region of the crop (changed, or ``uncertain``) that has a core point or a
        margin point: ``cloud`` (0 reference, 1 scan), ``uncertain``, ``evidence`` (code),
        ``confidence``, and over its core points ``core_count``, ``core_sum`` / ``core_min`` /
        ``core_max`` (shape (r, 3)), ``distance_sum``, ``distance_max``; its members (core
        and margin, indices into the whole cloud) are ``members[member_bounds[i]:
        member_bounds[i + 1]]`` with ``member_in_core`` saying which are core.
    figures : dict
        The crop's localisation figures (noise, alignment residual, thresholds, counts).
    """

    tile_index: int
    reference_index: NDArray[np.int64]
    scan_index: NDArray[np.int64]
    reference_label: NDArray[np.int8]
    scan_label: NDArray[np.int8]
    reference_distance: NDArray[np.float32]
    scan_distance: NDArray[np.float32]
    regions: dict[str, NDArray]
    figures: dict[str, Any]

    def save(self, path: str | Path) -> None:
        """Write the result as ``.npz``."""
        np.savez(
            path,
            tile_index=np.array(self.tile_index),
            reference_index=self.reference_index,
            scan_index=self.scan_index,
            reference_label=self.reference_label,
            scan_label=self.scan_label,
            reference_distance=self.reference_distance,
            scan_distance=self.scan_distance,
            figures=np.array(json.dumps(json_safe(self.figures))),
            **{f"region_{name}": self.regions[name] for name in REGION_FIELDS},
        )

    @classmethod
    def load(cls, path: str | Path) -> TileResult:
        """Read a result written by :meth:`save`."""
        with np.load(path, allow_pickle=False) as data:
            return cls(
                tile_index=int(data["tile_index"]),
                reference_index=data["reference_index"],
                scan_index=data["scan_index"],
                reference_label=data["reference_label"],
                scan_label=data["scan_label"],
                reference_distance=data["reference_distance"],
                scan_distance=data["scan_distance"],
                regions={name: data[f"region_{name}"] for name in REGION_FIELDS},
                figures=json.loads(str(data["figures"])),
            )


def compute_tile(
    plan: TilePlan,
    tile_index: int,
    source: TileSource,
    context: TileContext,
    *,
    threads: int | None = None,
) -> TileResult:
    """Localise tile ``tile_index`` of ``plan`` (see :mod:`app.core.tiling`).

    Parameters
    ----------
    plan : TilePlan
    tile_index : int
    source : TileSource
    context : TileContext
    threads : int, optional
        Threads of the localiser (the result does not depend on it).

    Returns
    -------
    TileResult
    """
    crop = source.crop(plan, tile_index, context)
    reference_core = plan.in_core(tile_index, crop.reference_points[:, :2])
    scan_core = plan.in_core(tile_index, crop.scan_points[:, :2])
    figures: dict[str, Any] = {
        "crop_reference_points": len(crop.reference_index),
        "crop_scan_points": len(crop.scan_index),
        "core_reference_points": int(np.count_nonzero(reference_core)),
        "core_scan_points": int(np.count_nonzero(scan_core)),
    }
    localised, thinned = crop, None
    if plan.thinning_cell(tile_index) > 0:
        limit = thinned_point_limit(
            plan.max_crop_points, len(crop.reference_index) + len(crop.scan_index)
        )
        localised, *thinned = thin_crop(crop, plan.thinning_cell(tile_index), limit)
        figures.update(
            thinning_cell_m=thinned[2],
            thinned_reference_points=len(localised.reference_index),
            thinned_scan_points=len(localised.scan_index),
        )
        share = len(localised.reference_index) + len(localised.scan_index)
        share /= max(1, len(crop.reference_index) + len(crop.scan_index))
        context = dataclasses.replace(  # the whole pair's floor is applied by the merge
            context, min_region_points=max(1, int(np.ceil(context.min_region_points * share)))
        )
    if min(len(localised.reference_index), len(localised.scan_index)) < MIN_CROP_POINTS:
        labels = [
            np.full(np.count_nonzero(core), LABEL_UNOBSERVED, dtype=np.int8)
            for core in (reference_core, scan_core)
        ]
        distances = [np.full(len(label), np.nan, dtype=np.float32) for label in labels]
        regions = _region_table([], crop, reference_core, scan_core, None)
        figures["localised"] = False
    else:
        localisation = localise_crop(localised, context, threads)
        if thinned:
            localisation = carried_back(localisation, thinned[0], thinned[1])
        labels = [
            localisation.reference_label[reference_core].astype(np.int8),
            localisation.scan_label[scan_core].astype(np.int8),
        ]
        distances = [
            localisation.reference_distance[reference_core].astype(np.float32),
            localisation.scan_distance[scan_core].astype(np.float32),
        ]
        tagged = [(region, False) for region in localisation.regions]
        tagged += [(region, True) for region in localisation.uncertain_regions]
        regions = _region_table(tagged, crop, reference_core, scan_core, localisation)
        figures["localised"] = True
        figures.update(localisation.parameters)
    return TileResult(
        tile_index=int(tile_index),
        reference_index=crop.reference_index[reference_core].astype(np.int64),
        scan_index=crop.scan_index[scan_core].astype(np.int64),
        reference_label=labels[0],
        scan_label=labels[1],
        reference_distance=distances[0],
        scan_distance=distances[1],
        regions=regions,
        figures=figures,
    )


def thin_crop(
    crop: TileCrop, cell: float, limit: int
) -> tuple[TileCrop, NDArray[np.int64], NDArray[np.int64], float]:
    """``crop`` thinned at ``cell`` (:func:`~app.core.tiling.thinning.representatives`, each
    cloud on its own), the cell coarsened while the thinned crop has more than ``limit``
    points (by ``sqrt(points / limit)``, at least
    :data:`~app.core.tiling.thinning.THINNING_CELL_STEP`), up to
    :data:`~app.core.tiling.thinning.MAX_THINNING_CELL_METRES`.

    Returns
    -------
    thinned : TileCrop
        The representatives, in crop order (their indices, points, stations and rays).
    reference_representative, scan_representative : ndarray, shape (a,) / (b,), int64
        Each crop point's row in ``thinned``.
    cell : float
        The cell used.

    Raises
    ------
    TileBudgetError
        Over ``limit`` even at the coarsest cell.
    """
    while True:
        reference_kept, reference_representative = representatives(crop.reference_points, cell)
        scan_kept, scan_representative = representatives(crop.scan_points, cell)
        total = len(reference_kept) + len(scan_kept)
        if total <= limit or cell >= MAX_THINNING_CELL_METRES:
            break
        # a surface keeps about area / cell**2 points: aim at the limit, at least one step
        aimed = cell * np.sqrt(total / max(1, limit))
        cell = min(MAX_THINNING_CELL_METRES, max(cell * THINNING_CELL_STEP, float(aimed)))
    if total > limit:
        crop_points = len(crop.reference_index) + len(crop.scan_index)
        missing = (total - limit) * LOCALISATION_BYTES_PER_POINT
        raise TileBudgetError(
            f"the pair does not fit the memory budget: a tile's crop of {crop_points:,} points "
            f"thinned at {cell * 100:g} cm still has {total:,} points to localise, more than "
            f"the {max(0, limit):,} the budget leaves beside the whole crop "
            f"({HELD_CROP_BYTES_PER_POINT} B a point); raise the memory budget by at least "
            f"{missing / 1024**2:,.0f} MiB"
        )
    thinned = TileCrop(
        reference_index=crop.reference_index[reference_kept],
        scan_index=crop.scan_index[scan_kept],
        reference_points=crop.reference_points[reference_kept],
        scan_points=crop.scan_points[scan_kept],
        reference_station=_taken(crop.reference_station, reference_kept),
        scan_station=_taken(crop.scan_station, scan_kept),
        reference_rays=_cropped_rays(crop.reference_rays, reference_kept),
        scan_rays=_cropped_rays(crop.scan_rays, scan_kept),
    )
    return thinned, reference_representative, scan_representative, float(cell)


def _region_table(
    tagged: list[tuple[Any, bool]],
    crop: TileCrop,
    reference_core: NDArray[np.bool_],
    scan_core: NDArray[np.bool_],
    localisation: Localisation | None,
) -> dict[str, NDArray]:
    """The :attr:`TileResult.regions` arrays of a crop's regions."""
    rows: dict[str, list] = {name: [] for name in REGION_FIELDS}
    bounds = [0]
    for region, uncertain in tagged:
        scan = region.kind == "added"
        index = crop.scan_index if scan else crop.reference_index
        core = scan_core if scan else reference_core
        points = crop.scan_points if scan else crop.reference_points
        local = region.point_indices
        in_core = core[local]
        core_points = points[local[in_core]]
        if localisation is not None and not uncertain:
            distance = (localisation.scan_distance if scan else localisation.reference_distance)[
                local[in_core]
            ].astype(np.float64)
            distance_sum = float(distance.sum())
            distance_max = float(distance.max()) if len(distance) else 0.0
        else:  # unobserved points carry no distance: the region's mean stands for them
            distance_sum = region.mean_distance * int(in_core.sum())
            distance_max = region.max_distance if in_core.any() else 0.0
        rows["cloud"].append(int(scan))
        rows["uncertain"].append(uncertain)
        rows["evidence"].append(EVIDENCE_CODES.get(region.evidence, 0))
        rows["confidence"].append(region.confidence)
        rows["core_count"].append(int(in_core.sum()))
        rows["core_sum"].append(core_points.sum(axis=0) if len(core_points) else np.zeros(3))
        rows["core_min"].append(core_points.min(axis=0) if len(core_points) else np.full(3, np.inf))
        rows["core_max"].append(
            core_points.max(axis=0) if len(core_points) else np.full(3, -np.inf)
        )
        rows["distance_sum"].append(distance_sum)
        rows["distance_max"].append(distance_max)
        rows["members"].append(index[local])
        rows["member_in_core"].append(in_core)
        bounds.append(bounds[-1] + len(local))
    dtypes = {
        "cloud": np.int8,
        "uncertain": bool,
        "evidence": np.int8,
        "confidence": np.float64,
        "core_count": np.int64,
        "distance_sum": np.float64,
        "distance_max": np.float64,
    }
    table = {name: np.asarray(rows[name], dtype=dtype) for name, dtype in dtypes.items()}
    for name in ("core_sum", "core_min", "core_max"):
        table[name] = np.asarray(rows[name], dtype=np.float64).reshape(-1, 3)
    table["member_bounds"] = np.asarray(bounds, dtype=np.int64)
    table["members"] = (
        np.concatenate(rows["members"]).astype(np.int64) if tagged else np.zeros(0, np.int64)
    )
    table["member_in_core"] = (
        np.concatenate(rows["member_in_core"]) if tagged else np.zeros(0, dtype=bool)
    )
    return table
