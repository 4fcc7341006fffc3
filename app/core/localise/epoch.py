"""One epoch's cloud as :func:`~app.core.localise.changes.localise_changes` takes it: its
points and what is known of the sensor that took them."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from app.core.localise.neighbourhoods import Neighbourhoods, NeighbourhoodSearch
from app.core.localise.settings import as_station_index
from app.core.localise.station_assignment import assign_stations
from app.core.localise.station_occlusion import reassign_hidden_returns


@dataclass(frozen=True)
class EpochCloud:
    """One epoch (the reference or the aligned scan) of a localisation.

    Attributes
    ----------
    points : array_like, shape (n, 3)
        In the comparison's frame (the scan already aligned into the reference's).
    origin : array_like, shape (3,) or (k, 3), optional
        The sensor's position, or one per station of a cloud merged from k stations, in the
        same frame.  Enables the ray visibility test for the *other* cloud's points
        (observed = observed by any station); without it they get the coverage test.
    station : array_like, shape (n,), int, optional
        Index into ``origin`` of the station that took each point.  Without it a cloud with
        several origins has its points assigned to stations
        (:func:`~app.core.localise.station_assignment.assign_stations`).
    stations_unknown : bool
        The cloud was sampled by lidars from several stations that are not known (nor
        recovered): the other cloud's candidates get the origin-free surface test
        (``origin_free_test="auto"``, :func:`~app.core.localise.visibility.label_candidates`).
    trajectory_rays : (ndarray, ndarray), optional
        The cloud was taken along a trajectory: ``origin`` holds its pseudo-stations' sensor
        positions, ``station`` each point's pseudo-station, and these ``(returns, bounds)`` the
        points each pseudo-station's rays end on
        (:class:`app.core.trajectory_poses.SensorGroups`); the other cloud's candidates get the
        trajectory test (:mod:`~app.core.localise.trajectory_visibility`).
    neighbourhoods : Neighbourhoods or NeighbourhoodSearch, optional
        :func:`~app.core.localise.neighbourhoods.nearest_neighbourhoods` of ``points`` with
        :func:`~app.core.localise.neighbourhoods.neighbourhood_size` neighbours, computed ahead
        (:func:`~app.core.localise.neighbourhoods.start_neighbourhood_search`).  The result is
        the same as without it.
    """

    points: ArrayLike
    origin: ArrayLike | None = None
    station: ArrayLike | None = None
    stations_unknown: bool = False
    trajectory_rays: tuple[NDArray, NDArray] | None = None
    neighbourhoods: Neighbourhoods | NeighbourhoodSearch | None = None

    @classmethod
    def of(cls, cloud: EpochCloud | ArrayLike) -> EpochCloud:
        """``cloud`` itself, or bare points (no origin known) as an epoch."""
        return cloud if isinstance(cloud, EpochCloud) else cls(points=cloud)

    def subset(self, keep: NDArray[np.bool_] | NDArray[np.integer]) -> EpochCloud:
        """The points selected by ``keep`` (a mask or indices, shape (n,) / (k,)), with their
        station indices; origins kept, neighbourhoods and trajectory rays dropped (they index
        the whole cloud).

        Raises
        ------
        ValueError
            With trajectory rays: a trajectory's pseudo-stations cannot be cropped this way.
        """
        if self.trajectory_rays is not None:
            raise ValueError("a cloud taken along a trajectory cannot be subset")
        station = None if self.station is None else np.asarray(self.station)[keep]
        return EpochCloud(
            points=np.asarray(self.points)[keep],
            origin=self.origin,
            station=station,
            stations_unknown=self.stations_unknown,
        )


def with_checked_stations(epoch: EpochCloud, name: str) -> tuple[EpochCloud, str]:
    """``epoch`` with its checked per-point station index and where that came from:
    ``"given"``, ``"assigned"`` (from the rings, several origins and no index), ``"single"``
    (one origin) or ``"none"`` (no origin).

    Raises
    ------
    InputError
        An index of the wrong shape or type, out of range, or without the origins.
    """
    points = np.asarray(epoch.points)
    origins = None if epoch.origin is None else np.asarray(epoch.origin)
    station, assignment = _stations_of(points, origins, epoch.station, name)
    return dataclasses.replace(epoch, station=station), assignment


def _stations_of(
    points: NDArray[np.float64],
    origins: NDArray[np.float64] | None,
    station: NDArray | None,
    name: str,
) -> tuple[NDArray[np.int64] | None, str]:
    """The checked per-point station index of one cloud, and where it came from.

    Returns
    -------
    station : ndarray, shape (n,), int64, or None
        None without origins or with one origin and no index (every point is its).
    source : {"none", "single", "given", "assigned"}
    """
    checked = as_station_index(
        station, points.shape[0], None if origins is None else len(origins), name
    )
    if checked is not None:
        return checked, "given"
    if origins is None:
        return None, "none"
    if len(origins) == 1:
        return None, "single"
    # by the rings, then each return hidden behind its station's own returns to one that saw it
    return reassign_hidden_returns(points, origins, assign_stations(points, origins)), "assigned"
