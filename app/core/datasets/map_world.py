"""Shared parts of the synthetic moving-sensor maps: furniture, sensors, paths, truth, the pair.

The scene classes of issue 29 (handheld RGB-D fused maps, robot / mobile laser scanning maps,
terrestrial multi-station scans) are built in :mod:`app.core.datasets.handheld` and
:mod:`app.core.datasets.robot` from the pieces here:

- a world is a closed shell with named objects, each a few solid axis-aligned boxes (a chair is
  four legs, a seat and a back; a desk a top and four legs; a board a thin vertical panel; a box a
  box), held as an :class:`app.core.datasets.lidar.LidarWorld` for its exact surface distance;
- a sensor model (:class:`SensorModel`: a camera frustum or an upright ring lidar) and a timed
  path of poses (:class:`SensorPath`);
- rays are cast from many origins at once (:func:`cast_rays`), so a thousand frames cost one
  pass over the boxes;
- the epochs' samples are voxel-thinned (:func:`voxel_thin`) and the truth is computed as the
  issue states it (:func:`assemble_pair`): a point is changed when its exact position lies more
  than :data:`CHANGE_DISTANCE` from every surface of the other epoch's world, and scored when a
  pose of the other epoch (every ``stride``-th pose) sees it in range, in its field of view and
  not hidden behind the other world.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from app.core.cloud import PointCloud
from app.core.datasets.furniture import MapChange, MapObject
from app.core.datasets.lidar import CHANGE_DISTANCE, LidarWorld
from app.core.trajectory import Trajectory

__all__ = [
    "CHANGE_DISTANCE",
    "MISALIGNMENT",
    "EpochSamples",
    "MapPair",
    "SensorModel",
    "SensorPath",
    "assemble_pair",
    "cast_rays",
    "voxel_thin",
]

MISALIGNMENT = ((0.02, 0.03), 0.3)
"""(translation range in metres, rotation in degrees) of a misaligned scan file."""
TESTED_POSES = 24
"""With ``stride=None``, the truth's ``scored`` tests about this many poses of the other epoch."""
MIN_VISIBLE_CHANGE = 50
"""A changed pair has at least this many changed, scored points (fewer for small pairs:
:func:`visible_enough`); else the layout is redrawn."""


def visible_enough(pair: MapPair) -> bool:
    """Whether a pair is unchanged, or its changes have enough changed, scored points: at least
    :data:`MIN_VISIBLE_CHANGE`, or one in 400 of the pair's points when that is fewer (at
    least 10)."""
    if pair.change == "none":
        return True
    visible = np.count_nonzero(pair.reference_changed & pair.reference_scored)
    visible += np.count_nonzero(pair.scan_changed & pair.scan_scored)
    total = len(pair.reference_changed) + len(pair.scan_changed)
    return bool(pair.changes) and visible >= max(10, min(MIN_VISIBLE_CHANGE, total // 400))


@dataclass(frozen=True)
class SensorModel:
    """Field of view and range of a camera (``"frustum"``) or an upright ring lidar.

    Attributes
    ----------
    kind : {"frustum", "lidar"}
    range_limits : (float, float)
        Metres: depth along the optical axis for a frustum, distance for a lidar.
    horizontal_deg : float
        Half the frustum's horizontal opening (unused for a lidar: 360 degrees).
    vertical_deg : (float, float)
        Lowest and highest elevation (lidar) or vertical angle from the optical axis (frustum).
    """

    kind: str
    range_limits: tuple[float, float]
    horizontal_deg: float
    vertical_deg: tuple[float, float]

    def in_view(
        self,
        position: NDArray[np.float64],
        rotation: NDArray[np.float64],
        points: NDArray[np.float64],
    ) -> NDArray[np.bool_]:
        """Whether ``points`` (p, 3) lie in range and field of view of the pose, shape (p,).

        ``rotation`` (3, 3) maps sensor axes to world axes (a frustum looks along its z, x to
        the right, y down; a lidar's z is up).
        """
        local = (points - position) @ rotation
        if self.kind == "frustum":
            depth = local[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                horizontal = np.degrees(np.arctan2(np.abs(local[:, 0]), depth))
                vertical = np.degrees(np.arctan2(local[:, 1], depth))
            return (
                (depth >= self.range_limits[0])
                & (depth <= self.range_limits[1])
                & (horizontal <= self.horizontal_deg)
                & (vertical >= self.vertical_deg[0])
                & (vertical <= self.vertical_deg[1])
            )
        distance = np.linalg.norm(local, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            elevation = np.degrees(np.arcsin(np.clip(local[:, 2] / distance, -1.0, 1.0)))
        return (
            (distance >= self.range_limits[0])
            & (distance <= self.range_limits[1])
            & (elevation >= self.vertical_deg[0])
            & (elevation <= self.vertical_deg[1])
        )


@dataclass(frozen=True)
class SensorPath:
    """Timed sensor poses in the world frame.

    Attributes
    ----------
    times : ndarray, shape (m,)
        Seconds, strictly increasing.
    positions : ndarray, shape (m, 3)
    rotations : ndarray, shape (m, 3, 3)
        Sensor-to-world rotations.
    """

    times: NDArray[np.float64]
    positions: NDArray[np.float64]
    rotations: NDArray[np.float64]


@dataclass(frozen=True)
class EpochSamples:
    """What one epoch's sensor returned, before thinning (world frame).

    Attributes
    ----------
    points : ndarray, shape (s, 3)
        Measured positions (noise and pose errors included).
    exact : ndarray, shape (s, 3)
        Noise-free surface positions.
    box : ndarray, shape (s,), int64
        Box of the epoch's world hit (-1: the shell).
    pose : ndarray, shape (s,), int64
        Row of the path the sample was taken from.
    path : SensorPath
        The poses as the map's trajectory records them (the estimated poses, errors included).
    """

    points: NDArray[np.float64]
    exact: NDArray[np.float64]
    box: NDArray[np.int64]
    pose: NDArray[np.int64]
    path: SensorPath


@dataclass(frozen=True)
class MapPair:
    """Two epochs of a moving-sensor map, in file coordinates, with per-point truth.

    Attributes
    ----------
    reference, scan : PointCloud
        The maps with their ``"time"`` attribute (float64 seconds of the frame, sweep or
        station that produced each kept point) and ``trajectory`` (one pose per rendered frame,
        sweep or station, as estimated: pose errors included; orientations map sensor axes to
        the file's axes: a camera's x right, y down, z forward; a lidar's x forward, z up);
        :meth:`clouds` gives them without.
    reference_changed, scan_changed : ndarray, shape (n,) and (m,), bool
        More than :data:`CHANGE_DISTANCE` from every surface of the other epoch's world.
    reference_scored, scan_scored : ndarray, bool
        Seen by some tested pose of the other epoch (others are not scored).
    reference_change, scan_change : ndarray, int64
        Index in ``changes`` of the change each point belongs to (a point of the changed
        object), -1 for none.
    reference_exact, scan_exact : ndarray, shape (n, 3) and (m, 3)
        Noise-free position of each kept point, in the reference file's frame.
    changes : list of MapChange
    true_transform : ndarray, shape (4, 4)
        Maps scan-file coordinates into the reference frame (identity unless misaligned).
    reference_world, scan_world : LidarWorld
        Each epoch's boxes and shell, in the reference file's frame (the truth's worlds).
    map_class, layout, change : str
    seed : int
    misaligned : bool
    visibility_stride : int
        Every this many poses of the other epoch were tested for ``*_scored`` (the larger of
        the two epochs' strides): a place seen only between tested poses is not scored.
    """

    reference: PointCloud
    scan: PointCloud
    reference_changed: NDArray[np.bool_]
    scan_changed: NDArray[np.bool_]
    reference_scored: NDArray[np.bool_]
    scan_scored: NDArray[np.bool_]
    reference_change: NDArray[np.int64]
    scan_change: NDArray[np.int64]
    reference_exact: NDArray[np.float64]
    scan_exact: NDArray[np.float64]
    changes: list[MapChange]
    true_transform: NDArray[np.float64]
    reference_world: LidarWorld
    scan_world: LidarWorld
    map_class: str
    layout: str
    change: str
    seed: int
    misaligned: bool
    visibility_stride: int = 1
    metadata: dict[str, float] = field(default_factory=dict)

    @property
    def reference_observed(self) -> NDArray[np.bool_]:
        """``reference_scored`` under the name the older synthetic pairs use."""
        return self.reference_scored

    @property
    def scan_observed(self) -> NDArray[np.bool_]:
        """``scan_scored`` under the name the older synthetic pairs use."""
        return self.scan_scored

    def clouds(self, with_trajectory: bool = False) -> tuple[PointCloud, PointCloud]:
        """(reference, scan): bare points as a map is usually exported ("nothing given"), or
        with their ``"time"`` attribute and ``trajectory`` when ``with_trajectory``."""
        if with_trajectory:
            return self.reference, self.scan
        return (
            PointCloud.from_array(self.reference.points.copy()),
            PointCloud.from_array(self.scan.points.copy()),
        )


def world_of(
    shell: tuple[NDArray, NDArray], objects: list[MapObject]
) -> tuple[LidarWorld, NDArray[np.int64]]:
    """The box world of ``objects`` in ``shell`` and, per box, the index of its object."""
    lows = [obj.low for obj in objects]
    highs = [obj.high for obj in objects]
    owner = [np.full(len(obj.low), index, dtype=np.int64) for index, obj in enumerate(objects)]
    world = LidarWorld(
        shell_low=np.asarray(shell[0], dtype=np.float64),
        shell_high=np.asarray(shell[1], dtype=np.float64),
        box_low=np.vstack(lows) if lows else np.zeros((0, 3)),
        box_high=np.vstack(highs) if highs else np.zeros((0, 3)),
    )
    return world, np.concatenate(owner) if owner else np.zeros(0, dtype=np.int64)


def cast_rays(
    world: LidarWorld,
    origins: NDArray[np.float64],
    directions: NDArray[np.float64],
    owner: NDArray[np.int64] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """First hit of rays with one origin each, inside the closed shell of ``world``.

    Parameters
    ----------
    world : LidarWorld
    origins, directions : ndarray, shape (r, 3)
        Ray origins (inside the shell, outside every box) and unit directions.
    owner : ndarray, shape (b,), int64, optional
        The object each box belongs to (:func:`world_of`): a ray is tested against an object's
        boxes only when it passes the object's bounds (the same hits, sooner).

    Returns
    -------
    distance : ndarray, shape (r,)
    box : ndarray, shape (r,), int64
        Box hit, -1 for the shell.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / directions
        exit_distance = np.where(
            inverse > 0,
            (world.shell_high - origins) * inverse,
            (world.shell_low - origins) * inverse,
        )
        distance = np.where(np.isfinite(exit_distance), exit_distance, np.inf).min(axis=1)
        box = np.full(len(directions), -1, dtype=np.int64)
        # each ray's segment inside the shell, as a box: most objects are far from most
        # segments; test an object's boxes only on the rays whose segment meets its bounds
        ends = origins + distance[:, None] * directions
        segment_low, segment_high = np.minimum(origins, ends), np.maximum(origins, ends)

        def meeting(rows: NDArray[np.int64], low: NDArray, high: NDArray) -> NDArray[np.int64]:
            inside = np.ones(len(rows), dtype=bool)
            for axis in range(3):
                inside &= segment_low[rows, axis] <= high[axis]
                inside &= segment_high[rows, axis] >= low[axis]
            return rows[inside]

        all_rows = np.arange(len(directions))
        groups = np.arange(len(world.box_low)) if owner is None else owner
        for group in np.unique(groups):
            members = np.flatnonzero(groups == group)
            group_rows = meeting(
                all_rows, world.box_low[members].min(axis=0), world.box_high[members].max(axis=0)
            )
            for index in members:
                low, high = world.box_low[index], world.box_high[index]
                rows = meeting(group_rows, low, high) if len(members) > 1 else group_rows
                if rows.size == 0:
                    continue
                t_low = (low - origins[rows]) * inverse[rows]
                t_high = (high - origins[rows]) * inverse[rows]
                t_near = np.fmin(t_low, t_high)
                t_far = np.fmax(t_low, t_high)
                t_near = np.where(np.isnan(t_near), -np.inf, t_near).max(axis=1)
                t_far = np.where(np.isnan(t_far), np.inf, t_far).min(axis=1)
                hits = (t_near <= t_far) & (t_near > 0.0) & (t_near < distance[rows])
                distance[rows[hits]] = t_near[hits]
                box[rows[hits]] = index
    return distance, box


def far_from_surfaces(
    world: LidarWorld, points: NDArray[np.float64], distance: float
) -> NDArray[np.bool_]:
    """Whether each point lies more than ``distance`` from every surface of ``world``, (p,).

    The same answer as ``world.surface_distance(points) > distance``, computed only for the
    points near each box.
    """
    inside_shell = np.minimum(points - world.shell_low, world.shell_high - points)
    far = np.abs(inside_shell).min(axis=1) > distance
    for low, high in zip(world.box_low, world.box_high, strict=True):
        rows = np.flatnonzero(
            far & np.all((points >= low - distance) & (points <= high + distance), axis=1)
        )
        if rows.size:
            near = LidarWorld(world.shell_low, world.shell_high, low[None], high[None])
            far[rows] = near.surface_distance(points[rows]) > distance
    return far


def seen_by_path(
    world: LidarWorld,
    sensor: SensorModel,
    path: SensorPath,
    points: NDArray[np.float64],
    stride: int,
    owner: NDArray[np.int64] | None = None,
    batch: int = 60_000,
) -> NDArray[np.bool_]:
    """Whether some pose (every ``stride``-th of ``path``) sees the exact ``points`` (p, 3) in
    ``world``: in range and view, and no surface of ``world`` before it, shape (p,).

    ``owner`` (b,): the object of each box of ``world``, as for :func:`cast_rays`."""
    seen = np.zeros(len(points), dtype=bool)
    pending_points: list[NDArray] = []
    pending_origins: list[NDArray] = []
    pending_rows: list[NDArray] = []

    def flush() -> None:
        if not pending_rows:
            return
        rows = np.concatenate(pending_rows)
        origins = np.vstack(pending_origins)
        offset = np.vstack(pending_points) - origins
        distance = np.linalg.norm(offset, axis=1)
        first, _ = cast_rays(world, origins, offset / distance[:, None], owner)
        seen[rows[first >= distance - (1e-6 + 1e-6 * distance)]] = True
        pending_points.clear()
        pending_origins.clear()
        pending_rows.clear()

    queued = 0
    for pose in range(0, len(path.times), max(1, stride)):
        rows = np.flatnonzero(~seen)
        rows = rows[sensor.in_view(path.positions[pose], path.rotations[pose], points[rows])]
        pending_rows.append(rows)
        pending_points.append(points[rows])
        pending_origins.append(np.broadcast_to(path.positions[pose], (len(rows), 3)))
        queued += len(rows)
        if queued >= batch:
            flush()
            queued = 0
    flush()
    return seen


def voxel_thin(
    points: NDArray[np.float64], voxel: float
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """One point per occupied voxel: the centroid of its samples, and the sample kept.

    Parameters
    ----------
    points : ndarray, shape (s, 3)
    voxel : float
        Edge of the cubic voxels (metres), on a grid anchored at the world origin.

    Returns
    -------
    centroids : ndarray, shape (v, 3)
        Mean of each voxel's points (inside the voxel).
    kept : ndarray, shape (v,), int64
        Row of ``points`` nearest each centroid: its time, pose and exact position stand for
        the voxel's.
    """
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, group, counts = np.unique(keys, return_inverse=True, return_counts=True)
    group = group.reshape(-1)
    centroids = np.column_stack(
        [np.bincount(group, weights=points[:, axis]) / counts for axis in range(3)]
    )
    spread = np.linalg.norm(points - centroids[group], axis=1)
    order = np.lexsort((spread, group))
    first = np.ones(len(order), dtype=bool)
    first[1:] = group[order][1:] != group[order][:-1]
    return centroids, order[first]


def misalignment(rng: np.random.Generator, centre: NDArray[np.float64]) -> NDArray[np.float64]:
    """A rigid (4, 4) pose: 0.3 degrees about a random axis through ``centre``, then 2-3 cm."""
    (t_low, t_high), angle = MISALIGNMENT
    axis = rng.normal(size=3)
    rotation = Rotation.from_rotvec(np.radians(angle) * axis / np.linalg.norm(axis)).as_matrix()
    direction = rng.normal(size=3)
    translation = rng.uniform(t_low, t_high) * direction / np.linalg.norm(direction)
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = centre - rotation @ centre + translation
    return pose


@dataclass(frozen=True)
class _Thinned:
    points: NDArray[np.float64]
    exact: NDArray[np.float64]
    times: NDArray[np.float64]
    objects: NDArray[np.int64]


def _thin(samples: EpochSamples, owner: NDArray[np.int64], voxel: float) -> _Thinned:
    centroids, kept = voxel_thin(samples.points, voxel)
    box = samples.box[kept]
    objects = np.where(box >= 0, owner[np.maximum(box, 0)] if len(owner) else -1, -1)
    return _Thinned(centroids, samples.exact[kept], samples.path.times[samples.pose[kept]], objects)


def _shifted(world: LidarWorld, offset: NDArray[np.float64]) -> LidarWorld:
    return LidarWorld(
        world.shell_low + offset,
        world.shell_high + offset,
        world.box_low + offset,
        world.box_high + offset,
    )


def _cloud(
    points: NDArray, times: NDArray, path: SensorPath, pose: NDArray[np.float64]
) -> PointCloud:
    """The file's cloud: points and trajectory mapped by the (4, 4) ``pose``."""
    positions = path.positions @ pose[:3, :3].T + pose[:3, 3]
    quaternions = Rotation.from_matrix(pose[:3, :3] @ path.rotations).as_quat()
    cloud = PointCloud.from_array(points @ pose[:3, :3].T + pose[:3, 3], {"time": times})
    return dataclasses.replace(cloud, trajectory=Trajectory(path.times, positions, quaternions))


def assemble_pair(
    *,
    shell: tuple[NDArray, NDArray],
    reference_objects: list[MapObject],
    scan_objects: list[MapObject],
    changes: list[MapChange],
    samples: tuple[EpochSamples, EpochSamples],
    sensor: SensorModel,
    voxel: float,
    stride: int | None,
    misaligned: bool,
    rng: np.random.Generator,
    labels: dict,
) -> MapPair:
    """Thin both epochs, compute the truth, move them into their files' frames.

    ``labels`` gives ``map_class``, ``layout``, ``change``, ``seed`` (and optional
    ``metadata``).  The reference file is the world shifted away from the origin; the scan file
    is that, moved by a :func:`misalignment` when ``misaligned``.  ``stride``: test every
    this many poses of the other epoch for ``scored``; None: a stride that tests about
    :data:`TESTED_POSES` poses.
    """
    worlds = [world_of(shell, objects) for objects in (reference_objects, scan_objects)]
    thinned = [_thin(epoch, world[1], voxel) for epoch, world in zip(samples, worlds, strict=True)]
    other = (1, 0)
    changed, scored, membership = [], [], []
    strides = [1, 1]
    for side in (0, 1):
        other_world = worlds[other[side]][0]
        exact = thinned[side].exact
        changed.append(far_from_surfaces(other_world, exact, CHANGE_DISTANCE))
        other_path = samples[other[side]].path
        strides[side] = stride or max(1, -(-len(other_path.times) // TESTED_POSES))
        scored.append(
            seen_by_path(
                other_world, sensor, other_path, exact, strides[side], worlds[other[side]][1]
            )
        )
        names = [obj.name for obj in (reference_objects, scan_objects)[side]]
        index = np.full(len(exact), -1, dtype=np.int64)
        for number, change in enumerate(changes):
            if (change.reference_box, change.scan_box)[side] is not None:
                index[thinned[side].objects == names.index(change.name)] = number
        membership.append(index)
    offset = np.array([*rng.uniform(-60.0, 60.0, 2), rng.uniform(-3.0, 3.0)])
    offset[:2] += np.sign(offset[:2]) * 5.0
    to_file = np.eye(4)
    to_file[:3, 3] = offset
    scan_pose = (
        misalignment(rng, (shell[0] + shell[1]) / 2.0 + offset) @ to_file if misaligned else to_file
    )
    orders = [rng.permutation(len(side.points)) for side in thinned]
    clouds = [
        _cloud(side.points[order], side.times[order], epoch.path, pose)
        for side, order, epoch, pose in zip(
            thinned, orders, samples, (to_file, scan_pose), strict=True
        )
    ]
    return MapPair(
        reference=clouds[0],
        scan=clouds[1],
        reference_changed=changed[0][orders[0]],
        scan_changed=changed[1][orders[1]],
        reference_scored=scored[0][orders[0]],
        scan_scored=scored[1][orders[1]],
        reference_change=membership[0][orders[0]],
        scan_change=membership[1][orders[1]],
        reference_exact=thinned[0].exact[orders[0]] + offset,
        scan_exact=thinned[1].exact[orders[1]] + offset,
        changes=changes,
        true_transform=to_file @ np.linalg.inv(scan_pose),
        reference_world=_shifted(worlds[0][0], offset),
        scan_world=_shifted(worlds[1][0], offset),
        map_class=labels["map_class"],
        layout=labels["layout"],
        change=labels["change"],
        seed=labels["seed"],
        misaligned=misaligned,
        visibility_stride=max(strides),
        metadata=dict(labels.get("metadata", {})),
    )
