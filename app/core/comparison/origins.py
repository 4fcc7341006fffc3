"""Stage 2, **origins**: where each cloud's sensor was, and which station took each point.

The reference's origins are resolved before the scan is aligned
(:func:`resolve_reference_origins`); the scan's after, in the aligned frame
(:func:`resolve_scan_origins`): its own frame's estimate is moved by the registration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.comparison.align import Alignment
from app.core.comparison.load import LoadedPair
from app.core.comparison.memory import ReferenceMemory
from app.core.localise import EpochCloud, Neighbourhoods, NeighbourhoodSearch
from app.core.origins.known_stations import origins_in_local_frame
from app.core.origins.own_frame import resolve_moved_cloud
from app.core.origins.resolve import ResolvedOrigin
from app.core.origins.station_recovery import resolve_stations
from app.core.origins.trajectory_origin import station_index, trajectory_origin, trajectory_rays
from app.core.registration import apply_transform


@dataclass(frozen=True)
class CloudOrigins:
    """One cloud's resolved sensor origins, in the comparison's (aligned, local) frame.

    Attributes
    ----------
    resolved : ResolvedOrigin
        The origin(s), where they came from, their confidence and warnings.
    station : ndarray, shape (n,), int, or None
        Index into the origins of the station that took each point (None: not known).
    """

    resolved: ResolvedOrigin
    station: NDArray | None

    @property
    def origin(self) -> NDArray[np.float64] | None:
        """The origin, shape (3,), or one per station, shape (k, 3); None if unknown."""
        return self.resolved.origin

    @property
    def stations_unknown(self) -> bool:
        """A merged lidar cloud whose stations are not known nor recovered."""
        return self.resolved.stations_unknown

    @property
    def trajectory_rays(self) -> tuple[NDArray, NDArray] | None:
        """The pseudo-stations' ``(returns, bounds)`` of a cloud with a trajectory, else None."""
        return trajectory_rays(self.resolved)

    def epoch(
        self,
        points: NDArray[np.float64],
        neighbourhoods: Neighbourhoods | NeighbourhoodSearch | None = None,
    ) -> EpochCloud:
        """``points``, shape (n, 3), in this frame with these origins, for the localiser."""
        return EpochCloud(
            points=points,
            origin=self.origin,
            station=self.station,
            stations_unknown=self.stations_unknown,
            trajectory_rays=self.trajectory_rays,
            neighbourhoods=neighbourhoods,
        )


@dataclass(frozen=True)
class SensorOrigins:
    """Both clouds' :class:`CloudOrigins`."""

    reference: CloudOrigins
    scan: CloudOrigins


def resolve_reference_origins(
    loaded: LoadedPair, memory: ReferenceMemory | None = None
) -> CloudOrigins:
    """The reference's origins: a trajectory's pseudo-stations, the cache's, or resolved
    (given, from the file, estimated or recovered: :func:`resolve_stations`) and cached."""
    reference, settings = loaded.reference, loaded.settings
    memory = memory or ReferenceMemory()
    resolved = memory.origins.load(memory.facts) if memory.origins is not None else None
    if reference.trajectory is not None:  # its pseudo-stations along the path
        resolved = trajectory_origin(reference, loaded.reference_points, loaded.local_origin)
    elif resolved is None:
        resolved = resolve_stations(
            "reference",
            loaded.reference_points,
            given=origins_in_local_frame(
                settings.reference_origin, None, loaded.local_origin, "reference_origin"
            ),
            from_file=origins_in_local_frame(None, reference.sensor_origin, loaded.local_origin),
            estimate=settings.estimate_origins,
            recover=settings.recover_stations,
            station_of=reference,
        )
        if memory.origins is not None:
            memory.origins.remember(resolved, memory.facts)
    return CloudOrigins(resolved, station_index(reference, resolved, "reference"))


def resolve_scan_origins(
    loaded: LoadedPair, alignment: Alignment, reference: CloudOrigins
) -> CloudOrigins:
    """The scan's origins in the aligned frame: a trajectory's pseudo-stations moved by the
    registration, else resolved in the scan's own frame and moved
    (:func:`resolve_moved_cloud`)."""
    scan, settings = loaded.scan, loaded.settings
    transform = alignment.registration.transform
    if scan.trajectory is not None:
        resolved: ResolvedOrigin = trajectory_origin(
            scan,
            alignment.aligned_scan,
            loaded.local_origin,
            lambda origins: apply_transform(origins, transform),
        )
    else:
        if loaded.scan_points is None:
            raise ValueError("the scan's local points were released before its origins")
        resolved = resolve_moved_cloud(
            "scan",
            loaded.scan_points,
            transform,
            aligned_points=alignment.aligned_scan,
            given=origins_in_local_frame(
                settings.scan_origin, None, loaded.local_origin, "scan_origin"
            ),
            from_file=origins_in_local_frame(None, scan.sensor_origin, loaded.local_origin),
            estimate=settings.estimate_origins,
            recover=settings.recover_stations,
            station_of=scan,
            # a reference surveyed from several stations: the scan's are searched first
            stations_first=reference.resolved.source == "recovered",
        )
    return CloudOrigins(resolved, station_index(scan, resolved, "scan"))
