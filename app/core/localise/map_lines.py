"""Single scan lines of the map test: a line of samples between the other epoch's lines.

A sparse map (a robot's 16-ring lidar) sees a ceiling or a floor far from its path in single
ring arcs, each sweep's arcs one ring spacing apart, and that spacing grows with the range
(a metre and more on a corridor's ceiling).  Each epoch's arcs fall where its own path put
them: an arc of one epoch lies metres from the other epoch's, farther than the change
distance and than the 0.5 m of :func:`~app.core.localise.map_planes.in_sampling_gap`, yet on
the plane the other epoch samples on both sides of it.  A line has no normal of its own to
continue along (its neighbours fit any plane through it), so the plane is taken through the
line, tried level, with the part's own normals and with the other cloud's normal nearby.

The reach follows the sampling there, not a sensor's ring pattern: the other epoch's lines
must lie on both sides of the line within :data:`LINE_SPACINGS` of this epoch's own line
spacing (the distance to this epoch's own samples of the plane, across the line, on the
farther side).  A face of a removed or added object lies on no plane of the other epoch, or
at its edge (the other epoch's surface on one side only).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE, PLANE_SLOPE
from app.core.localise.surface import LocalGeometry

__all__ = ["LINE_RATIO", "LINE_SPACINGS", "line_gap_share"]

LINE_RATIO = 0.25
"""A part is a line when its spread across (the second principal axis) is below this share
of its spread along (the first)."""
LINE_MIN_POINTS = 8
LINE_SAMPLE = 16
"""Points probed per line part, spread along it."""
LINE_SPACINGS = 3.0
"""The other epoch's lines must lie within this many of this epoch's own line spacings."""
REACHES = 0.25 * math.sqrt(2.0) ** np.arange(9)
"""Probe distances across the line (metres), 0.25 to 4."""
CONE_COSINE = math.cos(math.radians(35.0))
PROBE_NEIGHBOURS = 4


def _line_axes(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], bool]:
    """The principal axes of a part's points (columns: along, across, third) and whether it
    is a line (:data:`LINE_RATIO`); shape (n, 3) -> (3, 3), bool."""
    centred = points - points.mean(axis=0)
    values, vectors = np.linalg.eigh(centred.T @ centred / max(points.shape[0], 1))
    values, vectors = values[::-1], vectors[:, ::-1]
    is_line = values[1] <= LINE_RATIO**2 * max(values[0], 1e-12)
    return vectors, bool(is_line)


def _first_hit(
    points: NDArray[np.float64],
    unit: NDArray[np.float64],
    across: NDArray[np.float64],
    cloud: LocalGeometry,
    tolerance: float,
) -> NDArray[np.float64]:
    """Per point, the first of :data:`REACHES` at which ``cloud`` has surface on the plane
    (normal ``unit``) in the direction ``across`` (inf if none); shapes (p, 3) -> (p,)."""
    first = np.full(points.shape[0], np.inf)
    k = min(PROBE_NEIGHBOURS, cloud.points.shape[0])
    for reach in REACHES:
        todo = np.flatnonzero(np.isinf(first))
        if todo.shape[0] == 0 or k == 0:
            break
        _, index = cloud.tree.query(points[todo] + reach * across[todo], k=k)
        index = np.asarray(index).reshape(todo.shape[0], k)
        offset = cloud.points[index] - points[todo][:, None, :]
        distance = np.linalg.norm(offset, axis=2)
        along = np.einsum("pkd,pd->pk", offset, across[todo])
        off_plane = np.abs(np.einsum("pkd,pd->pk", offset, unit[todo]))
        agrees = np.abs(np.einsum("pkd,pd->pk", cloud.normal[index], unit[todo]))
        hit = (
            (distance <= 2.0 * reach)
            & (along >= CONE_COSINE * distance)
            & (along >= 0.5 * reach)
            & (off_plane <= tolerance + PLANE_SLOPE * distance)
            & (agrees >= NORMAL_AGREEMENT_COSINE)
        ).any(axis=1)
        first[todo[hit]] = reach
    return first


def _between(
    points: NDArray[np.float64],
    unit: NDArray[np.float64],
    along: NDArray[np.float64],
    own: LocalGeometry,
    other: LocalGeometry,
    tolerance: float,
) -> NDArray[np.bool_]:
    """Whether each point of a line (direction ``along``) has the other epoch's surface on the
    plane of normal ``unit`` on both sides within :data:`LINE_SPACINGS` of this epoch's own
    line spacing there; shapes (p, 3), (p, 3), (3,) -> (p,)."""
    unit = unit - np.outer(unit @ along, along)
    norm = np.linalg.norm(unit, axis=1)
    usable = norm > 0.5
    unit = unit / np.maximum(norm, 1e-12)[:, None]
    across = np.cross(unit, along)
    own_gap = np.zeros(points.shape[0])
    other_gap = np.zeros(points.shape[0])
    for side in (1.0, -1.0):
        own_gap = np.maximum(own_gap, _first_hit(points, unit, side * across, own, tolerance))
        other_gap = np.maximum(other_gap, _first_hit(points, unit, side * across, other, tolerance))
    own_gap = np.minimum(own_gap, REACHES[-1])
    return usable & (other_gap <= np.maximum(LINE_SPACINGS * own_gap, REACHES[0]))


def line_gap_share(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    labels: NDArray[np.int64],
    recheck: NDArray[np.bool_],
    *,
    own: LocalGeometry,
    other: LocalGeometry,
    tolerance: float,
) -> NDArray[np.float64]:
    """Per part marked in ``recheck`` that is a line (0 elsewhere), the share of its (up to
    :data:`LINE_SAMPLE`) probed points lying between the other epoch's samples of a plane
    through the line.

    Parameters
    ----------
    points, normal : ndarray, shape (c, 3)
        The candidates and their normals.
    labels : ndarray, shape (c,), int64
        Their surface parts.
    recheck : ndarray, shape (parts,), bool
    own, other : LocalGeometry
        This epoch's and the other epoch's clouds.
    tolerance : float
        ``tau``, the plane tolerance (metres).

    Returns
    -------
    ndarray, shape (parts,), float64
    """
    share = np.zeros(recheck.shape[0])
    level = np.array([0.0, 0.0, 1.0])
    for part in np.flatnonzero(recheck):
        members = np.flatnonzero(labels == part)
        if members.shape[0] < LINE_MIN_POINTS:
            continue
        axes, is_line = _line_axes(points[members])
        if not is_line:
            continue
        along = axes[:, 0]
        chosen = members[np.argsort(points[members] @ along)]
        chosen = chosen[np.linspace(0, chosen.shape[0] - 1, LINE_SAMPLE).round().astype(int)]
        chosen = np.unique(chosen)
        probe = points[chosen]
        _, nearest = other.tree.query(probe, k=1)
        found = np.zeros(chosen.shape[0], dtype=bool)
        own_normal = normal[members].astype(np.float64)
        main_normal = np.linalg.eigh(own_normal.T @ own_normal)[1][:, -1]
        for guess in (
            np.broadcast_to(level, probe.shape),
            np.broadcast_to(main_normal, probe.shape),
            np.broadcast_to(axes[:, 2], probe.shape),
            other.normal[np.asarray(nearest).ravel()].astype(np.float64),
        ):
            found |= _between(probe, np.array(guess), along, own, other, tolerance)
        share[part] = found.mean()
    return share
