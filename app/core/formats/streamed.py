"""Large point-cloud files read a block at a time, and as float32 coordinates near an offset.

:func:`read_point_cloud` builds a float64 :class:`~app.core.cloud.PointCloud` (what the
comparison needs). A view of a 100M-point job needs neither float64 nor every point at once:

- :func:`open_point_blocks` hands out a file's coordinates in file order, a block of
  ``block_points`` rows at a time, so memory stays at one block whatever the file's size:

  - ``.npy`` and binary PLY: their bodies are memory-mapped and each block is read from the
    file with ``pread`` (:class:`~app.core.blocks.FileRows`), so the map's pages never all
    become resident;
  - LAS/LAZ (COPC included): laspy's chunk iterator (lazrs decodes one chunk at a time);
  - E57: scan by scan, a chunk of a scan at a time (libE57Format's reader in pieces);
  - an ascii PLY is decoded whole (its coordinates only); any other format (text, PCD, ROS
    bags, ``.npz``) is read whole by
    :func:`read_point_cloud` first, then handed out in blocks.

- :func:`read_points_float32` gathers those blocks into one (n, 3) float32 array of the finite
  points minus an offset (12 bytes a point, half a float64 copy): subtracting a rounded offset
  near the cloud first keeps georeferenced coordinates (x ~ 5e5 m) to float32's resolution at
  the cloud's own extent (under a millimetre for a 10 km survey).

Rows are file rows (``source_index`` of the cloud :func:`read_point_cloud` returns, dropped
non-finite rows included), the rows a job's labels are stored in.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from app.core.blocks import coordinate_blocks
from app.core.cloud import choose_local_origin
from app.core.errors import PointCloudError
from app.core.formats import BagOptions, detect_format, read_point_cloud
from app.core.formats._common import Source, file_rows_of, open_source
from app.core.formats.e57 import declared_point_count, scan_blocks
from app.core.formats.las import declared_las_points, las_point_blocks
from app.core.formats.npy import read_npy
from app.core.formats.ply import read_ply
from app.core.threads import available_threads

BLOCK_POINTS = 1 << 18
"""Rows per block by default (6 MB of float64 coordinates)."""

DEFAULT_MAX_POINTS = 1_000_000_000
"""Largest file accepted by default (rows a header declares)."""


@dataclass
class PointBlocks:
    """A file's coordinates, a block at a time.

    Attributes
    ----------
    n_rows : int
        Rows of the file (for E57, the points its scan headers declare: an upper bound, since
        points flagged invalid are skipped).
    blocks : iterator of (int, ndarray)
        ``(first row, points)`` in file order; ``points`` shape (k, 3) float64, maybe with
        non-finite rows, a new array per block.
    """

    n_rows: int
    blocks: Iterator[tuple[int, NDArray[np.float64]]]


@contextmanager
def open_point_blocks(
    path: str | Path,
    format: str | None = None,
    *,
    max_points: int | None = DEFAULT_MAX_POINTS,
    block_points: int = BLOCK_POINTS,
    bag_options: BagOptions | None = None,
) -> Iterator[PointBlocks]:
    """Open a point-cloud file to read its coordinates a block at a time.

    Parameters
    ----------
    path : str or Path
    format : str, optional
        As for :func:`read_point_cloud`; default: detected from the name and content.
    max_points : int or None
        Refuse files whose header declares more rows.
    block_points : int
        Rows per block (E57: a chunk of one scan, :data:`~app.core.formats.e57.SCAN_CHUNK_POINTS`
        at most).
    bag_options : BagOptions, optional
        For a ROS bag, as for :func:`read_point_cloud`.

    Raises
    ------
    PointCloudError, UnsupportedFormatError
        As :func:`read_point_cloud` (the message starts with the file name).
    """
    path = Path(path)
    with open_source(path) as source:
        chosen = (format or "").lower().lstrip(".") or detect_format(path.name, source.head(4096))
        try:
            blocks = _blocks_of(path, source, chosen, max_points, block_points, bag_options)
        except PointCloudError as exc:
            raise PointCloudError(f"{path.name}: {exc}") from exc
        yield blocks


HEADER_COUNTED_FORMATS = ("npy", "ply", "las", "laz", "e57")
"""Formats whose header declares the point count (:func:`declared_rows`)."""


def declared_rows(path: str | Path, format: str | None = None) -> int | None:
    """Rows a file's header declares, read without decoding its points; None for a format
    read whole to count them (text, PCD, ROS bags, ``.npz``) or an unreadable file (the
    reader then says what is wrong).

    Parameters
    ----------
    path : str or Path
    format : str, optional
        As for :func:`read_point_cloud`; default: detected from the name and content.
    """
    path = Path(path)
    try:
        with open_source(path) as source:
            chosen = (format or "").lower().lstrip(".") or detect_format(
                path.name, source.head(4096)
            )
            if chosen not in HEADER_COUNTED_FORMATS:
                return None
            if chosen == "npy":
                return len(read_npy(source, None).points)
            if chosen == "ply":
                return len(read_ply(source, None, with_attributes=False).points)
            if chosen in ("las", "laz"):
                return declared_las_points(source)
            return declared_point_count(path)
    except (OSError, ValueError):  # PointCloudError and UnsupportedFormatError included
        return None


def _blocks_of(
    path: Path,
    source: Source,
    chosen: str,
    max_points: int | None,
    block_points: int,
    bag_options: BagOptions | None,
) -> PointBlocks:
    """The :class:`PointBlocks` of an opened file in format ``chosen``."""
    if chosen == "npy":
        return _view_blocks(read_npy(source, max_points).points, source, block_points)
    if chosen == "ply":  # binary: a view of the map; ascii: decoded whole (numpy.loadtxt)
        raw = read_ply(source, max_points, with_attributes=False)
        return _view_blocks(raw.points, source, block_points)
    if chosen in ("las", "laz"):
        n_rows = declared_las_points(source)
        # lazrs's decoder threads do not hold the GIL (as read_point_cloud's default)
        blocks = las_point_blocks(source, max_points, block_points, threads=available_threads())
        return PointBlocks(n_rows, blocks)
    if chosen == "e57":
        return PointBlocks(declared_point_count(path), _e57_blocks(path, max_points))
    cloud = read_point_cloud(path, chosen, max_points=max_points, bag_options=bag_options)
    rows = cloud.to_source_order(cloud.points, np.nan)
    return PointBlocks(len(rows), _array_blocks(rows, block_points))


def _view_blocks(points: NDArray, source: Source, block_points: int) -> PointBlocks:
    """Blocks of an (n, 3) view of the source's memory map, read with ``pread`` when it can."""
    file_rows = file_rows_of(points, source)

    def blocks() -> Iterator[tuple[int, NDArray[np.float64]]]:
        numbers = itertools.count()
        for start, block in coordinate_blocks(
            points, numbers, file_rows, contiguous=True, block_points=block_points
        ):
            with np.errstate(invalid="ignore"):  # signalling NaNs: non-finite rows like others
                yield start, block.astype(np.float64)

    return PointBlocks(len(points), blocks())


def _array_blocks(
    points: NDArray[np.float64], block_points: int
) -> Iterator[tuple[int, NDArray[np.float64]]]:
    """Blocks of an array already in memory (copies, as the other formats give)."""
    for start in range(0, len(points), block_points):
        yield start, points[start : start + block_points].copy()


def _e57_blocks(path: Path, max_points: int | None) -> Iterator[tuple[int, NDArray[np.float64]]]:
    """One block per E57 scan."""
    start = 0
    for points, _origin in scan_blocks(path, max_points):
        yield start, points
        start += len(points)


@dataclass(frozen=True, eq=False)
class Float32Points:
    """A cloud's finite points as float32 relative to an offset.

    Attributes
    ----------
    points : ndarray, shape (n, 3), float32
        Finite points minus ``offset``, in file order.
    offset : ndarray, shape (3,), float64
        Add it back for file coordinates.
    source_rows : ndarray, shape (n,), int64, or None
        File row of each point; None when no row was dropped (row i is point i).
    n_source : int
        Rows of the file, non-finite ones included.
    """

    points: NDArray[np.float32]
    offset: NDArray[np.float64]
    source_rows: NDArray[np.int64] | None
    n_source: int

    def file_coordinates(self) -> NDArray[np.float64]:
        """The points in the file's coordinates, shape (n, 3) float64 (a new array)."""
        return self.points.astype(np.float64) + self.offset


def read_points_float32(
    path: str | Path,
    format: str | None = None,
    *,
    offset: NDArray | None = None,
    max_points: int | None = DEFAULT_MAX_POINTS,
    block_points: int = BLOCK_POINTS,
) -> Float32Points:
    """A file's finite points as one float32 array, read a block at a time.

    Memory: the (n, 3) float32 result plus one block (see :func:`open_point_blocks`); no
    float64 copy of the cloud is made.

    Parameters
    ----------
    path, format, max_points, block_points
        As for :func:`open_point_blocks`.
    offset : array_like, shape (3,), optional
        Subtracted from every point; default :func:`~app.core.cloud.choose_local_origin` of the
        first block (zero near the origin, else a rounded point near the data).

    Raises
    ------
    PointCloudError, UnsupportedFormatError
        As :func:`read_point_cloud`; also a file without any finite point.
    """
    chosen_offset = None if offset is None else np.asarray(offset, np.float64).reshape(3)
    with open_point_blocks(
        path, format, max_points=max_points, block_points=block_points
    ) as opened:
        points = np.empty((opened.n_rows, 3), dtype=np.float32)
        kept_rows: list[NDArray[np.int64]] | None = None
        n_kept = 0
        n_source = 0
        for start, block in opened.blocks:
            finite = np.isfinite(block).all(axis=1)
            all_finite = bool(finite.all())
            if not all_finite:
                if kept_rows is None:
                    kept_rows = [np.arange(n_kept, dtype=np.int64)]
                kept_rows.append(start + np.flatnonzero(finite))
                block = block[finite]
            elif kept_rows is not None:
                kept_rows.append(np.arange(start, start + len(block), dtype=np.int64))
            if chosen_offset is None and len(block):
                chosen_offset = choose_local_origin(block)
            if len(block):
                block -= chosen_offset
                points[n_kept : n_kept + len(block)] = block
            n_kept += len(block)
            n_source = start + len(finite)
    if n_kept == 0:
        raise PointCloudError(f"{Path(path).name}: none of its points has finite coordinates")
    if n_kept < len(points):
        points.resize((n_kept, 3), refcheck=False)  # shrinks in place, no copy
    return Float32Points(
        points=points,
        offset=chosen_offset if chosen_offset is not None else np.zeros(3),
        source_rows=None if kept_rows is None else np.concatenate(kept_rows),
        n_source=n_source,
    )
