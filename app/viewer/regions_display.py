"""Regions as the 3D view shows them: relabelled live, paired into moved objects, labelled
without overlap.

* :func:`relabel` recomputes the changed points and regions of both scans from the stored
  distances at another distance threshold or minimum region size, clustering with the core's
  clustering only the candidate pools (points at least half the job's threshold away,
  :class:`~app.viewer.scene.CandidatePool`), so it is cheap.  At or above the job's threshold
  only the points the job found changed are kept or dropped (stricter settings are exact up to
  the spacing estimate, not smoothed over neighbours as the worker's); below it every observed
  point that far counts, without the worker's support and visibility tests: an approximation,
  which the panel says.  The job's own labels stay the default.
* :func:`pair_moved` joins a removed and an added region of similar size within a small
  distance into one "moved" object.
* :func:`declutter` keeps the labels of the largest regions and drops those that would
  overlap them on the screen (or, without a camera, in the world).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED
from app.core.localise.regions import cluster_labels
from app.core.localise.settings import DEFAULT_PARAMETERS
from app.viewer.scene import (
    SIDES,
    RegionBox,
    SceneData,
    SideCloud,
    region_boxes,
)

CLUSTER_FACTOR = float(DEFAULT_PARAMETERS["cluster_factor"])
"""Changed points closer than this many point spacings form one region (the core's default)."""

DEFAULT_MOVED_WITHIN = 1.0
"""A removed and an added region whose centres are this close (metres) are one moved object."""

MOVED_SIZE_RATIO = 0.5
"""Each of the two largest box edges of a moved pair is at least this fraction of the other's."""

LABEL_CHAR_PIXELS = 7.0
LABEL_HEIGHT_PIXELS = 18.0
"""Approximate size of a label's text on the screen, for overlap tests."""


@dataclass(frozen=True, eq=False)
class Relabelled:
    """Changed rows of each full cloud and the regions they form."""

    changed_rows: dict[str, NDArray[np.int64]]
    regions: tuple[RegionBox, ...]
    min_distance: float
    min_region_points: int

    def labels_of(self, side: SideCloud) -> NDArray[np.int8]:
        """The labels of a scan's drawn points under these settings (unobserved kept)."""
        labels = side.labels.copy()
        labels[labels == LABEL_CHANGED] = LABEL_UNCHANGED
        changed = np.isin(side.indices, self.changed_rows[side.side])
        labels[changed & (labels == LABEL_UNCHANGED)] = LABEL_CHANGED
        return labels


def relabel(data: SceneData, min_distance: float, min_region_points: int) -> Relabelled:
    """Changed points and regions from the stored distances at other settings.

    Parameters
    ----------
    data : SceneData
        The scene, with its candidate pools.
    min_distance : float
        A point farther than this (metres) from the other scan's surface is a change
        candidate (not below the pools' floor: closer points were not kept).
    min_region_points : int
        Smaller clusters of candidates are noise.
    """
    changed_rows: dict[str, NDArray[np.int64]] = {}
    summaries: list[dict] = []
    for side in SIDES:
        pool = data.pools.get(side)
        if pool is None or len(pool.indices) == 0:
            changed_rows[side] = np.zeros(0, dtype=np.int64)
            continue
        eligible = pool.distances >= min_distance
        if data.change_threshold is not None and min_distance >= data.change_threshold:
            eligible &= pool.changed  # stricter than the job: only what it found can stay
        selected = np.flatnonzero(eligible)
        points = pool.points[selected]
        components = cluster_labels(points, CLUSTER_FACTOR * pool.spacing[selected])
        sizes = np.bincount(components) if len(components) else np.zeros(0, dtype=np.int64)
        kept = sizes[components] >= min_region_points if len(components) else np.zeros(0, bool)
        changed_rows[side] = np.sort(pool.indices[selected[kept]])
        kind = "removed" if side == "reference" else "added"
        for component in np.flatnonzero(sizes >= min_region_points):
            members = components == component
            cluster = points[members] + data.origin
            distance = pool.distances[selected[members]]
            summaries.append(
                {
                    "id": None,
                    "kind": kind,
                    "n_points": int(members.sum()),
                    "centroid": cluster.mean(axis=0).tolist(),
                    "bbox_min": cluster.min(axis=0).tolist(),
                    "bbox_max": cluster.max(axis=0).tolist(),
                    "mean_distance": float(distance.mean()),
                    "max_distance": float(distance.max()),
                }
            )
    summaries.sort(key=lambda region: (-region["n_points"], region["kind"]))
    return Relabelled(
        changed_rows=changed_rows,
        regions=region_boxes(summaries, data.origin),
        min_distance=float(min_distance),
        min_region_points=int(min_region_points),
    )


@dataclass(frozen=True)
class MovedPair:
    """A removed region and an added one taken for the same object, moved."""

    removed: RegionBox
    added: RegionBox
    distance: float

    @property
    def label(self) -> str:
        """Text drawn at the pair: both numbers and how far it moved."""
        return f"#{self.removed.index + 1}→#{self.added.index + 1} moved {self.distance:.2f} m"


def pair_moved(regions: Sequence[RegionBox], within: float) -> tuple[MovedPair, ...]:
    """Removed and added regions of similar size closer than ``within`` metres, nearest first.

    Each region is in at most one pair (greedy by distance between box centres).
    """
    removed = [region for region in regions if region.kind == "removed"]
    added = [region for region in regions if region.kind == "added"]
    candidates = []
    for before in removed:
        for after in added:
            distance = float(np.linalg.norm(np.subtract(before.center_local, after.center_local)))
            if distance <= within and _similar_size(before, after):
                candidates.append((distance, before.index, after.index, before, after))
    candidates.sort(key=lambda item: item[:3])
    used: set[int] = set()
    pairs = []
    for distance, before_index, after_index, before, after in candidates:
        if before_index in used or after_index in used:
            continue
        used.update((before_index, after_index))
        pairs.append(MovedPair(removed=before, added=after, distance=distance))
    return tuple(pairs)


def _similar_size(first: RegionBox, second: RegionBox) -> bool:
    """Whether the two largest box edges of each are within :data:`MOVED_SIZE_RATIO`."""
    edges_first = np.sort(first.dimensions)[::-1][:2]
    edges_second = np.sort(second.dimensions)[::-1][:2]
    ratios = np.minimum(edges_first, edges_second) / np.maximum(edges_first, edges_second)
    return bool((ratios >= MOVED_SIZE_RATIO).all())


def box_edges(center: Sequence[float], dimensions: Sequence[float]) -> NDArray[np.float32]:
    """The 12 edges of an axis-aligned box, shape (12, 2, 3): outlines without diagonals."""
    half = np.asarray(dimensions, dtype=np.float64) / 2.0
    corners = np.array(
        [[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64
    )
    corners = np.asarray(center, dtype=np.float64) + corners * half
    edges = [
        (first, second)
        for first in range(8)
        for second in range(first + 1, 8)
        if bin(first ^ second).count("1") == 1  # corners differing in one coordinate
    ]
    return np.array([[corners[a], corners[b]] for a, b in edges], dtype=np.float32)


@dataclass(frozen=True)
class CameraView:
    """What is needed to project onto a browser's screen (viser's OpenCV camera convention)."""

    position: NDArray[np.float64]
    wxyz: NDArray[np.float64]
    fov: float
    """Vertical field of view, radians."""
    width: int
    height: int

    def project(self, points: NDArray[np.floating]) -> tuple[NDArray, NDArray]:
        """Pixel coordinates (n, 2) of ``points`` (n, 3) and whether each is in front."""
        rotation = quaternion_matrix(self.wxyz)
        camera = (np.asarray(points, dtype=np.float64) - self.position) @ rotation
        depth = camera[:, 2]
        focal = (self.height / 2.0) / np.tan(self.fov / 2.0)
        safe = np.where(depth > 1e-9, depth, 1.0)
        pixels = np.column_stack(
            [
                focal * camera[:, 0] / safe + self.width / 2.0,
                focal * camera[:, 1] / safe + self.height / 2.0,
            ]
        )
        return pixels, depth > 1e-9


def quaternion_matrix(wxyz: Sequence[float]) -> NDArray[np.float64]:
    """The rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


MAX_PLACED_TOGETHER = 3
"""At most this many labels are placed together (4 ** 3 combinations of anchors); more, one by
one."""

LABEL_ANCHORS = ("bottom-left", "top-left", "bottom-right", "top-right")
"""Where a label may sit around its point, in order of preference (viser's ``anchor``)."""


def label_box(
    pixel: NDArray[np.floating], text: str, anchor: str
) -> tuple[float, float, float, float]:
    """Screen box (left, top, right, bottom) of a label's text placed by ``anchor``."""
    width = LABEL_CHAR_PIXELS * len(text) + 8
    x, y = float(pixel[0]), float(pixel[1])
    left = x if anchor.endswith("left") else x - width
    top = y - LABEL_HEIGHT_PIXELS if anchor.startswith("bottom") else y
    return (left, top, left + width, top + LABEL_HEIGHT_PIXELS)


def _overlaps(box: tuple[float, ...], others: Sequence[tuple[float, ...]]) -> bool:
    """Whether ``box`` overlaps any of ``others``."""
    return any(
        box[0] < other[2] and other[0] < box[2] and box[1] < other[3] and other[1] < box[3]
        for other in others
    )


def declutter(
    anchors: NDArray[np.floating],
    texts: Sequence[str],
    camera: CameraView | None,
    world_separation: float,
    obstacles: Sequence[Sequence[tuple[float, float, float, float]]] | None = None,
    placed_together: int = 0,
) -> list[str | None]:
    """Where to show each label (a viser anchor) or None to hide it, so that none overlap.

    Labels come in priority order (first = the sensors, then the largest region).  With a
    camera, a label takes the first of :data:`LABEL_ANCHORS` whose text box
    (:data:`LABEL_CHAR_PIXELS` a character) overlaps no label already placed and, when one is
    free of them, none of its ``obstacles`` (screen boxes it should not cover: the other regions'
    boxes); it is hidden when no anchor is free of labels or its point is behind the camera.
    The first ``placed_together`` labels (the sensors', whose points are often a few
    centimetres apart) are placed first, together: the first combination of anchors where none
    of them overlap (two labels at one point: one above it, one below).
    Without a camera, a label is shown at its default place only ``world_separation`` from every
    shown label's point.
    """
    anchors = np.asarray(anchors, dtype=np.float64).reshape(-1, 3)
    placed: list[str | None] = [None] * len(anchors)
    if camera is None:
        shown: list[NDArray[np.float64]] = []
        for index, point in enumerate(anchors):
            if all(np.linalg.norm(other - point) >= world_separation for other in shown):
                shown.append(point)
                placed[index] = LABEL_ANCHORS[0]
        return placed
    pixels, in_front = camera.project(anchors)
    boxes: list[tuple[float, float, float, float]] = []
    first = min(placed_together, MAX_PLACED_TOGETHER, len(anchors))
    together = [index for index in range(first) if in_front[index]]
    for combination in itertools.product(LABEL_ANCHORS, repeat=len(together)):
        tried = [
            label_box(pixels[index], texts[index], anchor)
            for index, anchor in zip(together, combination, strict=True)
        ]
        if not any(_overlaps(box, tried[:number]) for number, box in enumerate(tried)):
            boxes.extend(tried)
            for index, anchor in zip(together, combination, strict=True):
                placed[index] = anchor
            break
    for index, text in enumerate(texts):
        if not in_front[index] or placed[index] is not None:  # hidden, or placed together
            continue
        free = [
            (anchor, box)
            for anchor in LABEL_ANCHORS
            if not _overlaps(box := label_box(pixels[index], text, anchor), boxes)
        ]
        if not free:
            continue
        avoid = obstacles[index] if obstacles is not None else ()
        anchor, box = next(((a, b) for a, b in free if not _overlaps(b, avoid)), free[0])
        boxes.append(box)
        placed[index] = anchor
    return placed


def screen_box(
    camera: CameraView, center: Sequence[float], dimensions: Sequence[float]
) -> tuple[float, float, float, float] | None:
    """Screen box (left, top, right, bottom) of a region's 3D box; None when it is (partly)
    behind the camera."""
    corners = box_edges(center, dimensions).reshape(-1, 3)
    pixels, in_front = camera.project(corners)
    if not in_front.all():
        return None
    low, high = pixels.min(axis=0), pixels.max(axis=0)
    return (float(low[0]), float(low[1]), float(high[0]), float(high[1]))
