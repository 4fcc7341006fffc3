"""A trajectory kept beside the scan file it belongs to (``<file>.trajectory.npz``).

Written when a trajectory is uploaded with a scan or added to it later, read with the scan by
the comparisons that use it.
"""

from __future__ import annotations

import dataclasses
import io
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from app.core.cloud import PointCloud
from app.core.trajectory import Trajectory

__all__ = [
    "TRAJECTORY_SUFFIX",
    "load_trajectory",
    "save_trajectory",
    "trajectory_path",
    "with_stored_trajectory",
]

TRAJECTORY_SUFFIX = ".trajectory.npz"


def trajectory_path(scan_path: Path) -> Path:
    """Where the trajectory of the scan stored at ``scan_path`` is kept (beside it)."""
    return scan_path.with_name(scan_path.name + TRAJECTORY_SUFFIX)


def save_trajectory(path: Path, trajectory: Trajectory) -> None:
    """Write the trajectory atomically to ``path`` (npz)."""
    buffer = io.BytesIO()
    arrays: dict[str, Any] = {
        "times": trajectory.times,
        "positions": trajectory.positions,
        "has_times": np.asarray(trajectory.has_times),
    }
    if trajectory.orientations is not None:
        arrays["orientations"] = trajectory.orientations
    np.savez(buffer, **arrays)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, name = tempfile.mkstemp(dir=path.parent, prefix=".trajectory-")
    with os.fdopen(handle, "wb") as stream:
        stream.write(buffer.getvalue())
    os.replace(name, path)


def load_trajectory(path: Path) -> Trajectory | None:
    """The trajectory stored at ``path``, or None when there is none."""
    if not path.is_file():
        return None
    with np.load(path, allow_pickle=False) as stored:
        return Trajectory(
            stored["times"],
            stored["positions"],
            stored["orientations"] if "orientations" in stored.files else None,
            has_times=bool(stored["has_times"]),
        )


def with_stored_trajectory(cloud: PointCloud, scan_path: Path) -> PointCloud:
    """``cloud`` with the trajectory stored beside its file, if any."""
    trajectory = load_trajectory(trajectory_path(scan_path))
    return cloud if trajectory is None else dataclasses.replace(cloud, trajectory=trajectory)
