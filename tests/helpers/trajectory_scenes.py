"""Small moving-sensor maps for the trajectory tests: a corridor swept along a path.

A closed corridor (12 x 4 x 3 m, offset from the file origin) with a partition near its far end
(a gap of 0.6 m by one wall), a box ``seen_box`` that the scan's path sees the place of, and a
box ``hidden_box`` behind the partition that only the reference's path sees.  Each epoch is a
spinning lidar (coarse grid) stopping every ``step`` metres along its own path for one sweep
of 0.1 s, merged and voxel-thinned; each point keeps its time, the trajectory holds a pose at
the start and the end of each sweep.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import PointCloud
from app.core.datasets.lidar import LidarWorld, lidar_directions
from app.core.trajectory import Trajectory

OFFSET = np.array([100.0, 200.0, 10.0])
SHELL_LOW = np.zeros(3)
SHELL_HIGH = np.array([12.0, 4.0, 3.0])
PARTITION = (np.array([7.0, 0.0, 0.0]), np.array([7.2, 3.4, 3.0]))
SEEN_BOX = (np.array([3.0, 2.6, 0.0]), np.array([3.7, 3.3, 0.8]))
HIDDEN_BOX = (np.array([9.0, 0.5, 0.0]), np.array([9.6, 1.1, 0.9]))
SWEEP_SECONDS = 0.1


@dataclass(frozen=True)
class SweptMap:
    """One epoch: its cloud (with ``"time"`` and its trajectory) and each point's true box."""

    cloud: PointCloud
    exact: NDArray[np.float64]
    trajectory: Trajectory


def _world(boxes: list[tuple[NDArray, NDArray]]) -> LidarWorld:
    return LidarWorld(
        shell_low=SHELL_LOW,
        shell_high=SHELL_HIGH,
        box_low=np.array([low for low, _ in boxes]).reshape(-1, 3),
        box_high=np.array([high for _, high in boxes]).reshape(-1, 3),
    )


def swept_map(
    boxes: list[tuple[NDArray, NDArray]],
    path: NDArray[np.float64],
    *,
    step_deg: float = 2.5,
    azimuth_step_deg: float | None = None,
    voxel: float = 0.05,
    noise: float = 0.005,
    start_time: float = 1000.0,
    seed: int = 0,
    with_times: bool = True,
) -> SweptMap:
    """Sweep the world with ``boxes`` from each pose of ``path`` (p, 3), merge, thin.

    Rings ``step_deg`` apart, columns ``azimuth_step_deg`` apart (``step_deg`` when None: a
    finer one gives a ring lidar's floor, lines far apart with dense samples along each)."""
    rng = np.random.default_rng(seed)
    world = _world(boxes)
    points, exact, times = [], [], []
    pose_times, pose_positions = [], []
    for number, position in enumerate(path):
        directions = lidar_directions(
            step_deg, azimuth_step_deg or step_deg, yaw_deg=rng.uniform(0, 360)
        )
        distance, _ = world.cast(position, directions)
        keep = distance >= 0.3
        directions, distance = directions[keep], distance[keep]
        exact.append(position + distance[:, None] * directions)
        measured = distance + rng.normal(0.0, noise, distance.shape)
        points.append(position + measured[:, None] * directions)
        sweep_start = start_time + number * 1.0
        azimuth = np.arctan2(directions[:, 1], directions[:, 0])
        times.append(sweep_start + SWEEP_SECONDS * (azimuth + np.pi) / (2 * np.pi))
        pose_times += [sweep_start, sweep_start + SWEEP_SECONDS + 1e-3]
        pose_positions += [position, position]
    merged, merged_exact, merged_times = np.vstack(points), np.vstack(exact), np.concatenate(times)
    _, first = np.unique(np.floor(merged / voxel).astype(np.int64), axis=0, return_index=True)
    first = np.sort(first)
    trajectory = Trajectory(np.array(pose_times), np.array(pose_positions) + OFFSET)
    attributes = {"time": merged_times[first]} if with_times else {}
    cloud = PointCloud.from_array(merged[first] + OFFSET, attributes)
    cloud = dataclasses.replace(cloud, trajectory=trajectory)
    return SweptMap(cloud=cloud, exact=merged_exact[first] + OFFSET, trajectory=trajectory)


def corridor_pair(*, with_times: bool = True, step: float = 0.5) -> tuple[SweptMap, SweptMap]:
    """(reference, scan): the reference has both boxes and walks the whole corridor through the
    partition's gap; the scan lost both boxes and walks only the near half."""
    reference_path = np.column_stack(
        [
            np.arange(1.0, 11.01, step),
            np.full(int(10 / step) + 1, 3.7),
            np.full(int(10 / step) + 1, 1.0),
        ]
    )
    scan_x = np.arange(1.0, 5.01, step)
    scan_path = np.column_stack([scan_x, np.full(scan_x.size, 1.2), np.full(scan_x.size, 1.1)])
    reference = swept_map(
        [PARTITION, SEEN_BOX, HIDDEN_BOX], reference_path, seed=1, with_times=with_times
    )
    scan = swept_map([PARTITION], scan_path, seed=2, start_time=5000.0, with_times=with_times)
    return reference, scan


def in_box(points: NDArray[np.float64], box: tuple[NDArray, NDArray], margin: float = 0.02):
    """Which points (file frame) lie on or in ``box`` (within ``margin``), shape (n,)."""
    low, high = box[0] + OFFSET - margin, box[1] + OFFSET + margin
    return ((points >= low) & (points <= high)).all(axis=1)


def without_band_round_box(
    cloud: PointCloud, box: tuple[NDArray, NDArray], margin: float, heights: tuple[float, float]
) -> PointCloud:
    """``cloud`` (times and trajectory kept) without its points over ``box``'s footprint widened
    by ``margin`` whose height (scene frame) lies strictly between ``heights``: the floor or
    the desk underside the other path's sweeps happened not to sample there."""
    points = np.asarray(cloud.points)
    local = points - OFFSET
    low, high = box[0][:2] - margin, box[1][:2] + margin
    hole = (
        np.all((local[:, :2] > low) & (local[:, :2] < high), axis=1)
        & (local[:, 2] > heights[0])
        & (local[:, 2] < heights[1])
    )
    kept = PointCloud.from_array(
        points[~hole], {"time": np.asarray(cloud.attributes["time"])[~hole]}
    )
    return dataclasses.replace(kept, trajectory=cloud.trajectory)
