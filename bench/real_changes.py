"""The hand-made truth of the real MultiChange3D pairs (``bench/real_changes.json``) and its score.

Each plain change (an object of 0.3 m or more removed, added or moved) is a few boxes in one
epoch or both; its points are the points of that epoch inside its boxes that lie more than
:data:`CHANGE_DISTANCE` from the other epoch's surface (:func:`surface_distance`: the local
plane of its nearest points, as the issue's truth measures from every surface of the other
epoch).  A change's recall is the share of its points that a compare calls changed; changed
points outside every box are counted apart.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from app.core.labels import LABEL_CHANGED

ANNOTATIONS = Path(__file__).resolve().parent / "real_changes.json"
CHANGE_DISTANCE = 0.10
"""Metres: a point farther than this from every point of the other epoch is changed."""
PLANE_NEIGHBOURS = 10


@dataclass(frozen=True)
class RealChange:
    """One annotated change: its name, kind, description, how it was found and its boxes."""

    name: str
    kind: str
    description: str
    found_by: str
    boxes: tuple[dict, ...]


def load_changes(path: Path = ANNOTATIONS) -> dict[str, list[RealChange]]:
    """The annotated changes of every pair, by pair name."""
    pairs = json.loads(path.read_text())["pairs"]
    return {
        name: [
            RealChange(
                name=change["name"],
                kind=change["kind"],
                description=change["description"],
                found_by=change["found_by"],
                boxes=tuple(change["boxes"]),
            )
            for change in changes
        ]
        for name, changes in pairs.items()
    }


def in_box(points: NDArray[np.float64], box: dict) -> NDArray[np.bool_]:
    """Which points (shape (n, 3)) lie in one annotated box (center, size, yaw about z)."""
    yaw = math.radians(box.get("yaw_degrees", 0.0))
    offset = points - np.asarray(box["center"], dtype=np.float64)
    along = offset[:, 0] * math.cos(yaw) + offset[:, 1] * math.sin(yaw)
    across = -offset[:, 0] * math.sin(yaw) + offset[:, 1] * math.cos(yaw)
    half = np.asarray(box["size"], dtype=np.float64) / 2.0
    return (
        (np.abs(along) <= half[0]) & (np.abs(across) <= half[1]) & (np.abs(offset[:, 2]) <= half[2])
    )


def surface_distance(
    points: NDArray[np.float64], other: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Distance of each point (shape (n, 3)) to the other epoch's surface (shape (m, 3)): to
    the plane of its :data:`PLANE_NEIGHBOURS` nearest points, or to the nearest point where
    that is nearer (a sparse scan's points lie up to a spacing apart on a flat ground)."""
    distance, index = cKDTree(other).query(points, k=PLANE_NEIGHBOURS)
    neighbours = other[index]
    centred = neighbours - neighbours.mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    normal = vectors[:, :, 0]
    across = np.abs(np.einsum("nd,nd->n", points - neighbours.mean(axis=1), normal))
    return np.minimum(distance[:, 0], across)


def change_masks(
    epochs: tuple[NDArray[np.float64], NDArray[np.float64]], changes: list[RealChange]
) -> list[tuple[NDArray[np.bool_], NDArray[np.bool_]]]:
    """Per change, the masks of its points in epoch 0 and epoch 1 (shapes (n,), (m,))."""
    far = [surface_distance(epochs[epoch], epochs[1 - epoch]) > CHANGE_DISTANCE for epoch in (0, 1)]
    masks = []
    for change in changes:
        mine = [np.zeros(points.shape[0], dtype=bool) for points in epochs]
        for box in change.boxes:
            epoch = int(box["epoch"])
            mine[epoch] |= in_box(epochs[epoch], box) & far[epoch]
        masks.append((mine[0], mine[1]))
    return masks


def score_changes(
    epochs: tuple[NDArray[np.float64], NDArray[np.float64]],
    labels: tuple[NDArray[np.integer], NDArray[np.integer]],
    changes: list[RealChange],
) -> tuple[list[tuple[RealChange, float, int]], int]:
    """Each change's recall and point count, and the changed points outside every change's
    boxes (both epochs)."""
    recalls = []
    boxed = [np.zeros(points.shape[0], dtype=bool) for points in epochs]
    for change in changes:
        for box in change.boxes:
            epoch = int(box["epoch"])
            boxed[epoch] |= in_box(epochs[epoch], box)
    for change, masks in zip(changes, change_masks(epochs, changes), strict=True):
        total = sum(int(mask.sum()) for mask in masks)
        found = sum(
            int(np.count_nonzero(mask & (label == LABEL_CHANGED)))
            for mask, label in zip(masks, labels, strict=True)
        )
        recalls.append((change, found / total if total else 0.0, total))
    outside = sum(
        int(np.count_nonzero((label == LABEL_CHANGED) & ~mask))
        for label, mask in zip(labels, boxed, strict=True)
    )
    return recalls, outside
