"""Synthetic moving-sensor maps with per-point truth: the scene classes of issue 29.

One entry point, :func:`map_pair`, for the three classes:

- ``"rgbd"``: handheld RGB-D fused maps of furnished rooms (:mod:`app.core.datasets.handheld`);
- ``"robot"``: robot / mobile laser scanning maps of corridors, offices and warehouses
  (:func:`app.core.datasets.robot.robot_pair`);
- ``"tls"``: terrestrial multi-station scans, registered, merged and thinned
  (:func:`app.core.datasets.robot.terrestrial_pair`).

Every pair (:class:`~app.core.datasets.map_world.MapPair`) holds both maps with their per-point
``"time"`` attribute and ``trajectory`` (``pair.clouds()`` gives them bare, as the files of the
"nothing given" case), the truth (``*_changed``: more than 10 cm from every surface of the other
epoch's world; ``*_scored``: seen by some tested pose of the other epoch), the changes (kind,
object, where) and the scan's true transform.  The same arguments give the same pair.
"""

from __future__ import annotations

from app.core.datasets.furniture import MAP_CHANGES, MapChange, MapObject
from app.core.datasets.handheld import handheld_pair
from app.core.datasets.map_world import CHANGE_DISTANCE, MapPair
from app.core.datasets.robot import ROBOT_LAYOUTS, robot_pair, terrestrial_pair

__all__ = [
    "CHANGE_DISTANCE",
    "MAP_CHANGES",
    "MAP_CLASSES",
    "MapChange",
    "MapObject",
    "MapPair",
    "class_layouts",
    "map_pair",
]

MAP_CLASSES = ("rgbd", "robot", "tls")
"""Values of ``map_class``."""


def class_layouts(map_class: str) -> tuple[str, ...]:
    """The layouts :func:`map_pair` accepts for ``map_class``."""
    if map_class not in MAP_CLASSES:
        raise ValueError(f"map_class must be one of {MAP_CLASSES}, got {map_class!r}")
    return ("room",) if map_class == "rgbd" else ROBOT_LAYOUTS


def map_pair(
    map_class: str,
    *,
    layout: str | None = None,
    change: str = "removed",
    misaligned: bool = False,
    size: float = 1.0,
    realism: str = "none",
    random_state: int = 0,
) -> MapPair:
    """A random two-epoch map of ``map_class`` with per-point truth.

    Parameters
    ----------
    map_class : {"rgbd", "robot", "tls"}
    layout : str, optional
        One of :func:`class_layouts` (default: the first).
    change : {"none", "removed", "added", "moved", "rotated", "mixed"}
    misaligned : bool
        Give the scan turned by 0.3 degrees and shifted by 2-3 cm (the truth stays in the
        reference frame; ``true_transform`` undoes the misalignment).
    size : float
        Scales the rays cast per epoch (1: about 100-150k points an epoch after thinning).
    realism : {"none", "drift"}
        RGB-D only: ``"drift"`` adds a real fused map's tracking drift, flying pixels and
        missing patches (:mod:`app.core.datasets.rgbd_artefacts`) to the same room; the lidar
        classes carry their own pose errors and accept ``"none"`` only.
    random_state : int

    Returns
    -------
    MapPair
    """
    layouts = class_layouts(map_class)
    layout = layouts[0] if layout is None else layout
    if layout not in layouts:
        raise ValueError(f"layout of a {map_class!r} map must be one of {layouts}, got {layout!r}")
    if size <= 0:
        raise ValueError(f"size must be positive, got {size}")
    if realism != "none" and map_class != "rgbd":
        raise ValueError(f"realism {realism!r} is for RGB-D maps only; use 'none' for {map_class}")
    if map_class == "rgbd":
        frames = max(8, round(160 * size**0.5))
        columns = max(4, round(36 * size**0.25))
        return handheld_pair(
            change=change,
            misaligned=misaligned,
            n_frames=frames,
            pixels=(columns, max(3, round(columns * 0.75))),
            realism=realism,
            random_state=random_state,
        )
    build = robot_pair if map_class == "robot" else terrestrial_pair
    return build(
        layout=layout,
        change=change,
        misaligned=misaligned,
        rays_per_epoch=max(5_000, round(150_000 * size)),
        random_state=random_state,
    )
