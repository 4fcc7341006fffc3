"""A reference scan's k-nearest-neighbour geometry kept on disk for its next comparisons.

A site's reference is compared with every new scan of the site, and its k-NN search (the
localiser's largest single cost) gives the same answer every time.  :class:`GeometryCache`
stores it once (neighbour index, k-th distance and spatial order: 4 (k + 1) + 16 bytes a
point) and hands it back to :func:`app.core.pipeline.compare`, which then builds only the
KD-tree (a fraction of the query's cost).

Nothing read back is trusted blindly: the file must carry the expected key (reference,
code version and localisation parameters, :func:`cache_key`), the expected point count and k,
a SHA-256 of its arrays that matches, and a sample of rows whose k-th distance matches the
points; otherwise :meth:`GeometryCache.load` returns None and the caller rebuilds (and
overwrites) it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.errors import InputError
from app.core.localise import neighbourhoods as neighbourhoods_module
from app.core.localise.neighbourhoods import (
    Neighbourhoods,
    NeighbourhoodSearch,
    nearest_neighbourhoods,
    neighbourhood_size,
    start_neighbourhood_search,
)
from app.core.localise.settings import resolve_parameters

__all__ = [
    "CACHE_FORMAT",
    "GeometryCache",
    "cache_key",
    "code_version",
    "reference_neighbourhoods",
]

CACHE_FORMAT = 1
"""Bumped whenever the file layout changes."""
MAGIC = b"SCANDIFF-GEOMETRY\n"
VERIFIED_ROWS = 256
"""Rows whose k-th neighbour distance is recomputed from the points on every load."""
_CODE_FILES = ("localise/neighbourhoods.py", "spatial_order.py", "geometry_cache.py")
"""Sources (under app/core) whose text is part of the code version."""


def code_version() -> str:
    """A digest of the code that computes the cached arrays (sources, pykdtree, format).

    Returns
    -------
    str
        16 hex digits; changes whenever the code or KD-tree library that made a cache changes.
    """
    digest = hashlib.sha256(f"format {CACHE_FORMAT}".encode())
    core_directory = Path(neighbourhoods_module.__file__).resolve().parent.parent
    for name in _CODE_FILES:
        digest.update((core_directory / name).read_bytes())
    try:
        digest.update(metadata.version("pykdtree").encode())
    except metadata.PackageNotFoundError:  # pragma: no cover - pykdtree is a dependency
        digest.update(b"pykdtree unknown")
    return digest.hexdigest()[:16]


def cache_key(reference_identity: str, localisation_params: Mapping[str, Any] | None) -> str:
    """The key of a reference's cached geometry.

    Parameters
    ----------
    reference_identity : str
        What identifies the reference's points, e.g. the SHA-256 of its file.
    localisation_params : mapping or None
        The comparison's localisation parameters (defaults filled in here, so an explicit
        default and an omitted one give the same key).

    Returns
    -------
    str
        64 hex digits.
    """
    settings = resolve_parameters(dict(localisation_params or {}))
    text = json.dumps(
        {"reference": reference_identity, "code": code_version(), "localisation": settings},
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()


def _arrays_digest(arrays: tuple[NDArray, ...]) -> str:
    digest = hashlib.sha256()
    for array in arrays:
        digest.update(memoryview(np.ascontiguousarray(array)).cast("B"))
    return digest.hexdigest()


@dataclass(frozen=True)
class GeometryCache:
    """One reference's cached k-NN geometry: a file and the key it must carry.

    Attributes
    ----------
    path : pathlib.Path
        The cache file (written atomically: a temporary name, then renamed).
    key : str
        :func:`cache_key` of the reference and parameters it is for.
    """

    path: Path
    key: str

    def load(self, points: NDArray[np.float64], n_neighbors: int) -> Neighbourhoods | None:
        """The cached neighbourhoods of ``points``, or None when missing or not to be trusted.

        Parameters
        ----------
        points : ndarray, shape (n, 3), float64
            The reference as the localiser gets it (its KD-tree is built here).
        n_neighbors : int
            k (:func:`~app.core.localise.neighbourhoods.neighbourhood_size`).

        Returns
        -------
        Neighbourhoods or None
            None when the file is missing, unreadable, for another key, cloud or k, its
            checksum does not match, or a sample of its rows disagrees with ``points``.
        """
        n, k = len(points), int(n_neighbors)
        try:
            with open(self.path, "rb") as source:
                if source.readline() != MAGIC:
                    return None
                header = json.loads(source.readline())
                if not isinstance(header, dict):
                    return None
                if (header.get("key"), header.get("n"), header.get("k")) != (self.key, n, k):
                    return None
                neighbor_index = np.fromfile(source, dtype="<u4", count=n * (k + 1))
                kth_distance = np.fromfile(source, dtype="<f8", count=n)
                order = np.fromfile(source, dtype="<i8", count=n)
                if source.read(1):
                    return None
        except (OSError, ValueError, UnicodeDecodeError):
            return None
        if len(neighbor_index) != n * (k + 1) or len(kth_distance) != n or len(order) != n:
            return None
        arrays = (neighbor_index, kth_distance, order)
        if _arrays_digest(arrays) != header.get("sha256"):
            return None
        neighbor_index = neighbor_index.reshape(n, k + 1)
        if not _sample_agrees(points, neighbor_index, kth_distance, order):
            return None
        return Neighbourhoods(
            KDTree(points), neighbor_index, kth_distance, order.astype(np.intp, copy=False)
        )

    def store(self, neighbourhoods: Neighbourhoods) -> int:
        """Write ``neighbourhoods`` (replacing any older file); the bytes written.

        Parameters
        ----------
        neighbourhoods : Neighbourhoods
            Of the reference this cache is for, with its spatial order.

        Returns
        -------
        int
            Size of the file.
        """
        n, width = neighbourhoods.neighbor_index.shape
        order = neighbourhoods.order
        if order is None:
            raise ValueError("only neighbourhoods with their spatial order can be cached")
        arrays = (
            np.ascontiguousarray(neighbourhoods.neighbor_index, dtype="<u4"),
            np.ascontiguousarray(neighbourhoods.kth_distance, dtype="<f8"),
            np.ascontiguousarray(order, dtype="<i8"),
        )
        header = {"key": self.key, "n": n, "k": width - 1, "sha256": _arrays_digest(arrays)}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        temporary = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            with open(temporary, "wb") as target:
                target.write(MAGIC)
                target.write(json.dumps(header).encode() + b"\n")
                for array in arrays:
                    array.tofile(target)
            os.replace(temporary, self.path)
        finally:
            temporary.unlink(missing_ok=True)
        return self.path.stat().st_size


def _sample_agrees(
    points: NDArray[np.float64],
    neighbor_index: NDArray[np.uint32],
    kth_distance: NDArray[np.float64],
    order: NDArray[np.int64],
) -> bool:
    """Whether the cached arrays fit ``points``: ``order`` is a permutation, and on
    :data:`VERIFIED_ROWS` evenly spread rows column 0 is the row itself (or a duplicate of
    it), every neighbour is a valid row, and the last neighbour is ``kth_distance`` away."""
    n = len(points)
    if n == 0 or order.min() < 0 or order.max() >= n:
        return False
    if np.count_nonzero(np.bincount(order, minlength=n) != 1):
        return False
    rows = np.unique(np.linspace(0, n - 1, min(VERIFIED_ROWS, n)).astype(np.int64))
    sample = neighbor_index[rows].astype(np.int64)
    if sample.max() >= n:
        return False
    own = np.linalg.norm(points[sample[:, 0]] - points[rows], axis=1)
    last = np.linalg.norm(points[sample[:, -1]] - points[rows], axis=1)
    return bool(np.all(own == 0.0) and np.allclose(last, kth_distance[rows], rtol=1e-9, atol=0))


def reference_neighbourhoods(
    reference_points: NDArray[np.float64],
    localisation_params: Mapping[str, Any],
    *,
    cache: GeometryCache | None,
    ahead: bool,
) -> Neighbourhoods | NeighbourhoodSearch | None:
    """The reference's neighbourhoods for ``localise_changes``: from ``cache`` when it holds
    them, else a search started now (on a thread of its own when ``ahead``) that writes them to
    ``cache``; None when there is neither a cache nor a search to start.

    A cache that cannot be written (a full or read-only disk) only costs the next comparison
    the search again.

    Parameters
    ----------
    reference_points : ndarray, shape (n, 3), float64
        The reference as the localiser gets it.
    localisation_params : mapping
        The comparison's localisation parameters (``n_neighbors`` sets k).
    cache : GeometryCache or None
    ahead : bool
        Start the search on its own thread (the pipeline aligns the scan meanwhile).

    Returns
    -------
    Neighbourhoods, NeighbourhoodSearch or None
    """
    if cache is None:
        if not ahead:
            return None
        return start_neighbourhood_search(reference_points, **localisation_params)
    try:
        n_neighbors = neighbourhood_size(len(reference_points), **localisation_params)
    except InputError:
        return None  # localise_changes reports the parameter itself
    store = _storing(cache)
    if ahead:  # loading (read, checksum, KD-tree build) overlaps the alignment too
        return start_neighbourhood_search(
            reference_points,
            on_found=store,
            stored=partial(cache.load, reference_points, n_neighbors),
            **localisation_params,
        )
    found = cache.load(reference_points, n_neighbors)
    if found is None:
        found = nearest_neighbourhoods(reference_points, n_neighbors)
        if found is not None:
            store(found)
    return found


def _storing(cache: GeometryCache) -> Callable[[Neighbourhoods], None]:
    def store(found: Neighbourhoods) -> None:
        with contextlib.suppress(OSError):  # not cached: the next comparison searches again
            cache.store(found)

    return store
