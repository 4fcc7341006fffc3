"""A :func:`~app.core.datasets.lidar.lidar_pair` written straight to binary PLY files, station by
station and ring by ring, in memory that does not grow with the pair (issue 30's 100M survey).

``lidar_pair`` holds every point of both epochs at once (about 230 bytes a point at its peak: a
100M-point pair does not fit in 24 GB).  :func:`write_lidar_pair` makes the same draws from the
same generator in the same order, so the files hold the same points as
``lidar_pair(...).reference`` and ``.scan`` written as float32; it casts each station's rays a
block of elevation rings at a time and keeps on disk what must wait for the later draws (the
file frame's offset and the scan's misalignment are drawn after every range's noise).

What differs: the points are in station order, each station's rays ring by ring, where
``lidar_pair`` shuffles each epoch (the shuffle needs the whole permutation in memory); the same
points, sorted, are identical (``tests/core/test_synthetic_lidar_files.py``).  The truth kept
beside the files (``truth.npz``) is the changed points' rows, whether the other epoch saw them,
the stations, the transform and the boxes of both worlds, all in the files' frames.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from app.core.datasets.lidar import (
    CHANGE_DISTANCE,
    ELEVATION_RANGE_DEG,
    MIN_VISIBLE_CHANGE,
    RANGE_LIMITS,
    LidarWorld,
    _observed_by,
    draw_scene,
    file_frame,
)
from app.core.datasets.scenes import _transform_points

__all__ = ["WRITE_CHUNK_RAYS", "WrittenLidarPair", "write_lidar_pair"]

WRITE_CHUNK_RAYS = 1 << 21
"""Rays cast (and points written) per step, at least one elevation ring: the files do not depend
on it; it bounds the memory (about 200 bytes a ray at once)."""
PLY_VERTEX_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")])


@dataclass(frozen=True)
class WrittenLidarPair:
    """Where :func:`write_lidar_pair` wrote the pair, and its sizes.

    Attributes
    ----------
    reference_path, scan_path : Path
        Binary little-endian PLY files, float32 ``x, y, z``.
    truth_path : Path
        ``truth.npz``: ``reference_changed_rows``, ``scan_changed_rows`` (int64 rows of the
        files), ``reference_changed_observed``, ``scan_changed_observed`` (bool, one per changed
        row), ``reference_origins``, ``scan_origins`` (s, 3), ``true_transform`` (4, 4),
        ``reference_box_low/high``, ``scan_box_low/high`` (b, 3, each world's boxes, in the
        reference file's frame), ``shell_low/high`` (3,).
    n_reference, n_scan : int
        Points in each file.
    """

    reference_path: Path
    scan_path: Path
    truth_path: Path
    n_reference: int
    n_scan: int


def ply_header(n_points: int) -> bytes:
    """The header of a binary little-endian PLY of ``n_points`` float32 ``x, y, z`` vertices
    (the bytes ``plyfile`` writes for it)."""
    lines = [
        "ply",
        "format binary_little_endian 1.0",
        f"element vertex {n_points}",
        "property float x",
        "property float y",
        "property float z",
        "end_header",
    ]
    return ("\n".join(lines) + "\n").encode("ascii")


def _ring_blocks(
    steps: tuple[float, float], yaw_deg: float, chunk_rays: int
) -> Iterator[NDArray[np.float64]]:
    """The rays of :func:`~app.core.datasets.lidar.lidar_directions` ``(*steps, yaw_deg)``, in
    its order, as blocks of whole elevation rings of about ``chunk_rays`` rays, shape (r, 3)."""
    low, high = ELEVATION_RANGE_DEG
    elevation = np.deg2rad(np.arange(low, high + 1e-9, steps[0]))
    azimuth = np.deg2rad(yaw_deg + np.arange(0.0, 360.0 - 1e-9, steps[1]))
    rings_a_block = max(1, chunk_rays // max(1, len(azimuth)))
    for start in range(0, len(elevation), rings_a_block):
        elevation_grid, azimuth_grid = np.meshgrid(
            elevation[start : start + rings_a_block], azimuth, indexing="ij"
        )
        cos_elevation = np.cos(elevation_grid.ravel())
        yield np.column_stack(
            [
                cos_elevation * np.cos(azimuth_grid.ravel()),
                cos_elevation * np.sin(azimuth_grid.ravel()),
                np.sin(elevation_grid.ravel()),
            ]
        )


@dataclass
class _EpochOnDisk:
    """One epoch cast to a float64 file of noisy world points, with its changed points."""

    points_path: Path
    count: int
    changed_rows: NDArray[np.int64]
    changed_exact: NDArray[np.float64]


def _cast_epoch(
    world: LidarWorld,
    other_world: LidarWorld,
    stations: NDArray[np.float64],
    steps: tuple[float, float],
    range_noise: float,
    rng: np.random.Generator,
    points_path: Path,
    chunk_rays: int,
) -> _EpochOnDisk:
    """``_scan_epoch``'s draws and points, block by block: the noisy world points appended to
    ``points_path`` (float64), the changed points (against ``other_world``) kept."""
    count = 0
    changed_rows: list[NDArray[np.int64]] = []
    changed_exact: list[NDArray[np.float64]] = []
    with points_path.open("wb") as output:
        for station in stations:
            for directions in _ring_blocks(steps, rng.uniform(0.0, 360.0), chunk_rays):
                distance, _ = world.cast(station, directions)
                keep = (distance >= RANGE_LIMITS[0]) & (distance <= RANGE_LIMITS[1])
                directions, distance = directions[keep], distance[keep]
                exact = station + distance[:, None] * directions
                measured = distance + rng.normal(0.0, range_noise, distance.shape)
                output.write(np.ascontiguousarray(station + measured[:, None] * directions))
                changed = np.flatnonzero(other_world.surface_distance(exact) > CHANGE_DISTANCE)
                changed_rows.append(changed + count)
                changed_exact.append(exact[changed])
                count += len(distance)
    return _EpochOnDisk(
        points_path,
        count,
        np.concatenate(changed_rows).astype(np.int64),
        np.vstack(changed_exact).reshape(-1, 3),
    )


def _write_ply(
    path: Path, epoch: _EpochOnDisk, offset: NDArray, pose: NDArray | None, chunk_rays: int
) -> None:
    """The epoch's world points moved into the file frame (``pose @ (p + offset)``), as float32
    binary PLY; the float64 file of world points removed."""
    with path.open("wb") as output, epoch.points_path.open("rb") as source:
        output.write(ply_header(epoch.count))
        while block := source.read(chunk_rays * 24):
            points = np.frombuffer(block, dtype=np.float64).reshape(-1, 3) + offset
            if pose is not None:
                points = _transform_points(points, pose)
            vertex = np.empty(len(points), dtype=PLY_VERTEX_DTYPE)
            vertex["x"], vertex["y"], vertex["z"] = points.T
            output.write(vertex.tobytes())
    epoch.points_path.unlink()


def write_lidar_pair(
    directory: str | Path,
    *,
    layout: str = "warehouse",
    change: str = "added",
    n_stations: int = 5,
    angular_step_deg: float | tuple[float, float] = 0.6,
    range_noise: float = 0.01,
    misaligned: bool = False,
    random_state: int | None = None,
    chunk_rays: int = WRITE_CHUNK_RAYS,
) -> WrittenLidarPair:
    """Write the pair :func:`~app.core.datasets.lidar.lidar_pair` makes with the same arguments
    to ``directory`` (``reference.ply``, ``scan.ply``, ``truth.npz``), in bounded memory.

    Parameters
    ----------
    directory : str or Path
        Created if missing; it also holds the two epochs' float64 world points (24 bytes a
        point) until each file is written.
    layout, change, n_stations, angular_step_deg, range_noise, misaligned, random_state
        As :func:`~app.core.datasets.lidar.lidar_pair`; ``random_state`` is an int or None.
    chunk_rays : int
        Rays a step (whole elevation rings); the files do not depend on it.

    Returns
    -------
    WrittenLidarPair

    Raises
    ------
    ValueError
        For the arguments ``lidar_pair`` refuses, and when ``lidar_pair`` would redraw its
        first layout (too few visible changed points): the writer does not redraw; another
        ``random_state`` does.
    """
    if n_stations < 1:
        raise ValueError(f"n_stations must be at least 1, got {n_stations}")
    steps = np.broadcast_to(np.asarray(angular_step_deg, dtype=np.float64), (2,))
    if not np.all((steps > 0.0) & (steps <= 10.0)):
        raise ValueError(f"angular_step_deg must be in (0, 10], got {angular_step_deg}")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(random_state)
    needed = max(10.0, MIN_VISIBLE_CHANGE * 0.36 / float(steps[0] * steps[1]))
    scene = draw_scene(layout, change, n_stations, rng)
    shell_low, shell_high = scene.shell_low, scene.shell_high
    reference_world, scan_world = scene.reference_world, scene.scan_world
    reference_stations, scan_stations = scene.reference_stations, scene.scan_stations
    step_pair = (float(steps[0]), float(steps[1]))
    epochs = [
        _cast_epoch(
            world,
            other,
            stations,
            step_pair,
            range_noise,
            rng,
            directory / f".{name}.world-f64",
            chunk_rays,
        )
        for name, world, other, stations in (
            ("reference", reference_world, scan_world, reference_stations),
            ("scan", scan_world, reference_world, scan_stations),
        )
    ]
    observed = [
        _observed_by(scan_world, scan_stations, epochs[0].changed_exact),
        _observed_by(reference_world, reference_stations, epochs[1].changed_exact),
    ]
    if change != "none" and sum(int(seen.sum()) for seen in observed) < needed:
        for epoch in epochs:
            epoch.points_path.unlink()
        raise ValueError(
            f"lidar_pair would redraw this layout (too few visible {change!r} points); "
            "the writer does not redraw: try another random_state"
        )
    offset, pose = file_frame(rng, shell_low, shell_high, misaligned)
    paths = (directory / "reference.ply", directory / "scan.ply")
    _write_ply(paths[0], epochs[0], offset, None, chunk_rays)
    _write_ply(paths[1], epochs[1], offset, pose, chunk_rays)
    truth_path = directory / "truth.npz"
    np.savez(
        truth_path,
        reference_changed_rows=epochs[0].changed_rows,
        scan_changed_rows=epochs[1].changed_rows,
        reference_changed_observed=observed[0],
        scan_changed_observed=observed[1],
        reference_origins=reference_stations + offset,
        scan_origins=_transform_points(scan_stations + offset, pose),
        true_transform=np.linalg.inv(pose),
        reference_box_low=reference_world.box_low + offset,
        reference_box_high=reference_world.box_high + offset,
        scan_box_low=scan_world.box_low + offset,
        scan_box_high=scan_world.box_high + offset,
        shell_low=shell_low + offset,
        shell_high=shell_high + offset,
    )
    return WrittenLidarPair(paths[0], paths[1], truth_path, epochs[0].count, epochs[1].count)
