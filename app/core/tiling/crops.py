"""Each tile's input in files of its own, written in one pass over the points (issue 30).

A fanned-out tile used to read the whole pair (``.npy`` memory maps of both clouds on shared
storage) and cut its crop from it: every worker's crop masks ran over every point, so each
worker's memory held the pages of the whole pair by the end of its tile, and the whole pair was
written to disk once more by the parent.  Here the parent cuts all the crops at once:

- :func:`write_tile_crops` walks each cloud a chunk at a time (:data:`CROP_CHUNK` points) and
  appends, for every tile whose crop holds some of the chunk's points, those points' records
  (coordinates as stored, global index, station) to that tile's file of that cloud, plus the
  tile's share of a trajectory's rays;
- :class:`TileCropFiles` is what a tile reads instead of a
  :class:`~app.core.tiling.tile.TileSource`: its :meth:`~TileCropFiles.crop` returns the same
  :class:`~app.core.tiling.tile.TileCrop` as :meth:`TileSource.crop
  <app.core.tiling.tile.TileSource.crop>` of the whole pair (the same points in the same
  order, the same float64 coordinates and stations), read from the tile's files only, so
  :func:`~app.core.tiling.tile.compute_tile` gives the same result.

The crop test is per point (:func:`~app.core.tiling.tile.crop_mask`), so a point's membership
does not depend on the chunk it is tested in; a chunk is first narrowed to the points within
the tile's ray reach (the only ones :func:`crop_mask` can keep).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from app.core.tiling.plan import TilePlan
from app.core.tiling.rays import (
    box_mask,
    cells_seen,
    expanded_marks,
    kept_by_direction,
    origin_direction_cells,
    own_direction_cells,
)
from app.core.tiling.tile import TileContext, TileCrop, TileSource, _cropped_rays, crop_mask

__all__ = [
    "CROP_CHUNK",
    "MAX_OPEN_TILES",
    "Chunks",
    "TileCropFiles",
    "box_direction_marks",
    "crop_file",
    "record_dtype",
    "tile_direction_marks",
    "write_crop_layout",
    "write_crops_from_chunks",
    "write_side_crops",
    "write_tile_crops",
]

CROP_CHUNK = 1 << 20
"""Points of a cloud handled at a time while the crops are written."""
READ_CHUNK = 1 << 22
"""Records of a crop file read at a time when a tile filters it by direction."""
MARK_PARTS = 16
"""Chunks' direction cells of a box and origin held apart before they are joined (a cell seen
in many chunks is then held once: the marks of a whole cloud stay the size of their union)."""
DIRECTION_CELLS_AT_ONCE = 1 << 22
"""Cell numbers (int64) computed at once for the direction marks: points a step times origins."""
MAX_OPEN_TILES = 128
"""Tiles whose files are open at once (more tiles: one more pass over the points)."""
META_FILE = "crops.json"
SIDES = ("reference", "scan")


def crop_file(directory: Path, tile_index: int, side: str) -> Path:
    """The file of tile ``tile_index``'s crop of cloud ``side`` (``reference`` or ``scan``)."""
    return Path(directory) / f"crop-{tile_index:05d}-{side}.bin"


def _rays_file(directory: Path, tile_index: int, side: str) -> Path:
    return Path(directory) / f"crop-{tile_index:05d}-{side}-rays.npz"


def record_dtype(points: NDArray[np.floating], n_points: int, n_stations: int | None) -> np.dtype:
    """One point of a crop file, packed (no padding): its coordinates as stored (``points``'
    dtype), its index in its cloud (uint32 below 2**32 points, else int64) and, with
    ``n_stations`` not None, its station (int8 up to 127 stations, int16, int32).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        The cloud (only its dtype is read).
    n_points : int
        Points of the cloud.
    n_stations : int or None
        Its stations (None: no station per point).
    """
    index = np.uint32 if n_points <= np.iinfo(np.uint32).max else np.int64
    fields: list[tuple[Any, ...]] = [
        ("point", np.asarray(points[:0]).dtype, (3,)),
        ("index", index),
    ]
    if n_stations is not None:
        station = np.int8 if n_stations <= 127 else np.int16 if n_stations <= 32767 else np.int32
        fields.append(("station", station))
    return np.dtype(fields)


Chunks = Callable[[], Iterator[tuple[int, NDArray[np.floating], NDArray | None]]]
"""A fresh pass over one cloud: ``(first index, points (c, 3), stations (c,) or None)``."""
TileMarks = list[list[NDArray[np.int64]]]
"""Per tile, per origin of a cloud: the direction cells marked by the other cloud's points in
the tile's crop box (:func:`tile_direction_marks`)."""


def tile_direction_marks(
    plan: TilePlan, other: Chunks, origins: NDArray[np.float64], cells: NDArray[np.float64]
) -> TileMarks:
    """Every tile's direction marks of a cloud's origins, in one pass over the other cloud.

    What :func:`~app.core.tiling.rays.crop_masks` computes for one tile from the whole other
    cloud (:func:`~app.core.tiling.rays.direction_marks` of its points in the crop box), for
    all tiles from the other cloud's chunks: the same cells, whatever the chunks.

    Parameters
    ----------
    plan : TilePlan
    other : Chunks
        A pass over the other cloud (its stations are not read).
    origins : ndarray, shape (k, 3)
        The cloud's origins.
    cells : ndarray, shape (k,)
        Their direction cells (:func:`~app.core.tiling.rays.ray_cell_sizes`).

    Returns
    -------
    TileMarks
    """
    boxes = [plan.crop_box(tile_index) for tile_index in range(plan.n_tiles)]
    return box_direction_marks((chunk for _, chunk, _ in other()), boxes, origins, cells)


def box_direction_marks(
    point_chunks: Iterable[NDArray[np.floating]],
    boxes: Sequence[tuple[NDArray[np.float64], NDArray[np.float64]]],
    origins: NDArray[np.float64],
    cells: NDArray[np.float64],
) -> TileMarks:
    """The direction marks of ``origins`` in each xy box ``(low, high)`` from the other
    cloud's points handed out in chunks (each shape (c, 3)): the same cells whatever the
    chunks (:func:`tile_direction_marks` for every tile, a tile's crop file for its own)."""
    found: list[list[list[NDArray[np.int64]]]] = [[[] for _ in origins] for _ in boxes]
    step = max(1 << 16, DIRECTION_CELLS_AT_ONCE // max(1, len(origins)))
    for chunk in point_chunks:
        for start in range(0, len(chunk), step):
            part = chunk[start : start + step]
            inside_boxes = [
                (number, box_mask(part, low, high)) for number, (low, high) in enumerate(boxes)
            ]
            inside_boxes = [(number, inside) for number, inside in inside_boxes if inside.any()]
            if not inside_boxes:
                continue
            # each point's cells once, whatever the boxes (crop boxes overlap by their margins)
            numbers = origin_direction_cells(part, origins, cells)
            for box_number, inside in inside_boxes:
                for number, row in enumerate(numbers):
                    parts = found[box_number][number]
                    parts.append(cells_seen(row[inside]))
                    if len(parts) >= MARK_PARTS:  # the same cells seen again: held once
                        parts[:] = [np.unique(np.concatenate(parts))]
    return [expanded_marks(parts, cells) for parts in found]


def write_tile_crops(
    directory: Path,
    plan: TilePlan,
    source: TileSource,
    context: TileContext,
    *,
    chunk_points: int = CROP_CHUNK,
) -> list[int]:
    """Write every tile's crop of both clouds into ``directory`` (see the module).

    Parameters
    ----------
    directory : Path
        Created if needed; one ``crop-<tile>-<side>.bin`` per tile and cloud, plus
        ``crops.json`` (the record layout) and a tile's rays when the cloud has a trajectory.
    plan : TilePlan
    source : TileSource
        The whole pair (arrays or memory maps), as :func:`~app.core.tiling.tile.compute_tile`
        would read it.
    context : TileContext
    chunk_points : int
        Points of a cloud tested at a time.

    Returns
    -------
    list of int
        Points of both clouds in each tile's crop.
    """

    def chunks_of(points: NDArray, station: NDArray | None) -> Chunks:
        def chunks() -> Iterator[tuple[int, NDArray, NDArray | None]]:
            for start in range(0, len(points), chunk_points):
                stop = start + chunk_points
                yield (
                    start,
                    np.asarray(points[start:stop]),
                    None if station is None else np.asarray(station[start:stop]),
                )

        return chunks

    sides = {
        side: (chunks_of(points, station), origins, _record_dtype_of(points, station), rays)
        for side, (points, station, origins), rays in zip(
            SIDES,
            source._sides(context),
            (source.reference_rays, source.scan_rays),
            strict=True,
        )
    }
    marks = {}  # by direction too, as TileSource.crop does when the context has cells
    for side, other in zip(SIDES, reversed(SIDES), strict=True):
        cells, origins = getattr(context, f"{side}_ray_cells"), sides[side][1]
        if cells is not None and origins is not None:
            marks[side] = tile_direction_marks(plan, sides[other][0], origins, cells)
    return write_crops_from_chunks(directory, plan, context, sides, marks=marks)


def _record_dtype_of(points: NDArray[np.floating], station: NDArray | None) -> np.dtype:
    """:func:`record_dtype` of a cloud held whole (its stations counted from ``station``)."""
    n_stations = None if station is None else int(np.max(station, initial=0)) + 1
    return record_dtype(points, len(points), n_stations)


def write_crops_from_chunks(
    directory: Path,
    plan: TilePlan,
    context: TileContext,
    sides: dict[str, tuple[Chunks, NDArray[np.float64] | None, np.dtype, Any]],
    *,
    threads: int = 1,
    marks: dict[str, TileMarks] | None = None,
) -> list[int]:
    """:func:`write_tile_crops` of clouds handed out in chunks.

    Parameters
    ----------
    directory : Path
    plan : TilePlan
    context : TileContext
    sides : dict
        For ``reference`` and ``scan``: ``(chunks, origins, record dtype, rays)``: a
        :data:`Chunks` pass (called once per :data:`MAX_OPEN_TILES` tiles), the origins in
        the context, :func:`record_dtype` of the points and stations, the trajectory's
        ``(returns, bounds)`` or None.
    threads : int
        With two or more, the clouds are written concurrently (numpy releases the GIL: a
        parent alone on the machine uses both cores while no tile runs yet).
    marks : dict, optional
        For a cloud whose context has direction cells (``<side>_ray_cells``): its
        :func:`tile_direction_marks`, so that its crops keep the other sensor's returns by
        direction too (:func:`~app.core.tiling.rays.crop_masks`); else the top view only (a
        streamed crop pass without the other cloud's file,
        :mod:`app.core.tiling.crop_passes`: kept by direction as each tile reads them).

    Returns
    -------
    list of int
        Points of both clouds in each tile's crop (as written).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)

    def write(side: str) -> NDArray[np.int64]:
        chunks, origins, dtype, rays = sides[side]
        cells = getattr(context, f"{side}_ray_cells")
        side_marks = None if marks is None or cells is None else marks.get(side)
        directions = None if side_marks is None else (cells, side_marks)
        sizes = write_side_crops(directory, plan, context, side, chunks, origins, dtype, directions)
        if rays is not None:
            for tile_index in range(plan.n_tiles):
                records = np.fromfile(crop_file(directory, tile_index, side), dtype=dtype)
                index = np.asarray(records["index"], dtype=np.int64)
                returns, bounds = _cropped_rays(rays, index)
                np.savez(_rays_file(directory, tile_index, side), returns=returns, bounds=bounds)
        return sizes

    # the clouds' passes are independent (their own files): one thread each when given two
    with ThreadPoolExecutor(max_workers=max(1, min(threads, len(sides)))) as pool:
        crop_sizes = sum(pool.map(write, list(sides)), np.zeros(plan.n_tiles, dtype=np.int64))
    layout = {
        side: {"dtype": dtype.descr, "rays": rays is not None, "directions": False}
        for side, (_, _, dtype, rays) in sides.items()
    }
    write_crop_layout(directory, layout)
    return [int(size) for size in crop_sizes]


def write_side_crops(
    directory: Path,
    plan: TilePlan,
    context: TileContext,
    side: str,
    chunks: Chunks,
    origins: NDArray[np.float64] | None,
    dtype: np.dtype,
    directions: tuple[NDArray[np.float64], TileMarks] | None = None,
) -> NDArray[np.int64]:
    """Every tile's crop file of one cloud, one pass over ``chunks`` per
    :data:`MAX_OPEN_TILES` tiles; the crops' point counts, shape (n_tiles,).

    Parameters
    ----------
    directory : Path
        Where the crop files go (:func:`crop_file`); it must exist.
    plan : TilePlan
    context : TileContext
    side : str
        ``reference`` or ``scan``.
    chunks : Chunks
        A pass over the cloud.
    origins : ndarray, shape (k, 3), or None
        The cloud's origins in the context.
    dtype : numpy.dtype
        :func:`record_dtype` of the points and stations.
    directions : (ndarray, TileMarks), optional
        The cloud's direction cells and :func:`tile_direction_marks`: kept by direction too;
        else in the top view only.
    """
    sizes = np.zeros(plan.n_tiles, dtype=np.int64)
    for first in range(0, plan.n_tiles, MAX_OPEN_TILES):
        tiles = range(first, min(plan.n_tiles, first + MAX_OPEN_TILES))
        sizes[first : tiles.stop] = _write_side(
            directory, plan, tiles, side, chunks, origins, context, dtype, directions
        )
    return sizes


def write_crop_layout(directory: Path, layout: dict[str, dict[str, Any]]) -> None:
    """Write the crops' record layout (``crops.json``, read by :class:`TileCropFiles`):
    per cloud, ``dtype`` (its ``descr``), ``rays`` and ``directions`` (see
    :func:`write_crops_from_chunks`)."""
    (Path(directory) / META_FILE).write_text(json.dumps(layout))


def _write_side(
    directory: Path,
    plan: TilePlan,
    tiles: range,
    side: str,
    chunks: Chunks,
    origins: NDArray[np.float64] | None,
    context: TileContext,
    dtype: np.dtype,
    directions: tuple[NDArray[np.float64], TileMarks] | None = None,
) -> NDArray[np.int64]:
    """One pass over one cloud writing the crops of ``tiles``; their point counts (with
    ``directions``, the cloud's cells and :func:`tile_direction_marks`: by direction too)."""
    counts = np.zeros(len(tiles), dtype=np.int64)
    boxes = [plan.crop_box(tile_index) for tile_index in tiles]
    reach = context.ray_reach if origins is not None and len(origins) else 0.0
    with ExitStack() as stack:
        files: list[IO[bytes]] = [
            stack.enter_context(open(crop_file(directory, tile_index, side), "wb"))
            for tile_index in tiles
        ]
        for start, chunk, chunk_station in chunks():
            # each point's direction from its station once, whatever the tiles it reaches
            point_cells = (
                None
                if directions is None or origins is None
                else own_direction_cells(chunk, chunk_station, origins, directions[0])
            )
            for number, (low, high) in enumerate(boxes):
                # the box test of crop_mask itself (float32 bounds rounded outward), widened
                near = np.flatnonzero(box_mask(chunk, low - reach, high + reach))
                if not len(near):
                    continue
                near_points = chunk[near]  # gathered once, the kept ones taken from it
                near_station = None if chunk_station is None else chunk_station[near]
                in_crop = crop_mask(
                    near_points,
                    near_station,
                    origins,
                    low,
                    high,
                    context.ray_reach,
                    cells=None if directions is None else directions[0],
                    marks=None if directions is None else directions[1][tiles[number]],
                    point_cells=None if point_cells is None else point_cells[near],
                )
                kept = near[in_crop]
                if not len(kept):
                    continue
                records = np.empty(len(kept), dtype=dtype)
                records["point"] = near_points[in_crop]
                records["index"] = start + kept
                if near_station is not None:
                    records["station"] = near_station[in_crop]
                files[number].write(records.view(np.uint8))  # its bytes, not a copy
                counts[number] += len(kept)
    return counts


class TileCropFiles:
    """The tiles' crops written by :func:`write_tile_crops`, read one tile at a time.

    Parameters
    ----------
    directory : Path
        Where :func:`write_tile_crops` wrote them.
    """

    def __init__(self, directory: Path) -> None:
        self.directory = Path(directory)
        layout = json.loads((self.directory / META_FILE).read_text())
        self._dtypes = {
            side: np.dtype([tuple(field) for field in layout[side]["dtype"]]) for side in SIDES
        }
        self._rays = {side: bool(layout[side]["rays"]) for side in SIDES}
        self._directions = {side: bool(layout[side].get("directions")) for side in SIDES}

    def written_points(self, n_tiles: int) -> NDArray[np.int64] | None:
        """Records of both clouds in each tile's crop files, shape (n_tiles,): the points each
        tile holds; None when a cloud's tiles keep the other sensor's returns by direction as
        they read (its files hold more than its tiles do)."""
        if any(self._directions.values()):
            return None
        counts = np.zeros(n_tiles, dtype=np.int64)
        for tile_index in range(n_tiles):
            for side in SIDES:
                path = crop_file(self.directory, tile_index, side)
                if path.exists():
                    counts[tile_index] += path.stat().st_size // self._dtypes[side].itemsize
        return counts

    def _records(self, tile_index: int, side: str) -> Iterator[NDArray]:
        """A tile's crop file of one cloud, :data:`READ_CHUNK` records at a time."""
        with open(crop_file(self.directory, tile_index, side), "rb") as file:
            while len(records := np.fromfile(file, self._dtypes[side], count=READ_CHUNK)):
                yield records

    def _marks(
        self, plan: TilePlan, tile_index: int, context: TileContext, side: str
    ) -> list[NDArray[np.int64]]:
        """The direction marks of ``side``'s origins for this tile, from the other cloud's
        points in its crop box (:func:`tile_direction_marks` of this tile)."""
        other_records = self._records(tile_index, SIDES[1 - SIDES.index(side)])
        return box_direction_marks(
            (records["point"] for records in other_records),
            [plan.crop_box(tile_index)],
            getattr(context, f"{side}_origins"),
            getattr(context, f"{side}_ray_cells"),
        )[0]

    def _filtered(
        self, plan: TilePlan, tile_index: int, context: TileContext, side: str
    ) -> NDArray:
        """A crop file written in the top view only, kept by direction as it is read."""
        marks = self._marks(plan, tile_index, context, side)
        low, high = plan.crop_box(tile_index)
        origins = getattr(context, f"{side}_origins")
        cells = getattr(context, f"{side}_ray_cells")
        has_station = "station" in self._dtypes[side].names
        kept = [
            records[
                kept_by_direction(
                    records["point"],
                    records["station"] if has_station else None,
                    origins,
                    low,
                    high,
                    cells,
                    marks,
                )
            ]
            for records in self._records(tile_index, side)
        ]
        return np.concatenate(kept) if kept else np.zeros(0, self._dtypes[side])

    def _side(
        self, plan: TilePlan, tile_index: int, context: TileContext, side: str
    ) -> tuple[
        NDArray[np.int64],
        NDArray[np.float64],
        NDArray[np.int64] | None,
        tuple[NDArray[np.int64], NDArray[np.int64]] | None,
    ]:
        """One cloud's crop of a tile: indices, float64 points, stations, rays."""
        dtype = self._dtypes[side]
        if self._directions[side]:
            records = self._filtered(plan, tile_index, context, side)
        else:
            records = np.fromfile(crop_file(self.directory, tile_index, side), dtype=dtype)
        station = (
            np.asarray(records["station"], dtype=np.int64) if "station" in dtype.names else None
        )
        rays = None
        if self._rays[side]:
            with np.load(_rays_file(self.directory, tile_index, side)) as data:
                rays = (data["returns"], data["bounds"])
        return (
            np.asarray(records["index"], dtype=np.int64),
            np.asarray(records["point"], dtype=np.float64),
            station,
            rays,
        )

    def crop(self, plan: TilePlan, tile_index: int, context: TileContext) -> TileCrop:
        """Tile ``tile_index``'s crop, as :meth:`TileSource.crop` of the whole pair gives it."""
        reference = self._side(plan, tile_index, context, "reference")
        scan = self._side(plan, tile_index, context, "scan")
        return TileCrop(
            reference_index=reference[0],
            scan_index=scan[0],
            reference_points=reference[1],
            scan_points=scan[1],
            reference_station=reference[2],
            scan_station=scan[2],
            reference_rays=reference[3],
            scan_rays=scan[3],
        )
