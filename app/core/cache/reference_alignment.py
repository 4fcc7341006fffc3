"""The reference's alignment arrays stored in its geometry cache file, between comparisons.

:func:`~app.core.registration.register_scan` spends about half its time on the reference (1M
points: its point spacing, a KD-tree build of 0.3 s; its voxel-grid centroids; their coarse and
quality-figure downsamplings), and a site's reference is aligned with every new scan of the
site.  :class:`ReferenceAlignmentCache` is the
:class:`~app.core.cache.reference_memory.ReferenceMemory` that keeps those arrays as *array
facts* of the reference's :class:`~app.core.cache.geometry.GeometryCache` file (so they count in
its size, and go with it), each under a key made of the file's key (reference, code,
localisation parameters), the text of the registration code, small_gicp's version, what the
array is and the parameters it was computed with.  An array for another key, or whose checksum
does not match, is not used: it is computed again and written back.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core import registration as registration_module
from app.core.cache import reference_memory as reference_memory_module
from app.core.cache.geometry import GeometryCache

__all__ = ["ALIGNMENT_FACT_PREFIX", "ReferenceAlignmentCache", "reference_alignment_key"]

ALIGNMENT_FACT_PREFIX = "alignment."
"""Array facts of a cache file named ``alignment.<name>`` hold
:class:`~app.core.cache.reference_memory.ReferenceMemory` arrays."""


def reference_alignment_key(geometry_key: str) -> str:
    """The key under which a reference's alignment arrays are kept in its cache file.

    Parameters
    ----------
    geometry_key : str
        :func:`~app.core.cache.geometry.cache_key` of the file.

    Returns
    -------
    str
        64 hex digits; changes with the file's key, the registration code and small_gicp.
    """
    digest = hashlib.sha256(geometry_key.encode())
    for module in (registration_module, reference_memory_module):
        digest.update(Path(module.__file__).read_bytes())
    try:
        digest.update(metadata.version("small_gicp").encode())
    except metadata.PackageNotFoundError:  # pragma: no cover - small_gicp is a dependency
        digest.update(b"small_gicp unknown")
    return digest.hexdigest()


@dataclass
class ReferenceAlignmentCache:
    """A :class:`~app.core.cache.reference_memory.ReferenceMemory` in the reference's cache file.

    Arrays recalled or computed are put into ``facts`` (written with the neighbourhoods when
    the file is written during the comparison); those computed and not in the file then are
    added by :meth:`keep`.

    Attributes
    ----------
    cache : GeometryCache
    key : str
        :func:`reference_alignment_key` of the cache's key.
    facts : dict
        The comparison's facts, ``{name: (key, value)}`` (shared with the origin's).
    computed : dict
        The arrays computed in this comparison, as facts.
    """

    cache: GeometryCache
    key: str
    facts: dict[str, tuple[str, Any]]
    computed: dict[str, tuple[str, Any]] = field(default_factory=dict)

    @classmethod
    def of(
        cls, cache: GeometryCache | None, facts: dict[str, tuple[str, Any]]
    ) -> ReferenceAlignmentCache | None:
        """The alignment memory of ``cache``'s reference (None without a cache)."""
        if cache is None:
            return None
        return cls(cache, reference_alignment_key(cache.key), facts)

    def _fact(self, name: str, parameters: tuple[float, ...]) -> tuple[str, str]:
        """The array fact's name and key for ``name`` computed with ``parameters``."""
        exact = [float(value).hex() for value in parameters]  # every bit of each number
        text = json.dumps([self.key, name, exact])
        return ALIGNMENT_FACT_PREFIX + name, hashlib.sha256(text.encode()).hexdigest()

    def recall(self, name: str, parameters: tuple[float, ...]) -> NDArray | None:
        """The array kept for ``name`` and ``parameters`` (None: missing, stale or damaged)."""
        fact_name, fact_key = self._fact(name, parameters)
        array = self.cache.load_array_fact(fact_name, fact_key)
        if array is None or not _plausible(name, array):
            return None
        self.facts[fact_name] = (fact_key, array)
        return array

    def remember(self, name: str, parameters: tuple[float, ...], array: NDArray) -> None:
        """Keep ``array``, computed for ``name`` and ``parameters``, to be written."""
        fact_name, fact_key = self._fact(name, parameters)
        entry = (fact_key, np.ascontiguousarray(array, dtype=np.float64))
        self.facts[fact_name] = entry
        self.computed[fact_name] = entry

    def keep(self) -> None:
        """Add the arrays computed to a cache file written without them (one rewrite);
        nothing when every one was read from the file or is there already."""
        if self.computed:
            with contextlib.suppress(OSError):
                self.cache.store_facts(self.computed)


def _plausible(name: str, array: NDArray) -> bool:
    """Whether ``array`` has the form of a :class:`~app.core.cache.reference_memory.ReferenceMemory`
    array called ``name``: finite float64, (1,) non-negative for the spacing, else (m, 3)."""
    if array.dtype != np.float64 or not np.isfinite(array).all():
        return False
    if name == "spacing":
        return array.shape == (1,) and bool(array[0] >= 0.0)
    return array.ndim == 2 and array.shape[1] == 3
