"""Tiled comparison: one large pair localised tile by tile within a memory budget (issue 30).

One comparison in one process holds both clouds and everything localisation derives from them
(about :data:`~app.core.tiling.plan.LOCALISATION_BYTES_PER_POINT` bytes a point of both clouds).
Here space is cut into tiles; each tile is localised on its crop (its core plus a margin wide
enough for neighbourhoods, visibility and clustering), only its core points keep their labels,
and the tiles' results are merged into one result in the clouds' order.

Contract (the unit of work a queue worker runs)
-----------------------------------------------
Everything a tile needs is plain arrays, so a tile is a pure function of saved inputs and its
result is a file; the order tiles run in, and the process each runs in, do not change the
merged result.

1. **Once per comparison** (the parent): load, register the scan on a subsample, resolve the
   sensor origins / stations of each cloud on the whole cloud, then

   - ``plan = plan_tiles(reference_points, scan_points, budget_bytes=..., margin=...)``:
     a :class:`~app.core.tiling.plan.TilePlan` (``plan.save(path)`` / ``TilePlan.load``,
     a small ``.npz``); raises :class:`~app.core.tiling.plan.TileBudgetError` (an
     ``InputError``: HTTP 4xx, CLI exit 2) when even one tile cannot fit the budget;
   - ``context = TileContext(...)``: what every tile shares besides the points (origins,
     flags, the localisation parameters, the whole pair's minimum region size);
     ``context.save(path)`` / ``TileContext.load``;
   - the points as a :class:`~app.core.tiling.tile.TileSource`: the reference and the
     *aligned* scan in the local frame, plus each point's station index (arrays or
     ``numpy.load(..., mmap_mode="r")`` memory maps of ``.npy`` files on shared storage).

2. **Per tile** (any worker, any order, retried freely: it writes nothing but its result)::

       result = compute_tile(plan, tile_index, source, context)  # -> TileResult
       result.save(path)                                         # .npz
       result = TileResult.load(path)

   A :class:`~app.core.tiling.tile.TileResult` holds, for the tile's *core* points only
   (global indices into each cloud), the label (int8) and distance (float32), plus the
   tile's changed and uncertain regions with their member points' global indices (core and
   margin: the margin members are how :func:`merge_tiles` joins a region cut by a border)
   and the tile's figures (alignment residual, noise, thresholds).

3. **Once at the end** (the parent)::

       merged = merge_tiles(plan, results, n_reference, n_scan, min_region_points)

   a :class:`~app.core.tiling.merge.MergedLocalisation` shaped like
   :class:`~app.core.localise.Localisation`: labels and distances in the clouds' order,
   regions joined across borders and filtered by the whole pair's minimum region size,
   moved surfaces marked on the joined regions, and per-tile figures.

:func:`~app.core.tiling.compare.compare_tiled` runs all of it in one process on clouds in
memory; a fan-out runs step 2 as tasks, each tile reading only its own crop's files
(:mod:`~app.core.tiling.crops`).  :func:`~app.core.tiling.streamed.compare_streamed` is the
same comparison of two files whose parent never holds either whole (chunks, subsamples, crops
written from the chunks, labels merged into files): what the CLI and the job runner use for
coordinates-only files over the budget.

Modules: :mod:`~app.core.tiling.plan` (tiles, margins, the memory model),
:mod:`~app.core.tiling.tile` (crop and localise one tile), :mod:`~app.core.tiling.thinning`
(a tile too dense for the budget even at the smallest size, localised on a thinned crop and
its labels carried back to every point), :mod:`~app.core.tiling.crops`
(each tile's crop in files of its own), :mod:`~app.core.tiling.merge` (join tiles),
:mod:`~app.core.tiling.compare` (the whole comparison in memory),
:mod:`~app.core.tiling.streamed` (the whole comparison streamed from the files).
"""

from importlib import import_module
from typing import Any

_HOMES = {
    "LOCALISATION_BYTES_PER_POINT": "plan",
    "TileBudgetError": "plan",
    "TilePlan": "plan",
    "plan_tiles": "plan",
    "MergedLocalisation": "merge",
    "merge_tiles": "merge",
    "TileContext": "tile",
    "TileResult": "tile",
    "TileSource": "tile",
    "compute_tile": "tile",
}
"""Where each public name lives: imported on first use, so that the API process can check a
budget with :mod:`app.core.tiling.plan` (numpy only) without loading the localiser."""

__all__ = sorted(_HOMES)


def __getattr__(name: str) -> Any:
    """The public name ``name`` from its module (see :data:`_HOMES`)."""
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(import_module(f"{__name__}.{_HOMES[name]}"), name)
