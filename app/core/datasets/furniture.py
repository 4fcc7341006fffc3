"""Furniture of the synthetic moving-sensor maps: objects made of boxes, placement, changes.

An object (:class:`MapObject`) is a few solid axis-aligned boxes with a name: a chair (four legs, a
seat, a back), a desk (four legs and a top), a box, a board (a thin vertical panel) or a rack.
:func:`place_object` puts one on the floor or on a desk, clear of the other objects and of the
sensors' paths; :func:`apply_change` draws the second epoch's objects (one removed, added, moved or
turned, or all four) and lists what changed (:class:`MapChange`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "MAP_CHANGES",
    "MOVABLE_KINDS",
    "MapChange",
    "MapObject",
    "Placement",
    "apply_change",
    "make_object",
    "place_object",
]

MAP_CHANGES = ("none", "removed", "added", "moved", "rotated", "mixed")
"""Values of ``change``: one object gone, new, moved, turned; ``"mixed"`` does the first four."""
MOVABLE_KINDS = ("chair", "box", "board")
"""Kinds of object that changes remove, add, move or turn (desks and racks stay)."""
MIN_MOVE = 0.5
"""A moved object's centre travels at least this far (metres)."""


@dataclass(frozen=True)
class MapObject:
    """A named piece of furniture made of solid axis-aligned boxes (world frame, metres).

    Attributes
    ----------
    name : str
    kind : {"chair", "box", "board", "desk", "rack"}
    low, high : ndarray, shape (k, 3)
        Corners of its boxes.
    """

    name: str
    kind: str
    low: NDArray[np.float64]
    high: NDArray[np.float64]

    @property
    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Corners ``(low, high)``, each shape (3,), of the box holding the whole object."""
        return self.low.min(axis=0), self.high.max(axis=0)

    def placed(self, corner: NDArray[np.float64], quarter_turns: int = 0) -> MapObject:
        """The object turned by ``quarter_turns`` x 90 degrees about z, its bounds' low corner
        moved to ``corner`` (shape (3,))."""
        low, high = self.low - self.bounds[0], self.high - self.bounds[0]
        for _ in range(quarter_turns % 4):  # (x, y) -> (-y, x), then shift back to x >= 0
            low, high = (
                np.column_stack([-high[:, 1], low[:, 0], low[:, 2]]),
                np.column_stack([-low[:, 1], high[:, 0], high[:, 2]]),
            )
            shift = np.array([low[:, 0].min(), 0.0, 0.0])
            low, high = low - shift, high - shift
        return MapObject(self.name, self.kind, low + corner, high + corner)


@dataclass(frozen=True)
class MapChange:
    """One change between the epochs: its kind, the object and where it was / is (world frame).

    Attributes
    ----------
    kind : {"removed", "added", "moved", "rotated"}
    name : str
        The object's name (the same in both epochs).
    reference_box, scan_box : tuple of two ndarrays, shape (3,), or None
        The object's bounds in the reference and the scan world (None where it is absent).
    """

    kind: str
    name: str
    reference_box: tuple[NDArray[np.float64], NDArray[np.float64]] | None
    scan_box: tuple[NDArray[np.float64], NDArray[np.float64]] | None


def make_object(name: str, kind: str, rng: np.random.Generator) -> MapObject:
    """A random piece of furniture of ``kind`` with its bounds' low corner at the origin.

    Chairs 0.4-0.5 m wide with a 0.42-0.48 m seat and a back up to 0.8-0.95 m; boxes 0.3-0.7 m;
    boards 0.6-1.2 m wide, 0.5-1.1 m tall, 2-3 cm thick; desks 1.2-1.8 x 0.6-0.8 m at 0.72-0.76
    m; racks 4-12 m long, 0.8-1.2 m deep, 2-4.5 m tall (solid).
    """
    if kind == "chair":
        width, seat, top = rng.uniform(0.4, 0.5), rng.uniform(0.42, 0.48), rng.uniform(0.8, 0.95)
        leg, board = 0.04, 0.04
        legs = [(0.0, 0.0), (width - leg, 0.0), (0.0, width - leg), (width - leg, width - leg)]
        low = [[x, y, 0.0] for x, y in legs] + [
            [0.0, 0.0, seat - board],
            [0.0, width - board, seat],
        ]
        high = [[x + leg, y + leg, seat - board] for x, y in legs]
        high += [[width, width, seat], [width, width, top]]
    elif kind == "box":
        size = rng.uniform(0.3, 0.7, 3)
        low, high = [[0.0, 0.0, 0.0]], [list(size)]
    elif kind == "board":
        low, high = [[0.0, 0.0, 0.0]], [[rng.uniform(0.6, 1.2), rng.uniform(0.02, 0.03), 0.0]]
        high[0][2] = rng.uniform(0.5, 1.1)
    elif kind == "desk":
        length, depth, height = (
            rng.uniform(1.2, 1.8),
            rng.uniform(0.6, 0.8),
            rng.uniform(0.72, 0.76),
        )
        leg = 0.05
        corners = [(0.0, 0.0), (length - leg, 0.0), (0.0, depth - leg), (length - leg, depth - leg)]
        low = [[x, y, 0.0] for x, y in corners] + [[0.0, 0.0, height - 0.03]]
        high = [[x + leg, y + leg, height - 0.03] for x, y in corners] + [[length, depth, height]]
    elif kind == "rack":
        size = [rng.uniform(4.0, 12.0), rng.uniform(0.8, 1.2), rng.uniform(2.0, 4.5)]
        low, high = [[0.0, 0.0, 0.0]], [size]
    else:
        raise ValueError(f"unknown object kind {kind!r}")
    return MapObject(name, kind, np.array(low, dtype=np.float64), np.array(high, dtype=np.float64))


@dataclass(frozen=True)
class Placement:
    """Where objects may go: the shell, and path samples they keep clear of.

    Attributes
    ----------
    shell_low, shell_high : ndarray, shape (3,)
    keep_out : ndarray, shape (q, 2)
        Horizontal positions of the sensors' paths (every 10-20 cm).
    clearance : float
        No object comes horizontally nearer than this (metres) to a ``keep_out`` position.
    desk_share : float
        Chance that a box or board goes on a desk (when there is one with room).
    """

    shell_low: NDArray[np.float64]
    shell_high: NDArray[np.float64]
    keep_out: NDArray[np.float64]
    clearance: float
    desk_share: float = 0.35


def _overlaps(candidate: MapObject, others: list[MapObject], margin: float) -> bool:
    low, high = candidate.bounds
    for other in others:
        other_low, other_high = other.bounds
        if (
            np.all(low[:2] < other_high[:2] + margin)
            and np.all(high[:2] > other_low[:2] - margin)
            and low[2] < other_high[2] - 1e-9
            and high[2] > other_low[2] + 1e-9
        ):
            return True
    return False


def _clear_of_paths(candidate: MapObject, placement: Placement) -> bool:
    if len(placement.keep_out) == 0:
        return True
    low, high = candidate.bounds
    gap = np.maximum(np.maximum(low[:2] - placement.keep_out, placement.keep_out - high[:2]), 0.0)
    return bool(np.linalg.norm(gap, axis=1).min() >= placement.clearance)


def fits(candidate: MapObject, others: list[MapObject], placement: Placement) -> bool:
    """Whether ``candidate`` lies in the shell, off ``others`` (10 cm apart) and off the paths."""
    low, high = candidate.bounds
    inside = np.all(low >= placement.shell_low - 1e-9) and np.all(
        high <= placement.shell_high + 1e-9
    )
    return (
        bool(inside)
        and not _overlaps(candidate, others, 0.1)
        and _clear_of_paths(candidate, placement)
    )


def place_object(
    template: MapObject,
    others: list[MapObject],
    placement: Placement,
    rng: np.random.Generator,
    attempts: int = 200,
    region: tuple[NDArray, NDArray] | None = None,
) -> MapObject | None:
    """``template`` turned and put at a random free place (on the floor, or a desk top), or None.

    ``region`` (low, high), shape (2,) each, limits where on the floor it may go.
    """
    desks = [other for other in others if other.kind == "desk"]
    floor_low = placement.shell_low[:2] if region is None else np.asarray(region[0])
    floor_high = placement.shell_high[:2] if region is None else np.asarray(region[1])
    for _ in range(attempts):
        turned = template.placed(np.zeros(3), int(rng.integers(4)))
        size = turned.bounds[1] - turned.bounds[0]
        low, high, height = floor_low, floor_high, placement.shell_low[2]
        if desks and template.kind in ("box", "board") and rng.uniform() < placement.desk_share:
            desk_low, desk_high = desks[int(rng.integers(len(desks)))].bounds
            low, high, height = desk_low[:2], desk_high[:2], desk_high[2]
        if np.any(high - low < size[:2]):
            continue
        corner = np.array([*rng.uniform(low, high - size[:2]), height])
        candidate = turned.placed(corner)
        if fits(candidate, others, placement):
            return candidate
    return None


def _centre(obj: MapObject) -> NDArray[np.float64]:
    low, high = obj.bounds
    return (low + high) / 2.0


def apply_change(
    change: str,
    objects: list[MapObject],
    placement: Placement,
    rng: np.random.Generator,
    new_object: Callable[[str], MapObject],
) -> tuple[list[MapObject], list[MapChange]]:
    """The scan epoch's objects after ``change``, and the changes made.

    Parameters
    ----------
    change : {"none", "removed", "added", "moved", "rotated", "mixed"}
    objects : list of MapObject
        The reference epoch's objects.
    placement : Placement
    rng : Generator
    new_object : callable
        ``new_object(name)``: a fresh movable object for an addition.

    Returns
    -------
    scan_objects : list of MapObject
    changes : list of MapChange
        Empty for ``"none"``; fewer than asked when no object or free place allowed one.
    """
    if change not in MAP_CHANGES:
        raise ValueError(f"change must be one of {MAP_CHANGES}, got {change!r}")
    scan = list(objects)
    changes: list[MapChange] = []
    movable = [i for i, obj in enumerate(objects) if obj.kind in MOVABLE_KINDS]
    movable = [movable[i] for i in rng.permutation(len(movable))]
    kinds = ("removed", "moved", "rotated", "added") if change == "mixed" else (change,)
    for kind in kinds:
        if kind == "removed" and movable:
            index = movable.pop()
            changes.append(MapChange("removed", objects[index].name, objects[index].bounds, None))
            scan[index] = None  # type: ignore[call-overload]
        elif kind == "moved":
            for index in list(movable):
                others = [obj for i, obj in enumerate(scan) if obj is not None and i != index]
                moved = None
                for _ in range(10):
                    moved = place_object(objects[index], others + list(objects), placement, rng)
                    if (
                        moved is not None
                        and np.linalg.norm(_centre(moved)[:2] - _centre(objects[index])[:2])
                        >= MIN_MOVE
                    ):
                        break
                    moved = None
                if moved is not None:
                    movable.remove(index)
                    scan[index] = moved
                    changes.append(
                        MapChange("moved", moved.name, objects[index].bounds, moved.bounds)
                    )
                    break
        elif kind == "rotated":
            for index in list(movable):
                original = objects[index]
                low_high = original.bounds
                low, high = low_high
                size = high - low
                if original.kind == "box" and abs(size[0] - size[1]) < 0.15:
                    continue  # a square box turned is the same box
                turned = original.placed(np.zeros(3), 1)
                turned_size = turned.bounds[1] - turned.bounds[0]
                corner = np.array([*(_centre(original)[:2] - turned_size[:2] / 2.0), low[2]])
                turned = turned.placed(corner)
                others = [obj for i, obj in enumerate(scan) if obj is not None and i != index]
                if fits(turned, others, placement):
                    movable.remove(index)
                    scan[index] = turned
                    changes.append(MapChange("rotated", turned.name, low_high, turned.bounds))
                    break
        elif kind == "added":
            template = new_object("added")
            others = [obj for obj in scan if obj is not None] + list(objects)
            added = place_object(template, others, placement, rng)
            if added is not None:
                scan.append(added)
                changes.append(MapChange("added", added.name, None, added.bounds))
    return [obj for obj in scan if obj is not None], changes
