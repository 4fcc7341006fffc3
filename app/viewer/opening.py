"""Where the 3D view's camera opens: on the change, from a side where nothing hides it.

A job's changed points are often behind something: boxes behind an office's near wall, a
pallet behind racks, a person inside a corridor.  :func:`choose_opening_view` puts candidate
cameras around the changed regions (azimuths x elevations, at the distance that frames the
regions' box) and casts a ray from each candidate to a sample of the changed points through an
occupancy grid of the unchanged points that will be drawn (:class:`OccupancyGrid`).  The
candidate whose rays are least blocked wins; when every side is blocked (a change in a closed
room seen from outside), the view opens cut just above the changes (what the "Cut the ceiling"
button does) and chooses again.  A job without change frames the whole scene.

Plain arrays only (no viser, no scene classes): :mod:`app.viewer.scene` calls it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

CAMERA_FOV = 75.0 * math.pi / 180.0
"""viser's default vertical field of view (radians), the one a browser opens with."""
ASSUMED_ASPECT = 1.6
"""Width / height of the canvas assumed before a browser reports its own (1280 x 800)."""
AZIMUTHS_DEG = tuple(range(0, 360, 30))
"""Candidate camera azimuths (degrees from +x, counter-clockwise seen from above)."""
ELEVATIONS_DEG = (25.0, 45.0, 65.0, 85.0)
"""Candidate camera elevations (degrees above the horizontal); 85: almost from above."""
PREFERRED_AZIMUTH_DEG = -126.0
"""Among equally clear sides, the one closest to the whole-scene view's (from the south-west)."""
PREFERRED_ELEVATION_DEG = 45.0
FACING_WEIGHT = 1.0
"""Among equally clear sides, how much seeing the changes' box face-on counts against the
preferred side (penalties run from 0 to about 1.5)."""
CLEAR_ENOUGH = 0.05
"""Candidates within this share of blocked rays of the clearest are equally clear."""
MOSTLY_BLOCKED = 0.4
"""When even the clearest side has more blocked rays than this, cut above the changes."""
CUT_MARGIN = 0.3
"""A cut keeps this much (metres) above the highest changed point."""
MAX_TARGETS = 256
"""Changed points a side is judged by (a deterministic sample)."""
MAX_GRID_CELLS = 4_000_000
"""Cells of the occupancy grid at most (the voxel grows in large scenes)."""
FRAME_MARGIN = 1.3
"""The framed sphere is this much larger than the regions' box (some context around them)."""
MIN_FRAME_RADIUS = 2.5
"""Radius (metres) framed at least, so a small change is seen with its surroundings."""
CONTEXT_SHARE = 0.2
"""...and at least this share of the whole scene's extent."""


@dataclass(frozen=True)
class OpeningView:
    """The camera a browser opens with, and the height it opens clipped at (local frame).

    ``position`` and ``look_at`` are shape (3,); ``clip_high`` is the highest height drawn
    (``inf``: no cut); ``reason`` says why (``"change"``, ``"change, cut above it"``,
    ``"whole scene"``); ``blocked_share`` is the share of the changed points whose line of sight
    from ``position`` crosses unchanged points (None without change).
    """

    position: NDArray[np.float64]
    look_at: NDArray[np.float64]
    clip_high: float
    reason: str
    blocked_share: float | None = None

    def to_json_dict(self, origin: NDArray[np.float64]) -> dict[str, Any]:
        """File-frame position and target, the clip height (None: no cut) and the reason."""
        return {
            "position": (self.position + origin).tolist(),
            "look_at": (self.look_at + origin).tolist(),
            "clip_high": float(self.clip_high + origin[2]) if np.isfinite(self.clip_high) else None,
            "reason": self.reason,
            "blocked_share": self.blocked_share,
        }


class OccupancyGrid:
    """Which cells of a regular grid hold unchanged points (dilated by one cell, so a sparse
    wall has no holes a ray could slip through)."""

    def __init__(self, points: NDArray[np.floating], voxel: float) -> None:
        """Occupied cells of ``points`` (n, 3) at ``voxel`` metres."""
        self.voxel = float(voxel)
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(points) == 0:
            self.low = np.zeros(3)
            self.cells = np.zeros((1, 1, 1), dtype=bool)
            return
        self.low = points.min(axis=0) - 2 * self.voxel
        shape = np.floor((points.max(axis=0) + 2 * self.voxel - self.low) / self.voxel) + 1
        self.cells = np.zeros(tuple(shape.astype(np.int64)), dtype=bool)
        index = np.floor((points - self.low) / self.voxel).astype(np.int64)
        self.cells[index[:, 0], index[:, 1], index[:, 2]] = True
        from scipy.ndimage import binary_dilation  # on first use: API processes need no scipy

        self.cells = binary_dilation(self.cells)

    def occupied(self, samples: NDArray[np.floating]) -> NDArray[np.bool_]:
        """Whether each of ``samples`` (..., 3) lies in an occupied cell (outside: free)."""
        index = np.floor((np.asarray(samples) - self.low) / self.voxel).astype(np.int64)
        inside = np.all((index >= 0) & (index < np.array(self.cells.shape)), axis=-1)
        result = np.zeros(index.shape[:-1], dtype=bool)
        chosen = index[inside]
        result[inside] = self.cells[chosen[:, 0], chosen[:, 1], chosen[:, 2]]
        return result


def blocked_shares(
    grid: OccupancyGrid,
    cameras: NDArray[np.floating],
    targets: NDArray[np.floating],
    near_margin: float,
) -> NDArray[np.float64]:
    """Per camera, the share of ``targets`` whose line of sight crosses an occupied cell.

    Parameters
    ----------
    grid : OccupancyGrid
        The unchanged points that will be drawn.
    cameras : ndarray, shape (c, 3)
    targets : ndarray, shape (t, 3)
    near_margin : float
        The last ``near_margin`` metres before a target do not count (the floor under an object
        and the wall behind it are next to it, not in front of it).

    Returns
    -------
    ndarray, shape (c,)
    """
    cameras = np.asarray(cameras, dtype=np.float64).reshape(-1, 3)
    targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    shares = np.zeros(len(cameras))
    if len(targets) == 0:
        return shares
    step = grid.voxel / 2.0
    for number, camera in enumerate(cameras):
        offsets = targets - camera
        lengths = np.linalg.norm(offsets, axis=1)
        usable = np.maximum(lengths - near_margin, 0.0)
        n_steps = max(math.ceil(usable.max() / step), 1)
        fractions = np.arange(n_steps) * step  # metres from the camera
        samples = (
            camera
            + (fractions[None, :, None] / np.maximum(lengths, 1e-9)[:, None, None])
            * (offsets[:, None, :])
        )
        before = fractions[None, :] < usable[:, None]
        blocked = (grid.occupied(samples) & before).any(axis=1)
        shares[number] = float(blocked.mean())
    return shares


def candidate_directions() -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit vectors from the target to each candidate camera (k, 3) and their preference
    penalties (k,): 0 for the whole-scene view's side at 45 degrees, growing away from it."""
    directions, penalties = [], []
    for elevation in ELEVATIONS_DEG:
        for azimuth in AZIMUTHS_DEG:
            a, e = math.radians(azimuth), math.radians(elevation)
            directions.append([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
            turn = abs((azimuth - PREFERRED_AZIMUTH_DEG + 180.0) % 360.0 - 180.0) / 180.0
            penalties.append(turn + abs(elevation - PREFERRED_ELEVATION_DEG) / 90.0)
    return np.array(directions), np.array(penalties)


def framing_distance(
    radius: float, fov: float = CAMERA_FOV, aspect: float = ASSUMED_ASPECT
) -> float:
    """Distance (metres) at which a sphere of ``radius`` fills the narrower field of view."""
    vertical = fov / 2.0
    horizontal = math.atan(math.tan(vertical) * aspect)
    return radius / math.sin(min(vertical, horizontal))


def point_spacing(points: NDArray[np.floating], sample_size: int = 2000) -> float:
    """Median nearest-neighbour distance of ``points`` (n, 3), metres (1 cm at least)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) < 2:
        return 0.1
    rng = np.random.default_rng(0)
    sample = points if len(points) <= sample_size else points[rng.choice(len(points), sample_size)]
    distances, _ = KDTree(points).query(sample, k=2)
    spacing = float(np.median(np.asarray(distances).reshape(len(sample), -1)[:, -1]))
    return max(spacing, 0.01) if np.isfinite(spacing) else 0.1


def whole_scene_view(
    scene_low: NDArray[np.floating], scene_high: NDArray[np.floating], clip_high: float
) -> OpeningView:
    """The whole scene from the south-west, above (the view of a job without change)."""
    low, high = np.asarray(scene_low, np.float64), np.asarray(scene_high, np.float64)
    centre = (low + high) / 2.0
    extent = max(float(np.linalg.norm(high - low)), 0.5)
    direction = np.array([-0.55, -0.75, 0.55])
    position = centre + direction / np.linalg.norm(direction) * extent
    return OpeningView(position=position, look_at=centre, clip_high=clip_high, reason="whole scene")


def choose_opening_view(
    unchanged: NDArray[np.floating],
    changed: NDArray[np.floating],
    scene_low: NDArray[np.floating],
    scene_high: NDArray[np.floating],
    clip_high: float = math.inf,
    regions_low: NDArray[np.floating] | None = None,
    regions_high: NDArray[np.floating] | None = None,
    fov: float = CAMERA_FOV,
    aspect: float = ASSUMED_ASPECT,
) -> OpeningView:
    """The camera that frames the changed points from the side where they are least hidden.

    Parameters
    ----------
    unchanged : ndarray, shape (n, 3)
        The unchanged points that will be drawn (local frame), the possible occluders.
    changed : ndarray, shape (m, 3)
        The changed points that will be drawn (removed and added).
    scene_low, scene_high : ndarray, shape (3,)
        The scene's bounds: what a job without change frames.
    clip_high : float
        The height the view opens clipped at (``inf``: no cut, e.g. outdoors); points above it
        neither hide nor count.
    regions_low, regions_high : ndarray, shape (r, 3), optional
        The regions' boxes; the framed box is theirs (else the changed points').
    fov, aspect : float
        Vertical field of view (radians) and width / height of the canvas.

    Returns
    -------
    OpeningView
        Looking at the centre of the changes' box from the clearest side at the distance that
        frames the box; opened cut :data:`CUT_MARGIN` above the highest change when every side
        is mostly blocked and the cut clears it.
    """
    unchanged = np.asarray(unchanged, dtype=np.float64).reshape(-1, 3)
    changed = np.asarray(changed, dtype=np.float64).reshape(-1, 3)
    changed = changed[changed[:, 2] <= clip_high]
    if len(changed) == 0:
        return whole_scene_view(scene_low, scene_high, clip_high)
    if regions_low is not None and regions_high is not None and len(regions_low):
        box_low = np.asarray(regions_low, np.float64).reshape(-1, 3).min(axis=0)
        box_high = np.asarray(regions_high, np.float64).reshape(-1, 3).max(axis=0)
    else:
        box_low, box_high = np.percentile(changed, [1.0, 99.0], axis=0)
    centre = (box_low + box_high) / 2.0
    scene_extent = float(np.linalg.norm(np.asarray(scene_high) - np.asarray(scene_low)))
    radius = max(
        FRAME_MARGIN * float(np.linalg.norm(box_high - box_low)) / 2.0,
        MIN_FRAME_RADIUS,
        CONTEXT_SHARE * scene_extent,
    )
    distance = framing_distance(radius, fov, aspect)
    rng = np.random.default_rng(0)
    targets = changed
    if len(changed) > MAX_TARGETS:
        targets = changed[rng.choice(len(changed), MAX_TARGETS, replace=False)]
    directions, penalties = candidate_directions()
    cameras = centre + directions * distance
    # How much of the changes' box each side sees (its projected area, 1 for the largest): a
    # thin change, such as the one face of a box a lidar saw, is not looked at edge-on.
    size = np.maximum(box_high - box_low, 0.01)
    faces = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]])
    area = np.abs(directions) @ faces
    facing = area / area.max()

    def best_for(cut: float) -> tuple[int, float]:
        """The clearest candidate under a clip at ``cut`` and its blocked share."""
        reach = distance + radius
        near = np.all(np.abs(unchanged - centre) <= reach, axis=1) & (unchanged[:, 2] <= cut)
        occluders = unchanged[near]
        spacing = point_spacing(occluders)
        span = 2.0 * reach
        voxel = max(1.5 * spacing, 0.05, span / MAX_GRID_CELLS ** (1.0 / 3.0))
        grid = OccupancyGrid(occluders, voxel)
        shares = blocked_shares(grid, cameras, targets, near_margin=3.0 * voxel)
        clear = np.flatnonzero(shares <= shares.min() + CLEAR_ENOUGH)
        chosen = int(clear[np.argmin(penalties[clear] - FACING_WEIGHT * facing[clear])])
        return chosen, float(shares[chosen])

    chosen, share = best_for(clip_high)
    reason = "change"
    if share > MOSTLY_BLOCKED:
        cut = float(changed[:, 2].max()) + CUT_MARGIN
        if cut < clip_high:
            cut_chosen, cut_share = best_for(cut)
            if cut_share < share:
                chosen, share, clip_high = cut_chosen, cut_share, cut
                reason = "change, cut above it"
    return OpeningView(
        position=cameras[chosen],
        look_at=centre,
        clip_high=clip_high,
        reason=reason,
        blocked_share=share,
    )


TOP_VIEW_MARGIN = 1.04
"""The top view leaves this much room around the scene's footprint."""


def top_view_pose(
    scene_low: NDArray[np.floating],
    scene_high: NDArray[np.floating],
    fov: float = CAMERA_FOV,
    aspect: float = ASSUMED_ASPECT,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Camera position and target (shape (3,) each) looking straight down so the scene's
    footprint fills the canvas: its longer side across the wider screen axis.

    Parameters
    ----------
    scene_low, scene_high : ndarray, shape (3,)
        The scene's bounds (z up).
    fov : float
        Vertical field of view (radians).
    aspect : float
        Canvas width / height.
    """
    low, high = np.asarray(scene_low, np.float64), np.asarray(scene_high, np.float64)
    span = np.maximum(high[:2] - low[:2], 0.1)
    x_across = (span[0] >= span[1]) == (aspect >= 1.0)
    across, along = (span[0], span[1]) if x_across else (span[1], span[0])
    half_tan = math.tan(fov / 2.0)
    distance = TOP_VIEW_MARGIN * max(along / 2.0 / half_tan, across / 2.0 / (half_tan * aspect))
    look_at = (low + high) / 2.0  # the footprint fits at mid-height
    # a hair to the south (or west), so the screen's up is north (or east): the up axis is z
    nudge = np.array([0.0, -1e-3, 0.0]) if x_across else np.array([-1e-3, 0.0, 0.0])
    position = look_at + np.array([0.0, 0.0, distance]) + nudge * distance
    return position, look_at
