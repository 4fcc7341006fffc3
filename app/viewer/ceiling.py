"""Find an indoor scene's ceiling, so the 3D view opens cut below it.

A room, corridor or warehouse scanned from inside is closed above: seen from the default
oblique camera, its ceiling hides every change.  A ceiling is a thin slab at the top of the
height range that covers most of the scene's footprint; an outdoor scan (trees, roofs, poles)
has no such slab and is left uncut.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

CELL_SIZE = 0.5
"""Footprint grid cell (m)."""
SLAB_THICKNESS = 0.3
"""A ceiling's points lie within this of the highest points (m)."""
MIN_COVER = 0.5
"""The slab must cover at least this share of the footprint's cells."""
BIN = 0.02
"""Height histogram bin (m) to find the ceiling's height within the slab."""
BELOW_CEILING = 0.15
"""The cut lies this far below the ceiling's height (m): its noise and a slight tilt."""


def ceiling_cut_height(points: NDArray[np.floating]) -> float | None:
    """The height to cut at, just below the scene's ceiling; None when it has none.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        The drawn points of both scans, z up, in one frame.

    Returns
    -------
    float or None
        ``BELOW_CEILING`` under the ceiling's height (the densest height of the top slab), or
        None when no thin slab at the top covers at least half of the footprint.
    """
    if len(points) < 100:
        return None
    heights = points[:, 2]
    top = float(np.quantile(heights, 0.999))
    bottom = float(np.quantile(heights, 0.001))
    if top - bottom < 4 * SLAB_THICKNESS:  # too flat to have a ceiling above anything
        return None
    cells = np.floor(points[:, :2] / CELL_SIZE).astype(np.int64)
    footprint = np.unique(cells, axis=0)
    in_slab = heights >= top - SLAB_THICKNESS
    covered = np.unique(cells[in_slab], axis=0)
    if len(covered) < MIN_COVER * len(footprint):
        return None
    # The ceiling's height: the slab's densest height (walls reach into the slab too).
    slab_heights = heights[in_slab]
    edges = np.arange(top - SLAB_THICKNESS, slab_heights.max() + 2 * BIN, BIN)
    counts, edges = np.histogram(slab_heights, bins=edges)
    peak = int(np.argmax(counts))
    return float((edges[peak] + edges[peak + 1]) / 2) - BELOW_CEILING


CHANGE_HEADROOM = 0.05
"""The opening cut stays at least this far (metres) above the highest change."""


def opening_clip_height(points: NDArray[np.floating], change_tops: list[float]) -> float:
    """The height the 3D view opens clipped at: below the ceiling, never below a change.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        The drawn points of both scans, z up, in one frame.
    change_tops : list of float
        The top of each changed region (and of the changed points).

    Returns
    -------
    float
        The cut's height, or ``inf`` when the scene has no ceiling (nothing is cut).
    """
    cut = ceiling_cut_height(points)
    if cut is None:
        return float("inf")
    if change_tops:
        cut = max(cut, max(change_tops) + CHANGE_HEADROOM)
    return float(cut)
