"""Ingest speed of ``bench/perf.py``: ``read_point_cloud`` against ``numpy.fromfile``.

The same ray-cast cloud is written as binary PLY, binary PCD and LAZ (millimetre scale); each
file is read once to warm the page cache, then the best of ``repeats`` reads is kept for both
``read_point_cloud`` and ``numpy.fromfile`` of the file's bytes (the floor: no parsing).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pypcd4
from numpy.typing import NDArray

from app.core.formats import read_point_cloud
from app.core.synthetic import raycast_scene
from bench.perf_workers import SCENE_SEED, write_binary_ply


def write_pcd(path: Path, points: NDArray[np.float64]) -> None:
    """A binary PCD with float32 x, y, z."""
    pypcd4.PointCloud.from_xyz_points(points.astype(np.float32)).save(str(path))


def write_laz(path: Path, points: NDArray[np.float64]) -> None:
    """A LAZ 1.2 file, point format 3, millimetre scale."""
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = points.min(axis=0)
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.write(str(path), do_compress=True)


def best_seconds(action: Callable[[], object], repeats: int) -> float:
    """Fastest of ``repeats`` timed calls of ``action``."""
    timings = []
    for _ in range(repeats):
        started = time.perf_counter()
        action()
        timings.append(time.perf_counter() - started)
    return min(timings)


def measure_ingest(work_dir: Path, n_points: int, repeats: int = 3) -> dict[str, dict[str, Any]]:
    """Per format: file size, read and fromfile seconds, share of fromfile speed, MB/s."""
    points = raycast_scene(n_points=n_points, change="none", random_state=SCENE_SEED).reference
    ingest_dir = work_dir / "ingest"
    ingest_dir.mkdir(parents=True, exist_ok=True)
    writers = {"ply": write_binary_ply, "pcd": write_pcd, "laz": write_laz}
    results: dict[str, dict[str, Any]] = {}
    for name, writer in writers.items():
        path = ingest_dir / f"cloud.{name}"
        writer(path, points)
        cloud = read_point_cloud(path)  # warm the page cache and check the content
        if len(cloud) != len(points):
            raise RuntimeError(f"{name}: read {len(cloud)} of {len(points)} points")
        read_seconds = best_seconds(lambda path=path: read_point_cloud(path), repeats)
        fromfile_seconds = best_seconds(
            lambda path=path: np.fromfile(path, dtype=np.uint8), repeats
        )
        megabytes = path.stat().st_size / 1e6
        results[name] = {
            "megabytes": megabytes,
            "read_seconds": read_seconds,
            "fromfile_seconds": fromfile_seconds,
            "share_of_fromfile": fromfile_seconds / read_seconds,
            "mb_per_second": megabytes / read_seconds,
            "points_per_second": len(points) / read_seconds,
        }
    return results
