"""The files kept beside a stored scan, named from the scan file's path.

* ``<file>.trajectory.npz``: the moving sensor's trajectory sent with the scan or added later
  (:func:`save_trajectory`, :func:`with_stored_trajectory`);
* ``<file>.bag-options.json``: the parameters an uploaded ROS bag is read with
  (:func:`save_bag_options`, :func:`stored_bag_options`), so that every later read (a job, a
  labels download, the 3D view) builds the same map.

Service file layout, not numeric code: the core reads clouds and trajectories, this module
says where the service keeps them.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from app.core.cloud import PointCloud
from app.core.files import write_atomically
from app.core.formats.rosbag import BagOptions, bag_options_from_strings
from app.core.trajectory import Trajectory

__all__ = [
    "BAG_OPTIONS_SUFFIX",
    "TRAJECTORY_SUFFIX",
    "bag_options_path",
    "load_trajectory",
    "save_bag_options",
    "save_trajectory",
    "stored_bag_options",
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


BAG_OPTIONS_SUFFIX = ".bag-options.json"


def bag_options_path(bag_path: Path) -> Path:
    """Where the parameters of the bag stored at ``bag_path`` are kept (beside it)."""
    return bag_path.with_name(bag_path.name + BAG_OPTIONS_SUFFIX)


def save_bag_options(bag_path: Path, parameters: dict[str, str]) -> Path:
    """Keep ``parameters`` (``KEY=VALUE`` strings, as the upload took them) beside the bag,
    atomically; the file written."""
    path = bag_options_path(bag_path)
    write_atomically(path, lambda temporary: temporary.write_text(json.dumps(parameters)))
    return path


def stored_bag_options(bag_path: Path) -> BagOptions | None:
    """The parameters kept beside ``bag_path`` (:func:`bag_options_path`), None without."""
    path = bag_options_path(Path(bag_path))
    if not path.is_file():
        return None
    return bag_options_from_strings(json.loads(path.read_text(encoding="utf-8")))
