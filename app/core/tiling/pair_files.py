"""The files of a streamed tiled comparison (:mod:`app.core.tiling.streamed`): the input
clouds read a chunk at a time, the tiles' results read one at a time, and the per-point outputs
written range by range and copied into a job's result files.

Nothing here holds a per-point array of a whole cloud: the inputs are read in windows of
:data:`CHUNK` finite points (:func:`~app.core.formats.streamed.open_point_blocks`: binary PLY
and ``.npy`` read with ``pread``), the outputs are ``.npy`` files written :data:`OUTPUT_RANGE`
points at a time through a mapping opened and closed per range, and copied into ``.npz``
archives by reads (:func:`write_labels_npz`, :func:`write_details_npz`).  The module imports
numpy and the readers only, so the API and the CLI can check files (:func:`coordinates_only`)
and write results without loading the comparison.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from app.core.formats.station_fields import has_station_fields
from app.core.formats.streamed import open_point_blocks
from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED, LABEL_UNOBSERVED

if TYPE_CHECKING:
    from app.core.pipeline import ComparisonResult
    from app.core.tiling.tile import TileResult

__all__ = [
    "CHUNK",
    "OUTPUT_FILES",
    "OUTPUT_RANGE",
    "StoredTileResults",
    "StreamedCloud",
    "coordinates_only",
    "finite_chunks",
    "side_arrays",
    "streamed_outputs",
    "subsample_offsets",
    "survey",
    "write_details_npz",
    "write_labels_npz",
    "write_outputs",
]

SAMPLING_VOXEL_POINTS = 90_000
"""Points of a subsampled file kept as whole voxels at full density (the lidar sampling test
examines up to 100,000: :data:`app.core.origins.sampling.SAMPLING_MAX_POINTS`)."""
CHUNK = 1 << 20
"""Finite points of a file per step (the lean conversion's and the transform's own step, so
the float32 points and the aligned scan are those of the lean tiled comparison bit for bit)."""
OUTPUT_RANGE = 1 << 24
"""Points of a cloud merged at a time (9 bytes a point of buffers)."""
OUTPUT_FILES = {
    "label": (np.int8, LABEL_UNOBSERVED),
    "distance": (np.float32, np.nan),
    "region": (np.int32, -1),
}
"""Per-point outputs of each cloud: ``<side>_<name>.npy``, dtype and the value of a point no
tile labelled (a non-finite row)."""


@dataclass(frozen=True)
class StreamedCloud:
    """One file of a streamed comparison, as its first pass found it.

    Attributes
    ----------
    path : Path
    format : str or None
    n_rows : int
        Rows of the file.
    dropped : ndarray, shape (d,), int64
        Rows with a non-finite coordinate (no point of the comparison), sorted.
    step : int
        The subsample keeps about one finite point in ``step`` (:func:`subsample_offsets`).
    low, high : ndarray, shape (3,)
        The finite points' extremes (file frame).
    """

    path: Path
    format: str | None
    n_rows: int
    dropped: NDArray[np.int64]
    step: int
    low: NDArray[np.float64]
    high: NDArray[np.float64]

    @property
    def n_points(self) -> int:
        """Finite points (the comparison's points)."""
        return self.n_rows - len(self.dropped)

    def chunks(self) -> Iterator[tuple[int, NDArray[np.float64]]]:
        """``(first finite index, finite points (c, 3) float64)``, :data:`CHUNK` at a time."""
        yield from finite_chunks(self.path, self.format)

    def file_rows(self, first: int, count: int) -> NDArray[np.int64]:
        """The file rows of finite points ``first .. first + count - 1``."""
        finite = np.arange(first, first + count, dtype=np.int64)
        if not len(self.dropped):
            return finite
        before = self.dropped - np.arange(len(self.dropped))  # finite points before each
        return finite + np.searchsorted(before, finite, side="right")


def finite_chunks(path: Path, format: str | None) -> Iterator[tuple[int, NDArray[np.float64]]]:
    """A file's finite points in windows of exactly :data:`CHUNK` (the last shorter)."""
    pending: list[NDArray[np.float64]] = []
    count = first = 0
    with open_point_blocks(path, format, block_points=CHUNK) as blocks:
        for _, block in blocks.blocks:
            finite = np.isfinite(block).all(axis=1)
            pending.append(block if finite.all() else block[finite])
            count += int(finite.sum())
            while count >= CHUNK:
                joined = np.concatenate(pending) if len(pending) > 1 else pending[0]
                yield first, joined[:CHUNK]
                first += CHUNK
                pending, count = [joined[CHUNK:]], len(joined) - CHUNK
    if count:
        yield first, np.concatenate(pending)


SUBSAMPLE_SALT = np.uint64(0x9E3779B97F4A7C15)
"""Mixed into each point's index before the hash of :func:`subsample_offsets` (any odd
constant: the golden-ratio increment of splitmix64)."""


def subsample_offsets(first: int, count: int, step: int) -> NDArray[np.int64]:
    """Which of the finite points ``first .. first + count - 1`` are in a streamed subsample:
    their offsets from ``first``, shape (m,), each point kept when a hash of its index
    (splitmix64's finaliser) is a multiple of ``step``, about one in ``step``.

    Not every ``step``-th point: a file in scan order (a terrestrial station's rings or
    columns, one after the other) would be sampled in step with its own lattice, so that no
    two points of one column were kept (a 100M-point survey's stations were not recovered
    from such a subsample, issue 30).  The hash keeps points independently of the file's
    order, as a random draw would, and the same points whoever asks (the first pass and the
    outputs' writer)."""
    if step <= 1:
        return np.arange(count, dtype=np.int64)
    mixed = np.arange(first, first + count, dtype=np.uint64) + SUBSAMPLE_SALT
    mixed = (mixed ^ (mixed >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    mixed = (mixed ^ (mixed >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    mixed ^= mixed >> np.uint64(31)
    return np.flatnonzero(mixed % np.uint64(step) == 0)


def survey(
    path: Path, format: str | None, most: int
) -> tuple[StreamedCloud, NDArray[np.float64], NDArray[np.float64] | None]:
    """A file's first pass: its :class:`StreamedCloud`, its subsample (float64, file frame,
    about one finite point in ``step = max(1, rows // most)``: :func:`subsample_offsets`) and,
    when that is not the whole cloud, whole voxels of it at full density for the lidar sampling
    test (:class:`~app.core.origins.voxels.WholeVoxelSample`, file frame; else None)."""
    from app.core.origins.voxels import WholeVoxelSample  # here: the CLI's checks need no scipy

    dropped, kept = [], []
    low, high = np.full(3, np.inf), np.full(3, -np.inf)
    n_rows, step = 0, 1
    with open_point_blocks(path, format, block_points=CHUNK) as blocks:
        step = max(1, blocks.n_rows // most)
        voxels = WholeVoxelSample(blocks.n_rows, SAMPLING_VOXEL_POINTS) if step > 1 else None
        finite_before = 0
        for first_row, block in blocks.blocks:
            finite = np.isfinite(block).all(axis=1)
            dropped.append(first_row + np.flatnonzero(~finite))
            points = block[finite]
            if len(points):
                low, high = (
                    np.minimum(low, points.min(axis=0)),
                    np.maximum(high, points.max(axis=0)),
                )
                if voxels is not None:
                    voxels.add(points)
            kept.append(points[subsample_offsets(finite_before, len(points), step)])
            finite_before += len(points)
            n_rows = first_row + len(block)
    cloud = StreamedCloud(
        Path(path),
        format,
        n_rows,
        np.concatenate(dropped).astype(np.int64) if dropped else np.zeros(0, np.int64),
        step,
        low,
        high,
    )
    subsample = np.concatenate(kept) if kept else np.zeros((0, 3))
    return cloud, subsample, None if voxels is None else voxels.points()


def coordinates_only(path: str | Path, format: str | None = None) -> bool:
    """Whether a file can be compared streamed: a binary PLY whose vertices have no station
    fields, or an ``.npy`` of plain (n, 3) coordinates (what the rest of a file could carry,
    per-point stations and origins, needs the whole cloud read).

    Parameters
    ----------
    path : str or Path
    format : str, optional
        The file's format (None: from its name).
    """
    path = Path(path)
    chosen = (format or path.suffix).lower().lstrip(".")
    try:
        if chosen == "npy":
            array = np.load(path, mmap_mode="r")
            return array.dtype.names is None and array.ndim == 2 and array.shape[1] == 3
        if chosen != "ply":
            return False
        with open(path, "rb") as file:
            header = file.read(PLY_HEADER_BYTES).split(b"end_header", 1)[0].decode("latin-1")
    except (OSError, ValueError):
        return False
    lines = [line.split() for line in header.splitlines()]
    if ["format", "ascii", "1.0"] in lines:
        return False
    names, in_vertex = [], False
    for words in lines:
        if words[:1] == ["element"]:
            in_vertex = words[1:2] == ["vertex"]
        elif in_vertex and words[:1] == ["property"]:
            names.append(words[-1])
    return {"x", "y", "z"} <= set(names) and not has_station_fields(names)


PLY_HEADER_BYTES = 1 << 16
"""Most bytes of a PLY header :func:`coordinates_only` reads."""


def streamed_outputs(result: ComparisonResult) -> dict[str, Path] | None:
    """The output files of a result of :func:`compare_streamed` (its per-point arrays are
    ``.npy`` memory maps), by ``<side>_<name>``; None for any other result."""
    outputs = {}
    for side in ("reference", "scan"):
        for name in OUTPUT_FILES:
            array = getattr(result, f"{side}_{name}")
            if not isinstance(array, np.memmap) or not array.filename:
                return None
            outputs[f"{side}_{name}"] = Path(array.filename)
    return outputs


def write_labels_npz(path: Path, outputs: Mapping[str, Path], chunk_points: int = CHUNK) -> None:
    """A streamed result's ``labels.npz``, as
    :meth:`~app.core.pipeline.ComparisonResult.write_labels_npz` writes it, copied from its
    output files (:func:`streamed_outputs`) a chunk at a time: no per-point array of the whole
    clouds is held or mapped."""
    import zipfile

    from app.core.comparison.result import LABELS_COMPRESS_LEVEL

    with zipfile.ZipFile(
        path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=LABELS_COMPRESS_LEVEL
    ) as archive:
        for name, source, changed in (
            ("reference_changed", outputs["reference_label"], True),
            ("scan_changed", outputs["scan_label"], True),
            ("reference_label", outputs["reference_label"], False),
            ("scan_label", outputs["scan_label"], False),
        ):
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                _copy_npy(source, member, chunk_points, changed)


def write_details_npz(path: Path, outputs: Mapping[str, Path], chunk_points: int = CHUNK) -> None:
    """A streamed result's distances and region numbers as one ``.npz`` (a job's
    ``details.npz``), copied from its output files a chunk at a time."""
    import zipfile

    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as archive:
        for name in ("reference_distance", "scan_distance", "reference_region", "scan_region"):
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                _copy_npy(outputs[name], member, chunk_points, False)


def _copy_npy(source: Path, member: Any, chunk_points: int, changed: bool) -> None:
    """Copy an ``.npy`` file into ``member`` by reads (``changed``: its values ==
    :data:`LABEL_CHANGED` as a bool array instead)."""
    with open(source, "rb") as file:
        version = np.lib.format.read_magic(file)
        read_header = (
            np.lib.format.read_array_header_1_0
            if version == (1, 0)
            else np.lib.format.read_array_header_2_0
        )
        shape, _, dtype = read_header(file)
        header = {"descr": np.lib.format.dtype_to_descr(np.dtype(bool) if changed else dtype)}
        header.update(fortran_order=False, shape=shape)
        np.lib.format.write_array_header_1_0(member, header)
        while True:
            values = np.fromfile(file, dtype=dtype, count=chunk_points)
            if not len(values):
                return
            member.write((values == LABEL_CHANGED if changed else values).tobytes())


class StoredTileResults(Sequence["TileResult"]):
    """Tile results in files, read one at a time when asked for (nothing kept).

    Parameters
    ----------
    paths : sequence of Path
        Tile ``i``'s result (:meth:`TileResult.save`) at ``paths[i]``.
    """

    def __init__(self, paths: Sequence[Path]) -> None:
        self.paths = list(paths)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: Any) -> Any:
        if isinstance(index, slice):
            return [self[number] for number in range(len(self))[index]]
        from app.core.tiling.tile import TileResult  # the localiser: only when a tile is read

        return TileResult.load(self.paths[index])

    def side(self, index: int, side: str) -> tuple[NDArray, NDArray, NDArray]:
        """Tile ``index``'s ``(core indices, labels, distances)`` of one cloud only."""
        with np.load(self.paths[index], allow_pickle=False) as data:
            return data[f"{side}_index"], data[f"{side}_label"], data[f"{side}_distance"]


def side_arrays(results: Sequence[TileResult], index: int, side: str) -> tuple[NDArray, ...]:
    """One tile's core indices, labels and distances of one cloud."""
    if isinstance(results, StoredTileResults):
        return results.side(index, side)
    result = results[index]
    return tuple(getattr(result, f"{side}_{name}") for name in ("index", "label", "distance"))


@dataclass
class _Written:
    paths: dict[str, Path]
    sub: dict[str, NDArray]
    changed: int = 0
    unobserved: int = 0


def write_outputs(
    work_dir: Path,
    side: str,
    cloud: StreamedCloud,
    results: Sequence[TileResult],
    regions: list[tuple[int, NDArray[np.int64]]],
    unchanged: NDArray[np.int64],
) -> _Written:
    """One cloud's labels, distances and region numbers, range by range, into ``.npy`` files
    in the file's row order; with the subsample's values and the counts."""
    paths = {f"{side}_{name}": work_dir / f"{side}_{name}.npy" for name in OUTPUT_FILES}
    for (dtype, fill), path in zip(OUTPUT_FILES.values(), paths.values(), strict=True):
        output = np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=(cloud.n_rows,))
        output[cloud.dropped] = fill  # a non-finite row's; the others are written range by range
        del output
    written = _Written(paths, {name: [] for name in OUTPUT_FILES})  # type: ignore[arg-type]
    covered = 0
    for first in range(0, cloud.n_points, OUTPUT_RANGE):
        stop = min(cloud.n_points, first + OUTPUT_RANGE)
        values = {
            name: np.full(stop - first, fill, dtype=dtype)
            for name, (dtype, fill) in OUTPUT_FILES.items()
        }
        seen = np.zeros(stop - first, dtype=np.uint8)
        for number in range(len(results)):
            index, label, distance = side_arrays(results, number, side)
            low, high = np.searchsorted(index, [first, stop])
            local = index[low:high] - first
            values["label"][local] = label[low:high]
            values["distance"][local] = distance[low:high]
            seen[local] += 1
        covered += int(np.count_nonzero(seen == 1))
        if np.any(seen > 1):
            raise ValueError("the tiles' cores overlap")
        label = values["label"]
        for points in (unchanged,):
            low, high = np.searchsorted(points, [first, stop])
            local = points[low:high] - first
            label[local[label[local] == LABEL_CHANGED]] = LABEL_UNCHANGED
        for region_number, points in regions:
            low, high = np.searchsorted(points, [first, stop])
            values["region"][points[low:high] - first] = region_number
        written.changed += int(np.count_nonzero(label == LABEL_CHANGED))
        written.unobserved += int(np.count_nonzero(label == LABEL_UNOBSERVED))
        rows = cloud.file_rows(first, stop - first) if len(cloud.dropped) else slice(first, stop)
        subsample = subsample_offsets(first, stop - first, cloud.step)
        for name, path in zip(OUTPUT_FILES, paths.values(), strict=True):
            written.sub[name].append(values[name][subsample])
            output = np.load(path, mmap_mode="r+")
            output[rows] = values[name]
            del output  # unmapped: its pages leave this process
    if covered != cloud.n_points:
        raise ValueError("the tiles' cores do not cover every point exactly once")
    written.sub = {
        name: np.concatenate(parts) if parts else np.zeros(0, OUTPUT_FILES[name][0])
        for name, parts in written.sub.items()
    }
    return written
