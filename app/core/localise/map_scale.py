"""Metric-scale surfaces for the map test of a dense, noisy fused map.

The local geometry fits each point's plane over its 10 nearest neighbours.  A handheld RGB-D
map thinned to 5-10 mm voxels with 1-2 cm of depth noise has those neighbours within 2-3 cm:
their normals tilt by tens of degrees and more of them tilt the denser the map.  Every figure
of the map test that compares normals (border continuation, coplanar probes, adjoining
surfaces) then depends on the density, not on the surfaces.

Here a dense cloud (median spacing under
:data:`~app.core.localise.surface_levels.SPARSE_AXIS_SPACINGS` noise sigmas, the same test
that tells a sparse cloud's trustworthy normals) is thinned to
:data:`VOXEL` cubes, a plane is fitted to each cube's :data:`NEIGHBOURS` nearest cubes (a disc
of ~5 cm whatever the density), and each point takes the plane of the flattest of the cubes
next to its own (near an edge, the cube on one face).  A sparse cloud (a robot map) keeps its
own fits.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.distance import Side
from app.core.localise.rays import Candidates
from app.core.localise.surface import neighbourhood_planes

__all__ = ["VOXEL", "MetricPlanes", "metric_candidates", "metric_planes", "metric_side"]

VOXEL = 0.02
"""Metres: edge of the cubes a dense cloud is thinned to before its planes are fitted."""
NEIGHBOURS = 24
"""Cubes per plane fit: a disc of ~5 cm at :data:`VOXEL`.  Wider fits (48 cubes of 3 cm) are
flatter on a synthetic wall with 1.2 cm of noise everywhere, but round the edges of boxes and
boards off: unchanged RGB-D room 604 1,086 -> 2,344 false points (427 with these)."""
DENSE_SPACING = 0.8 * VOXEL
"""Metres: a cloud whose median spacing is under this is dense: its 10 neighbours lie within
2-3 cm, where 1-2 cm of noise tilts their plane (the noise estimate of those same fits is low
by about 3x, so it cannot tell).  A robot map voxel-filtered at 2-5 cm keeps its own fits."""
EDGE_NEIGHBOURS = 7
"""Cubes around a point's own among which the flattest gives its plane."""


@dataclasses.dataclass(frozen=True)
class MetricPlanes:
    """A dense cloud's metric-scale planes (:func:`metric_planes`).

    Attributes
    ----------
    cube : ndarray, shape (n,), intp
        Each point's cube.
    normal : ndarray, shape (m, 3), float32
        Per cube, the unit normal of the flattest plane next to it.
    constant : ndarray, shape (m,), float64
        That plane's constant.
    """

    cube: NDArray[np.intp]
    normal: NDArray[np.float32]
    constant: NDArray[np.float64]


def _dense(side: Side) -> bool:
    """Whether ``side`` is sampled finer than :data:`DENSE_SPACING` (module docstring)."""
    return float(np.median(side.geometry.spacing)) < DENSE_SPACING


def _cube_planes(
    points: NDArray[np.float64],
) -> tuple[NDArray[np.intp], NDArray[np.float32], NDArray[np.float64]]:
    """Each point's cube (shape (n,)), and per cube the unit normal (shape (m, 3)) and
    constant (shape (m,)) of the plane of the flattest cube next to it."""
    cells = np.floor((points - points.min(axis=0)) / VOXEL).astype(np.int64)
    extent = cells.max(axis=0) + 1
    keys = (cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]
    _, cube, counts = np.unique(keys, return_inverse=True, return_counts=True)
    centroids = np.stack(
        [np.bincount(cube, weights=points[:, axis]) / counts for axis in range(3)], axis=1
    )
    k = min(NEIGHBOURS, centroids.shape[0] - 1)
    tree = KDTree(centroids)
    _, index = tree.query(centroids, k=k + 1)
    index = np.asarray(index).reshape(centroids.shape[0], k + 1)
    normal, constant, _, _, variation = neighbourhood_planes(centroids, index)
    near = index[:, : min(EDGE_NEIGHBOURS, k) + 1]
    flattest = near[np.arange(near.shape[0]), np.argmin(variation[near], axis=1)]
    return cube, normal[flattest], constant[flattest]


def metric_planes(side: Side) -> MetricPlanes | None:
    """``side``'s metric-scale planes if it is dense (module docstring), else None.  A
    comparison fits each cloud's once (:func:`~app.core.localise.visibility.map_test_planes`):
    each cloud's map test runs with the other's."""
    if side.points.shape[0] < NEIGHBOURS + 1 or not _dense(side):
        return None
    return MetricPlanes(*_cube_planes(side.points))


def metric_side(side: Side, planes: MetricPlanes | None) -> tuple[Side, NDArray[np.float32] | None]:
    """``side`` with its metric-scale ``planes`` (as it is when None), and those normals per
    point (shape (n, 3); None when kept)."""
    if planes is None:
        return side, None
    own = side.geometry.normal
    point_normal = planes.normal[planes.cube]
    flip = np.einsum("nd,nd->n", point_normal, own) < 0
    point_normal[flip] *= -1
    point_constant = np.where(flip, -planes.constant[planes.cube], planes.constant[planes.cube])
    geometry = dataclasses.replace(
        side.geometry, normal=point_normal, plane_constant=point_constant
    )
    return dataclasses.replace(side, geometry=geometry), point_normal


def metric_candidates(
    candidates: Candidates, point_normal: NDArray[np.float32] | None
) -> Candidates:
    """``candidates`` with the metric-scale normals of their points (as they are if None)."""
    if point_normal is None:
        return candidates
    return dataclasses.replace(candidates, normal=point_normal[candidates.index])
