"""Noise fragments of surface parts, and the part each lies in.

:func:`~app.core.localise.map_parts.surface_parts` links candidates whose normals agree.  On
a noisy surface the normals of a few neighbourhoods tilt together (each fitted over the same
handful of points), so a far wall of a fused RGB-D map, voxel-thinned finer than its depth
noise, falls apart into many small parts inside its large ones.  Such a fragment has almost
no border of its own with the rest of the map, so nothing continues from it; judged alone,
a piece of a coverage gap high on a wall that the other path never looked at became a
change, and more of them the denser the map (a fragment's point count is set by the
neighbourhoods that tilt together, not by its area: the false points grew with density).
The floor is an area, so a sparse map's small faces (a robot map's box side of 20-40 points
at 4-5 cm) stay parts of their own.

A fragment (a part covering less than :data:`FRAGMENT_AREA`, its candidates' squared
spacings summed) carries no surface of its own: fragments linked to each other form one
group, and a group lies in the non-fragment part it has the most links with (one part only,
so a fragment at a crease never joins a board to the floor it stands on).  A group linked to
no larger part lies in itself.  A fragment in a coverage difference is one too
(:func:`~app.core.localise.map_evidence.map_test`); a fragment of a change keeps its own
verdict (a fragment's verdict is never made a change by its host).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.regions import CLUSTER_NEIGHBOURS

__all__ = ["FRAGMENT_AREA", "fragment_hosts", "host_coverage"]

FRAGMENT_AREA = 0.02
"""Square metres: smaller parts are fragments, under a quarter of a face of the smallest
object the issue asks for (0.3 m: 0.09 m^2); a tilted patch of the normal fits
(:data:`~app.core.localise.regions.CLUSTER_NEIGHBOURS` points each) is far smaller on a dense
map (10-50 points at 1-2 cm, 0.001-0.02 m^2)."""


def fragment_hosts(
    labels: NDArray[np.int64],
    points: NDArray[np.float64],
    radius: NDArray[np.float64],
    spacing: NDArray[np.float64],
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The parts with linked fragments grouped, and per part the part it lies in: a
    fragment group's larger part (module docstring), every other part itself.

    Parameters
    ----------
    labels : ndarray, shape (c,), int64
        :func:`~app.core.localise.map_parts.surface_parts` of the candidates.
    points : ndarray, shape (c, 3)
    radius : ndarray, shape (c,)
        Candidates within a candidate's radius (its nearest
        :data:`~app.core.localise.regions.CLUSTER_NEIGHBOURS`) are linked.
    spacing : ndarray, shape (c,)
        The cloud's local spacing at each candidate (a part's area is its squared spacings).

    Returns
    -------
    grouped : ndarray, shape (c,), int64
        Part label per candidate, each group of linked fragments one part.
    host : ndarray, shape (grouped parts,), int64
        The host part of each part of ``grouped``.
    """
    count = points.shape[0]
    n_parts = int(labels.max()) + 1 if count else 0
    host = np.arange(n_parts)
    fragment = np.bincount(labels, weights=np.square(spacing), minlength=n_parts) < FRAGMENT_AREA
    if count <= 1 or not fragment.any() or fragment.all():
        return labels, host
    k = min(CLUSTER_NEIGHBOURS + 1, count)
    distance, neighbour = KDTree(points).query(points, k=k, distance_upper_bound=radius.max())
    neighbour = np.minimum(neighbour[:, 1:], count - 1)
    linked = distance[:, 1:] <= radius[:, None]
    rows = np.broadcast_to(np.arange(count)[:, None], neighbour.shape)[linked]
    columns = neighbour[linked]
    in_fragment = fragment[labels]
    # fragments linked to each other form one group
    groups = _grouped(labels, rows, columns, in_fragment[rows] & in_fragment[columns])
    # a group lies in the larger part it has the most links with
    towards = in_fragment[rows] & ~in_fragment[columns]
    groups = np.unique(groups, return_inverse=True)[1].astype(np.int64)
    host = np.arange(int(groups.max()) + 1)
    if not towards.any():
        return groups, host
    pairs, links = np.unique(
        np.stack([groups[rows[towards]], labels[columns[towards]]], axis=1),
        axis=0,
        return_counts=True,
    )
    order = np.lexsort((-links, pairs[:, 0]))
    first = np.ones(order.shape[0], dtype=bool)
    first[1:] = pairs[order[1:], 0] != pairs[order[:-1], 0]
    host[pairs[order[first], 0]] = _group_of(groups, labels, n_parts)[pairs[order[first], 1]]
    return groups, host


def _grouped(
    labels: NDArray[np.int64],
    rows: NDArray[np.int64],
    columns: NDArray[np.int64],
    joins: NDArray[np.bool_],
) -> NDArray[np.int64]:
    """Labels with the parts linked by the ``joins`` links (rows -> columns) merged; shape (c,)."""
    from scipy.sparse import coo_matrix  # on first use: API processes need no scipy
    from scipy.sparse.csgraph import connected_components

    n_parts = int(labels.max()) + 1
    first, second = labels[rows[joins]], labels[columns[joins]]
    graph = coo_matrix(
        (np.ones(first.shape[0], dtype=np.int8), (first, second)), (n_parts, n_parts)
    )
    _, merged = connected_components(graph, directed=True, connection="weak")
    return merged[labels].astype(np.int64)


def _group_of(groups: NDArray[np.int64], labels: NDArray[np.int64], n_parts: int) -> NDArray:
    """The group of each part of ``labels`` (shape (parts,))."""
    group_of_part = np.zeros(n_parts, dtype=np.int64)
    group_of_part[labels] = groups
    return group_of_part


def host_coverage(
    coverage: NDArray[np.bool_], confidence: NDArray[np.float64], host: NDArray[np.int64]
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Per part (shapes (parts,)), whether it is a coverage difference and the confidence,
    with each part whose ``host`` is one made one too, at its host's confidence; a host's
    change verdict is never passed on."""
    hosted = ~coverage & coverage[host]
    return coverage | hosted, np.where(hosted, confidence[host], confidence)
