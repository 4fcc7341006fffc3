"""Colours of the 3D view: the signed-distance colour map, its colour bar, the legend and the
depth cue (points shaded by height, since viser 1.1 has no eye-dome lighting).

Signed distance: a reference point's distance to the scan's surface counts negative (material
that is gone: "removed" side), a scan point's distance to the reference's surface positive
(material that is new: "added" side).  The colour map runs from the removed red through a
neutral grey at zero to the added green, so both colour modes speak the same language.
"""

from __future__ import annotations

import html
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

RGB = tuple[int, int, int]

REMOVED_COLOUR: RGB = (230, 25, 25)
"""Changed points of the reference (gone from the scan), drawn at full colour."""
ADDED_COLOUR: RGB = (20, 200, 50)
"""Changed points of the scan (new), drawn at full colour."""

DISTANCE_MAP_ANCHORS: tuple[tuple[float, RGB], ...] = (
    (-1.0, (180, 0, 30)),
    (-0.5, (240, 90, 70)),
    (0.0, (215, 215, 215)),
    (0.5, (90, 200, 110)),
    (1.0, (0, 130, 50)),
)
"""Signed distance / limit -> colour (piecewise linear; beyond +-1 the end colours)."""

NO_DISTANCE_COLOUR: RGB = (120, 120, 140)
"""Points without a distance (unobserved, or a job from before distances were stored)."""

DEPTH_CUE_DARKEST = 0.55
"""Brightness of the lowest points when the depth cue is on (the highest keep full colour)."""


def signed_distance_colours(signed: NDArray[np.floating], limit: float) -> NDArray[np.uint8]:
    """Colours of signed distances on the removed-grey-added map.

    Parameters
    ----------
    signed : ndarray, shape (n,)
        Signed distances (metres); NaN draws :data:`NO_DISTANCE_COLOUR`.
    limit : float
        The distance drawn in the end colours (and beyond), > 0.

    Returns
    -------
    ndarray, shape (n, 3), uint8
    """
    signed = np.asarray(signed, dtype=np.float64).reshape(-1)
    positions = np.array([anchor for anchor, _ in DISTANCE_MAP_ANCHORS])
    colours = np.array([colour for _, colour in DISTANCE_MAP_ANCHORS], dtype=np.float64)
    scaled = np.clip(np.nan_to_num(signed / max(limit, 1e-9), nan=0.0), -1.0, 1.0)
    channels = [np.interp(scaled, positions, colours[:, channel]) for channel in range(3)]
    out = np.rint(np.column_stack(channels)).astype(np.uint8)
    out[np.isnan(signed)] = NO_DISTANCE_COLOUR
    return out


def shade_by_height(
    colours: NDArray[np.uint8],
    heights: NDArray[np.floating],
    low: float,
    high: float,
    darkest: float = DEPTH_CUE_DARKEST,
) -> NDArray[np.uint8]:
    """``colours`` darkened with decreasing height: ``darkest`` at ``low``, unchanged at ``high``.

    Parameters
    ----------
    colours : ndarray, shape (n, 3) uint8, or (3,)
    heights : ndarray, shape (n,)
    low, high : float
        The height range (metres); points outside it are clipped to it.
    """
    heights = np.asarray(heights, dtype=np.float64).reshape(-1)
    span = max(high - low, 1e-9)
    brightness = darkest + (1.0 - darkest) * np.clip((heights - low) / span, 0.0, 1.0)
    base = np.broadcast_to(np.asarray(colours, dtype=np.float64), (heights.shape[0], 3))
    return np.rint(base * brightness[:, None]).astype(np.uint8)


def distance_limit(distances: Sequence[NDArray[np.floating]], threshold: float | None) -> float:
    """The colour map's limit: the 98th percentile of the finite distances, at least 2x the
    change threshold (so unchanged points stay near grey), at least 1 cm."""
    finite = [np.abs(array[np.isfinite(array)]) for array in distances]
    values = np.concatenate(finite) if finite else np.zeros(0)
    limit = float(np.percentile(values, 98.0)) if values.size else 0.0
    if threshold is not None and np.isfinite(threshold):
        limit = max(limit, 2.0 * float(threshold))
    return max(limit, 0.01)


def hex_colour(colour: Sequence[int]) -> str:
    """``#rrggbb``."""
    return "#" + "".join(f"{int(value):02x}" for value in colour[:3])


def colour_bar_html(limit: float) -> str:
    """The signed-distance colour bar: a CSS gradient of the map with its end labels."""
    stops = ", ".join(
        f"{hex_colour(colour)} {(anchor + 1.0) * 50.0:.0f}%"
        for anchor, colour in DISTANCE_MAP_ANCHORS
    )
    return (
        f'<div class="scandiff-colour-bar" data-limit="{limit:.6g}" '
        'style="font-size:12px;margin:4px 0">'
        '<div style="display:flex;justify-content:space-between">'
        f"<span>&minus;{limit:.3g} m removed</span><span>0</span>"
        f"<span>+{limit:.3g} m added</span></div>"
        f'<div class="scandiff-colour-bar-gradient" style="height:12px;border-radius:3px;'
        f'background:linear-gradient(to right, {stops})"></div>'
        '<div style="opacity:0.75">signed distance to the other scan (reference points '
        "negative, scan points positive)</div></div>"
    )


def legend_html(entries: Sequence[tuple[str, RGB, str]]) -> str:
    """A legend: one swatch, name and description per ``(name, colour, description)``."""
    rows = "".join(
        f'<div class="scandiff-legend-entry" data-name="{html.escape(name)}" '
        f'data-colour="{hex_colour(colour)}" style="display:flex;gap:6px;align-items:center">'
        f'<span style="display:inline-block;width:12px;height:12px;border-radius:6px;'
        f'background:{hex_colour(colour)}"></span>'
        f"<span><b>{html.escape(name)}</b> {html.escape(description)}</span></div>"
        for name, colour, description in entries
    )
    return f'<div class="scandiff-legend" style="font-size:12px">{rows}</div>'
