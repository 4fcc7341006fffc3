"""Tiles of a comparison: an adaptive kd split of the xy plane sized by a memory budget.

Memory model
------------
Localising a crop of ``p`` points (both clouds together) peaks at about
:data:`LOCALISATION_BYTES_PER_POINT` bytes a point above the process's baseline (k-NN indices
and distances, plane fits, the other cloud's nearest neighbours, candidates and the ray
test's KD-trees; measured with ``bench/tiled.py --measure-model``, peak RSS of
``localise_changes`` over warehouse pairs of 0.25-2M points a cloud).  The process running the
tiles also holds the whole pair (:data:`RESIDENT_BYTES_PER_POINT` a point of both clouds:
float64 points, the aligned scan, station indices, the per-point outputs) plus
:data:`BASELINE_BYTES` (interpreter and libraries).  So a budget ``B`` for ``N`` points
allows crops of ``(B - BASELINE_BYTES - N * RESIDENT_BYTES_PER_POINT) /
LOCALISATION_BYTES_PER_POINT`` points; a worker that reads only its crop (a later fan-out)
sets ``resident_points=0``.

A crop is its tile's core box grown by the margin, plus the other cloud's returns whose ray
from their station crosses that box (the ray visibility test needs what the other sensor saw
behind and in front of a candidate).  A tile whose crop is over the limit is split at the
median of its longer side.  A tile that cannot be split further (narrower than twice the
margin) and still does not fit is *thinned* (:mod:`app.core.tiling.thinning`): its crop is
localised on one point a cube of the plan's thinning cell, which follows from the budget and
the crop's extent, and every point takes its representative's label.  Only when even that
cannot fit (the whole crop cannot be held beside its thinned copy, or the cell would exceed
:data:`~app.core.tiling.thinning.MAX_THINNING_CELL_METRES`) is the budget too small:
:class:`TileBudgetError`, naming the budget to set.  Crop counts made on a sample can be low
for one tile (22 % at 100M + 100M): once a streamed pair's crops are written,
:func:`thinned_as_written` thins, by the same rule, a tile planned whole whose crop is over the
limit.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from app.core.errors import InputError
from app.core.tiling.thinning import (
    HELD_CROP_BYTES_PER_POINT,
    MAX_THINNING_CELL_METRES,
    SURFACE_AREA_FACTOR,
    thinning_cell,
)

__all__ = [
    "BASELINE_BYTES",
    "DEFAULT_MARGIN_METRES",
    "DEFAULT_RAY_REACH_METRES",
    "LEAN_RESIDENT_BYTES_PER_POINT",
    "LOCALISATION_BYTES_PER_POINT",
    "RESIDENT_BYTES_PER_POINT",
    "TileBudgetError",
    "TilePlan",
    "crop_point_limit",
    "plan_tiles",
    "thinned_as_written",
    "thinned_point_limit",
]

LOCALISATION_BYTES_PER_POINT = 200
"""Peak bytes a point (of both clouds) of one crop's localisation: 156-170 measured on the
five-station warehouse pair of ``bench/tiled.py`` (1M and 4M points, two threads), plus
headroom for the tests that need more (the origin-free surface test's growing neighbourhoods,
the ray test's per-station trees)."""
RESIDENT_BYTES_PER_POINT = 72
"""Bytes a point of the whole pair (averaged over both clouds) the tiling process holds
besides the crops: the float64 points as read (24), the aligned scan (12 averaged), the
station index (8), the labels, distances and region numbers and their copies in file order
(18), and spare for the merge."""
LEAN_RESIDENT_BYTES_PER_POINT = 32
""":data:`RESIDENT_BYTES_PER_POINT` of a pair read lean (:mod:`app.core.tiling.lean`): float32
points (6 averaged), the scan's and the aligned scan's float32 points (12 averaged), the
station index (int8: 1), the tiles' results kept until the merge (core index, label, distance:
13) and none of the file-order copies (the merge's arrays are the result)."""
BASELINE_BYTES = 400 * 1024**2
"""Interpreter, numpy, scipy, the detectors' libraries and small buffers."""
DEFAULT_MARGIN_METRES = 1.0
"""Overlap of a tile's crop beyond its core: k-NN neighbourhoods and cluster links
(centimetres at these densities) and the surface and map tests' neighbourhoods fit inside it;
a region longer than it is joined across the border by the merge.  On the five-station 2M +
2M pair 1 m and 2 m give the same labels (IoU 0.998 against one process) but the crops hold
1.75x against 2.43x the pair's points (CPU 36 s against 53 s)."""
DEFAULT_RAY_REACH_METRES = 8.0
"""How far beyond a crop the returns whose rays crossed it are kept: the ray test's evidence
that a candidate's place was seen empty is the surface behind it (a floor, a rack, a wall).
Beyond it a tile holding a station would need that station's whole cloud."""
MIN_THINNED_POINTS = 1000
"""Fewest points a thinned crop must be allowed (:func:`thinned_point_limit`): with fewer
the budget cannot hold the crop beside a thinned copy worth localising."""
COUNT_SAMPLE = 400_000
"""Points of each cloud the planner counts crops on (scaled up to the whole cloud)."""
MAX_DEPTH = 24


class TileBudgetError(InputError):
    """Even one tile of the pair does not fit the memory budget; the message gives the
    smallest budget that would do."""


@dataclass(frozen=True)
class TilePlan:
    """Tiles covering the xy plane (each point's core tile is unique), with their crops.

    Attributes
    ----------
    lower, upper : ndarray, shape (t, 2), float64
        Each tile's core box in xy, half-open ``[lower, upper)``; the outer tiles extend to
        -inf / +inf so every point has a core tile.
    margin : float
        Metres a crop extends beyond its core box.
    crop_points : ndarray, shape (t,), int64
        Estimated points of both clouds in each crop.
    max_crop_points : int
        The limit the plan was made for.
    thinning_cells : ndarray, shape (t,), float64, or None
        Each tile's thinning cell in metres (:mod:`app.core.tiling.thinning`), 0 for a tile
        localised whole; None: no tile is thinned.
    """

    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    margin: float
    crop_points: NDArray[np.int64]
    max_crop_points: int
    thinning_cells: NDArray[np.float64] | None = None

    def thinning_cell(self, tile_index: int) -> float:
        """Tile ``tile_index``'s thinning cell in metres; 0: localised whole."""
        return 0.0 if self.thinning_cells is None else float(self.thinning_cells[tile_index])

    @property
    def thinned_tiles(self) -> list[int]:
        """The tiles localised on a thinned crop."""
        return [] if self.thinning_cells is None else np.flatnonzero(self.thinning_cells).tolist()

    @property
    def n_tiles(self) -> int:
        """Number of tiles."""
        return int(self.lower.shape[0])

    def crop_box(self, tile_index: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The xy box of tile ``tile_index``'s crop: its core grown by the margin."""
        return self.lower[tile_index] - self.margin, self.upper[tile_index] + self.margin

    def in_core(self, tile_index: int, xy: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which of ``xy`` (shape (p, 2)) lie in the tile's core box."""
        low, high = self.lower[tile_index], self.upper[tile_index]
        return np.all((xy >= low) & (xy < high), axis=1)

    def save(self, path: str | Path) -> None:
        """Write the plan as a small ``.npz``."""
        np.savez(
            path,
            lower=self.lower,
            upper=self.upper,
            crop_points=self.crop_points,
            **({} if self.thinning_cells is None else {"thinning_cells": self.thinning_cells}),
            meta=np.array(
                json.dumps({"margin": self.margin, "max_crop_points": self.max_crop_points})
            ),
        )

    @classmethod
    def load(cls, path: str | Path) -> TilePlan:
        """Read a plan written by :meth:`save`."""
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            return cls(
                lower=data["lower"],
                upper=data["upper"],
                margin=float(meta["margin"]),
                crop_points=data["crop_points"],
                max_crop_points=int(meta["max_crop_points"]),
                thinning_cells=data.get("thinning_cells", None),
            )


def crop_point_limit(
    budget_bytes: int,
    resident_points: int,
    resident_bytes_per_point: int = RESIDENT_BYTES_PER_POINT,
) -> int:
    """Most points of both clouds one crop may have under ``budget_bytes`` (see the model).

    Parameters
    ----------
    budget_bytes : int
        The process's memory budget.
    resident_points : int
        Points of both clouds the process holds whole (0 for a worker reading its crop only).
    resident_bytes_per_point : int
        What it holds a point of them (:data:`LEAN_RESIDENT_BYTES_PER_POINT` for a pair read
        lean).

    Returns
    -------
    int
        May be <= 0: nothing fits.
    """
    free = budget_bytes - BASELINE_BYTES - resident_points * resident_bytes_per_point
    return int(free // LOCALISATION_BYTES_PER_POINT)


def thinned_point_limit(max_crop_points: int, crop_points: int) -> int:
    """Points of a thinned crop a budget of ``max_crop_points`` unthinned ones leaves once the
    whole crop of ``crop_points`` points is held
    (:data:`~app.core.tiling.thinning.HELD_CROP_BYTES_PER_POINT`); may be <= 0."""
    free = max(0, max_crop_points) * LOCALISATION_BYTES_PER_POINT
    return int((free - crop_points * HELD_CROP_BYTES_PER_POINT) // LOCALISATION_BYTES_PER_POINT)


def _mib(count: int) -> str:
    return f"{count / 1024**2:,.0f} MiB"


def plan_tiles(
    reference_xy: NDArray[np.float64],
    scan_xy: NDArray[np.float64],
    *,
    max_crop_points: int,
    count_crop: Callable[[NDArray[np.float64], NDArray[np.float64]], int],
    margin: float = DEFAULT_MARGIN_METRES,
    budget_bytes: int | None = None,
) -> TilePlan:
    """Cut the xy plane into tiles whose crops have at most ``max_crop_points`` points.

    Parameters
    ----------
    reference_xy, scan_xy : ndarray, shape (n, 2) / (m, 2)
        The points' xy (a subsample is enough: they only place the median cuts).
    max_crop_points : int
        Most points of both clouds in one crop (:func:`crop_point_limit`).
    count_crop : callable
        ``count_crop(low, high)``: points of both clouds in the crop of the core box
        ``[low, high)`` (:meth:`~app.core.tiling.tile.TileSource.count_crop`).
    margin : float
        Metres a crop extends beyond its core box.
    budget_bytes : int, optional
        Named in the error message when nothing fits.

    Returns
    -------
    TilePlan
        One tile when the whole pair fits; a tile that cannot be split further and is over
        the limit gets a thinning cell (:attr:`TilePlan.thinning_cells`).

    Raises
    ------
    TileBudgetError
        A tile that cannot be split further does not fit even thinned.
    """
    if margin <= 0:
        raise InputError(f"the tile margin must be > 0 metres, got {margin}")
    sample = np.concatenate([_thinned(reference_xy), _thinned(scan_xy)])
    infinite = np.array([np.inf, np.inf])
    leaves: list[tuple[NDArray, NDArray, int, float]] = []
    pending = [(-infinite, infinite, sample, 0)]
    while pending:
        low, high, inside, depth = pending.pop()
        count = count_crop(low, high)
        if count <= max_crop_points:
            leaves.append((low, high, count, 0.0))
            continue
        extent = inside.max(axis=0) - inside.min(axis=0) if len(inside) else np.zeros(2)
        axis = int(np.argmax(extent))
        cut = float(np.median(inside[:, axis])) if len(inside) else 0.0
        if extent[axis] < 2 * margin or depth >= MAX_DEPTH:
            cell = _leaf_thinning_cell(count, extent, margin, max_crop_points, budget_bytes)
            leaves.append((low, high, count, cell))
            continue
        left_high, right_low = high.copy(), low.copy()
        left_high[axis] = right_low[axis] = cut
        below = inside[:, axis] < cut
        pending.append((right_low, high, inside[~below], depth + 1))
        pending.append((low, left_high, inside[below], depth + 1))
    leaves.sort(key=lambda leaf: (leaf[0][1], leaf[0][0]))  # row by row, as read
    return TilePlan(
        lower=np.array([leaf[0] for leaf in leaves], dtype=np.float64).reshape(-1, 2),
        upper=np.array([leaf[1] for leaf in leaves], dtype=np.float64).reshape(-1, 2),
        margin=float(margin),
        crop_points=np.array([leaf[2] for leaf in leaves], dtype=np.int64),
        max_crop_points=int(max_crop_points),
        thinning_cells=(
            np.array([leaf[3] for leaf in leaves], dtype=np.float64)
            if any(leaf[3] for leaf in leaves)
            else None
        ),
    )


def _leaf_thinning_cell(
    count: int,
    extent: NDArray[np.float64],
    margin: float,
    max_crop_points: int,
    budget_bytes: int | None,
) -> float:
    """The thinning cell of a tile of ``count`` crop points whose points span ``extent``
    (shape (2,), metres) in xy; :class:`TileBudgetError` when it does not fit even thinned."""
    area = float(np.prod(extent + 2 * margin))
    localised = thinned_point_limit(max_crop_points, count)
    if localised < MIN_THINNED_POINTS:
        raise TileBudgetError(_refusal(count, extent, area, max_crop_points, budget_bytes))
    return thinning_cell(area, localised)


def thinned_as_written(
    plan: TilePlan,
    written_points: NDArray[np.int64],
    reference_xy: NDArray[np.float64],
    scan_xy: NDArray[np.float64],
    budget_bytes: int | None = None,
) -> TilePlan:
    """The plan once its crops are written: a tile planned whole whose crop holds more than
    :attr:`TilePlan.max_crop_points` gets the thinning cell :func:`plan_tiles` gives such a
    tile (its count was estimated on a sample, its crop as written is what it holds).

    Parameters
    ----------
    plan : TilePlan
    written_points : ndarray, shape (t,), int64
        Points of both clouds in each tile's crop as written.
    reference_xy, scan_xy : ndarray, shape (n, 2) / (m, 2)
        The points' xy as given to :func:`plan_tiles` (a tile's extent is its points').
    budget_bytes : int, optional
        Named in the error message when a tile does not fit even thinned.

    Returns
    -------
    TilePlan
        ``plan`` itself when no tile planned whole is over the limit; else a copy with those
        tiles' thinning cells (the other tiles', and every count, unchanged).

    Raises
    ------
    TileBudgetError
        Such a tile does not fit even thinned.
    """
    written = np.asarray(written_points, dtype=np.int64)
    cells = np.zeros(plan.n_tiles) if plan.thinning_cells is None else plan.thinning_cells.copy()
    over = np.flatnonzero((written > plan.max_crop_points) & (cells == 0))
    if len(over) == 0:
        return plan
    sample = np.concatenate([_thinned(reference_xy), _thinned(scan_xy)])
    for tile_index in over.tolist():
        inside = sample[plan.in_core(tile_index, sample)]
        extent = inside.max(axis=0) - inside.min(axis=0) if len(inside) else np.zeros(2)
        cells[tile_index] = _leaf_thinning_cell(
            int(written[tile_index]), extent, plan.margin, plan.max_crop_points, budget_bytes
        )
    return dataclasses.replace(plan, thinning_cells=cells)


def _refusal(
    count: int,
    extent: NDArray[np.float64],
    area: float,
    max_crop_points: int,
    budget_bytes: int | None,
) -> str:
    """Why a tile that cannot be split does not fit even thinned, and the budget to set."""
    thinned = int(np.ceil(SURFACE_AREA_FACTOR * area / MAX_THINNING_CELL_METRES**2))
    needed = count * HELD_CROP_BYTES_PER_POINT + thinned * LOCALISATION_BYTES_PER_POINT
    missing = max(1024**2, needed - max(0, max_crop_points) * LOCALISATION_BYTES_PER_POINT)
    hint = (
        f"; raise the memory budget by at least {_mib(missing)} "
        f"(set it to at least {_mib(budget_bytes + missing)})"
        if budget_bytes is not None
        else ""
    )
    budget = f" of {_mib(budget_bytes)}" if budget_bytes is not None else ""
    return (
        f"the pair does not fit the memory budget{budget}: a tile of "
        f"{extent[0]:.1f} x {extent[1]:.1f} m still has {count:,} points to localise "
        f"(its crop and the rays crossing it), more than the {max(0, max_crop_points):,} "
        f"the budget allows, and it cannot be thinned within the budget: holding the crop "
        f"beside its copy thinned at {MAX_THINNING_CELL_METRES * 100:g} cm needs about "
        f"{_mib(needed)}{hint}"
    )


def _thinned(xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """At most :data:`COUNT_SAMPLE` of ``xy``, evenly strided."""
    step = max(1, len(xy) // COUNT_SAMPLE)
    return np.asarray(xy[::step, :2], dtype=np.float64)
