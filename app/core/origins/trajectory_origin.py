"""The sensor origins of a cloud taken along a trajectory: its pseudo-stations.

A cloud with a :class:`~app.core.trajectory.Trajectory` skips the origin search: its points are
cut into pseudo-stations along the path (:func:`~app.core.trajectory_poses.sensor_groups`, with
the ``"time"`` attribute when the cloud has one), whose mean sensor positions are its origins
and whose index per point is its station index.  ``sensor_origins`` reports the trajectory
(``{"source": "trajectory", "poses", "time_span", "points_outside", ...}``, with the path
thinned for the 3D view) instead of one entry per station.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import PointCloud
from app.core.origins.known_stations import station_index_of
from app.core.origins.resolve import ResolvedOrigin
from app.core.trajectory_poses import sensor_groups

__all__ = [
    "PATH_POINTS",
    "TIME_ATTRIBUTE",
    "TrajectoryOrigin",
    "station_index",
    "trajectory_origin",
    "trajectory_rays",
]

TIME_ATTRIBUTE = "time"
PATH_POINTS = 500
"""Most path positions reported (for the 3D view's polyline)."""


@dataclass(frozen=True)
class TrajectoryOrigin(ResolvedOrigin):
    """A :class:`ResolvedOrigin` from a trajectory: ``origin`` (k, 3) the pseudo-stations'.

    Attributes
    ----------
    station : ndarray, shape (n,), int64
        Each point's pseudo-station.
    rays : (ndarray, ndarray)
        ``(returns, bounds)``: the points each pseudo-station's rays end on
        (:class:`~app.core.trajectory_poses.SensorGroups`).
    path_report : dict
        The trajectory's entry of ``sensor_origins`` (file frame).
    """

    station: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    rays: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None
    path_report: dict[str, Any] = field(default_factory=dict)

    def visibility_report(self) -> dict[str, Any]:
        """``{"origins": "trajectory", "trajectory": {poses, groups, assignment...}}``."""
        summary = {key: value for key, value in self.path_report.items() if key != "path"}
        return {"origins": "trajectory", "stations_unknown": False, "trajectory": summary}

    def report(self, to_file: Callable[[NDArray[np.float64]], NDArray[np.float64]]) -> list:
        """``[{"source": "trajectory", "poses", "time_span", "points_outside", "path", ...}]``
        (the path is in the file's frame already: ``to_file`` is not needed)."""
        return [dict(self.path_report)]


def trajectory_origin(
    cloud: PointCloud,
    points: NDArray[np.float64],
    local_origin: NDArray[np.float64],
    to_points: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None,
) -> TrajectoryOrigin:
    """The pseudo-stations of ``cloud`` (which has a trajectory) in the frame of ``points``.

    Parameters
    ----------
    cloud : PointCloud
        Its ``points``, ``trajectory`` and optional ``"time"`` attribute, in the file's frame.
    points : ndarray, shape (n, 3)
        The same points as compared (shifted by ``local_origin``; the scan also aligned).
    local_origin : ndarray, shape (3,)
    to_points : callable, optional
        Maps (k, 3) positions shifted by ``local_origin`` into the frame of ``points`` (the
        scan's registration); identity when None.

    Raises
    ------
    TrajectoryError
        The trajectory does not cover the points' times, or has none where they are needed.
    """
    trajectory = cloud.trajectory
    assert trajectory is not None
    times = cloud.attributes.get(TIME_ATTRIBUTE)
    groups = sensor_groups(  # in the file's frame, as the trajectory
        cloud.points, trajectory, None if times is None else np.asarray(times, dtype=np.float64)
    )
    origins = groups.origins - local_origin
    if to_points is not None:
        origins = to_points(origins)
    thinned = trajectory.positions[
        np.unique(
            np.linspace(0, len(trajectory) - 1, min(PATH_POINTS, len(trajectory))).astype(int)
        )
    ]
    report = {**groups.report, "path": thinned.tolist()}
    return TrajectoryOrigin(
        origin=np.asarray(origins, dtype=np.float64),
        source="trajectory",
        confidence=None,
        station=groups.group,
        rays=(groups.returns, groups.bounds),
        path_report=report,
    )


def station_index(cloud: PointCloud, resolved: ResolvedOrigin, name: str) -> NDArray | None:
    """Each point's pseudo-station for a trajectory, else the cloud's checked station index
    (:func:`~app.core.origins.known_stations.station_index_of`)."""
    if isinstance(resolved, TrajectoryOrigin):
        return resolved.station
    return station_index_of(cloud, resolved, name)


def trajectory_rays(resolved: ResolvedOrigin) -> tuple[NDArray, NDArray] | None:
    """The pseudo-stations' rays of a trajectory's resolution, else None."""
    return resolved.rays if isinstance(resolved, TrajectoryOrigin) else None
