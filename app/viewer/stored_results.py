"""A finished job's per-point results read for its 3D view, without loading what is not needed.

``labels.npz`` (int8 labels, one per file row, deflated) is read whole: one byte a point.
``details.npz`` is written uncompressed (``numpy.savez``), so its float32 distances are read
a range of rows at a time straight from the file (:class:`StoredColumn`), never all at once.
"""

from __future__ import annotations

import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from app.jobs.results import read_labels

ZIP_LOCAL_HEADER_BYTES = 30
"""A zip member's local file header before its name and extra field."""


@dataclass(frozen=True)
class StoredColumn:
    """A 1-D array stored in a file (an ``.npz`` member), read a range of rows at a time.

    ``in_memory`` holds the whole array when the member is compressed (then read at once).
    """

    path: Path | None
    offset: int
    dtype: np.dtype
    length: int
    in_memory: NDArray | None = None

    @classmethod
    def constant(cls, length: int, value: float) -> StoredColumn:
        """A column of ``length`` copies of ``value`` (float32), e.g. NaN distances."""
        return cls(None, 0, np.dtype(np.float32), length, np.full(length, value, np.float32))

    def read(self, start: int, stop: int) -> NDArray:
        """Rows ``start`` to ``stop`` (a new array, shape (stop - start,))."""
        stop = min(stop, self.length)
        if self.in_memory is not None:
            return np.array(self.in_memory[start:stop])
        count = max(stop - start, 0)
        return np.fromfile(
            self.path,
            dtype=self.dtype,
            count=count,
            offset=self.offset + start * self.dtype.itemsize,
        )

    def at(self, rows: NDArray[np.int64], chunk_rows: int) -> NDArray:
        """The values at sorted ``rows``, read ``chunk_rows`` at a time, shape (len(rows),)."""
        values = np.empty(len(rows), dtype=self.dtype)
        for start in range(0, self.length, chunk_rows):
            low, high = np.searchsorted(rows, [start, start + chunk_rows])
            if high > low:
                values[low:high] = self.read(start, start + chunk_rows)[rows[low:high] - start]
        return values


def npz_column(path: Path, name: str) -> StoredColumn:
    """The 1-D array ``name`` of the ``.npz`` at ``path``: read in place when stored
    uncompressed, else decompressed once.

    Raises
    ------
    KeyError
        No such member.
    """
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo(f"{name}.npy")
        if info.compress_type != zipfile.ZIP_STORED:
            with archive.open(info) as member:
                array = np.lib.format.read_array(member, allow_pickle=False).reshape(-1)
            return StoredColumn(None, 0, array.dtype, len(array), array)
    with open(path, "rb") as handle:
        handle.seek(info.header_offset)
        local = handle.read(ZIP_LOCAL_HEADER_BYTES)
        name_bytes, extra_bytes = struct.unpack_from("<HH", local, 26)
        handle.seek(info.header_offset + ZIP_LOCAL_HEADER_BYTES + name_bytes + extra_bytes)
        version = np.lib.format.read_magic(handle)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(handle)
        else:
            shape, _, dtype = np.lib.format.read_array_header_2_0(handle)
        offset = handle.tell()
    return StoredColumn(path, offset, dtype, int(np.prod(shape)))


def stored_labels(labels_path: Path) -> dict[str, NDArray[np.int8]]:
    """``{"reference": labels, "scan": labels}``, int8, one per file row
    (:func:`app.jobs.results.read_labels`)."""
    reference, scan = read_labels(labels_path)
    return {"reference": reference, "scan": scan}


def stored_distances(details_path: Path, n_rows: dict[str, int]) -> dict[str, StoredColumn]:
    """Per side, the distances of ``details.npz`` (NaN columns when the job has none)."""
    if not details_path.is_file():  # jobs from before details.npz
        return {side: StoredColumn.constant(n, np.nan) for side, n in n_rows.items()}
    return {side: npz_column(details_path, f"{side}_distance") for side in n_rows}
