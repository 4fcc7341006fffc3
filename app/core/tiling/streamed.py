"""A tiled comparison whose parent never holds the whole pair: the files streamed (issue 30).

:func:`~app.core.tiling.compare.compare_tiled` holds both clouds whole in the process that
plans, cuts and merges the tiles (32 bytes a point read lean: 6.4 GB for 100M + 100M points).
:func:`compare_streamed` reads each file a chunk at a time
(:data:`~app.core.tiling.pair_files.CHUNK` points,
:func:`~app.core.formats.streamed.open_point_blocks`: memory-mapped PLY/NPY read with
``pread``, laspy's chunk iterator) and keeps only:

- a subsample of each cloud (about one finite point in k, about :data:`SUBSAMPLE_POINTS`,
  drawn by a hash of each point's index, not every k-th point, which a file in scan order
  would alias: :func:`~app.core.tiling.pair_files.subsample_offsets`), float32 in the local
  frame: the stages of
  :func:`app.core.pipeline.run_stages` run on it (the reference's and the scan's origins,
  the registration, whose own sample is then the same points as the whole pair's, the
  detectors' sample) and the planner counts crops on it, scaled to the whole clouds;
- each tile's input, written in one pass over each file's chunks into files of its own
  (:mod:`app.core.tiling.crops`), one :class:`~app.core.tiling.crop_passes.CropPass` a file,
  run by ``run_crops`` (here, or on the workers: :mod:`app.jobs.crop_passes`): the chunk
  moved into the local frame, the scan's aligned,
  each point's station assigned (:func:`~app.core.localise.station_assignment.best_stations`
  with the contrasts of the subsample); with stations, the other sensor's returns are kept
  by direction too (:mod:`app.core.tiling.rays`): each pass first reads the other cloud's
  file for every tile's direction marks of its own origins (the other cloud's points in the
  tile's box) and writes only the returns the tile reads, so the crops on disk are the
  points the plan counts (not the top view's, about 3x more at 100M + 100M); the direction
  cells from the subsample's station counts scaled up;
- the merge, range by range of :data:`~app.core.tiling.pair_files.OUTPUT_RANGE` points: each
  tile's result is read from its file for the range, and the labels, distances and region
  numbers are written into ``.npy`` files in the files' row order
  (:data:`~app.core.tiling.pair_files.OUTPUT_FILES`).

The result is a :class:`~app.core.pipeline.ComparisonResult` whose per-point arrays are those
files, memory-mapped read-only.  When a cloud has at most :data:`SUBSAMPLE_POINTS` points the
subsample is the whole cloud and the result is the lean tiled comparison's, point for point.
The files must carry coordinates only (no sensor origin, stations or trajectory: those need the
whole cloud read); :func:`~app.core.tiling.pair_files.coordinates_only` says whether a file
can go this way, and :mod:`~app.core.tiling.pair_files` writes a job's result files from the
outputs without loading them.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Unpack

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import PointCloud, choose_local_origin
from app.core.comparison.align import Alignment
from app.core.comparison.load import LoadedPair, PairOptions, load_pair
from app.core.comparison.origins import SensorOrigins
from app.core.localise import Localisation
from app.core.localise.changes import _default_min_region_points
from app.core.localise.settings import DEFAULT_PARAMETERS
from app.core.localise.station_assignment import best_stations, station_contrasts
from app.core.pipeline import ComparisonResult, ProgressCallback, run_stages
from app.core.threads import available_threads
from app.core.tiling.compare import REGISTRATION_SAMPLE, TileRunner, origin_array
from app.core.tiling.crop_passes import (
    CropPass,
    CropRunner,
    write_crop_passes_here,
    write_pass_layout,
)
from app.core.tiling.crops import TileCropFiles
from app.core.tiling.disk import FreeDisk, check_disk, free_disk_bytes, needed_disk_bytes
from app.core.tiling.merge import join_regions, merged_parameters
from app.core.tiling.pair_files import (
    StoredTileResults,
    StreamedCloud,
    survey,
    write_outputs,
)
from app.core.tiling.plan import (
    DEFAULT_MARGIN_METRES,
    DEFAULT_RAY_REACH_METRES,
    LEAN_RESIDENT_BYTES_PER_POINT,
    TilePlan,
    crop_point_limit,
    plan_tiles,
    thinned_as_written,
)
from app.core.tiling.rays import MAX_DIRECTION_STATIONS, cells_of_counts, crop_masks
from app.core.tiling.tile import COUNT_CELL_SCALE, TileContext, TileResult, compute_tile

__all__ = [
    "COUNT_SAMPLE",
    "PLAN_FILE",
    "SUBSAMPLE_POINTS",
    "StreamedLocalisation",
    "compare_streamed",
    "compute_tiles_to_files",
]

SUBSAMPLE_POINTS = REGISTRATION_SAMPLE
"""Points of each cloud kept for the stages (the registration's sample size)."""
COUNT_SAMPLE = 400_000
"""Points of each cloud the planner counts crops on (as :meth:`TileSource.count_crop`)."""
PLAN_FILE = "plan.npz"
"""The plan (:meth:`~app.core.tiling.plan.TilePlan.save`), written into ``work_dir`` once it
is made, before the crops."""


@contextmanager
def timed_phase(timings: dict[str, float], name: str) -> Iterator[None]:
    """Add the ``with`` block's wall seconds to ``timings[name]`` and this process's CPU
    seconds (all its threads) to ``timings[name + "_cpu"]``."""
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        yield
    finally:
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - wall
        timings[f"{name}_cpu"] = timings.get(f"{name}_cpu", 0.0) + time.process_time() - cpu


def compute_tiles_to_files(directory: Path) -> TileRunner:
    """A :data:`TileRunner` computing each tile here in turn, each result saved into
    ``directory`` as it is done and handed back as :class:`StoredTileResults`."""

    def run(
        plan: TilePlan, source: Any, context: TileContext, threads: int, report: ProgressCallback
    ) -> list[TileResult]:
        directory.mkdir(parents=True, exist_ok=True)
        paths = []
        for tile_index in range(plan.n_tiles):
            path = directory / f"tile-{tile_index:05d}.npz"
            compute_tile(plan, tile_index, source, context, threads=threads).save(path)
            paths.append(path)
            report("localise", 0.35 + 0.5 * (tile_index + 1) / plan.n_tiles)
        return StoredTileResults(paths)  # type: ignore[return-value]

    return run


@dataclass(frozen=True)
class StreamedLocalisation:
    """The localise step of a streamed comparison (:class:`app.core.pipeline.LocaliseStep`):
    ``loaded`` holds the subsamples; the tiles' inputs and the merged per-point outputs are
    files under ``work_dir`` (see the module).

    Attributes
    ----------
    budget_bytes, max_crop_points, margin, ray_reach, run_tiles, detection_seed
        As :class:`~app.core.tiling.compare.TiledLocalisation`.
    reference, scan : StreamedCloud
    offset : ndarray, shape (3,)
        The local frame's origin.
    work_dir : Path
        ``crops/`` (the tiles' inputs) and the outputs
        (:data:`~app.core.tiling.pair_files.OUTPUT_FILES`).
    outputs : dict
        Filled by :meth:`localise`: the output files' paths by ``<side>_<name>``.
    ray_directions : bool
        Crops keep the other sensor's returns by direction too (:mod:`app.core.tiling.rays`).
    run_crops : CropRunner
        Who runs each cloud's crop pass (:mod:`app.core.tiling.crop_passes`).
    keep_free_disk_bytes, free_disk
        Disk that must stay free under ``work_dir`` and how free disk is measured: a pair
        whose crops and results would not fit is refused once planned
        (:func:`~app.core.tiling.disk.check_disk`).
    """

    budget_bytes: int
    max_crop_points: int | None
    margin: float
    ray_reach: float
    run_tiles: TileRunner
    detection_seed: int
    reference: StreamedCloud
    scan: StreamedCloud
    offset: NDArray[np.float64]
    work_dir: Path
    outputs: dict[str, Path] = field(default_factory=dict)
    registration_sample: int = REGISTRATION_SAMPLE
    detection_sample: int = REGISTRATION_SAMPLE
    detect_fraction: float = 0.85
    ray_directions: bool = True
    run_crops: CropRunner = write_crop_passes_here
    keep_free_disk_bytes: int = 0
    free_disk: FreeDisk = free_disk_bytes

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
        """Plan on the subsamples, write the crops from the files, run the tiles, merge.

        Adds each phase's wall and CPU seconds to ``timings`` (:func:`timed_phase`):
        ``stream_stations`` (the subsamples' stations), ``stream_plan``, ``stream_crops``,
        ``stream_tiles`` and ``stream_merge``.
        """
        for cloud in (origins.reference, origins.scan):
            if cloud.station is not None or cloud.trajectory_rays is not None:
                raise ValueError("a streamed comparison takes files with coordinates only")
        with timed_phase(timings, "stream_stations"):
            passes, sub_stations = self._passes(loaded, alignment, origins)
        sub = [loaded.reference_points, alignment.aligned_scan]
        context = self._context(loaded, origins, sub_stations, [len(points) for points in sub])
        with timed_phase(timings, "stream_plan"):
            plan = self._plan(sub, sub_stations, context)
        plan.save(self.work_dir / PLAN_FILE)  # how the pair was cut, before any crop
        report("localise", 0.36)  # planned
        crops, partial = self.work_dir / "crops", self.work_dir / "crops.partial"
        with timed_phase(timings, "stream_crops"):
            # an earlier attempt's crops go first (the disk is for these), and these are
            # swapped in whole: a tile never reads a half-written crop
            for stale in (partial, crops):
                shutil.rmtree(stale, ignore_errors=True)
            n_points = self.reference.n_points + self.scan.n_points
            record_bytes = max(crop_pass.dtype.itemsize for crop_pass in passes)
            needed = needed_disk_bytes(plan, record_bytes, n_points)
            check_disk(self.work_dir, needed, self.keep_free_disk_bytes, self.free_disk)
            partial.mkdir(parents=True, exist_ok=True)
            self.run_crops(partial, plan, context, passes, loaded.threads, report)
            write_pass_layout(partial, context, passes)
            partial.rename(crops)
        report("localise", 0.37)  # the tiles' inputs written
        files = TileCropFiles(crops)
        # the plan counted crops on a sample: a tile planned whole whose crop as written is
        # over the limit is thinned, as the planner would have (the crops are unchanged)
        written = files.written_points(plan.n_tiles)
        if written is not None:
            rethinned = thinned_as_written(
                plan, written, *(points[:, :2] for points in sub), self.budget_bytes
            )
            if rethinned is not plan:
                plan = rethinned
                plan.save(self.work_dir / PLAN_FILE)
        with timed_phase(timings, "stream_tiles"):
            results = self.run_tiles(plan, files, context, loaded.threads, report)  # type: ignore[arg-type]
        with timed_phase(timings, "stream_merge"):
            localisation = self._merge(plan, results, context.min_region_points)
        return localisation, context.min_region_points

    def _plan(
        self,
        sub: Sequence[NDArray[np.float32]],
        sub_stations: Sequence[NDArray | None],
        context: TileContext,
    ) -> TilePlan:
        """The tiles, planned on the subsamples (``sub``: the reference's and the aligned
        scan's, (m, 3)); each candidate crop counted on at most :data:`COUNT_SAMPLE` points a
        cloud and scaled to the whole clouds."""
        limit = self.max_crop_points
        if limit is None:
            limit = crop_point_limit(
                self.budget_bytes, len(sub[0]) + len(sub[1]), LEAN_RESIDENT_BYTES_PER_POINT
            )
        full = [self.reference.n_points, self.scan.n_points]
        all_origins = [context.reference_origins, context.scan_origins]
        all_cells = [context.reference_ray_cells, context.scan_ray_cells]

        def count_crop(low: NDArray[np.float64], high: NDArray[np.float64]) -> int:
            # as TileSource.count_crop: at most COUNT_SAMPLE points a cloud, coarser cells then
            if np.all(np.isinf(low)) and np.all(np.isinf(high)):
                return full[0] + full[1]  # the unbounded box (the plan's first): every point
            steps = [max(1, len(points) // COUNT_SAMPLE) for points in sub]
            masks = crop_masks(
                [
                    (points[::step], None if station is None else station[::step], side_origins)
                    for points, station, side_origins, step in zip(
                        sub, sub_stations, all_origins, steps, strict=True
                    )
                ],
                [
                    None if cells is None else cells * (COUNT_CELL_SCALE if step > 1 else 1.0)
                    for cells, step in zip(all_cells, steps, strict=True)
                ],
                low - self.margin,
                high + self.margin,
                context.ray_reach,
            )
            total = 0.0
            for mask, points, n, step in zip(masks, sub, full, steps, strict=True):
                total += np.count_nonzero(mask) * n / max(1, len(points[::step]))
            return int(np.ceil(total))

        return plan_tiles(
            sub[0][:, :2],
            sub[1][:, :2],
            max_crop_points=limit,
            count_crop=count_crop,
            margin=self.margin,
            budget_bytes=self.budget_bytes,
        )

    def _context(
        self,
        loaded: LoadedPair,
        origins: SensorOrigins,
        sub_stations: Sequence[NDArray | None],
        sub_sizes: Sequence[int],
    ) -> TileContext:
        """What every tile shares; the region size floor of the whole clouds; with
        :attr:`ray_directions`, each cloud's direction cells from its subsample's stations."""
        params = dict(loaded.settings.localisation)
        min_region_points = params.get("min_region_points") or _default_min_region_points(
            self.reference.n_points, self.scan.n_points
        )
        angle_factor = float(
            params.get("visibility_angle_factor", DEFAULT_PARAMETERS["visibility_angle_factor"])
        )
        cells = [
            self._cells(side_origins, station, n_sub, cloud.n_points, angle_factor)
            for side_origins, station, n_sub, cloud in zip(
                (origin_array(origins.reference), origin_array(origins.scan)),
                sub_stations,
                sub_sizes,
                (self.reference, self.scan),
                strict=True,
            )
        ]
        return TileContext(
            reference_origins=origin_array(origins.reference),
            scan_origins=origin_array(origins.scan),
            reference_stations_unknown=origins.reference.stations_unknown,
            scan_stations_unknown=origins.scan.stations_unknown,
            min_region_points=int(min_region_points),
            localisation_params=params,
            ray_reach=self.ray_reach,
            reference_ray_cells=cells[0],
            scan_ray_cells=cells[1],
        )

    def _cells(
        self,
        origins: NDArray[np.float64] | None,
        station: NDArray | None,
        n_sub: int,
        n_points: int,
        angle_factor: float,
    ) -> NDArray[np.float64] | None:
        """A cloud's direction cells (:func:`~app.core.tiling.rays.ray_cell_sizes`), its
        stations' returns counted on the subsample and scaled up (the whole cloud's counts
        when the subsample is the whole cloud)."""
        if not self.ray_directions or origins is None:
            return None
        if not 0 < len(origins) <= MAX_DIRECTION_STATIONS:
            return None
        if station is None:
            counts = np.zeros(len(origins), dtype=np.float64)
            counts[0] = n_points
        else:
            counts = np.bincount(np.asarray(station, dtype=np.int64), minlength=len(origins))
            counts = counts[: len(origins)].astype(np.float64)
            if n_sub != n_points:
                counts = counts * (n_points / max(1, n_sub))
        return cells_of_counts(counts, angle_factor)

    def _passes(
        self, loaded: LoadedPair, alignment: Alignment, sensor_origins: SensorOrigins
    ) -> tuple[list[CropPass], list[NDArray | None]]:
        """Each cloud's crop pass over its file (local frame, the scan aligned, stations) and
        its subsample's stations."""
        passes, sub_stations = [], []
        for side, cloud, sub, origins, move in (
            (
                "reference",
                self.reference,
                loaded.reference_points,
                origin_array(sensor_origins.reference),
                None,
            ),
            (
                "scan",
                self.scan,
                alignment.aligned_scan,
                origin_array(sensor_origins.scan),
                alignment.registration.transform,
            ),
        ):
            several = origins is not None and len(origins) >= 2
            contrasts = station_contrasts(sub, origins) if several else None
            sub_stations.append(
                best_stations(sub, origins, contrasts).astype(  # type: ignore[arg-type]
                    np.int8 if len(origins) <= 127 else np.int32  # type: ignore[arg-type]
                )
                if several
                else None
            )
            passes.append(
                CropPass(
                    side=side,
                    path=cloud.path,
                    format=cloud.format,
                    offset=self.offset,
                    transform=move,
                    station_origins=origins if several else None,
                    contrasts=None
                    if contrasts is None
                    else np.stack([grid.packed() for grid in contrasts]),
                    n_points=cloud.n_points,
                )
            )
        # each pass reads the other cloud's file too, for its crops' direction marks
        reference, scan = passes
        return [
            dataclasses.replace(
                one,
                other_path=other.path,
                other_format=other.format,
                other_transform=other.transform,
            )
            for one, other in ((reference, scan), (scan, reference))
        ], sub_stations

    def _merge(
        self, plan: TilePlan, results: Sequence[TileResult], min_region_points: int
    ) -> Localisation:
        """The tiles joined; per-point outputs written to files; the subsample's localisation."""
        tables, tiles = [], []
        for result in results:
            tables.append(result.regions)
            core = len(result.reference_index) + len(result.scan_index)
            tiles.append((result.tile_index, core, result.figures))
        if sorted(tile[0] for tile in tiles) != list(range(plan.n_tiles)):
            raise ValueError("the tiles' results do not match the plan")
        unchanged: list[list[NDArray[np.int64]]] = [[], []]
        regions, uncertain = join_regions(
            tables, min_region_points, lambda cloud, points: unchanged[cloud].append(points)
        )
        del tables
        counts: dict[str, int] = {}
        sub: dict[str, NDArray] = {}
        for cloud_number, (side, cloud) in enumerate(
            (("reference", self.reference), ("scan", self.scan))
        ):
            kind = "added" if cloud_number else "removed"
            numbered = [
                (number, region.point_indices)
                for number, region in enumerate(regions)
                if region.kind == kind
            ]
            dropped = (
                np.sort(np.concatenate(unchanged[cloud_number]))
                if unchanged[cloud_number]
                else np.zeros(0, np.int64)
            )
            written = write_outputs(self.work_dir, side, cloud, results, numbered, dropped)
            self.outputs.update(written.paths)
            counts[f"n_{side}_changed"] = written.changed
            counts[f"n_{side}_unobserved"] = written.unobserved
            sub.update({f"{side}_{name}": values for name, values in written.sub.items()})
        parameters = merged_parameters(plan, tiles, counts, len(uncertain))
        return Localisation(
            reference_label=sub["reference_label"],
            scan_label=sub["scan_label"],
            reference_distance=sub["reference_distance"],
            scan_distance=sub["scan_distance"],
            reference_region=sub["reference_region"],
            scan_region=sub["scan_region"],
            regions=regions,
            parameters=parameters,
            uncertain_regions=uncertain,
        )


def compare_streamed(
    reference_path: str | Path,
    scan_path: str | Path,
    *,
    budget_bytes: int,
    work_dir: str | Path,
    formats: tuple[str | None, str | None] = (None, None),
    progress: ProgressCallback | None = None,
    site_calibration: Mapping[str, Any] | None = None,
    max_crop_points: int | None = None,
    margin: float = DEFAULT_MARGIN_METRES,
    ray_reach: float = DEFAULT_RAY_REACH_METRES,
    run_tiles: TileRunner | None = None,
    run_crops: CropRunner | None = None,
    subsample_points: int = SUBSAMPLE_POINTS,
    ray_directions: bool = True,
    keep_free_disk_bytes: int = 0,
    free_disk: FreeDisk = free_disk_bytes,
    **options: Unpack[PairOptions],
) -> ComparisonResult:
    """:func:`~app.core.tiling.compare.compare_tiled` of two files, never holding either whole.

    Parameters
    ----------
    reference_path, scan_path : str or Path
        Point-cloud files with coordinates only (:func:`streamable`).
    budget_bytes, progress, site_calibration, max_crop_points, margin, ray_reach
        As :func:`~app.core.tiling.compare.compare_tiled`.
    work_dir : str or Path
        The tiles' inputs (``crops/``), results (``tiles/``, by the default runner) and the
        per-point outputs (:data:`~app.core.tiling.pair_files.OUTPUT_FILES`) go here; the
        outputs stay (the result's per-point arrays are them, memory-mapped).
    formats : (str or None, str or None)
        Each file's format (None: detected).
    run_tiles : TileRunner, optional
        Who computes the tiles (gets :class:`~app.core.tiling.crops.TileCropFiles` as its
        source); default :func:`compute_tiles_to_files` under ``work_dir/tiles``.
    run_crops : CropRunner, optional
        Who runs each cloud's crop pass (:mod:`app.core.tiling.crop_passes`); default
        :func:`~app.core.tiling.crop_passes.write_crop_passes_here`.
    subsample_points : int
        About how many points of each cloud the stages see (one in ``rows // subsample_points``,
        :func:`~app.core.tiling.pair_files.subsample_offsets`).
    ray_directions : bool
        Crops keep the other sensor's returns by direction too (as
        :func:`~app.core.tiling.compare.compare_tiled`'s): each tile marks the directions it
        needs from the other cloud's points in its box, its crop pass reading that file too.
    keep_free_disk_bytes, free_disk
        As :class:`StreamedLocalisation`: refused (:class:`~app.core.tiling.disk.DiskSpaceError`)
        before a crop is written when the files would not fit the disk.
    **options
        As :func:`app.core.pipeline.compare` (``method``, ``variant``, ``align``,
        ``random_state``, ``params``, ``threads``).

    Returns
    -------
    ComparisonResult
        Per-point arrays in the files' row order, read-only memory maps of the output files.
    """
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    threads = options.get("threads") or available_threads()
    timings: dict[str, float] = {}
    with (
        timed_phase(timings, "stream_survey"),
        ThreadPoolExecutor(max_workers=2 if threads >= 2 else 1) as pool,  # one file each
    ):
        (reference, reference_sub, reference_voxels), (scan, scan_sub, scan_voxels) = pool.map(
            lambda number: survey(
                Path((reference_path, scan_path)[number]), formats[number], subsample_points
            ),
            (0, 1),
        )
    offset = choose_local_origin(np.stack([reference.low, reference.high]))
    clouds = [
        PointCloud(
            (sub - offset).astype(np.float32),
            None,  # type: ignore[arg-type]
            len(sub),
            sampling_points=None if voxels is None else voxels - offset,
        )
        for sub, voxels in ((reference_sub, reference_voxels), (scan_sub, scan_voxels))
    ]
    del reference_sub, scan_sub
    loaded = load_pair(clouds[0], clouds[1], frame_offset=offset, **options)
    step = StreamedLocalisation(
        budget_bytes=budget_bytes,
        max_crop_points=max_crop_points,
        margin=margin,
        ray_reach=ray_reach,
        run_tiles=run_tiles or compute_tiles_to_files(work_dir / "tiles"),
        detection_seed=options.get("random_state", 0),
        reference=reference,
        scan=scan,
        offset=offset,
        work_dir=work_dir,
        ray_directions=ray_directions,
        run_crops=run_crops or write_crop_passes_here,
        keep_free_disk_bytes=keep_free_disk_bytes,
        free_disk=free_disk,
    )
    started_cpu = time.process_time()
    result = run_stages(
        loaded, progress=progress, site_calibration=site_calibration, localise_step=step
    )
    stages_cpu = time.process_time() - started_cpu
    localise_cpu = sum(value for name, value in result.timings.items() if name.endswith("_cpu"))
    timings.update(result.timings)
    timings["stream_other_stages_cpu"] = stages_cpu - localise_cpu  # origins, align, detect
    return dataclasses.replace(
        result,
        timings=timings,
        n_reference=reference.n_points,
        n_scan=scan.n_points,
        **{name: np.load(path, mmap_mode="r") for name, path in step.outputs.items()},
    )
