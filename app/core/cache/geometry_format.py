"""The byte layout of a :class:`~app.core.cache.geometry.GeometryCache` file, and its checksums.

A file is :data:`~app.core.cache.geometry.MAGIC`, a one-line JSON header, the neighbourhood
arrays (:data:`LAYOUT`, ``n`` values a point each), then the *array facts* named in the header's
``array_facts`` list, in its order (each its dtype, shape, key and SHA-256).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping
from typing import Any, BinaryIO

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "LAYOUT",
    "array_fact_bytes",
    "array_fact_entries",
    "array_fact_entry",
    "arrays_bytes",
    "arrays_digest",
    "copy_bytes",
    "fact_digest",
    "fact_entry",
]


def fact_digest(value: Any) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()


def fact_entry(key: str, value: Any) -> dict[str, Any]:
    return {"key": key, "value": value, "sha256": fact_digest(value)}


def arrays_digest(arrays: tuple[NDArray, ...]) -> str:
    digest = hashlib.sha256()
    for array in arrays:
        digest.update(memoryview(np.ascontiguousarray(array)).cast("B"))
    return digest.hexdigest()


def array_fact_entry(name: str, key: str, array: NDArray) -> dict[str, Any]:
    array = np.ascontiguousarray(array)
    return {
        "name": name,
        "key": key,
        "dtype": array.dtype.str,
        "shape": list(array.shape),
        "sha256": arrays_digest((array,)),
    }


def array_fact_bytes(entry: Any) -> int | None:
    """Bytes of an array fact's payload (None: not a valid entry)."""
    try:
        dtype = np.dtype(entry["dtype"])
        shape = [int(size) for size in entry["shape"]]
        if dtype.hasobject or any(size < 0 for size in shape) or not isinstance(entry["key"], str):
            return None
        return dtype.itemsize * int(np.prod(shape, dtype=np.int64))
    except (KeyError, TypeError, ValueError):
        return None


def array_fact_entries(header: Mapping[str, Any]) -> list[dict[str, Any]] | None:
    """The header's array facts, in file order (None: malformed)."""
    entries = header.get("array_facts", [])
    if not isinstance(entries, list) or not all(
        isinstance(entry, dict) and array_fact_bytes(entry) is not None for entry in entries
    ):
        return None
    return entries


def copy_bytes(source: BinaryIO, target: BinaryIO, count: int) -> None:
    """Copy ``count`` bytes from ``source`` to ``target``, 4 MiB at a time."""
    while count > 0:
        chunk = source.read(min(count, 1 << 22))
        if not chunk:
            raise ValueError("the file ended early")
        target.write(chunk)
        count -= len(chunk)


def arrays_bytes(header: Mapping[str, Any]) -> int | None:
    """Bytes of a file's neighbourhood arrays (between its header and its array facts)."""
    n, k = header.get("n"), header.get("k")
    if not isinstance(n, int) or not isinstance(k, int) or n < 0 or k < 0:
        return None
    layout = LAYOUT if isinstance(header.get("noise"), float) else LAYOUT[:3]
    return sum(n * width(k) * np.dtype(dtype).itemsize for dtype, width in layout)


LAYOUT: tuple[tuple[str, Callable[[int], int]], ...] = (
    ("<u4", lambda k: k + 1),  # neighbour index
    ("<f8", lambda k: 1),  # k-th distance
    ("<i8", lambda k: 1),  # spatial order
    ("<f4", lambda k: 3),  # surfaces: normal
    ("<f8", lambda k: 1),  # plane constant
    ("<f8", lambda k: 1),  # spacing
    ("u1", lambda k: 1),  # linear
    ("<f8", lambda k: 1),  # variation
)
"""The arrays of a file in order: type and values a point for k neighbours (the last five only
with ``noise`` in the header: the reference's :class:`Surfaces`)."""
