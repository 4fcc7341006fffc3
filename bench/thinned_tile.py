"""A thinned tile's peak memory against the planner's model (issue 30, thinned tiles).

A floor 6 x 6 m with a dense disc of 1.5 m round a station's foot (85 % of the points, about
as dense as the 100M pair's near field at a few million points), the scan adding a 0.5 m box
on the disc.  The parent plans the pair with crops of ``--crop-share`` of its points (so the
disc's tiles are thinned), writes every tile's crop files (:mod:`app.core.tiling.crops`) and
runs the largest thinned tile in a child process that reads only its crop files, as a
fanned-out worker does.  Printed: the crop's points before and after thinning, the cell, the
child's CPU seconds, its peak RSS (``VmHWM``) above its RSS before the tile, and the model's
figure for the same tile (``crop * HELD_CROP_BYTES_PER_POINT + thinned *
LOCALISATION_BYTES_PER_POINT``).

Run: ``python -m bench.thinned_tile --points 2000000 [--crop-share 0.6] [--work-dir DIR]``.

``--densest DIR``: the densest crop of the pair in DIR (``bench.tiled --densest-crop``: a
1.5 x 1.3 m core plus 1 m margins, each file in its own frame), read at full density, and the
points :func:`~app.core.tiling.thinning.representatives` keeps of it at 2 mm times powers
of sqrt(2), up to 2 cm (the cells a tile may use), with the CPU seconds and peak RSS of this
process.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.perf_round2 import PROJECT_ROOT, _child


def _floor(rng: np.random.Generator, n_points: int, box: bool) -> np.ndarray:
    """The floor, its dense disc and (``box``) the added box's lid and sides; 2 mm noise."""
    dense = int(0.85 * n_points)
    radius = 1.5 * np.sqrt(rng.uniform(0, 1, dense))
    angle = rng.uniform(0, 2 * np.pi, dense)
    parts = [
        np.column_stack([rng.uniform(-3, 3, (n_points - dense, 2)), np.zeros(n_points - dense)]),
        np.column_stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros(dense)]),
    ]
    if box:
        count, side = 40_000, 0.5
        u, v = rng.uniform(0, side, (2, count))
        face = rng.integers(0, 3, count)
        wall = np.where(rng.uniform(0, 1, count) < 0.5, 0.0, side)
        lid = np.column_stack([u, v, np.full(count, side)])
        x_wall = np.column_stack([wall, u, v])
        y_wall = np.column_stack([u, wall, v])
        parts.append(np.choose(face[:, None], [lid, x_wall, y_wall]) + np.array([0.3, 0.3, 0.0]))
    points = np.concatenate(parts)
    return points + rng.normal(0, 0.002, points.shape)


def _vm_hwm_bytes() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmHWM in /proc/self/status")


def _rss_bytes() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def worker(directory: Path, tile_index: int) -> None:
    """Compute one tile from its crop files; print its figures and the memory it took."""
    from app.core.tiling.crops import TileCropFiles
    from app.core.tiling.plan import TilePlan
    from app.core.tiling.tile import TileContext, compute_tile

    plan = TilePlan.load(directory / "plan.npz")
    context = TileContext.load(directory / "context.npz")
    before = _rss_bytes()
    result = compute_tile(plan, tile_index, TileCropFiles(directory / "crops"), context, threads=2)
    figures = {name: value for name, value in result.figures.items() if "point" in name}
    figures["thinning_cell_m"] = result.figures.get("thinning_cell_m")
    figures["regions"] = len(result.regions["cloud"])
    figures["rss_before_mb"] = round(before / 1024**2)
    figures["peak_above_before_mb"] = round((_vm_hwm_bytes() - before) / 1024**2)
    print(json.dumps(figures), flush=True)


def densest(scene_dir: Path) -> None:
    """Thin the densest crop of the pair in ``scene_dir`` at each cell from 2 mm to 2 cm."""
    import resource

    from app.core.formats.streamed import open_point_blocks
    from app.core.tiling.thinning import (
        MAX_THINNING_CELL_METRES,
        MIN_THINNING_CELL_METRES,
        THINNING_CELL_STEP,
        representatives,
    )
    from bench.tiled import densest_crop

    report = densest_crop(scene_dir)
    low = np.array(report["centre"]) - np.array(report["crop_m"]) / 2
    high = low + np.array(report["crop_m"])
    kept = {}
    for side in ("reference", "scan"):
        parts = []
        with open_point_blocks(scene_dir / f"{side}.ply", "ply", max_points=None) as blocks:
            for _, block in blocks.blocks:
                inside = np.all((block[:, :2] >= low) & (block[:, :2] < high), axis=1)
                parts.append(np.asarray(block[inside], dtype=np.float64))
        kept[side] = np.concatenate(parts)
    cells = [MIN_THINNING_CELL_METRES]  # up to the ceiling, the ceiling last
    while cells[-1] < MAX_THINNING_CELL_METRES:
        cells.append(min(MAX_THINNING_CELL_METRES, cells[-1] * THINNING_CELL_STEP))
    counts = {
        round(cell * 1000, 2): sum(
            len(representatives(points, cell)[0]) for points in kept.values()
        )
        for cell in cells
    }
    usage = resource.getrusage(resource.RUSAGE_SELF)
    print(
        json.dumps(
            {
                "crop_points": {side: len(points) for side, points in kept.items()},
                "thinned_points_by_cell_mm": counts,
                "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
                "peak_rss_mb": round(_vm_hwm_bytes() / 1024**2),
            }
        ),
        flush=True,
    )


def main() -> None:
    """Parse the command line; plan, write the crops, run the largest thinned tile."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=2_000_000, help="points a cloud")
    parser.add_argument("--crop-share", type=float, default=0.6)
    parser.add_argument("--work-dir", type=Path)
    parser.add_argument("--worker", nargs=2, metavar=("DIR", "TILE"))
    parser.add_argument("--densest", type=Path, metavar="DIR")
    args = parser.parse_args()
    if args.densest:
        densest(args.densest)
        return
    if args.worker:
        worker(Path(args.worker[0]), int(args.worker[1]))
        return
    from app.core.tiling.crops import write_tile_crops
    from app.core.tiling.plan import LOCALISATION_BYTES_PER_POINT, plan_tiles
    from app.core.tiling.thinning import HELD_CROP_BYTES_PER_POINT
    from app.core.tiling.tile import TileContext, TileSource

    directory = args.work_dir or Path(tempfile.mkdtemp(prefix="scandiff-thinned-"))
    directory.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(30)
    reference, scan = _floor(rng, args.points, box=False), _floor(rng, args.points, box=True)
    source = TileSource(reference, scan)
    context = TileContext(None, None, False, False, min_region_points=100)
    total = len(reference) + len(scan)
    plan = plan_tiles(
        reference[:, :2],
        scan[:, :2],
        max_crop_points=int(args.crop_share * total),
        count_crop=lambda low, high: source.count_crop(low, high, 1.0, context),
    )
    plan.save(directory / "plan.npz")
    context.save(directory / "context.npz")
    write_tile_crops(directory / "crops", plan, source, context)
    thinned = plan.thinned_tiles
    print(json.dumps({"tiles": plan.n_tiles, "thinned_tiles": thinned}), flush=True)
    if not thinned:
        return
    tile = max(thinned, key=lambda index: int(plan.crop_points[index]))
    command = [sys.executable, "-m", "bench.thinned_tile", "--worker", str(directory), str(tile)]
    child = _child(command, dict(os.environ), PROJECT_ROOT)
    if child["code"] != 0:
        print(child["stderr"][-3000:])
        return
    figures = json.loads(child["stdout"].strip().splitlines()[-1])
    crop = figures["crop_reference_points"] + figures["crop_scan_points"]
    after = figures["thinned_reference_points"] + figures["thinned_scan_points"]
    model = crop * HELD_CROP_BYTES_PER_POINT + after * LOCALISATION_BYTES_PER_POINT
    print(
        json.dumps(
            {
                "tile": tile,
                **figures,
                "cpu_s": round(child["cpu_seconds"], 1),
                "model_mb": round(model / 1024**2),
                "measured_bytes_per_crop_point": round(
                    figures["peak_above_before_mb"] * 1024**2 / crop, 1
                ),
            }
        ),
        flush=True,
    )
    if args.work_dir is None:
        shutil.rmtree(directory, ignore_errors=True)


if __name__ == "__main__":
    main()
