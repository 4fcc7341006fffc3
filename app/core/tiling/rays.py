"""Which of the other sensor's returns a tile's crop keeps for the ray visibility test.

The ray test (:mod:`app.core.localise.rays`) judges a candidate by the other cloud's returns
whose direction from their station lies within a few angular steps of the candidate's: in
front of it (they may hide it) or behind it (they saw through its place).  A crop must hold
those returns for every point of its box, wherever they landed.

Two filters, both conservative:

- **In the top view** (:func:`crop_mask`): the returns whose ray from their station crosses the
  crop box, within ``ray_reach`` metres of it.  Alone, this keeps every return of a station
  standing in or near the box (all its rays cross it): about three quarters of a
  terrestrial station's points lie within ten metres of it (the floor and the ceiling round
  it), which is why a station's box did not fit a crop at 20M points a scan.
- **By direction** (:func:`direction_marks`, :func:`crop_masks`): of those, only the returns
  whose direction from their station falls in a cell (of a grid on the unit vectors, cells
  of :func:`ray_cell_sizes` chord) next to the direction of a point of the other cloud in
  the box.  A cell is at least ``RAY_CELL_FACTOR`` times the test's angular reach
  (``visibility_angle_factor`` times the station's angular step, which a station's count of
  returns bounds from above: ``sqrt(4 pi / n)``), so every return the test can read for a
  point of the box lies in a marked cell or a neighbouring one.  Near a station the box's
  floor and ceiling are seen steeply, and the rays in those directions end in the box: the
  crop keeps the box, not the station.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "MAX_DIRECTION_STATIONS",
    "RAY_CELL_FACTOR",
    "cells_of_counts",
    "cells_seen",
    "crop_mask",
    "crop_masks",
    "direction_cells",
    "direction_marks",
    "expanded_marks",
    "kept_by_direction",
    "origin_direction_cells",
    "own_direction_cells",
    "ray_cell_sizes",
]

MASK_CHUNK = 1 << 20
"""Points per step of the crop masks."""
RAY_CELL_FACTOR = 2.0
"""A direction cell's chord over the ray test's angular reach (``visibility_angle_factor``
steps): the test measures the step on the crop's returns, so the reach it reads may exceed
the bound from the station's count; twice that bound covers it."""
MAX_DIRECTION_STATIONS = 127
"""Clouds with more origins (a trajectory's pseudo-stations) keep the top-view filter only."""
MIN_CELL_CHORD = 1e-4
"""The finest cell (about 0.006 degrees): keeps cell numbers within int64."""


def ray_cell_sizes(
    station: NDArray[np.integer] | None,
    n_points: int,
    origins: NDArray[np.float64] | None,
    angle_factor: float,
) -> NDArray[np.float64] | None:
    """The direction cell (chord of unit vectors) of each origin's returns.

    Parameters
    ----------
    station : ndarray, shape (n,), int, or None
        Each point's origin (None: all the first one).
    n_points : int
        Points of the cloud.
    origins : ndarray, shape (k, 3), or None
    angle_factor : float
        The ray test's ``visibility_angle_factor``.

    Returns
    -------
    ndarray, shape (k,), float64, or None
        ``RAY_CELL_FACTOR * angle_factor * sqrt(4 pi / returns)`` for each origin (an origin
        with no return gets the coarsest cell, 2); None: no origins, or more than
        :data:`MAX_DIRECTION_STATIONS` (the direction filter is off for the cloud).
    """
    if origins is None or not 0 < len(origins) <= MAX_DIRECTION_STATIONS:
        return None
    if station is None:
        counts = np.zeros(len(origins), dtype=np.int64)
        counts[0] = n_points
    else:
        counts = np.zeros(len(origins), dtype=np.int64)
        for start in range(0, len(station), MASK_CHUNK):
            chunk = np.asarray(station[start : start + MASK_CHUNK], dtype=np.int64)
            counts += np.bincount(chunk, minlength=len(origins))[: len(origins)]
    return cells_of_counts(counts.astype(np.float64), angle_factor)


def cells_of_counts(counts: NDArray[np.float64], angle_factor: float) -> NDArray[np.float64]:
    """The direction cell (chord) of origins with ``counts`` returns each, shape (k,).

    ``RAY_CELL_FACTOR * angle_factor * sqrt(4 pi / count)`` (an origin with no return gets the
    coarsest cell, 2); the counts may be estimates (a subsample's, scaled up: a streamed
    parent's, :mod:`app.core.tiling.streamed`).
    """
    with np.errstate(divide="ignore"):
        step = np.sqrt(4.0 * math.pi / np.asarray(counts, dtype=np.float64))
    cells = np.minimum(RAY_CELL_FACTOR * angle_factor * step, 2.0)
    return np.maximum(cells, MIN_CELL_CHORD)


def _cell_numbers(directions: NDArray[np.float64], cell: float) -> NDArray[np.int64]:
    """The cell of each unit vector (shape (p, 3)) on a grid of ``cell`` over [-1, 1]^3, padded
    by one cell on each side so that the neighbours of any cell are numbered too."""
    side = int(2.0 / cell) + 3
    index = np.floor((directions + 1.0) / cell).astype(np.int64) + 1
    return (index[:, 0] * side + index[:, 1]) * side + index[:, 2]


def _neighbour_offsets(cell: float) -> NDArray[np.int64]:
    side = int(2.0 / cell) + 3
    step = np.arange(-1, 2, dtype=np.int64)
    return (step[:, None, None] * side * side + step[None, :, None] * side + step).ravel()


def direction_marks(
    points: NDArray[np.floating],
    in_box: NDArray[np.bool_],
    origins: NDArray[np.float64],
    cells: NDArray[np.float64],
) -> list[NDArray[np.int64]]:
    """For each origin, the direction cells next to those of ``points[in_box]`` seen from it.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        The other cloud (whose points in the box are the candidates the rays are for).
    in_box : ndarray, shape (n,), bool
    origins : ndarray, shape (k, 3)
        The stations whose returns are filtered.
    cells : ndarray, shape (k,)
        Their cells (:func:`ray_cell_sizes`).

    Returns
    -------
    list of ndarray, int64
        Per origin, the sorted numbers of the marked cells and their 26 neighbours.
    """
    box_index = np.flatnonzero(in_box)
    found: list[list[NDArray[np.int64]]] = [[] for _ in origins]
    for start in range(0, len(box_index), MASK_CHUNK):
        chunk = points[box_index[start : start + MASK_CHUNK]]
        for number, cells_seen in enumerate(direction_cells(chunk, origins, cells)):
            found[number].append(cells_seen)
    return expanded_marks(found, cells)


def direction_cells(
    points: NDArray[np.floating], origins: NDArray[np.float64], cells: NDArray[np.float64]
) -> list[NDArray[np.int64]]:
    """For each origin, the sorted direction cells of ``points`` (shape (p, 3)) seen from it:
    the cells of a box's points, a chunk at a time (:func:`expanded_marks` joins them)."""
    return [cells_seen(row) for row in origin_direction_cells(points, origins, cells)]


def origin_direction_cells(
    points: NDArray[np.floating], origins: NDArray[np.float64], cells: NDArray[np.float64]
) -> NDArray[np.int64]:
    """The direction cell of every point seen from every origin.

    Parameters
    ----------
    points : ndarray, shape (p, 3)
    origins : ndarray, shape (k, 3)
    cells : ndarray, shape (k,)
        The origins' cells (:func:`ray_cell_sizes`).

    Returns
    -------
    ndarray, shape (k, p), int64
        Cell numbers, ``-1`` for a point at the origin (it has no direction).
    """
    numbers = np.empty((len(origins), len(points)), dtype=np.int64)
    for number, (origin, cell) in enumerate(zip(origins, cells, strict=True)):
        numbers[number] = _direction_cells_from(points, origin, float(cell))
    return numbers


def own_direction_cells(
    points: NDArray[np.floating],
    station: NDArray[np.integer] | None,
    origins: NDArray[np.float64],
    cells: NDArray[np.float64],
) -> NDArray[np.int64]:
    """The direction cell of each point (shape (p, 3)) seen from its own origin
    (``origins[station]``; None: the first), ``-1`` for a point at its origin; shape (p,)."""
    numbers = np.empty(len(points), dtype=np.int64)
    if station is None:
        numbers[:] = _direction_cells_from(points, origins[0], float(cells[0]))
        return numbers
    for number in np.unique(station):
        rows = np.flatnonzero(station == number)
        numbers[rows] = _direction_cells_from(points[rows], origins[number], float(cells[number]))
    return numbers


def cells_seen(numbers: NDArray[np.int64]) -> NDArray[np.int64]:
    """The sorted distinct cells of :func:`origin_direction_cells`' numbers (no ``-1``)."""
    distinct = np.unique(numbers)
    return distinct[distinct >= 0]


def _direction_cells_from(
    points: NDArray[np.floating], origin: NDArray[np.float64], cell: float
) -> NDArray[np.int64]:
    """Each point's direction cell from ``origin``, ``-1`` at the origin (:func:`_cell_numbers`)."""
    offset = np.asarray(points, dtype=np.float64) - origin
    length = np.sqrt(np.einsum("pd,pd->p", offset, offset))
    with np.errstate(divide="ignore", invalid="ignore"):
        directions = offset / length[:, None]
    directions[length == 0] = 0.0  # numbered, then dropped: no NaN reaches the cast
    return np.where(length > 0, _cell_numbers(directions, cell), -1)


def expanded_marks(
    found: Sequence[Sequence[NDArray[np.int64]]], cells: NDArray[np.float64]
) -> list[NDArray[np.int64]]:
    """Per origin, the union of the cells ``found`` (:func:`direction_cells` of the chunks of a
    box's points) and their 26 neighbours, sorted: :func:`direction_marks`' answer."""
    marks = []
    for parts, cell in zip(found, cells, strict=True):
        own = np.unique(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.int64)
        marks.append(np.unique((own[:, None] + _neighbour_offsets(float(cell))).ravel()))
    return marks


def _marked(
    points: NDArray[np.float64] | None,
    station: NDArray[np.integer] | None,
    origins: NDArray[np.float64],
    cells: NDArray[np.float64],
    marks: Sequence[NDArray[np.int64]],
    point_cells: NDArray[np.int64] | None = None,
) -> NDArray[np.bool_]:
    """Which of ``points`` (shape (p, 3)) lie in a marked cell of their origin
    (``point_cells``: their :func:`own_direction_cells`, when already known; ``points`` is
    then not read and may be None)."""
    if point_cells is None:
        if points is None:
            raise ValueError("_marked needs the points or their direction cells")
        point_cells = own_direction_cells(points, station, origins, cells)
    keep = np.zeros(len(point_cells), dtype=bool)
    which = np.zeros(len(point_cells), dtype=np.int64) if station is None else station
    for number in np.unique(which):
        mark = marks[number]
        if not len(mark):  # no point of the other cloud in the box seen from this origin
            continue
        rows = np.flatnonzero(which == number)
        cell_number = point_cells[rows]
        position = np.minimum(np.searchsorted(mark, cell_number), len(mark) - 1)
        keep[rows] = mark[position] == cell_number  # never -1: marks are cells' numbers
    return keep


def kept_by_direction(
    points: NDArray[np.floating],
    station: NDArray[np.integer] | None,
    origins: NDArray[np.float64],
    low: NDArray[np.float64],
    high: NDArray[np.float64],
    cells: NDArray[np.float64],
    marks: Sequence[NDArray[np.int64]],
) -> NDArray[np.bool_]:
    """Which points of a crop kept in the top view only (:func:`crop_mask` without marks)
    :func:`crop_mask` with ``cells`` and ``marks`` keeps too: those in the xy box ``[low,
    high]``, and the others (returns whose ray crossed it) whose direction is marked.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    station : ndarray, shape (n,), int, or None
        Each point's index into ``origins`` (None: the first origin).
    origins : ndarray, shape (k, 3)
    low, high : ndarray, shape (2,)
    cells : ndarray, shape (k,)
    marks : list of ndarray
        Each origin's marked cells (:func:`direction_marks`).

    Returns
    -------
    ndarray, shape (n,), bool
    """
    keep = box_mask(points, low, high)
    rows = np.flatnonzero(~keep)
    if len(rows):
        keep[rows] = _marked(
            np.asarray(points[rows], dtype=np.float64),
            None if station is None else np.asarray(station[rows], dtype=np.int64),
            origins,
            cells,
            marks,
        )
    return keep


def _float32_bounds(
    low: NDArray[np.float64], high: NDArray[np.float64], grow: float = 0.0
) -> tuple[float, float, float, float]:
    """The box ``[low - grow, high + grow]`` as float32 values rounded outward (x0, y0, x1,
    y1): a cloud's float32 coordinates compare with them without a float64 copy."""
    lower = np.nextafter(np.asarray(low - grow, dtype=np.float32), np.float32(-np.inf))
    upper = np.nextafter(np.asarray(high + grow, dtype=np.float32), np.float32(np.inf))
    return float(lower[0]), float(lower[1]), float(upper[0]), float(upper[1])


def _in_box(
    points: NDArray[np.floating], chunk: slice, bounds: tuple[float, float, float, float]
) -> NDArray[np.bool_]:
    """Which points of ``points[chunk]`` lie in the xy box ``bounds`` (:func:`_float32_bounds`)."""
    x, y = points[chunk, 0], points[chunk, 1]
    return (x >= bounds[0]) & (x <= bounds[2]) & (y >= bounds[1]) & (y <= bounds[3])


def box_mask(
    points: NDArray[np.floating], low: NDArray[np.float64], high: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """Points (shape (n, 3)) in the xy box ``[low, high]`` (float32 points: within its
    rounding)."""
    bounds = _float32_bounds(low, high)
    mask = np.empty(len(points), dtype=bool)
    for start in range(0, len(points), MASK_CHUNK):
        chunk = slice(start, start + MASK_CHUNK)
        mask[chunk] = _in_box(points, chunk, bounds)
    return mask


FAR = 1e9
"""An outer tile's infinite side, for the wedges (:func:`_wedges`)."""
WEDGE_SLACK = 1e-3
"""Metres the box is grown by for the wedges (rays along its sides count as crossing it)."""


def _wedges(
    origins: NDArray[np.float64], low: NDArray[np.float64], high: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """The xy directions from each origin bounding the box: a half-line from an origin outside
    the box meets it when its direction lies between the two (counter-clockwise).

    Returns
    -------
    first, second : ndarray, shape (k, 2)
        The clockwise-most and the counter-clockwise-most corner, relative to each origin.
    inside : ndarray, shape (k,), bool
        The origin is in the box: every half-line from it meets the box.
    """
    low = np.clip(low - WEDGE_SLACK, -FAR, FAR)
    high = np.clip(high + WEDGE_SLACK, -FAR, FAR)
    sensor = origins[:, :2]
    inside = np.all((sensor >= low) & (sensor <= high), axis=1)
    corners = np.array([[low[0], low[1]], [high[0], low[1]], [high[0], high[1]], [low[0], high[1]]])
    toward = corners[None, :, :] - sensor[:, None, :]  # (k, 4, 2)
    centre = toward.mean(axis=1)  # inside the box's angular span from an origin outside it
    angle = np.arctan2(
        centre[:, None, 0] * toward[..., 1] - centre[:, None, 1] * toward[..., 0],
        np.einsum("kd,kcd->kc", centre, toward),
    )
    rows = np.arange(len(sensor))
    return toward[rows, angle.argmin(axis=1)], toward[rows, angle.argmax(axis=1)], inside


def _crosses(
    xy: NDArray[np.float64],
    which: NDArray[np.int64],
    sensor: NDArray[np.float64],
    wedges: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]],
) -> NDArray[np.bool_]:
    """Whether the half-line from each point's sensor (``sensor[which]``) through it meets the
    box of ``wedges`` (:func:`_wedges`).

    ``cross(first, xy - sensor) >= 0`` is written ``cross(first, xy) >= cross(first, sensor)``
    so that only per-sensor scalars are gathered per point.
    """
    first, second, inside = wedges
    x, y = xy[:, 0], xy[:, 1]
    first_offset = first[:, 0] * sensor[:, 1] - first[:, 1] * sensor[:, 0]
    second_offset = second[:, 0] * sensor[:, 1] - second[:, 1] * sensor[:, 0]
    after_first = first[which, 0] * y - first[which, 1] * x >= first_offset[which]
    before_second = second[which, 0] * y - second[which, 1] * x <= second_offset[which]
    return inside[which] | (after_first & before_second)


def crop_mask(
    points: NDArray[np.floating],
    station: NDArray[np.integer] | None,
    origins: NDArray[np.float64] | None,
    low: NDArray[np.float64],
    high: NDArray[np.float64],
    ray_reach: float = np.inf,
    *,
    cells: NDArray[np.float64] | None = None,
    marks: Sequence[NDArray[np.int64]] | None = None,
    point_cells: NDArray[np.int64] | None = None,
) -> NDArray[np.bool_]:
    """Points in the xy box ``[low, high]``, or whose ray from their sensor crosses it and
    that lie within ``ray_reach`` metres of it (in x and y), and (with ``marks``) whose
    direction from their sensor is marked.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    station : ndarray, shape (n,), int, or None
        Index into ``origins`` of each point's sensor (None: the first origin).
    origins : ndarray, shape (k, 3), or None
        Without origins only the box counts.
    low, high : ndarray, shape (2,)
    ray_reach : float
        How far beyond the box a return whose ray crossed it is still kept.
    cells : ndarray, shape (k,), optional
        Each origin's direction cell (:func:`ray_cell_sizes`); with ``marks``.
    marks : list of ndarray, optional
        Each origin's marked cells (:func:`direction_marks`); None: the top view only.
    point_cells : ndarray, shape (n,), int64, optional
        The points' :func:`own_direction_cells` when already known (computed here otherwise).

    Returns
    -------
    ndarray, shape (n,), bool
    """
    box, reach = _float32_bounds(low, high), _float32_bounds(low, high, ray_reach)
    rays = origins is not None and len(origins) > 0
    wedges = _wedges(origins, low, high) if rays else None
    mask = np.empty(len(points), dtype=bool)
    for start in range(0, len(points), MASK_CHUNK):
        chunk = slice(start, start + MASK_CHUNK)
        inside = _in_box(points, chunk, box)
        if rays and wedges is not None:
            rows = np.flatnonzero(_in_box(points, chunk, reach) & ~inside)
            which = (
                np.zeros(len(rows), dtype=np.int64)
                if station is None
                else np.asarray(station[chunk], dtype=np.int64)[rows]
            )
            xy = np.asarray(points[chunk][rows, :2], dtype=np.float64)
            crossing = _crosses(xy, which, origins[:, :2], wedges)
            rows, which = rows[crossing], which[crossing]
            if marks is not None and cells is not None and len(rows):
                seen = _marked(
                    None  # the cells answer it: no float64 copy of the crossing rows
                    if point_cells is not None
                    else np.asarray(points[chunk][rows], dtype=np.float64),
                    None if station is None else which,
                    origins,
                    cells,
                    marks,
                    None if point_cells is None else point_cells[chunk][rows],
                )
                rows = rows[seen]
            inside[rows] = True
        mask[chunk] = inside
    return mask


def crop_masks(
    sides: Sequence[
        tuple[NDArray[np.floating], NDArray[np.integer] | None, NDArray[np.float64] | None]
    ],
    cells: Sequence[NDArray[np.float64] | None],
    low: NDArray[np.float64],
    high: NDArray[np.float64],
    ray_reach: float,
) -> list[NDArray[np.bool_]]:
    """Both clouds' crop masks of the xy box ``[low, high]``: the box, and each cloud's returns
    whose rays the other cloud's points in the box need (both filters of this module).

    Parameters
    ----------
    sides : two (points, station, origins)
        The reference and the scan: points shape (n, 3), each point's origin (or None),
        origins shape (k, 3) (or None: no rays).
    cells : two ndarray or None
        Each cloud's direction cells (:func:`ray_cell_sizes`); None: the top view only.
    low, high : ndarray, shape (2,)
    ray_reach : float

    Returns
    -------
    list of two ndarray, bool
    """
    boxes = [box_mask(points, low, high) for points, _, _ in sides]
    masks = []
    for side, (points, station, origins) in enumerate(sides):
        own_cells = cells[side]
        marks = None
        if origins is not None and own_cells is not None:
            other_points = sides[1 - side][0]
            marks = direction_marks(other_points, boxes[1 - side], origins, own_cells)
        masks.append(
            crop_mask(points, station, origins, low, high, ray_reach, cells=own_cells, marks=marks)
        )
    return masks
