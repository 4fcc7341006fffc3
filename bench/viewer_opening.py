"""Where the 3D view opens (issue 31): the time to choose the opening camera, and how much of
the change the unchanged points hide from it and from the old whole-scene camera.

    .venv/bin/python bench/viewer_opening.py --step 2.0

Scenes with their ground-truth labels: lidar rescans of a room, a corridor and a warehouse
(a box removed, a box added; ``--step`` degrees between lidar rays), and with
``--kitti`` the real KITTI street frame 0 with a car-sized box of points added 12 m ahead.
Prints, per scene, the points drawn, the milliseconds to choose the camera, the reason, and the
share of changed points whose line of sight crosses unchanged points (occupancy grid of the
chooser) from the chosen camera and from the old one (south-west, above, the whole scene).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from app.core.datasets.lidar import lidar_pair
from app.viewer.opening import (
    OccupancyGrid,
    blocked_shares,
    point_spacing,
    whole_scene_view,
)
from app.viewer.scene import SceneData, build_scene_data

KITTI = (
    Path(__file__).resolve().parents[2]
    / "shared/data/real/kitti_2011_09_26_drive_0002_pointcloudset/frame0.ply"
)


def truth_labels(changed: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """1 changed, 0 unchanged, -1 unobserved."""
    labels = np.where(changed, 1, 0).astype(np.int8)
    labels[~observed & ~changed] = -1
    return labels


def hidden_from(data: SceneData, camera: np.ndarray) -> float:
    """Share of the drawn changed points hidden from ``camera`` by the drawn unchanged ones."""
    clip = data.opening.clip_high
    unchanged = np.concatenate([data.layer(name).points for name in ("reference", "scan")])
    unchanged = unchanged[unchanged[:, 2] <= clip].astype(np.float64)
    changed = np.concatenate([data.layer(name).points for name in ("removed", "added")])
    changed = changed[changed[:, 2] <= clip].astype(np.float64)
    if len(changed) == 0:
        return math.nan
    voxel = max(1.5 * point_spacing(unchanged), 0.05, float(np.ptp(unchanged, axis=0).max()) / 300)
    grid = OccupancyGrid(unchanged, voxel)
    return float(blocked_shares(grid, camera.reshape(1, 3), changed[:256], 3.0 * voxel)[0])


def report(name: str, data: SceneData) -> None:
    """Choose the camera (timed) and print the line of one scene."""
    start = time.perf_counter()
    opening = data.opening
    elapsed = (time.perf_counter() - start) * 1000.0
    old = whole_scene_view(data.bounds_min, data.bounds_max, opening.clip_high)
    print(
        f"{name:28s} {data.n_shown:>8,d} pts  choose {elapsed:7.1f} ms  {opening.reason:22s} "
        f"hidden: chosen {hidden_from(data, opening.position):.2f}, "
        f"old {hidden_from(data, old.position):.2f}"
    )


def main() -> None:
    """Run the scenes and print their lines."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--step", type=float, default=2.0, help="degrees between lidar rays")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--kitti", action="store_true", help="also the real KITTI frame")
    arguments = parser.parse_args()
    for layout in ("room", "corridor", "warehouse"):
        for change in ("removed", "added"):
            for seed in range(arguments.seeds):
                pair = lidar_pair(
                    layout=layout,
                    change=change,
                    angular_step_deg=(arguments.step, arguments.step / 2),
                    random_state=seed,
                )
                data = build_scene_data(
                    pair.reference,
                    pair.scan,
                    reference_labels=truth_labels(pair.reference_changed, pair.reference_observed),
                    scan_labels=truth_labels(pair.scan_changed, pair.scan_observed),
                    transform=pair.true_transform,
                )
                report(f"{layout} {change} seed {seed}", data)
    if arguments.kitti and KITTI.exists():
        from app.core.formats import read_point_cloud

        street = read_point_cloud(KITTI).points
        car = np.random.default_rng(0).uniform([10, 2.1, -1.7], [14, 3.9, -0.2], (4000, 3))
        labels = np.concatenate([np.zeros(len(street), np.int8), np.ones(len(car), np.int8)])
        data = build_scene_data(
            street,
            np.vstack([street, car]),
            reference_labels=np.zeros(len(street), np.int8),
            scan_labels=labels,
        )
        report("kitti frame 0 + car", data)


if __name__ == "__main__":
    main()
