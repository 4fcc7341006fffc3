"""Synthetic scan pairs with exact per-point truth: scandiff's datasets, as ``sklearn.datasets``.

Every generator is deterministic for its seed, needs no file or network, and returns the clouds
together with what a comparison should find (which points changed, which could be seen), so
tests, benchmarks and notebooks score a comparison against the truth
(:mod:`app.core.ground_truth`).  See ``docs/datasets.md``.

Generators
----------
:func:`paper_corridor`
    The corridor of the paper's section IV: two walls and a ceiling, a box pushed out of a wall
    (:class:`SyntheticPair`).
:func:`raycast_scene`
    A spinning-lidar scan of two furnished rooms taken twice, with an object added, removed or
    moved, occlusions and a pose error (:class:`SyntheticPair`).
:func:`lidar_pair`
    Ray-cast rescans of a room, corridor or warehouse, from one or several stations
    (:class:`LidarPair`).
:func:`map_pair`
    Moving-sensor maps: handheld RGB-D, robot / mobile laser scanning and terrestrial
    multi-station scans, with trajectories (:class:`MapPair`).
:func:`site_history`
    A reference and rescans of one room where a bin moves every time and, now and then, a crate
    appears (:class:`SiteVisit`).

Modules
-------
:mod:`~app.core.datasets.scenes` (corridor and two rooms), :mod:`~app.core.datasets.lidar`
(written to files in bounded memory by :mod:`~app.core.datasets.lidar_files`),
:mod:`~app.core.datasets.maps` (with :mod:`~app.core.datasets.handheld`,
:mod:`~app.core.datasets.robot`, :mod:`~app.core.datasets.map_world` and
:mod:`~app.core.datasets.furniture`), :mod:`~app.core.datasets.site`.
"""

from app.core.datasets.lidar import LidarPair, lidar_pair
from app.core.datasets.maps import MapPair, map_pair
from app.core.datasets.scenes import SyntheticPair, paper_corridor, raycast_scene
from app.core.datasets.site import SiteVisit, site_history

__all__ = [
    "LidarPair",
    "MapPair",
    "SiteVisit",
    "SyntheticPair",
    "lidar_pair",
    "map_pair",
    "paper_corridor",
    "raycast_scene",
    "site_history",
]
