"""The moving sensors' paths in the 3D view: one polyline per side that has a trajectory.

A job whose cloud was taken along a trajectory reports it in ``sensor_origins`` as
``{"source": "trajectory", "path": [[x, y, z], ...], ...}`` (thinned, in the file's frame).  The
scan's path is moved into the reference frame with the job's registration, like its points.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.registration import apply_transform

__all__ = ["TrajectoryPath", "draw_trajectory_paths", "trajectory_paths"]

SIDES = ("reference", "scan")


@dataclass(frozen=True)
class TrajectoryPath:
    """One side's sensor path.

    Attributes
    ----------
    side : {"reference", "scan"}
    positions_local : ndarray, shape (p, 3), float32
        The path's positions in the scene's local frame (reference frame minus its origin).
    """

    side: str
    positions_local: NDArray[np.float32]

    @property
    def segments(self) -> NDArray[np.float32]:
        """Consecutive positions as line segments, shape (p - 1, 2, 3)."""
        return np.stack([self.positions_local[:-1], self.positions_local[1:]], axis=1)


def trajectory_paths(
    sensor_origins: Mapping[str, Any], transform: NDArray[np.float64], origin: NDArray[np.float64]
) -> tuple[TrajectoryPath, ...]:
    """The paths a job's ``sensor_origins`` report (malformed entries are skipped).

    Parameters
    ----------
    sensor_origins : mapping
        ``{"reference": [...], "scan": [...]}`` as a job stores it.
    transform : ndarray, shape (4, 4)
        The registration: maps scan-file coordinates into the reference frame.
    origin : ndarray, shape (3,)
        The scene's local origin.
    """
    paths = []
    for side in SIDES:
        entries = sensor_origins.get(side) if isinstance(sensor_origins, Mapping) else None
        for entry in entries if isinstance(entries, Sequence) else ():
            if not isinstance(entry, Mapping) or entry.get("source") != "trajectory":
                continue
            try:
                positions = np.asarray(entry.get("path"), dtype=np.float64).reshape(-1, 3)
            except (TypeError, ValueError):
                continue
            if positions.shape[0] < 2 or not np.isfinite(positions).all():
                continue
            if side == "scan":
                positions = apply_transform(positions, transform)
            paths.append(TrajectoryPath(side, (positions - origin).astype(np.float32)))
    return tuple(paths)


def draw_trajectory_paths(
    scene: Any,
    paths: Sequence[TrajectoryPath],
    colours: Mapping[str, tuple[int, int, int]],
    thickness: float,
) -> list[Any]:
    """A polyline in its side's colour per path (viser line segments); the handles."""
    return [
        scene.add_line_segments(
            f"/trajectories/{path.side}-{number}",
            points=path.segments,
            colors=np.asarray(colours[path.side], dtype=np.uint8),
            thickness=thickness,
        )
        for number, path in enumerate(paths)
    ]
