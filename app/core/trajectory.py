"""A moving sensor's trajectory: timed poses, in the frame of the cloud it belongs to.

Robot SLAM maps, mobile laser scanning and handheld RGB-D maps are taken from a path rather than
from a station.  A :class:`Trajectory` holds that path (pose times, positions, optional
orientations); per-point times, where a file has them, live in the cloud's ``"time"`` attribute.
Readers of trajectory files and the per-point sensor positions derived from a trajectory build
on this container.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.errors import InputError


class TrajectoryError(InputError):
    """A trajectory file or array is malformed, or does not fit the cloud it is given with."""


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Timed sensor poses along a path.

    Attributes
    ----------
    times : ndarray, shape (m,), float64
        Pose times in seconds, strictly increasing (the same clock as the points' ``"time"``
        attribute, when the cloud has one).
    positions : ndarray, shape (m, 3), float64
        Sensor positions, in the frame of the cloud's points.
    orientations : ndarray, shape (m, 4), float64, or None
        Unit quaternions ``(qx, qy, qz, qw)`` of the sensor's attitude, when known.
    has_times : bool
        False when the file gave no times (KITTI poses without a times file or rate): ``times``
        is then the pose order (0, 1, ...), enough for points without per-point times (each
        takes its nearest visible pose) but not for points with times.
    """

    times: NDArray[np.float64]
    positions: NDArray[np.float64]
    orientations: NDArray[np.float64] | None = None
    has_times: bool = True

    def __post_init__(self) -> None:
        times = np.asarray(self.times, dtype=np.float64)
        positions = np.asarray(self.positions, dtype=np.float64)
        if times.ndim != 1 or positions.shape != (times.shape[0], 3):
            raise TrajectoryError(
                f"a trajectory needs m times and (m, 3) positions, got {times.shape} and "
                f"{positions.shape}"
            )
        if times.shape[0] < 1:
            raise TrajectoryError("the trajectory has no poses")
        if not (np.isfinite(times).all() and np.isfinite(positions).all()):
            raise TrajectoryError("the trajectory has non-finite times or positions")
        if times.shape[0] > 1 and not (np.diff(times) > 0).all():
            raise TrajectoryError("the trajectory's times must be strictly increasing")
        orientations = self.orientations
        if orientations is not None:
            orientations = np.asarray(orientations, dtype=np.float64)
            if orientations.shape != (times.shape[0], 4):
                raise TrajectoryError(
                    f"a trajectory's orientations must have shape (m, 4), got {orientations.shape}"
                )
            if not np.isfinite(orientations).all():
                raise TrajectoryError("the trajectory has non-finite quaternions")
            norms = np.linalg.norm(orientations, axis=1)
            if np.abs(norms - 1.0).max() > 1e-3:
                raise TrajectoryError(
                    "the trajectory's quaternions must be unit quaternions (qx, qy, qz, qw): "
                    f"norms range {norms.min():.4g}-{norms.max():.4g}"
                )
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "orientations", orientations)

    def __len__(self) -> int:
        return int(self.times.shape[0])
