"""Handheld RGB-D fused maps of furnished rooms: the first scene class of issue 29.

A room 4-8 x 3.5-6 x 2.5-3 m with desks, chairs, boxes and boards is filmed by a depth camera
carried along a smooth loop 0.8-1.8 m above the floor (a 60 x 45 degree frustum, depth 0.3-5 m,
depth noise ``1.5 mm * z**2``, z in metres), at 30 frames a second; every ``frame_stride``-th
frame is rendered (a jittered grid of pixels), the frames are fused in the world frame and the
map is thinned to one point per 5-10 mm voxel.  The second epoch's loop is drawn anew (another
shape, direction, start and extent), so the two maps cover the room differently.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from app.core.datasets.furniture import (
    MOVABLE_KINDS,
    MapObject,
    Placement,
    apply_change,
    make_object,
    place_object,
)
from app.core.datasets.lidar import LidarWorld
from app.core.datasets.map_world import (
    EpochSamples,
    MapPair,
    SensorModel,
    SensorPath,
    assemble_pair,
    cast_rays,
    visible_enough,
    world_of,
)
from app.core.datasets.rgbd_artefacts import (
    DepthArtefacts,
    drift_errors,
    fly_edge_pixels,
    missing_patches,
    realism_artefacts,
)

__all__ = ["CAMERA", "FRAME_RATE", "camera_rotation", "handheld_pair"]

CAMERA = SensorModel("frustum", (0.3, 5.0), 30.0, (-22.5, 22.5))
"""A depth camera: 60 x 45 degrees, depth 0.3-5 m."""
FRAME_RATE = 30.0
"""Frames a second of the camera (the rendered frames are every ``frame_stride``-th)."""
DEPTH_NOISE = 0.0015
"""Standard deviation of the depth at 1 m (metres); it grows with the square of the depth."""
HEIGHT_RANGE = (0.8, 1.8)
WALL_MARGIN = 0.9
"""The camera's loop stays this far (metres) from the walls."""


def camera_rotation(yaw: NDArray[np.float64], pitch: NDArray[np.float64]) -> NDArray[np.float64]:
    """Camera-to-world rotations, shape (m, 3, 3), looking along ``yaw`` / ``pitch`` (radians,
    pitch below zero looks down); camera x to the right, y down, z forward."""
    forward = np.column_stack(
        [np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)]
    )
    right = np.column_stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)])
    down = np.cross(forward, right)
    return np.stack([right, down, forward], axis=2)


def _camera_loop(
    rng: np.random.Generator,
    shell_high: NDArray[np.float64],
    n_frames: int,
    frame_stride: int,
    start_time: float,
) -> tuple[SensorPath, NDArray[np.float64]]:
    """A rendered-frame path along a random closed loop, and dense horizontal samples of it."""
    centre = shell_high[:2] / 2.0 + rng.uniform(-0.3, 0.3, 2)
    radius = np.maximum(shell_high[:2] / 2.0 - WALL_MARGIN - 0.3, 0.4) * rng.uniform(0.55, 1.0, 2)
    extent = rng.uniform(0.7, 1.0) * 2.0 * np.pi
    direction = rng.choice([-1.0, 1.0])
    phase = rng.uniform(0.0, 2.0 * np.pi)
    wobble = rng.uniform(0.0, 0.15, 2)
    wobble_phase = rng.uniform(0.0, 2.0 * np.pi, 2)

    def positions_at(angle: NDArray) -> NDArray:
        turn = phase + direction * angle
        scale = 1.0 + wobble[:, None] * np.sin(3.0 * turn + wobble_phase[:, None])
        xy = centre[:, None] + radius[:, None] * scale * np.array([np.cos(turn), np.sin(turn)])
        low, high = WALL_MARGIN, shell_high[:2, None] - WALL_MARGIN
        return np.clip(xy, low, high).T

    angle = np.linspace(0.0, extent, n_frames)
    xy = positions_at(angle)
    dense = positions_at(np.linspace(0.0, extent, max(200, 20 * n_frames)))
    height = HEIGHT_RANGE[0] + (HEIGHT_RANGE[1] - HEIGHT_RANGE[0]) * (
        0.5 + 0.5 * np.sin(rng.uniform(1.0, 4.0) * angle + rng.uniform(0.0, 2.0 * np.pi))
    )
    step = np.gradient(xy, axis=0)
    heading = np.arctan2(step[:, 1], step[:, 0])
    sweep = rng.uniform(0.6, 1.4) * np.sin(
        rng.uniform(3.0, 8.0) * angle + rng.uniform(0.0, 2.0 * np.pi)
    )
    pitch = -np.radians(rng.uniform(15.0, 35.0)) + np.radians(12.0) * np.sin(
        rng.uniform(2.0, 6.0) * angle
    )
    times = start_time + np.arange(n_frames) * frame_stride / FRAME_RATE
    positions = np.column_stack([xy, height])
    return SensorPath(times, positions, camera_rotation(heading + sweep, pitch)), dense


def _render(
    world_and_owner: tuple[LidarWorld, NDArray[np.int64]],
    path: SensorPath,
    pixels: tuple[int, int],
    rng: np.random.Generator,
    realism: tuple[DepthArtefacts, np.random.Generator] | None = None,
) -> EpochSamples:
    """Every frame of ``path``: a jittered ``pixels`` (columns, rows) grid of depth samples.

    ``realism``: the artefacts of a real fused map and their own generator (flying pixels,
    drifting poses, missing patches; :mod:`app.core.datasets.rgbd_artefacts`); None: exact
    poses, every pixel as measured."""
    world = world_and_owner[0]
    columns, rows = pixels
    n_frames = len(path.times)
    half_width, (low, high) = np.radians(CAMERA.horizontal_deg), np.radians(CAMERA.vertical_deg)
    grid_x = (np.arange(columns) + rng.uniform(0, 1, (n_frames, 1, columns))) / columns
    grid_y = (np.arange(rows)[:, None] + rng.uniform(0, 1, (n_frames, rows, 1))) / rows
    tan_x = np.tan(
        -half_width + 2.0 * half_width * np.broadcast_to(grid_x, (n_frames, rows, columns))
    )
    tan_y = np.tan(low + (high - low) * np.broadcast_to(grid_y, (n_frames, rows, columns)))
    local = np.stack([tan_x, tan_y, np.ones_like(tan_x)], axis=-1).reshape(n_frames, -1, 3)
    local /= np.linalg.norm(local, axis=-1, keepdims=True)
    directions = np.einsum("fij,fpj->fpi", path.rotations, local).reshape(-1, 3)
    pose = np.repeat(np.arange(n_frames), rows * columns)
    origins = path.positions[pose]
    distance, box = cast_rays(world, origins, directions, world_and_owner[1])
    depth = distance * local.reshape(-1, 3)[:, 2]
    keep = (depth >= CAMERA.range_limits[0]) & (depth <= CAMERA.range_limits[1])
    exact = origins[keep] + distance[keep, None] * directions[keep]
    if realism is not None:  # the same draws of ``rng`` with and without the artefacts
        flown = fly_edge_pixels(
            depth.reshape(n_frames, rows, columns),
            box.reshape(n_frames, rows, columns),
            realism[0],
            realism[1],
        ).reshape(-1)
        depth = np.where(keep, np.clip(flown, *CAMERA.range_limits), depth)
    noisy_depth = depth[keep] + rng.normal(0.0, 1.0, keep.sum()) * DEPTH_NOISE * depth[keep] ** 2
    measured = noisy_depth / local.reshape(-1, 3)[keep, 2]
    points = origins[keep] + measured[:, None] * directions[keep]
    samples = EpochSamples(points, exact, box[keep], pose[keep], path)
    return samples if realism is None else _with_drift_and_holes(samples, *realism)


def _with_drift_and_holes(
    samples: EpochSamples, artefacts: DepthArtefacts, rng: np.random.Generator
) -> EpochSamples:
    """``samples`` fused with drifting frame poses (each frame's points turned and shifted by
    its pose error about its camera), without their missing patches; the path as estimated."""
    path = samples.path
    error_rotation, error_shift = drift_errors(rng, len(path.times), artefacts)
    origins = path.positions[samples.pose]
    relative = np.einsum("pij,pj->pi", error_rotation[samples.pose], samples.points - origins)
    points = origins + error_shift[samples.pose] + relative
    estimated = SensorPath(
        path.times,
        path.positions + error_shift,
        np.einsum("pij,pjk->pik", error_rotation, path.rotations),
    )
    remaining = missing_patches(samples.exact, artefacts, rng)
    return EpochSamples(
        points[remaining],
        samples.exact[remaining],
        samples.box[remaining],
        samples.pose[remaining],
        estimated,
    )


def _furnish(rng: np.random.Generator, placement: Placement) -> list[MapObject]:
    """Desks first (against a wall or free-standing), then chairs, boxes and boards."""
    objects: list[MapObject] = []
    counts = {"desk": int(rng.integers(1, 4)), "chair": int(rng.integers(2, 6))}
    counts.update(box=int(rng.integers(1, 5)), board=int(rng.integers(1, 4)))
    for kind, count in counts.items():
        for number in range(count):
            placed = place_object(
                make_object(f"{kind} {number}", kind, rng), objects, placement, rng
            )
            if placed is not None:
                objects.append(placed)
    return objects


def handheld_pair(
    *,
    change: str = "removed",
    misaligned: bool = False,
    n_frames: int = 160,
    pixels: tuple[int, int] = (36, 27),
    voxel: float | None = None,
    visibility_stride: int = 4,
    realism: str = "none",
    random_state: int = 0,
) -> MapPair:
    """A random two-epoch handheld RGB-D map of a furnished room, with per-point truth.

    Parameters
    ----------
    change : {"none", "removed", "added", "moved", "rotated", "mixed"}
        What happens to the chairs, boxes and boards between the epochs
        (:func:`app.core.datasets.furniture.apply_change`).
    misaligned : bool
        Give the scan turned by 0.3 degrees and shifted by 2-3 cm (``true_transform`` undoes
        it).
    n_frames : int
        Frames rendered per epoch; they are every 10th-20th frame of a 30 Hz recording of
        thousands of frames (the stride is drawn per epoch and sets the frames' times).
    pixels : (int, int)
        Columns and rows of depth samples per rendered frame (a jittered grid).
    voxel : float, optional
        Edge (metres) of the thinning voxels; default drawn in 5-10 mm.
    visibility_stride : int
        The truth's ``scored`` tests every this many frames of the other epoch.
    realism : {"none", "drift"}
        ``"drift"``: the artefacts of a real fused map (tracking drift with a partial loop
        closure, flying pixels at depth edges, missing patches;
        :mod:`app.core.datasets.rgbd_artefacts`), drawn from their own generator so the room,
        paths and change are those of ``"none"``.  The truth stays the world's.
    random_state : int
        Seeds every draw: the same seed gives the same pair.

    Returns
    -------
    MapPair
        ``map_class`` ``"rgbd"``, ``layout`` ``"room"``; a changed pair has at least
        :data:`~app.core.datasets.map_world.MIN_VISIBLE_CHANGE` changed, scored points (the
        layout is redrawn until it does, up to 10 times).
    """
    rng = np.random.default_rng(random_state)
    artefacts = realism_artefacts(realism)
    artefact_rng = np.random.default_rng([random_state, 29])
    settings = (n_frames, pixels, voxel, visibility_stride)
    for _ in range(10):
        pair = _draw(
            rng,
            change,
            misaligned,
            settings,
            None if artefacts is None else (artefacts, artefact_rng),
        )
        if visible_enough(pair):
            return replace(pair, seed=random_state)
    raise ValueError(f"no visible {change!r} change in 10 layouts; try another seed")


def _draw(
    rng: np.random.Generator,
    change: str,
    misaligned: bool,
    settings: tuple[int, tuple[int, int], float | None, int],
    realism: tuple[DepthArtefacts, np.random.Generator] | None,
) -> MapPair:
    n_frames, pixels, voxel, stride = settings
    shell_high = np.array([rng.uniform(4.0, 8.0), rng.uniform(3.5, 6.0), rng.uniform(2.5, 3.0)])
    shell = (np.zeros(3), shell_high)
    frame_strides = rng.integers(10, 21, 2)
    paths = []
    for epoch in range(2):
        paths.append(
            _camera_loop(rng, shell_high, n_frames, int(frame_strides[epoch]), 100.0 + 5000 * epoch)
        )
    keep_out = np.vstack([dense for _, dense in paths])
    placement = Placement(shell[0], shell_high, keep_out, clearance=0.4)
    objects = _furnish(rng, placement)

    def new_object(name: str) -> MapObject:
        kind = str(rng.choice(MOVABLE_KINDS))
        return make_object(f"{name} {kind}", kind, rng)

    scan_objects, changes = apply_change(change, objects, placement, rng, new_object)
    samples = tuple(
        _render(world_of(shell, epoch_objects), path, pixels, rng, realism)
        for epoch_objects, (path, _) in zip((objects, scan_objects), paths, strict=True)
    )
    voxel_size = float(rng.uniform(0.005, 0.010)) if voxel is None else float(voxel)
    return assemble_pair(
        shell=shell,
        reference_objects=objects,
        scan_objects=scan_objects,
        changes=changes,
        samples=samples,  # type: ignore[arg-type]
        sensor=CAMERA,
        voxel=voxel_size,
        stride=stride,
        misaligned=misaligned,
        rng=rng,
        labels={
            "map_class": "rgbd",
            "layout": "room",
            "change": change,
            "seed": 0,
            "metadata": {"voxel": voxel_size, "frames": float(n_frames)}
            | ({} if realism is None else {"drift": 1.0}),
        },
    )
