"""A moved cloud's origin, from whichever of its two frames has the lidar's rings level.

A scan is compared after alignment onto the reference, but its lidar's axis is vertical in
only one of its two frames: a Velodyne frame is level in its own file and tilted once aligned
onto a reference taken at another pitch (the car pitched between frames), while a file tilted
against the world (a misaligned export) is level only after alignment.  The estimators
(:mod:`~app.core.origins.estimate`) assume the axis is vertical within a degree or so, so:
resolve in the aligned frame first; when nothing was given and no confident origin came out,
but the returns still lie on rings (one spinning lidar, seen a little tilted), estimate again
in the cloud's own frame, where its axis is vertical, and move that origin by the alignment.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import PointCloud
from app.core.localise.station_assignment import STATION_INDEX_ATTRIBUTE
from app.core.origins.estimate import RING_SHARE_RANGE
from app.core.origins.resolve import ResolvedOrigin
from app.core.origins.station_recovery import EarlySearch, recovered_before_apex, resolve_stations
from app.core.registration import apply_transform

__all__ = ["OWN_FRAME_RETRY_RING_SHARE", "resolve_moved_cloud"]

OWN_FRAME_RETRY_RING_SHARE = RING_SHARE_RANGE[0]
"""The origin is estimated again in the cloud's own frame when this share of its returns lay
on rings once aligned (a KITTI frame: 0.70; the synthetic merged surveys: at most 0.49, so
they skip the second estimate, ~0.3 s at 100k points, which could not succeed) ..."""
OWN_FRAME_RETRY_TILT_DEG = 1.0
"""... or when the alignment tilts the cloud's z axis by more than this (degrees): a few
degrees of tilt blur a lidar's rings, so the aligned ring share no longer tells (the synthetic
misaligned pairs tilt 0.3-0.4 degrees)."""


def resolve_moved_cloud(
    side: str,
    own_points: NDArray[np.float64],
    transform: NDArray[np.float64],
    *,
    aligned_points: NDArray[np.float64] | None = None,
    given: NDArray[np.float64] | None,
    from_file: NDArray[np.float64] | None,
    estimate: bool,
    recover: bool | str,
    station_of: PointCloud | None = None,
    stations_first: bool = False,
) -> ResolvedOrigin:
    """The origin(s) of a cloud moved by ``transform``, in the moved (aligned) frame.

    Parameters
    ----------
    side : str
        "reference" or "scan" (for the warnings).
    own_points : ndarray, shape (n, 3)
        The cloud in its own frame.
    transform : ndarray, shape (4, 4)
        From its own frame to the aligned one.
    aligned_points : ndarray, shape (n, 3), optional
        ``own_points`` moved by ``transform`` (computed when not given).
    given, from_file : ndarray, shape (k, 3) / (3,), or None
        Origins in the cloud's own frame.
    estimate : bool
    recover : {True, False, "auto"}
        As for :func:`~app.core.origins.station_recovery.resolve_stations`; with ``"auto"`` the
        stations are searched (in the aligned frame) only when the own frame gives no
        origin either.
    station_of : PointCloud, optional
        The cloud ``own_points`` come from (its per-point station index, if any).
    stations_first : bool
        The other epoch was a merged survey: with ``"auto"``, the stations are searched before
        the single-origin estimate
        (:func:`~app.core.origins.station_recovery.recovered_before_apex`), and used without the
        own-frame retry when they qualify.

    Returns
    -------
    ResolvedOrigin
        Resolved in the aligned frame; or, when nothing was given and that gave no origin
        though at least :data:`OWN_FRAME_RETRY_RING_SHARE` of the returns lay on rings or the
        alignment tilts the cloud by more than :data:`OWN_FRAME_RETRY_TILT_DEG`, resolved in
        the own frame and moved by ``transform``.
    """
    if aligned_points is None:
        aligned_points = apply_transform(own_points, transform)

    def aligned(origins: NDArray[np.float64] | None) -> NDArray[np.float64] | None:
        return None if origins is None else apply_transform(origins, transform)

    # "auto": the stations are searched only once the own frame gave no origin either
    deferred = recover == "auto" and given is None and from_file is None
    own_station_of = station_of
    if station_of is not None and station_of.sampling_points is not None:
        # a subsample's whole voxels at full density, moved with it (the stations' search)
        station_of = dataclasses.replace(
            station_of, sampling_points=aligned(station_of.sampling_points)
        )
    options = {
        "estimate": estimate,
        "recover": False if deferred else recover,
        "station_of": station_of,
    }

    def unresolved(resolved: ResolvedOrigin) -> ResolvedOrigin:
        if not deferred:
            return resolved
        return resolve_stations(
            side,
            aligned_points,
            given=None,
            from_file=None,
            resolved=resolved,
            early=early,
            recover="auto",
            estimate=estimate,
            station_of=station_of,
        )

    early: EarlySearch | None = None  # the stations searched before the apex search, if so
    tilt = np.rad2deg(np.arccos(np.clip(np.asarray(transform)[2, 2], -1.0, 1.0)))
    by_station = station_of is not None and STATION_INDEX_ATTRIBUTE in station_of.attributes
    if deferred and estimate and tilt <= OWN_FRAME_RETRY_TILT_DEG and not by_station:
        # a merged survey's stations before the apex search, when no retry in the own frame
        # would come first (rings too unclear for one and not tilted)
        early = recovered_before_apex(
            side,
            aligned_points,
            {"given": None, "from_file": None, "estimate": estimate},
            0,
            stations_first=stations_first,
            station_of=station_of,
        )
        if early is not None and early[0].origin is not None:
            ring_share = early[0].evidence.get("ring_share", 1.0)
            # searched first, against a merged reference: no single lidar to retry for
            if (
                early[0].source != "recovered"
                or ring_share < OWN_FRAME_RETRY_RING_SHARE
                or stations_first
            ):
                return early[0]
        if early is not None and early[0].origin is not None:
            early = None  # a single origin found there; the rest does not reuse it
    resolved = resolve_stations(
        side, aligned_points, given=aligned(given), from_file=aligned(from_file), **options
    )
    if resolved.origin is not None or given is not None or from_file is not None:
        return resolved
    ring_share = (resolved.evidence or {}).get("ring_share", 0.0)
    if not estimate or (
        ring_share < OWN_FRAME_RETRY_RING_SHARE and tilt <= OWN_FRAME_RETRY_TILT_DEG
    ):
        return unresolved(resolved)  # level, not a single lidar's rings: no retry
    own_frame = resolve_stations(
        side, own_points, given=None, from_file=None, **{**options, "station_of": own_station_of}
    )
    if own_frame.origin is None:
        return unresolved(resolved)
    origin = np.asarray(own_frame.origin, dtype=np.float64)
    moved = apply_transform(origin.reshape(-1, 3), transform).reshape(origin.shape)
    return dataclasses.replace(own_frame, origin=moved)
