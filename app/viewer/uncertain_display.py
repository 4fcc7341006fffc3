"""Uncertain regions in the 3D view: places one epoch has and the other never covered.

A job lists, besides its regions, the clusters of candidates whose evidence is ``no_coverage``
(``uncertain_regions``: the other epoch's path did not reach that place, so nothing says whether
it changed).  They are never changes: they are not counted, paired into moved objects nor
relabelled, and they do not steer the opening camera.  The view draws them apart, as grey
dashed boxes (a change's box is a solid red or green outline), behind a toggle of their own, and
lists them under the region buttons with their evidence.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.viewer.scene import EVIDENCE_WORDS, RegionBox

__all__ = [
    "UNCERTAIN_COLOUR",
    "dashed_box_edges",
    "draw_uncertain_regions",
    "uncertain_label",
]

UNCERTAIN_COLOUR = (150, 150, 150)
"""A muted grey: reported, not a change."""
DASHES_PER_EDGE = 4
"""Dashes drawn along each of a box's 12 edges (with gaps between them)."""
DASH_SHARE = 0.6
"""A dash's share of a dash and the gap after it (the last dash, at a corner, has no gap)."""
LINE_PIXELS = 1.5


def uncertain_label(box: RegionBox) -> str:
    """Its button's text: number, side, size, evidence and that it is not counted."""
    why = EVIDENCE_WORDS.get(box.evidence, box.evidence)
    if box.confidence is not None:
        why = f"{why} {round(100 * box.confidence)} %"
    return f"U{box.index + 1} {box.kind} · {box.n_points:,} pts · {why} · not counted"


def dashed_box_edges(
    center: Sequence[float], dimensions: Sequence[float], dashes: int = DASHES_PER_EDGE
) -> NDArray[np.float32]:
    """The dashes of an axis-aligned box's 12 edges, shape (12 * dashes, 2, 3).

    Each edge has ``dashes`` equal dashes, the first and last at its corners (so the corners
    read as a box), with gaps between them (:data:`DASH_SHARE`).
    """
    half = np.asarray(dimensions, dtype=np.float64) / 2.0
    centre = np.asarray(center, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    corners = centre + corners * half
    pairs = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    gap_per_dash = (1.0 - DASH_SHARE) / DASH_SHARE
    dash = 1.0 / (dashes + (dashes - 1) * gap_per_dash)  # dashes at both corners
    starts = np.arange(dashes) * dash * (1.0 + gap_per_dash)
    ends = starts + dash
    segments = [
        [corners[a] + (corners[b] - corners[a]) * s, corners[a] + (corners[b] - corners[a]) * e]
        for a, b in pairs
        for s, e in zip(starts, ends, strict=True)
    ]
    return np.asarray(segments, dtype=np.float32)


def draw_uncertain_regions(
    scene: Any,
    boxes: Sequence[RegionBox],
    *,
    visible: bool,
    inside_clip: Callable[[RegionBox], bool] = lambda _box: True,
) -> list[tuple[RegionBox, Any]]:
    """A grey dashed outline per uncertain region (viser line segments); ``(box, handle)``."""
    return [
        (
            box,
            scene.add_line_segments(
                f"/uncertain/{box.index}",
                points=dashed_box_edges(box.center_local, box.dimensions),
                colors=np.asarray(UNCERTAIN_COLOUR, dtype=np.uint8),
                thickness=LINE_PIXELS,
                thickness_units="screen",
                visible=visible and inside_clip(box),
            ),
        )
        for box in boxes
    ]
