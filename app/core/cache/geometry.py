"""A reference scan's k-nearest-neighbour geometry kept on disk for its next comparisons.

A site's reference is compared with every new scan of the site, and its k-NN search (the
localiser's largest single cost) gives the same answer every time.  :class:`GeometryCache`
stores it once (neighbour index, k-th distance and spatial order: 4 (k + 1) + 16 bytes a
point) and hands it back to :func:`app.core.pipeline.compare`, which then builds only the
KD-tree (a fraction of the query's cost).  Its header also keeps small *facts* about the
reference that cost seconds to work out and do not depend on the scan (its resolved sensor
origin, :mod:`app.core.cache.reference_origin`), each under its own key and checksum, and
*array facts* after its arrays (the reference's alignment grids,
:mod:`app.core.cache.reference_alignment`), likewise keyed and checksummed.

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

from app.core.cache.geometry_format import (
    LAYOUT,
    array_fact_bytes,
    array_fact_entries,
    array_fact_entry,
    arrays_bytes,
    arrays_digest,
    copy_bytes,
    fact_digest,
    fact_entry,
)
from app.core.errors import InputError
from app.core.localise import neighbourhoods as neighbourhoods_module
from app.core.localise.neighbourhoods import (
    Neighbourhoods,
    NeighbourhoodSearch,
    Surfaces,
    nearest_neighbourhoods,
    neighbourhood_size,
    start_neighbourhood_search,
)
from app.core.localise.settings import resolve_parameters
from app.core.localise.surface import LINEAR_EIGENVALUE_RATIO, neighbourhood_planes, with_surfaces

__all__ = [
    "CACHE_FORMAT",
    "GeometryCache",
    "cache_key",
    "code_version",
    "reference_neighbourhoods",
]

CACHE_FORMAT = 3
"""Bumped whenever the file layout changes (3: array facts after the arrays)."""
MAGIC = b"SCANDIFF-GEOMETRY\n"
VERIFIED_ROWS = 256
"""Rows whose k-th neighbour distance is recomputed from the points on every load."""
_CODE_FILES = (
    "localise/neighbourhoods.py",
    "localise/surface.py",
    "spatial_order.py",
    "cache/geometry.py",
    "cache/geometry_format.py",
)
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

    def _header(self) -> dict[str, Any] | None:
        """The file's header when it is this key's (None: missing, unreadable or another's)."""
        try:
            with open(self.path, "rb") as source:
                if source.readline() != MAGIC:
                    return None
                header = json.loads(source.readline())
        except (OSError, ValueError, UnicodeDecodeError):
            return None
        if not isinstance(header, dict) or header.get("key") != self.key:
            return None
        return header

    def load_fact(self, name: str, key: str) -> Any | None:
        """The fact ``name`` stored under ``key`` (None: missing, for another key, or damaged).

        Parameters
        ----------
        name : str
            E.g. :data:`ORIGIN_FACT`.
        key : str
            What the fact must have been stored for (e.g. :func:`reference_origin_key`).

        Returns
        -------
        JSON value or None
        """
        header = self._header()
        facts = None if header is None else header.get("facts")
        entry = facts.get(name) if isinstance(facts, dict) else None
        if not isinstance(entry, dict) or entry.get("key") != key or "value" not in entry:
            return None
        if entry.get("sha256") != fact_digest(entry["value"]):
            return None
        return entry["value"]

    def store_fact(self, name: str, key: str, value: Any) -> bool:
        """Add (or replace) a fact in the existing file, which keeps its arrays.

        The file is rewritten (a temporary copy with the new header, then renamed); nothing is
        written when there is no valid file of this key yet (:meth:`store` writes the facts it
        is given) or the fact is there already.

        Returns
        -------
        bool
            Whether the file was rewritten.
        """
        return self.store_facts({name: (key, value)})

    def store_facts(self, facts: Mapping[str, tuple[str, Any]]) -> bool:
        """Add (or replace) facts, JSON values or arrays, in the existing file in one rewrite.

        Parameters
        ----------
        facts : mapping
            ``{name: (key, value)}``; a numpy array ``value`` is an array fact
            (:meth:`load_array_fact`), anything else a JSON fact (:meth:`load_fact`).

        Returns
        -------
        bool
            Whether the file was rewritten (not when there is no valid file of this key, or
            every fact is there already).
        """
        header = self._header()
        entries = None if header is None else array_fact_entries(header)
        if header is None or entries is None:
            return False
        json_facts = header.get("facts")
        json_facts = dict(json_facts) if isinstance(json_facts, dict) else {}
        new_arrays: dict[str, NDArray] = {}
        for name, (key, value) in facts.items():
            if isinstance(value, np.ndarray):
                stored = self.load_array_fact(name, key)  # checked: a damaged one is replaced
                if (
                    stored is None
                    or stored.dtype != value.dtype
                    or not np.array_equal(stored, value)
                ):
                    new_arrays[name] = np.ascontiguousarray(value)
            elif self.load_fact(name, key) != value:
                json_facts[name] = fact_entry(key, value)
        if not new_arrays and json_facts == (header.get("facts") or {}):
            return False
        header["facts"] = json_facts
        temporary = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            with open(self.path, "rb") as source, open(temporary, "wb") as target:
                source.readline()
                if json.loads(source.readline()).get("sha256") != header.get("sha256"):
                    return False  # replaced meanwhile (another comparison rebuilt it)
                neighbourhood_bytes = arrays_bytes(header)
                if neighbourhood_bytes is None:
                    return False
                added = {
                    name: array_fact_entry(name, facts[name][0], array)
                    for name, array in new_arrays.items()
                }
                present = {entry["name"] for entry in entries}
                header["array_facts"] = [  # a replaced fact keeps its place
                    *(added.get(entry["name"], entry) for entry in entries),
                    *(entry for name, entry in added.items() if name not in present),
                ]
                target.write(MAGIC)
                target.write(json.dumps(header).encode() + b"\n")
                copy_bytes(source, target, neighbourhood_bytes)
                for entry in entries:
                    payload = source.read(array_fact_bytes(entry) or 0)
                    name = entry["name"]
                    target.write(payload if name not in added else new_arrays[name].tobytes())
                for name, array in new_arrays.items():
                    if name not in present:
                        array.tofile(target)
            os.replace(temporary, self.path)
        except (OSError, ValueError, UnicodeDecodeError, AttributeError):
            return False
        finally:
            temporary.unlink(missing_ok=True)
        return True

    def load_array_fact(self, name: str, key: str) -> NDArray | None:
        """The array fact ``name`` stored under ``key`` (None: missing, for another key, or
        damaged: its checksum does not match).

        Parameters
        ----------
        name : str
        key : str
            What the array must have been stored for.

        Returns
        -------
        ndarray or None
            Of the dtype and shape it was stored with.
        """
        try:
            with open(self.path, "rb") as source:
                if source.readline() != MAGIC:
                    return None
                header = json.loads(source.readline())
                if not isinstance(header, dict) or header.get("key") != self.key:
                    return None
                entries = array_fact_entries(header)
                offset = arrays_bytes(header)
                if entries is None or offset is None:
                    return None
                for entry in entries:
                    size = array_fact_bytes(entry) or 0
                    if entry["name"] == name:
                        if entry["key"] != key:
                            return None
                        source.seek(offset, os.SEEK_CUR)
                        payload = source.read(size)
                        break
                    offset += size
                else:
                    return None
        except (OSError, ValueError, UnicodeDecodeError):
            return None
        if len(payload) != size:
            return None
        array = np.frombuffer(payload, dtype=np.dtype(entry["dtype"])).reshape(entry["shape"])
        if arrays_digest((array,)) != entry.get("sha256"):
            return None
        return array

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
                noise = header.get("noise")
                layout = LAYOUT if isinstance(noise, float) else LAYOUT[:3]
                entries = array_fact_entries(header)
                if entries is None:
                    return None
                arrays = tuple(
                    np.fromfile(source, dtype=dtype, count=n * width(k)) for dtype, width in layout
                )
                after = sum(array_fact_bytes(entry) or 0 for entry in entries)
                if os.fstat(source.fileno()).st_size != source.tell() + after:
                    return None
        except (OSError, ValueError, UnicodeDecodeError):
            return None
        if any(
            len(array) != n * width(k) for array, (_, width) in zip(arrays, layout, strict=True)
        ):
            return None
        if arrays_digest(arrays) != header.get("sha256"):
            return None
        neighbor_index, kth_distance, order = arrays[:3]
        neighbor_index = neighbor_index.reshape(n, k + 1)
        if not _sample_agrees(points, neighbor_index, kth_distance, order):
            return None
        surfaces = None
        if len(arrays) > 3:
            normal, plane_constant, spacing, linear, variation = arrays[3:]
            surfaces = Surfaces(
                normal.reshape(n, 3), plane_constant, spacing, noise, linear.view(bool), variation
            )
            if not _surfaces_agree(points, neighbor_index, surfaces):
                return None
        return Neighbourhoods(
            KDTree(points),
            neighbor_index,
            kth_distance,
            order.astype(np.intp, copy=False),
            surfaces,
        )

    def store(
        self, neighbourhoods: Neighbourhoods, facts: Mapping[str, tuple[str, Any]] | None = None
    ) -> int:
        """Write ``neighbourhoods`` (replacing any older file); the bytes written.

        Parameters
        ----------
        neighbourhoods : Neighbourhoods
            Of the reference this cache is for, with its spatial order.
        facts : mapping, optional
            ``{name: (key, value)}``: JSON values kept in the header (:meth:`load_fact`),
            numpy arrays after the neighbourhood arrays (:meth:`load_array_fact`).

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
        surfaces = neighbourhoods.surfaces
        if surfaces is not None:
            arrays += (
                np.ascontiguousarray(surfaces.normal, dtype="<f4"),
                np.ascontiguousarray(surfaces.plane_constant, dtype="<f8"),
                np.ascontiguousarray(surfaces.spacing, dtype="<f8"),
                np.ascontiguousarray(surfaces.linear, dtype="u1"),
                np.ascontiguousarray(surfaces.variation, dtype="<f8"),
            )
        header: dict[str, Any] = {
            "key": self.key,
            "n": n,
            "k": width - 1,
            "sha256": arrays_digest(arrays),
        }
        if surfaces is not None:
            header["noise"] = float(surfaces.noise)
        array_facts = {
            name: (key, np.ascontiguousarray(value))
            for name, (key, value) in (facts or {}).items()
            if isinstance(value, np.ndarray)
        }
        json_facts = {
            name: fact_entry(key, value)
            for name, (key, value) in (facts or {}).items()
            if name not in array_facts
        }
        if json_facts:
            header["facts"] = json_facts
        if array_facts:
            header["array_facts"] = [
                array_fact_entry(name, key, value) for name, (key, value) in array_facts.items()
            ]
        self.path.parent.mkdir(parents=True, exist_ok=True)
        temporary = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            with open(temporary, "wb") as target:
                target.write(MAGIC)
                target.write(json.dumps(header).encode() + b"\n")
                for array in arrays:
                    array.tofile(target)
                for _, value in array_facts.values():
                    value.tofile(target)
            os.replace(temporary, self.path)
        finally:
            temporary.unlink(missing_ok=True)
        return self.path.stat().st_size


def _surfaces_agree(
    points: NDArray[np.float64], neighbor_index: NDArray[np.uint32], surfaces: Surfaces
) -> bool:
    """Whether the cached planes fit ``points``: on :data:`VERIFIED_ROWS` evenly spread rows
    whose k neighbours are not a line (those are refitted wider), the plane fitted again is
    the cached one."""
    n = len(points)
    rows = np.unique(np.linspace(0, n - 1, min(VERIFIED_ROWS, n)).astype(np.int64))
    normal, plane_constant, _, middle_over_largest, _ = neighbourhood_planes(
        points, neighbor_index[rows]
    )
    planar = middle_over_largest >= LINEAR_EIGENVALUE_RATIO
    return bool(
        np.allclose(normal[planar], surfaces.normal[rows][planar], rtol=0, atol=1e-5)
        and np.allclose(
            plane_constant[planar], surfaces.plane_constant[rows][planar], rtol=0, atol=1e-6
        )
    )


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
    facts: Mapping[str, tuple[str, Any]] | None = None,
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
    facts : mapping, optional
        Written with the neighbourhoods (:meth:`GeometryCache.store`): what it holds when they
        are written (the caller may add to it meanwhile).

    Returns
    -------
    Neighbourhoods, NeighbourhoodSearch or None
    """
    if cache is None:
        if not ahead:
            return None
        # the surfaces too: their fits (~0.6 CPU s a 1M-point cloud) fill the second core
        # beside the alignment, which holds the GIL in small_gicp's calls
        return start_neighbourhood_search(
            reference_points, finish=partial(with_surfaces, reference_points), **localisation_params
        )
    try:
        n_neighbors = neighbourhood_size(len(reference_points), **localisation_params)
    except InputError:
        return None  # localise_changes reports the parameter itself
    store = _storing(cache, facts)
    if ahead:  # loading (read, checksum, KD-tree build) overlaps the alignment too
        return start_neighbourhood_search(
            reference_points,
            on_found=store,
            stored=partial(cache.load, reference_points, n_neighbors),
            finish=partial(with_surfaces, reference_points),
            **localisation_params,
        )
    found = cache.load(reference_points, n_neighbors)
    if found is None:
        found = nearest_neighbourhoods(reference_points, n_neighbors)
        if found is not None:
            found = with_surfaces(reference_points, found)
            store(found)
    return found


def _storing(
    cache: GeometryCache, facts: Mapping[str, tuple[str, Any]] | None
) -> Callable[[Neighbourhoods], None]:
    def store(found: Neighbourhoods) -> None:
        with contextlib.suppress(OSError):  # not cached: the next comparison searches again
            cache.store(found, None if facts is None else dict(facts))

    return store
