"""A whole comparison in tiles, in one process: what ``scandiff compare`` runs when a pair does
not fit the memory budget (and the job runner, until tiles fan out to the workers).

The stages around localisation are those of :func:`app.core.pipeline.compare`
(:func:`app.core.pipeline.run_stages`, with :class:`TiledLocalisation` as its localise step),
with three differences that bound memory:

- **Registration** runs on at most :data:`REGISTRATION_SAMPLE` points of each cloud (evenly
  strided: GICP thins both clouds on a voxel grid anyway; the alignment then draws its own
  random :data:`~app.core.registration.SAMPLE_POINTS` of them); each tile then measures the
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
from typing import Any, Unpack

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import PointCloud
from app.core.comparison.align import Alignment
from app.core.comparison.load import LoadedPair, PairOptions, load_pair
from app.core.comparison.origins import CloudOrigins, SensorOrigins
from app.core.localise import Localisation
from app.core.localise.changes import _default_min_region_points
from app.core.localise.settings import DEFAULT_PARAMETERS
from app.core.localise.station_assignment import assign_stations
from app.core.pipeline import ComparisonResult, ProgressCallback, run_stages
from app.core.tiling.merge import merge_tiles
from app.core.tiling.plan import (
    DEFAULT_MARGIN_METRES,
    DEFAULT_RAY_REACH_METRES,
    LEAN_RESIDENT_BYTES_PER_POINT,
    RESIDENT_BYTES_PER_POINT,
    TilePlan,
    crop_point_limit,
    plan_tiles,
)
from app.core.tiling.rays import ray_cell_sizes
from app.core.tiling.tile import TileContext, TileResult, TileSource, compute_tile

__all__ = [
    "DETECTION_SAMPLE",
    "REGISTRATION_SAMPLE",
    "compare_tiled",
    "compare_within_budget",
    "fits_budget",
    "origin_array",
]

REGISTRATION_SAMPLE = 2_000_000
DETECTION_SAMPLE = 2_000_000


def fits_budget(n_reference: int, n_scan: int, budget_bytes: int) -> bool:
    """Whether the one-process comparison of a pair this size fits ``budget_bytes``."""
    return crop_point_limit(budget_bytes, n_reference + n_scan) >= n_reference + n_scan


def _stations(
    points: NDArray[np.floating], origins: NDArray | None, station: NDArray | None
) -> NDArray | None:
    """Each point's station: given, or assigned once for the whole cloud (several origins)."""
    if station is not None or origins is None or len(np.atleast_2d(origins)) < 2:
        return station
    origins = np.atleast_2d(origins)
    return assign_stations(points, origins, np.int8 if len(origins) <= 127 else np.int32)


def compare_tiled(
    reference: PointCloud,
    scan: PointCloud,
    *,
    budget_bytes: int,
    progress: ProgressCallback | None = None,
    site_calibration: Mapping[str, Any] | None = None,
    max_crop_points: int | None = None,
    margin: float = DEFAULT_MARGIN_METRES,
    ray_reach: float = DEFAULT_RAY_REACH_METRES,
    run_tiles: TileRunner | None = None,
    ray_directions: bool = True,
    **options: Unpack[PairOptions],
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
    ray_directions : bool
        Crops keep the other sensor's returns by direction too (:mod:`app.core.tiling.rays`):
        far smaller crops round stations (the streamed parent, :mod:`app.core.tiling.streamed`,
        crops the same way).  False: the top view only.
    run_tiles : callable, optional
        ``run_tiles(plan, source, context, threads, report) -> list[TileResult]`` (in tile
        order): who computes the tiles.  Default: each in turn in this process
        (:func:`compute_tiles_here`); a job worker passes one that fans them out on the queue
        (:mod:`app.jobs.tiles`).
    frame_offset : ndarray, shape (3,), optional
        The clouds were read lean (:func:`app.core.tiling.lean.read_pair`): their points are
        float32 minus this offset, the local frame's origin; the whole clouds stay float32
        throughout (the aligned scan too, each point's station int8) and the plan counts
        :data:`~app.core.tiling.plan.LEAN_RESIDENT_BYTES_PER_POINT` for them.

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
    loaded = load_pair(reference, scan, **options)
    tiles = TiledLocalisation(
        budget_bytes=budget_bytes,
        max_crop_points=max_crop_points,
        margin=margin,
        ray_reach=ray_reach,
        run_tiles=run_tiles or compute_tiles_here,
        ray_directions=ray_directions,
        detection_seed=options.get("random_state", 0),
        resident_bytes_per_point=(
            RESIDENT_BYTES_PER_POINT
            if options.get("frame_offset") is None
            else LEAN_RESIDENT_BYTES_PER_POINT
        ),
    )
    return run_stages(
        loaded, progress=progress, site_calibration=site_calibration, localise_step=tiles
    )


TileRunner = Callable[[TilePlan, TileSource, TileContext, int, ProgressCallback], list[TileResult]]
"""Who computes a plan's tiles: ``run_tiles(plan, source, context, threads, report)``."""


@dataclass(frozen=True)
class TiledLocalisation:
    """The localise step of :func:`app.core.pipeline.run_stages` done tile by tile within a
    memory budget (:class:`app.core.pipeline.LocaliseStep`), with the samples that bound the
    alignment and the detection around it.

    Attributes
    ----------
    budget_bytes : int
        Memory this process may use; tile sizes follow from it.
    max_crop_points : int or None
        Points of both clouds a tile's crop may have (None: the budget's figure).
    margin, ray_reach : float
        Metres (see :func:`compare_tiled`).
    run_tiles : TileRunner
        Who computes the tiles.
    detection_seed : int
        Seeds the detection's subsample.
    resident_bytes_per_point : int
        What the process holds a point of the whole clouds besides the crops
        (:mod:`app.core.tiling.plan`; less for a pair read lean).
    """

    budget_bytes: int
    max_crop_points: int | None
    margin: float
    ray_reach: float
    run_tiles: TileRunner
    detection_seed: int
    resident_bytes_per_point: int = RESIDENT_BYTES_PER_POINT
    registration_sample: int = REGISTRATION_SAMPLE
    detection_sample: int = DETECTION_SAMPLE
    detect_fraction: float = 0.85
    ray_directions: bool = True

    @property
    def params(self) -> Mapping[str, Any]:
        """The budget, reported among the parameters in effect."""
        return {"memory_budget_bytes": int(self.budget_bytes)}

    def localise(
        self,
        loaded: LoadedPair,
        origins: SensorOrigins,
        alignment: Alignment,
        report: ProgressCallback,
        timings: dict[str, float],
    ) -> tuple[Localisation, int]:
        """Plan the tiles, have them computed and merge them; with the region size floor."""
        started = time.perf_counter()
        context, source = _tile_inputs(
            loaded, origins, alignment, self.ray_reach, self.ray_directions
        )
        limit = (
            self.max_crop_points
            if self.max_crop_points is not None
            else crop_point_limit(
                self.budget_bytes,
                len(source.reference_points) + len(source.scan_points),
                self.resident_bytes_per_point,
            )
        )
        plan = plan_tiles(
            source.reference_points[:, :2],
            source.scan_points[:, :2],
            max_crop_points=limit,
            count_crop=lambda low, high: source.count_crop(low, high, self.margin, context),
            margin=self.margin,
            budget_bytes=self.budget_bytes,
        )
        timings["plan"] = time.perf_counter() - started
        # the tiles' results are dropped when this returns: only the merged arrays stay
        results = self.run_tiles(plan, source, context, loaded.threads, report)
        localisation = merge_tiles(
            plan,
            results,
            len(source.reference_points),
            len(source.scan_points),
            context.min_region_points,
        )
        return localisation, context.min_region_points


def _tile_inputs(
    loaded: LoadedPair,
    origins: SensorOrigins,
    alignment: Alignment,
    ray_reach: float,
    ray_directions: bool = False,
) -> tuple[TileContext, TileSource]:
    """What every tile shares, and the points with each one's station."""
    localisation_params = dict(loaded.settings.localisation)
    min_region_points = localisation_params.get("min_region_points") or (
        _default_min_region_points(len(loaded.reference_points), len(alignment.aligned_scan))
    )
    reference_origins, scan_origins = origin_array(origins.reference), origin_array(origins.scan)
    source = TileSource(
        reference_points=loaded.reference_points,
        scan_points=alignment.aligned_scan,
        reference_station=_stations(
            loaded.reference_points, reference_origins, origins.reference.station
        ),
        scan_station=_stations(alignment.aligned_scan, scan_origins, origins.scan.station),
        reference_rays=origins.reference.trajectory_rays,
        scan_rays=origins.scan.trajectory_rays,
    )
    angle_factor = float(
        localisation_params.get(
            "visibility_angle_factor", DEFAULT_PARAMETERS["visibility_angle_factor"]
        )
    )
    context = TileContext(
        reference_origins=reference_origins,
        scan_origins=scan_origins,
        reference_stations_unknown=origins.reference.stations_unknown,
        scan_stations_unknown=origins.scan.stations_unknown,
        min_region_points=int(min_region_points),
        localisation_params=localisation_params,
        ray_reach=ray_reach,
        # a trajectory's pseudo-stations group their rays otherwise: the top view only
        reference_ray_cells=None
        if source.reference_rays is not None or not ray_directions
        else ray_cell_sizes(
            source.reference_station, len(source.reference_points), reference_origins, angle_factor
        ),
        scan_ray_cells=None
        if source.scan_rays is not None or not ray_directions
        else ray_cell_sizes(
            source.scan_station, len(source.scan_points), scan_origins, angle_factor
        ),
    )
    return context, source


def origin_array(cloud: CloudOrigins) -> NDArray[np.float64] | None:
    """A cloud's origins as a (k, 3) array, or None."""
    return None if cloud.origin is None else np.atleast_2d(cloud.origin).astype(np.float64)


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


def compare_within_budget(
    reference: PointCloud,
    scan: PointCloud,
    *,
    budget_bytes: int | None,
    frame_offset: NDArray[np.float64] | None = None,
    **options: Any,
) -> ComparisonResult:
    """:func:`app.core.pipeline.compare` when the pair fits ``budget_bytes`` (or no budget),
    else :func:`compare_tiled` (the ``geometry_cache`` option applies to the former only).

    Parameters
    ----------
    reference, scan : PointCloud
    budget_bytes : int or None
        Memory the comparison may use; None: no limit (always one process).
    frame_offset : ndarray, shape (3,), optional
        The clouds were read lean (:func:`app.core.tiling.lean.read_pair`, which decided they
        will be tiled): always :func:`compare_tiled`.
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

    if frame_offset is not None:  # read lean for tiles (app.core.tiling.lean.read_pair)
        options.pop("geometry_cache", None)
        return compare_tiled(
            reference, scan, budget_bytes=budget_bytes or 0, frame_offset=frame_offset, **options
        )
    if budget_bytes is None or fits_budget(len(reference), len(scan), budget_bytes):
        return compare(reference, scan, **options)
    options.pop("geometry_cache", None)
    return compare_tiled(reference, scan, budget_bytes=budget_bytes, **options)
