"""Faces hanging under the other epoch's top edge: a closed body's sides it never saw.

A box a robot passed on one side only has, in that epoch's map, its top and the one or two
sides the path faced; the other sides are not sampled.  The truth is the world: a point of
the other epoch within the change distance of such an unseen side is no change.  Robot
warehouse 1104 (a box turned a quarter in place): the new box's long face stands 2-9 cm past
the old box's faces the reference never saw, and the new top's east end 7 cm past the old
one's; with nothing of the reference there, they were changed.

:func:`hanging_face_points` takes a changed point that lies under (or level with) the other
epoch's top and outside the footprint of the body under it, within ``c`` of it horizontally.
Of the other cloud's samples within :data:`REACH_FACTOR` ``c`` (horizontally) of the point,
the top is the lowest level surface at most :data:`TOP_REACH` over it (its level samples
within ``tau`` of that height, :data:`MIN_TOP_SAMPLES` at least), and the body its samples
with the upright ones between the point's height (less ``c``) and the top: a half-plane round
the point holds none of them (the point is outside), and the convex hull of their horizontal
positions is within ``c`` of it.  The sides the other epoch never saw stand at or beyond that
hull, so the point is within ``c`` of one, if the top is a closed body's: within
:data:`OPEN_REACH` of the point, fewer than :data:`MIN_TOP_SAMPLES` of the other cloud's level
samples between :data:`TOP_REACH` and ``c`` under the top lie inside the hull of its samples
there (by ``tau``).  A box's top hides its inside and the floor under it; an open table's or
desk's top has the floor seen under it, and a point by its edge may be far from every surface
of it (it stays a change).  Such a point is unobserved (the other epoch never saw that side:
``no_coverage``).  Only for the clouds the map test or the trajectory test judged.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from app.core.labels import LABEL_CHANGED, LABEL_UNOBSERVED
from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE
from app.core.localise.map_planes import widest_empty_angle
from app.core.localise.regions import EVIDENCE_NO_COVERAGE
from app.core.localise.turned_faces import MOVING_SENSOR_TESTS
from app.core.localise.visibility import Labelled

__all__ = ["hanging_face_points", "judges_hanging_faces", "with_hanging_faces"]

REACH_FACTOR = 2.0
"""The other cloud's level samples within this many change thresholds (horizontally) of a
changed point are its top's."""
TOP_REACH = 1.2
"""A top stands at most this far over the point (metres); the probes for a level surface
under the top reach as far (``map_parts.SEE_THROUGH_REACH``)."""
MIN_TOP_SAMPLES = 3
"""Fewer level samples are no top (and fewer under a top are no level surface there)."""
OPEN_REACH = 0.5
"""A top is looked under within this many metres (horizontally) of the point."""
MAX_LOWER_SAMPLES = 4096
"""The level samples under a top tried for being inside it, at most (evenly thinned)."""


def judges_hanging_faces(test: str) -> bool:
    """Whether the visibility test named ``test`` judges a moving sensor's map (the map test
    or the trajectory test): the clouds whose unseen sides this module infers."""
    return test in MOVING_SENSOR_TESTS


def _hull_distance(point: NDArray[np.float64], body: NDArray[np.float64]) -> float:
    """Horizontal distance (metres) from ``point`` (shape (2,)) to the convex hull of ``body``
    (shape (b, 2)), the point outside it; the nearest sample's when the hull is flat."""
    from scipy.spatial import ConvexHull, QhullError  # scipy loads with its first use

    try:
        corners = body[ConvexHull(body).vertices]
    except QhullError:
        return float(np.hypot(*(body - point).T).min())
    start, edge = corners, np.roll(corners, -1, axis=0) - corners
    along = np.einsum("ed,ed->e", point - start, edge) / np.maximum(
        np.einsum("ed,ed->e", edge, edge), 1e-12
    )
    foot = start + np.clip(along, 0.0, 1.0)[:, None] * edge
    return float(np.hypot(*(foot - point).T).min())


def _inside(
    corners: NDArray[np.float64], points: NDArray[np.float64], margin: float
) -> NDArray[np.bool_]:
    """Which ``points`` (shape (p, 2)) lie inside the convex hull of ``corners`` (shape (t, 2))
    by more than ``margin`` (metres); none when the hull is flat."""
    from scipy.spatial import ConvexHull, QhullError  # scipy loads with its first use

    if points.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    try:
        equations = ConvexHull(corners).equations
    except QhullError:
        return np.zeros(points.shape[0], dtype=bool)
    return np.all(points @ equations[:, :2].T + equations[:, 2] < -margin, axis=1)


def _outside_body(
    point: NDArray[np.float64],
    other: Side,
    members: NDArray[np.int64],
    level: NDArray[np.bool_],
    tolerances: tuple[float, float],
) -> float | None:
    """The height of ``other``'s top over ``point`` (shape (3,)) when the point lies outside
    the footprint of the body under it, within the change threshold horizontally; None
    otherwise.  ``members`` are ``other``'s points near it, ``tolerances`` ``(tau, c)``."""
    threshold, change_threshold = tolerances
    heights = other.points[members, 2]
    above = members[level[members] & (heights >= point[2] - threshold)]
    above = above[other.points[above, 2] <= point[2] + TOP_REACH]
    if above.shape[0] < MIN_TOP_SAMPLES:
        return None
    top_height = float(other.points[above, 2].min())
    top = above[other.points[above, 2] <= top_height + threshold]
    if top.shape[0] < MIN_TOP_SAMPLES or point[2] > top_height + threshold:
        return None
    sides = members[
        ~level[members]
        & (heights >= point[2] - change_threshold)
        & (heights <= top_height + threshold)
    ]
    body = other.points[np.concatenate([top, sides]), :2]
    offset = body - point[:2]
    angle = np.arctan2(offset[:, 1], offset[:, 0])[None, :]
    if widest_empty_angle(angle, np.ones_like(angle, dtype=bool))[0] < np.pi:
        return None
    if _hull_distance(point[:2], body) > change_threshold:
        return None
    return top_height


def _closed(
    level_points: NDArray[np.float64],
    members: NDArray[np.int64],
    top_height: float,
    tolerances: tuple[float, float],
) -> bool:
    """Whether the top at ``top_height`` among ``level_points[members]`` (the other cloud's
    level samples within :data:`OPEN_REACH` of the point) has no level surface under it:
    fewer than :data:`MIN_TOP_SAMPLES` lower level samples inside its hull (by ``tau``)."""
    threshold, change_threshold = tolerances
    heights = level_points[members, 2]
    top = members[np.abs(heights - top_height) <= threshold]
    lower = members[(heights < top_height - change_threshold) & (heights > top_height - TOP_REACH)]
    lower = lower[:: max(1, lower.shape[0] // MAX_LOWER_SAMPLES)]
    inside = _inside(level_points[top, :2], level_points[lower, :2], threshold)
    return int(np.count_nonzero(inside)) < MIN_TOP_SAMPLES


def _tops(
    own: Side, other: Side, changed: NDArray[np.int64], threshold: float, change_threshold: float
) -> list[int]:
    """Each ``changed`` point (indices into ``own``) outside the footprint of a closed body of
    ``other`` within ``change_threshold`` horizontally (module docstring)."""
    if changed.shape[0] == 0:
        return []
    from scipy.spatial import cKDTree  # scipy loads with its first use

    level = np.abs(other.geometry.normal[:, 2]) >= NORMAL_AGREEMENT_COSINE
    level_points = other.points[level]
    level_tree = cKDTree(level_points[:, :2])
    tree = cKDTree(other.points[:, :2])
    points = own.points[changed]
    near = tree.query_ball_point(points[:, :2], r=REACH_FACTOR * change_threshold)
    tolerances = (threshold, change_threshold)
    found: list[int] = []
    for point, index, members in zip(points, changed, near, strict=True):
        top_height = _outside_body(
            point, other, np.asarray(members, dtype=np.int64), level, tolerances
        )
        if top_height is None:
            continue
        around = np.asarray(level_tree.query_ball_point(point[:2], r=OPEN_REACH), dtype=np.int64)
        if _closed(level_points, around, top_height, tolerances):
            found.append(int(index))
    return found


def hanging_face_points(
    own: Side,
    other: Side,
    label: NDArray[np.int8],
    *,
    threshold: float,
    change_threshold: float,
) -> NDArray[np.int64]:
    """``own``'s changed points within ``change_threshold`` of a side of a closed body of
    ``other`` that hangs under its top's edge (module docstring).

    Parameters
    ----------
    own, other : Side
    label : ndarray, shape (n,), int8
        ``own``'s labels; its changed points are looked at.
    threshold, change_threshold : float
        ``tau`` and ``c`` (metres).

    Returns
    -------
    ndarray, shape (p,), int64
        Indices into ``own``'s points, ascending.
    """
    found = _tops(own, other, np.flatnonzero(label == LABEL_CHANGED), threshold, change_threshold)
    return np.asarray(sorted(found), dtype=np.int64)


def with_hanging_faces(
    sides: tuple[Side, Side],
    labelled: tuple[Labelled, Labelled],
    *,
    threshold: float,
    change_threshold: float,
) -> tuple[Labelled, Labelled]:
    """Both sides' labels with each moving-sensor side's changed points on the other epoch's
    unseen hanging faces (:func:`hanging_face_points`, from both sides' labels as given) made
    unobserved (``no_coverage``); ``threshold`` and ``change_threshold`` are ``tau`` and ``c``
    (metres)."""
    result = []
    for side, other, own in zip(sides, sides[::-1], labelled, strict=True):
        if not judges_hanging_faces(str(own.report.get(f"{side.name}_visibility", ""))):
            result.append(own)
            continue
        chosen = hanging_face_points(
            side, other, own.label, threshold=threshold, change_threshold=change_threshold
        )
        label, evidence, confidence = own.label.copy(), own.evidence.copy(), own.confidence.copy()
        label[chosen] = LABEL_UNOBSERVED
        evidence[chosen] = EVIDENCE_NO_COVERAGE
        confidence[chosen] = 0.5
        report = {**own.report, f"{side.name}_map_hanging_faces": int(chosen.shape[0])}
        result.append(
            dataclasses.replace(
                own, label=label, evidence=evidence, confidence=confidence, report=report
            )
        )
    return result[0], result[1]
