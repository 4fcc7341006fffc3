"""A rough origin sharpened on the returns' elevation rings: the fallback for real lidars.

The column lines of :mod:`~app.core.origins.columns` assume every column is a vertical
half-plane through the axis. A real Velodyne HDL-64 fires its 64 lasers at per-laser azimuth
offsets (and from two blocks at different heights), so its columns are not half-planes and the
lines concur only roughly (0.3-1.3 m off on the KITTI frames). Its rings are exact, though: every
laser keeps one elevation, so from the true origin the elevation histogram of the returns is a
comb of sharp peaks, and it blurs within a decimetre of it (the spike measured on KITTI frames:
7x sharper at the origin than 0.15 m away). So, from the rough origin:

1. the top-view centre: a grid search of the elevation histogram's sharpness (returns 2.5-15 m
   away, where an offset moves elevations most), 0.8 m around the start in 0.1 m steps, then
   0.1 m in 0.02 m, then 0.02 m in 0.005 m;
2. the height: the sharpest elevation histogram of the nearer half of the returns on level
   surfaces (the ground rings round the sensor, where the height matters most for visibility)
   within 0.5 m of the rough height (on a lidar with one apex only when clearly sharper than
   from there, :data:`LEVEL_GAIN`: else it is noise); on the HDL-64
   the wall returns' rings converge 0.2 m above the sensor frame's origin and the near ground
   rings 0.12-0.15 m above it (its two laser blocks sit at different heights);
3. the evidence: the spike (sharpness at the origin over the largest of eight 0.3 m away) and
   the share of wall returns on rings from there (:func:`~app.core.origins.rings.fit_ring_height`).

A cloud merged from several stations has no single sharp origin (spike ~1, ring share < 0.7),
nor has a cloud without rings.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.core.origins.rings import (
    FINE_BIN_DEG,
    RingOriginFit,
    elevation_sharpness,
    fit_ring_height,
    sharpest_height,
)

__all__ = ["sharpen_origin"]

SEARCH_STEPS = ((1.6, 0.1), (0.1, 0.02), (0.02, 0.005))
"""(half-width, step) in metres of the successive top-view grid searches."""
SEARCH_BIN_DEG = 0.05
NEAR_RANGE = (2.5, 15.0)
"""Top-view distances (m) from the start of the returns whose sharpness is searched."""
SAMPLE_POINTS = 4000
SPIKE_DISTANCE = 0.3
HEIGHT_SPAN = 0.5
LEVEL_GAIN = 1.5
"""The level returns' height replaces the rough (wall rings') height only when its rings are
this many times sharper: on KITTI HDL-64 frames 1.9-2.1 (the lower laser block's ground rings
converge 5-8 cm below the wall rings); on a lidar with one apex 1.0-1.15, where the near ground
rings blur within the top-view search's last 5 mm step (0.02 degree bins) and their sharpest
height is noise, 1-7 cm off."""
ONE_APEX_RING_SHARE = 0.9
"""Wall returns' ring share from the sharpened centre from which the lidar is taken to have one
apex and :data:`LEVEL_GAIN` applies (ray-cast lidars 0.95-1; Budapest HDL-64 frames without
ground 0.83-0.86: their wall rings' height is the upper laser block's, 0.2 m above the sensor,
and the level returns' height decides whether the apex search runs)."""
LEVEL_NORMAL_Z = 0.97
WALL_NORMAL_Z = 0.2
NEIGHBOURS = 9
SURFACE_QUERIES = 12_000
"""Returns of the patch whose neighbours are examined (level or wall)."""


def _sharpness(
    sample: NDArray[np.float64], centre: NDArray, height: float, bin_deg: float
) -> float:
    horizontal = np.hypot(sample[:, 0] - centre[0], sample[:, 1] - centre[1])
    usable = horizontal > 1.0
    return elevation_sharpness(sample[usable, 2], horizontal[usable], height, bin_deg)


def _surfaces(
    patch: NDArray[np.float64], rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Returns on level surfaces and on walls (by their neighbours' plane), shapes (m, 3)."""
    queries = patch[rng.choice(len(patch), size=min(len(patch), SURFACE_QUERIES), replace=False)]
    from scipy.spatial import cKDTree  # on first use: API processes need no scipy

    _, neighbour = cKDTree(patch).query(queries, k=NEIGHBOURS)
    local = patch[neighbour]
    centred = local - local.mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("qki,qkj->qij", centred, centred))
    normal_z = np.abs(vectors[:, 2, 0])
    return queries[normal_z > LEVEL_NORMAL_Z], queries[normal_z < WALL_NORMAL_Z]


def _level_height(
    level: NDArray[np.float64], centre: NDArray, rough: float, one_apex: bool
) -> float:
    """The height within :data:`HEIGHT_SPAN` of ``rough`` whose level returns fall on the
    sharpest rings; with ``one_apex`` (the wall rings explain nearly every wall return) only
    if :data:`LEVEL_GAIN` times sharper than from ``rough``, else ``rough``."""
    horizontal = np.hypot(level[:, 0] - centre[0], level[:, 1] - centre[1])
    usable = horizontal > 1.0
    if np.count_nonzero(usable) < 200:
        return rough
    usable &= horizontal <= np.median(horizontal[usable])  # the nearer half: the ground round
    z, horizontal = level[usable, 2], horizontal[usable]  # the sensor, where height matters most
    best = sharpest_height(z, horizontal, rough, HEIGHT_SPAN)
    gain = elevation_sharpness(z, horizontal, best, FINE_BIN_DEG) / max(
        elevation_sharpness(z, horizontal, rough, FINE_BIN_DEG), 1e-12
    )
    return best if gain >= LEVEL_GAIN or not one_apex else rough


def sharpen_origin(
    points: NDArray[np.float64],
    patch: NDArray[np.float64],
    start: NDArray[np.float64],
    rng: np.random.Generator,
) -> RingOriginFit:
    """Sharpen a rough origin ``start`` (3,) on the elevation rings of ``points`` (n, 3).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        The cloud (z along the lidar's axis).
    patch : ndarray, shape (m, 3)
        Whole voxels of it (:func:`~app.core.origins.voxels.whole_voxels`): their
        neighbours tell level surfaces from walls.
    start : ndarray, shape (3,)
    rng : Generator
    """
    centre = np.asarray(start[:2], dtype=np.float64).copy()
    height = float(start[2])
    horizontal = np.hypot(points[:, 0] - centre[0], points[:, 1] - centre[1])
    near = points[(horizontal > NEAR_RANGE[0]) & (horizontal < NEAR_RANGE[1])]
    level, walls = _surfaces(patch, rng)
    if len(near) < 500 or len(walls) < 100:
        return RingOriginFit(np.asarray(start, dtype=np.float64), 0.0, 0.0)
    sample = near[rng.choice(len(near), size=min(len(near), SAMPLE_POINTS), replace=False)]
    for span, step in SEARCH_STEPS:
        offsets = np.arange(-span, span + step / 2, step)
        grid = np.array(
            [
                [
                    _sharpness(sample, centre + np.array([dx, dy]), height, SEARCH_BIN_DEG)
                    for dy in offsets
                ]
                for dx in offsets
            ]
        )
        row, column = np.unravel_index(int(np.argmax(grid)), grid.shape)
        centre = centre + np.array([offsets[row], offsets[column]])
    rings = fit_ring_height(walls, centre, rng)
    height = _level_height(level, centre, height, rings.ring_share >= ONE_APEX_RING_SHARE)
    peak = _sharpness(sample, centre, height, SEARCH_BIN_DEG)
    angles = np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)
    around = max(
        _sharpness(
            sample,
            centre + SPIKE_DISTANCE * np.array([np.cos(a), np.sin(a)]),
            height,
            SEARCH_BIN_DEG,
        )
        for a in angles
    )
    return RingOriginFit(
        origin=np.array([*centre, height]),
        spike=float(peak / max(around, 1e-12)),
        ring_share=rings.ring_share,
    )
