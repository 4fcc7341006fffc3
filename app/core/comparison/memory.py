"""What a comparison keeps of its reference between comparisons: one geometry cache's facts."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from app.core.cache.geometry import GeometryCache
from app.core.cache.reference_alignment import ReferenceAlignmentCache
from app.core.cache.reference_origin import ReferenceOriginCache
from app.core.comparison.load import LoadedPair


@dataclass(frozen=True)
class ReferenceMemory:
    """The reference's cached geometry, resolved origin and alignment arrays (all None
    without a cache).

    Attributes
    ----------
    cache : GeometryCache or None
    facts : dict
        Facts to write with the reference's neighbourhoods, filled as they are computed.
    origins : ReferenceOriginCache or None
    alignment : ReferenceAlignmentCache or None
    """

    cache: GeometryCache | None = None
    facts: dict[str, tuple[str, Any]] = field(default_factory=dict)
    origins: ReferenceOriginCache | None = None
    alignment: ReferenceAlignmentCache | None = None

    @classmethod
    def of(cls, cache: GeometryCache | None, loaded: LoadedPair) -> ReferenceMemory:
        """The memory of ``loaded``'s reference in ``cache``."""
        settings = loaded.settings
        origins = ReferenceOriginCache.of(
            cache,
            loaded.reference,
            loaded.local_origin,
            given=settings.reference_origin,
            estimate=settings.estimate_origins,
            recover=settings.recover_stations,
        )
        facts: dict[str, tuple[str, Any]] = {}
        alignment = ReferenceAlignmentCache.of(cache, facts)
        return cls(cache=cache, facts=facts, origins=origins, alignment=alignment)

    def keep(self) -> None:
        """Write what was computed and not read from the cache."""
        if self.origins is not None:
            self.origins.keep()
        if self.alignment is not None:
            self.alignment.keep()
