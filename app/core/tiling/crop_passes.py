"""A streamed parent's crops pass, one unit of work per cloud, runnable in any process (issue 30).

A streamed tiled comparison (:mod:`app.core.tiling.streamed`) writes every tile's crop of both
clouds from the files before any tile runs (:mod:`app.core.tiling.crops`).  Each cloud's pass
reads its own file and writes its own crop files, so the two passes are independent:
:class:`CropPass` holds what one needs besides the plan and the context (the file, the local
frame's origin, the scan's alignment, the stations' origins and ring contrasts), and saves to
and loads from a small file so that another worker can run it (:mod:`app.jobs.crop_passes`
hands the passes to the queue); :func:`write_crop_pass` runs it.  A pass computes the same
points, stations and records in whichever process runs it.

Who runs the passes is a :data:`CropRunner`: :func:`write_crop_passes_here` (the default) runs
them in this process, one thread each when given two.  Whoever ran them, the parent then writes
the layout (:func:`write_pass_layout`).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from app.core.comparison.align import transformed
from app.core.localise.station_assignment import StationGrid, best_stations
from app.core.tiling.crops import (
    record_dtype,
    tile_direction_marks,
    write_crop_layout,
    write_side_crops,
)
from app.core.tiling.pair_files import finite_chunks
from app.core.tiling.plan import TilePlan
from app.core.tiling.tile import TileContext

__all__ = [
    "CropPass",
    "CropRunner",
    "write_crop_pass",
    "write_crop_passes_here",
    "write_pass_layout",
]

ProgressCallback = Callable[[str, float], None]


@dataclass(frozen=True)
class CropPass:
    """One cloud's pass over its file, writing its share of every tile's crop.

    Attributes
    ----------
    side : str
        ``reference`` or ``scan``.
    path : Path
        The cloud's file (coordinates only).
    format : str or None
        Its format (None: detected).
    offset : ndarray, shape (3,)
        The local frame's origin (subtracted from the file's coordinates).
    transform : ndarray, shape (4, 4), or None
        The scan's alignment (applied to the float32 local points, chunk by chunk).
    station_origins : ndarray, shape (k, 3), or None
        With two stations or more: their origins, each point assigned its station.
    contrasts : ndarray, shape (k, n_bins), or None
        The stations' ring and column contrasts from the subsample, one packed row a station
        (:func:`~app.core.localise.station_assignment.station_contrasts`,
        :meth:`~app.core.localise.station_assignment.StationGrid.packed`).
    """

    side: str
    path: Path
    format: str | None
    offset: NDArray[np.float64]
    transform: NDArray[np.float64] | None
    station_origins: NDArray[np.float64] | None
    contrasts: NDArray[np.float64] | None
    n_points: int = 0
    other_path: Path | None = None
    other_format: str | None = None
    other_transform: NDArray[np.float64] | None = None

    @property
    def dtype(self) -> np.dtype:
        """The crop files' records (:func:`~app.core.tiling.crops.record_dtype`)."""
        n_stations = None if self.station_origins is None else len(self.station_origins)
        return record_dtype(np.zeros((0, 3), np.float32), self.n_points, n_stations)

    def chunks(self) -> Iterator[tuple[int, NDArray[np.float32], NDArray | None]]:
        """A pass over the file: ``(first index, float32 local (aligned) points (c, 3),
        stations (c,) or None)``, the file's finite points in the streamed chunks."""
        for first, local in _local_chunks(self.path, self.format, self.offset, self.transform):
            station = None
            if self.station_origins is not None and self.contrasts is not None:
                grids = [StationGrid.of_packed(row) for row in self.contrasts]
                station = best_stations(local, self.station_origins, grids)
            yield first, local, station

    def other_chunks(self) -> Iterator[tuple[int, NDArray[np.float32], None]]:
        """A pass over the other cloud's file (:attr:`other_path`): its float32 local (aligned)
        points as its own pass reads them, without stations."""
        if self.other_path is None:
            return
        for first, local in _local_chunks(
            self.other_path, self.other_format, self.offset, self.other_transform
        ):
            yield first, local, None

    def save(self, path: str | Path) -> None:
        """Write the pass as a small ``.npz`` (the files' paths as given)."""
        arrays = {
            name: value
            for name, value in (
                ("transform", self.transform),
                ("station_origins", self.station_origins),
                ("contrasts", self.contrasts),
                ("other_transform", self.other_transform),
            )
            if value is not None
        }
        meta = {
            "side": self.side,
            "path": str(self.path),
            "format": self.format,
            "n_points": int(self.n_points),
            "other_path": None if self.other_path is None else str(self.other_path),
            "other_format": self.other_format,
        }
        with open(path, "wb") as file:
            np.savez(file, meta=np.array(json.dumps(meta)), offset=self.offset, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> CropPass:
        """Read a pass written by :meth:`save`."""
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            return cls(
                side=str(meta["side"]),
                path=Path(meta["path"]),
                format=meta["format"],
                offset=data["offset"],
                transform=data.get("transform", None),
                station_origins=data.get("station_origins", None),
                contrasts=data.get("contrasts", None),
                n_points=int(meta.get("n_points", 0)),
                other_path=None if meta.get("other_path") is None else Path(meta["other_path"]),
                other_format=meta.get("other_format"),
                other_transform=data.get("other_transform", None),
            )

    def filters_by_direction(self, context: TileContext) -> bool:
        """Whether its crops keep the other sensor's returns by direction as they are written
        (its context has direction cells and origins, and it reads the other cloud's file)."""
        return self.other_path is not None and _has_directions(context, self.side)


def _has_directions(context: TileContext, side: str) -> bool:
    return (
        getattr(context, f"{side}_ray_cells") is not None
        and getattr(context, f"{side}_origins") is not None
    )


def _local_chunks(
    path: Path, format: str | None, offset: NDArray[np.float64], transform: NDArray | None
) -> Iterator[tuple[int, NDArray[np.float32]]]:
    """A file's finite points in the streamed chunks, float32 in the local frame, moved by
    ``transform`` when given: ``(first index, points (c, 3))``."""
    for first, points in finite_chunks(path, format):
        local = (points - offset).astype(np.float32)
        if transform is not None:
            local = transformed(local, transform)
        yield first, local


CropRunner = Callable[
    [Path, TilePlan, TileContext, Sequence[CropPass], int, ProgressCallback], None
]
"""Runs every pass, writing the crop files into the directory given:
``(directory, plan, context, passes, threads, report)``."""


def write_crop_pass(
    directory: Path, plan: TilePlan, context: TileContext, crop_pass: CropPass
) -> NDArray[np.int64]:
    """Write one cloud's crop file of every tile into ``directory`` (created if needed); the
    crops' point counts, shape (n_tiles,).

    When the pass :meth:`~CropPass.filters_by_direction`, it first reads the other cloud's
    file for every tile's direction marks of this cloud's origins
    (:func:`~app.core.tiling.crops.tile_direction_marks`) and writes only the returns a tile
    reads (:func:`~app.core.tiling.rays.crop_mask` with the marks); else in the top view (each
    tile then keeps the other sensor's returns by direction as it reads,
    :class:`~app.core.tiling.crops.TileCropFiles`).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    origins = getattr(context, f"{crop_pass.side}_origins")
    directions = None
    if crop_pass.filters_by_direction(context):
        cells = getattr(context, f"{crop_pass.side}_ray_cells")
        directions = (cells, tile_direction_marks(plan, crop_pass.other_chunks, origins, cells))
    return write_side_crops(
        directory,
        plan,
        context,
        crop_pass.side,
        crop_pass.chunks,
        origins,
        crop_pass.dtype,
        directions,
    )


def write_crop_passes_here(
    directory: Path,
    plan: TilePlan,
    context: TileContext,
    passes: Sequence[CropPass],
    threads: int,
    report: ProgressCallback,
) -> None:
    """The default :data:`CropRunner`: every pass in this process, concurrently with two
    threads or more (numpy releases the GIL; each pass writes its own files)."""
    with ThreadPoolExecutor(max_workers=max(1, min(threads, len(passes)))) as pool:
        for _ in pool.map(lambda one: write_crop_pass(directory, plan, context, one), passes):
            pass  # each pass's errors raised here


def write_pass_layout(directory: Path, context: TileContext, passes: Sequence[CropPass]) -> None:
    """The crops' layout once every pass is written: each cloud's records, no rays, and whether
    its tiles keep the other sensor's returns by direction as they read (its context has
    direction cells and origins, and its pass wrote them in the top view)."""
    write_crop_layout(
        directory,
        {
            crop_pass.side: {
                "dtype": crop_pass.dtype.descr,
                "rays": False,
                "directions": _has_directions(context, crop_pass.side)
                and not crop_pass.filters_by_direction(context),
            }
            for crop_pass in passes
        },
    )
