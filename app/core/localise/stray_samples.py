"""Stray samples of a fused map: flying pixels and lone returns, no surface of their own.

A depth camera's pixel on a depth edge mixes the foreground's and the background's depth and
lands in the air between them (a *flying pixel*); a fused handheld RGB-D map keeps many of them,
one per voxel, scattered behind every silhouette the camera passed (about 0.7 % of a thinned
map's points more than 10 cm from every surface).  Each lies farther than the change threshold
from the other epoch's surfaces, so each is a change candidate, and the scattered candidates of
one silhouette link into "added" and "removed" regions of 30-90 points spread over 0.5-2.5 m:
an unchanged RGB-D room with drift and flying pixels got 10 regions where it had 4.

A sample on a surface has its cloud's other samples of that surface around it, about one local
spacing apart; a flying pixel has none: its nearest own point is several spacings away.  So a
candidate with at most :data:`STRAY_NEIGHBOURS` other points of its own cloud within
:data:`STRAY_RADIUS_FACTOR` of the cloud's median spacing is a *stray sample*: it is not a
surface, says nothing of a change, and is labelled unchanged without a visibility test.  Only for
moving-sensor maps (the other cloud has no stations, or a trajectory): a station scan's sparse
far returns are its resolution limit, judged by its ray test.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.core.localise.distance import Side
from app.core.localise.rays import Candidates

__all__ = ["STRAY_NEIGHBOURS", "STRAY_RADIUS_FACTOR", "stray_rows", "stray_samples"]

STRAY_RADIUS_FACTOR = 4.0
"""The radius a sample's neighbours are counted in, in the cloud's median spacings."""
STRAY_NEIGHBOURS = 1
"""A candidate with at most this many other own points within the radius is a stray sample."""


def stray_samples(own: Side, candidates: Candidates) -> NDArray[np.bool_]:
    """Which of ``own``'s candidates are stray samples, shape (c,).

    Parameters
    ----------
    own : Side
        The candidates' cloud (its KD-tree and spacing).
    candidates : Candidates

    Returns
    -------
    ndarray, shape (c,), bool
        At most :data:`STRAY_NEIGHBOURS` other points of ``own`` lie within
        :data:`STRAY_RADIUS_FACTOR` times the median of ``own``'s spacing.
    """
    if candidates.index.size == 0:
        return np.zeros(0, dtype=bool)
    radius = STRAY_RADIUS_FACTOR * float(np.median(own.geometry.spacing))
    wanted = min(STRAY_NEIGHBOURS + 2, own.points.shape[0])
    distance, _ = own.geometry.tree.query(
        np.ascontiguousarray(candidates.points), k=wanted, distance_upper_bound=radius
    )
    distance = np.asarray(distance).reshape(len(candidates.index), wanted)
    return ~np.isfinite(distance[:, -1])


def stray_rows(own: Side, other: Side, candidates: Candidates) -> NDArray[np.int64]:
    """Rows of ``own`` (s,) of its stray candidates when ``other`` is a moving sensor's map
    (no stations, or a trajectory); none otherwise."""
    if other.origins is not None and other.trajectory_rays is None:
        return np.zeros(0, dtype=np.int64)
    return candidates.index[stray_samples(own, candidates)]
