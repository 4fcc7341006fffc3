"""A reference's resolved sensor origin, kept in its geometry cache file between comparisons.

Estimating a reference's origin takes about half a second a million points, and gives the same
answer for every scan compared with it.  :class:`ReferenceOriginCache` keeps the
:class:`~app.core.origins.resolve.ResolvedOrigin` as a fact of the reference's
:class:`~app.core.cache.geometry.GeometryCache` file (its header), under a key made of the
file's key (reference, code, localisation parameters), the text of the origin code and every
input of the resolution; a fact for another key or with a wrong checksum is not used (the origin
is resolved again and the fact rewritten).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.cache.geometry import GeometryCache
from app.core.cloud import PointCloud
from app.core.origins.resolve import ResolvedOrigin
from app.core.origins.station_recovery import STATION_INDEX_ATTRIBUTE

__all__ = [
    "ORIGIN_FACT",
    "ReferenceOriginCache",
    "origin_from_record",
    "origin_record",
    "reference_origin_key",
]

_ORIGIN_CODE_PATTERNS = ("origins/*.py", "localise/station_assignment.py", "localise/settings.py")
"""Sources (under app/core) whose text is part of the key of a cached reference origin."""
ORIGIN_FACT = "reference_origin"
"""Name of the reference's resolved sensor origin among a cache file's facts."""


def reference_origin_key(geometry_key: str, inputs: Mapping[str, Any]) -> str:
    """The key of a reference's resolved sensor origin kept in its cache file.

    Parameters
    ----------
    geometry_key : str
        :func:`cache_key` of the file (the reference, its code and parameters).
    inputs : mapping
        JSON-serialisable inputs of the resolution besides the points (origins given or from
        the file, the estimate and recover switches...).

    Returns
    -------
    str
        64 hex digits; changes with any input and with the source of the origin code.
    """
    digest = hashlib.sha256(geometry_key.encode())
    core_directory = Path(__file__).resolve().parent.parent
    for pattern in _ORIGIN_CODE_PATTERNS:
        for path in sorted(core_directory.glob(pattern)):
            digest.update(path.name.encode() + b"\0" + path.read_bytes())
    digest.update(json.dumps(dict(inputs), sort_keys=True, default=str).encode())
    return digest.hexdigest()


def origin_record(resolved: ResolvedOrigin) -> dict[str, Any] | None:
    """``resolved`` as plain JSON values, or None when they would not give it back exactly."""
    origin = resolved.origin
    record = {
        "origin": None if origin is None else np.asarray(origin, dtype=np.float64).tolist(),
        "source": resolved.source,
        "confidence": resolved.confidence,
        "warnings": list(resolved.warnings),
        "evidence": _kept_evidence(resolved.evidence),
        "station_confidence": resolved.station_confidence,
    }
    try:
        record = json.loads(json.dumps(record))
    except (TypeError, ValueError):
        return None
    back = origin_from_record(record)
    if back is None or not _same_origin(back, resolved):
        return None
    return record


def origin_from_record(record: Any) -> ResolvedOrigin | None:
    """The :class:`~app.core.origins.resolve.ResolvedOrigin` of :func:`origin_record`'s
    ``record`` (None when it is not one)."""
    try:
        origin = record["origin"]
        return ResolvedOrigin(
            origin=None if origin is None else np.asarray(origin, dtype=np.float64),
            source=record["source"],
            confidence=record["confidence"],
            warnings=[str(warning) for warning in record["warnings"]],
            evidence=dict(record["evidence"]),
            station_confidence=record["station_confidence"],
        )
    except (KeyError, TypeError, ValueError):
        return None


VOLATILE_EVIDENCE = ("seconds",)
"""Evidence not kept in the record (the estimate's run time: it would make every rewrite of a
cache file differ; the reference's evidence is not reported)."""


def _kept_evidence(evidence: Mapping[str, Any]) -> dict[str, Any]:
    return {name: value for name, value in evidence.items() if name not in VOLATILE_EVIDENCE}


def _same_origin(first: ResolvedOrigin, second: ResolvedOrigin) -> bool:
    if (first.origin is None) != (second.origin is None):
        return False
    if first.origin is not None and not np.array_equal(
        np.asarray(first.origin, dtype=np.float64), np.asarray(second.origin, dtype=np.float64)
    ):
        return False
    return (
        first.source == second.source
        and first.confidence == second.confidence
        and list(first.warnings) == list(second.warnings)
        and _kept_evidence(first.evidence) == _kept_evidence(second.evidence)
        and first.station_confidence == second.station_confidence
    )


@dataclass
class ReferenceOriginCache:
    """The reference's resolved origin kept in its geometry cache file (a fact of the file,
    :meth:`GeometryCache.load_fact`), keyed by the file's key, the origin code's sources and
    every input of the resolution; not used for a cloud with per-point stations."""

    cache: GeometryCache
    key: str
    computed: dict[str, Any] | None = None

    @classmethod
    def of(
        cls,
        cache: GeometryCache | None,
        reference: PointCloud,
        local_origin: NDArray[np.float64],
        *,
        given: Any,
        estimate: bool,
        recover: bool | str,
    ) -> ReferenceOriginCache | None:
        """The origin cache of ``reference`` (its origins ``given``, the ``estimate`` and
        ``recover`` switches of :func:`~app.core.origins.station_recovery.resolve_stations`), or
        None (no geometry cache, or a cloud with per-point stations)."""
        if cache is None or STATION_INDEX_ATTRIBUTE in reference.attributes:
            return None
        sensor_origin = reference.sensor_origin
        inputs = {
            "given": None if given is None else np.asarray(given).tolist(),
            "from_file": None if sensor_origin is None else np.asarray(sensor_origin).tolist(),
            "local_origin": np.asarray(local_origin).tolist(),
            "estimate": bool(estimate),
            "recover": recover if isinstance(recover, str) else bool(recover),
            "n_points": len(reference),
        }
        return cls(cache, reference_origin_key(cache.key, inputs))

    def load(self, facts: dict[str, tuple[str, Any]]) -> ResolvedOrigin | None:
        """The cached resolution, or None (missing, stale or damaged: resolve it again); put
        into ``facts`` (kept if the neighbourhoods are written again)."""
        record = self.cache.load_fact(ORIGIN_FACT, self.key)
        resolved = origin_from_record(record)
        if resolved is not None:
            facts[ORIGIN_FACT] = (self.key, record)
        return resolved

    def remember(self, resolved: ResolvedOrigin, facts: dict[str, tuple[str, Any]]) -> None:
        """Put a resolution just made into ``facts`` (written with the neighbourhoods)."""
        self.computed = origin_record(resolved)
        if self.computed is not None:
            facts[ORIGIN_FACT] = (self.key, self.computed)

    def keep(self) -> None:
        """Add the resolution made to a cache file written without it (e.g. the origin code
        changed since); nothing when it was read from the file or is there already."""
        if self.computed is not None:
            with contextlib.suppress(OSError):
                self.cache.store_fact(ORIGIN_FACT, self.key, self.computed)
