"""Tiled comparison (issue 30): the whole ``scandiff compare`` of a merged-station pair against
the sum of its tiles' cKDTree floors, and its peak RSS.

The pair: a five-station warehouse survey per epoch (:func:`app.core.datasets.lidar.lidar_pair`
with ``n_stations=5``, an added box, the scan misaligned), float32 binary PLY without station
information, as bench/perf_round2.py writes its pairs (written once into ``--work-dir``, in a
child process, and reused).

Measured in one run:

* ``compare``: ``scandiff compare REF SCAN --json --labels OUT.npz --memory-budget B`` as a child
  process: wall seconds, CPU seconds and peak RSS from ``os.wait4`` (bench/perf_round2.py's
  :func:`~bench.perf_round2.run_command`), the number of tiles, the stations recovered and the
  regions found;
* ``tile floors``: for each tile the command reported (its core box grown by the margin), one
  ``cKDTree`` build and nearest-neighbour query each way between the two clouds' points in that
  box, two query threads (compute seconds only, in a child process), summed;
* optionally (``--one-process``) the same command with no budget, for the labels' IoU and the
  regions against the tiled run (and its own RSS and wall).

Targets (issue 30): peak RSS <= 2.5 GB; wall <= 3x the sum of the per-tile floors.

Run: ``.venv/bin/python -m bench.tiled --work-dir /tmp/tiled --points 2000000
[--memory-budget 1.2G] [--one-process]``.  ``--measure-model DIR`` prints the bytes a point of
``localise_changes`` on crops of the pair in DIR (the figure behind
:data:`app.core.tiling.plan.LOCALISATION_BYTES_PER_POINT`); ``--plan-only DIR
--memory-budget B`` plans the streamed comparison of the pair in DIR and stops before the
crops (tiles, thinned tiles, the largest crops, CPU seconds and peak RSS).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.perf_round2 import PROJECT_ROOT, SCANDIFF, _child

SCENE_SEED = 18
N_STATIONS = 5
RSS_TARGET_MB = 2.5 * 1024
RATIO_TARGET = 3.0


def write_pair(scene_dir: Path, n_points: int) -> dict[str, Path]:
    """Write the merged-station pair of about ``n_points`` points a scan once (a child process)."""
    scene_dir.mkdir(parents=True, exist_ok=True)
    paths = {"reference": scene_dir / "reference.ply", "scan": scene_dir / "scan.ply"}
    if not all(path.exists() for path in paths.values()):
        command = [sys.executable, "-m", "bench.tiled", "--write-pair", str(scene_dir)]
        subprocess.run([*command, str(n_points)], check=True, cwd=PROJECT_ROOT)
    return paths


def _scene_options(n_points: int) -> dict[str, Any]:
    """The five-station warehouse pair of about ``n_points`` a scan, as both writers draw it."""
    from app.core.datasets.lidar import steps_for_points

    return {
        "layout": "warehouse",
        "change": "added",
        "n_stations": N_STATIONS,
        "angular_step_deg": steps_for_points(n_points, N_STATIONS),
        "misaligned": True,
        "random_state": SCENE_SEED,
    }


def _write_pair_here(scene_dir: Path, n_points: int) -> None:
    from app.core.datasets.lidar import lidar_pair
    from bench.perf_workers import write_binary_ply

    scene_dir.mkdir(parents=True, exist_ok=True)
    pair = lidar_pair(**_scene_options(n_points))
    write_binary_ply(scene_dir / "reference.ply", pair.reference)
    write_binary_ply(scene_dir / "scan.ply", pair.scan)


def _write_pair_streamed(scene_dir: Path, n_points: int) -> None:
    """The same pair as :func:`_write_pair_here` (same points, in station order), written station
    by station in bounded memory (:func:`app.core.datasets.lidar_files.write_lidar_pair`), with
    ``truth.npz`` (the changed rows, stations, boxes) beside it; prints its sizes and peak RSS."""
    from app.core.datasets.lidar_files import write_lidar_pair

    written = write_lidar_pair(scene_dir, **_scene_options(n_points))
    print(
        json.dumps(
            {
                "points": [written.n_reference, written.n_scan],
                "bytes": [written.reference_path.stat().st_size, written.scan_path.stat().st_size],
                "peak_rss_mb": round(_rss_bytes("VmHWM") / 1024**2),
            }
        ),
        flush=True,
    )


def densest_crop(scene_dir: Path, core: tuple[float, float] = (1.5, 1.3)) -> dict[str, Any]:
    """Print the most points of both clouds one crop of a ``core`` box (metres, plus the
    planner's margin each side) can hold, from each file's 2M-point subsample (as the
    streamed parent's), and how far each epoch's stations (``truth.npz``) are from it: the
    floor the planner meets near a station, whatever the budget."""
    from scipy.ndimage import uniform_filter

    from app.core.tiling.pair_files import survey
    from app.core.tiling.plan import DEFAULT_MARGIN_METRES

    cell = 0.1
    size = [round((side + 2 * DEFAULT_MARGIN_METRES) / cell) for side in core]
    clouds = [
        survey(scene_dir / f"{side}.ply", "ply", 2_000_000)[:2] for side in ("reference", "scan")
    ]
    low = np.min([sample[:, :2].min(axis=0) for _, sample in clouds], axis=0)
    high = np.max([sample[:, :2].max(axis=0) for _, sample in clouds], axis=0)
    edges = [np.arange(low[axis], high[axis] + cell, cell) for axis in (0, 1)]
    windows = []
    for cloud, sample in clouds:
        counts, _, _ = np.histogram2d(sample[:, 0], sample[:, 1], bins=edges)
        scale = cloud.n_rows / len(sample)
        windows.append(uniform_filter(counts * scale, size=size, mode="constant") * np.prod(size))
    both = windows[0] + windows[1]
    row, column = np.unravel_index(int(np.argmax(both)), both.shape)
    centre = np.array([edges[0][row], edges[1][column]])
    report: dict[str, Any] = {
        "crop_m": [round(side * cell, 1) for side in size],
        "points": round(float(both[row, column])),
        "per_side": [round(float(window[row, column])) for window in windows],
        "centre": centre.round(2).tolist(),
    }
    if (scene_dir / "truth.npz").exists():
        with np.load(scene_dir / "truth.npz") as truth:
            for side in ("reference", "scan"):
                offsets = truth[f"{side}_origins"][:, :2] - centre
                report[f"{side}_stations_m"] = np.linalg.norm(offsets, axis=1).round(2).tolist()
    print(json.dumps(report), flush=True)
    return report


class _StopAfterPlanError(Exception):
    """Raised by :func:`plan_only`'s progress callback once the plan is written."""


def _budget_bytes(budget: str) -> int:
    """``2.5G``, ``2560M``, or a byte count."""
    if budget[-1] in "KMG":
        return round(float(budget[:-1]) * 1024 ** ("KMG".index(budget[-1]) + 1))
    return int(budget)


def plan_only(scene_dir: Path, budget: str) -> None:
    """Plan the streamed comparison of the pair in ``scene_dir`` (``reference.ply``,
    ``scan.ply``) under ``budget`` and stop before any crop is written (the progress callback
    stops the run once :data:`~app.core.tiling.streamed.PLAN_FILE` exists): the tiles, the
    thinned tiles, the largest crops before and (as the budget bounds it) after thinning,
    with this process's CPU seconds and peak RSS (``VmHWM``)."""
    import resource
    import shutil
    import tempfile

    from app.core.tiling.crops import record_dtype
    from app.core.tiling.plan import TilePlan, thinned_point_limit
    from app.core.tiling.streamed import PLAN_FILE, compare_streamed

    budget_bytes = _budget_bytes(budget)
    work_dir = Path(tempfile.mkdtemp(prefix="scandiff-plan-only-"))

    def stop(stage: str, fraction: float) -> None:
        if (work_dir / PLAN_FILE).exists():
            raise _StopAfterPlanError

    try:
        compare_streamed(
            scene_dir / "reference.ply",
            scene_dir / "scan.ply",
            budget_bytes=budget_bytes,
            work_dir=work_dir,
            formats=("ply", "ply"),
            progress=stop,
        )
        raise RuntimeError("the comparison ran past its plan")
    except _StopAfterPlanError:
        plan = TilePlan.load(work_dir / PLAN_FILE)
    finally:
        shutil.rmtree(work_dir, ignore_errors=True)
    usage = resource.getrusage(resource.RUSAGE_SELF)
    thinned = plan.thinned_tiles
    whole = [int(plan.crop_points[tile]) for tile in range(plan.n_tiles) if tile not in thinned]
    bounds = [thinned_point_limit(plan.max_crop_points, int(plan.crop_points[t])) for t in thinned]
    cells = [plan.thinning_cell(tile) for tile in thinned]
    report = {
        "budget_bytes": budget_bytes,
        "max_crop_points": plan.max_crop_points,
        "tiles": plan.n_tiles,
        "thinned_tiles": len(thinned),
        "largest_whole_crop": max(whole, default=0),
        "largest_crop_before_thinning": max((int(plan.crop_points[t]) for t in thinned), default=0),
        "largest_thinned_crop_allowed": max(bounds, default=0),
        "smallest_thinned_crop_allowed": min(bounds, default=0),
        "thinning_cells_m": [round(min(cells), 4), round(max(cells), 4)] if cells else [],
        "crop_points_sum": int(plan.crop_points.sum()),
        # the crop files as the passes write them (clouds under 2**32 points, with stations)
        "crops_planned_bytes": int(plan.crop_points.sum())
        * record_dtype(np.zeros((0, 3), np.float32), 0, 2).itemsize,
        "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
        "peak_rss_mb": round(_rss_bytes("VmHWM") / 1024**2),
    }
    print(json.dumps(report), flush=True)


def run_compare(paths: dict[str, Path], labels: Path, budget: str | None) -> dict[str, Any]:
    """The command as a child: wall, CPU, peak RSS and its JSON report."""
    arguments = [str(SCANDIFF), "compare", str(paths["reference"]), str(paths["scan"])]
    arguments += ["--json", "--labels", str(labels), "--memory-budget", budget or "none"]
    child = _child(arguments, dict(os.environ), PROJECT_ROOT)
    if child["code"] != 0:
        return {"error": child["stderr"].strip().splitlines()[-1:], "code": child["code"]}
    report = json.loads(child["stdout"].strip().splitlines()[-1])
    tiles = report["localisation"].get("tiles")
    return {
        "seconds": round(child["wall"], 1),
        "cpu_seconds": round(child["cpu_seconds"], 1),
        "peak_rss_mb": round(child["peak_rss_mb"]),
        "timings": {key: round(value, 1) for key, value in report["timings"].items()},
        "changed": report["changed"],
        "regions": [(r["kind"], r["n_points"]) for r in report["regions"]],
        "stations_recovered": {
            side: report["visibility"][side].get("stations_recovered")
            for side in ("reference", "scan")
        },
        "tests": {side: report["visibility"][side].get("test") for side in ("reference", "scan")},
        "tiles": tiles,
    }


def run_tile_floors(paths: dict[str, Path], tiles: dict[str, Any]) -> dict[str, Any]:
    """The per-tile floors in a child process (its own RSS, not the bench's)."""
    boxes = [[tile["core_min"], tile["core_max"]] for tile in tiles["per_tile"]]
    spec = json.dumps(
        {"boxes": boxes, "margin": tiles["margin_m"], **{k: str(v) for k, v in paths.items()}}
    )
    command = [sys.executable, "-m", "bench.tiled", "--floor-worker", spec]
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    child = _child(command, environment, PROJECT_ROOT)
    if child["code"] != 0:
        return {"error": child["stderr"].strip().splitlines()[-1:]}
    return json.loads(child["stdout"].strip().splitlines()[-1])


def _floor_worker(spec: dict[str, Any]) -> None:
    """Print the summed seconds of a cKDTree build + query each way per tile crop."""
    from scipy.spatial import cKDTree

    from app.core.formats import read_point_cloud

    reference = read_point_cloud(spec["reference"]).points
    scan = read_point_cloud(spec["scan"]).points
    margin = float(spec["margin"])
    seconds = []
    for low, high in spec["boxes"]:  # the outer tiles' infinite sides come as null
        low = np.array([-np.inf if v is None else v for v in low], dtype=np.float64) - margin
        high = np.array([np.inf if v is None else v for v in high], dtype=np.float64) + margin
        crops = [
            np.ascontiguousarray(
                points[np.all((points[:, :2] >= low) & (points[:, :2] <= high), 1)]
            )
            for points in (reference, scan)
        ]
        started = time.perf_counter()
        for built, queried in ((crops[0], crops[1]), (crops[1], crops[0])):
            if len(built) and len(queried):
                cKDTree(built).query(queried, k=1, workers=2)
        seconds.append(time.perf_counter() - started)
    print(
        json.dumps({"seconds": round(sum(seconds), 2), "per_tile": [round(s, 2) for s in seconds]})
    )


def labels_iou(first: Path, second: Path) -> dict[str, float]:
    """IoU of the changed points of two labels files, per cloud."""
    result = {}
    with np.load(first) as one, np.load(second) as other:
        for name in ("reference_changed", "scan_changed"):
            union = np.count_nonzero(one[name] | other[name])
            both = np.count_nonzero(one[name] & other[name])
            result[name] = 1.0 if union == 0 else round(both / union, 4)
    return result


def measure_model(scene_dir: Path) -> None:
    """Peak bytes a point of ``localise_changes`` on spatial crops of the pair (x quantiles)."""
    for fraction in (0.25, 0.5, 1.0):
        command = [sys.executable, "-m", "bench.tiled", "--model-worker", str(scene_dir)]
        subprocess.run([*command, str(fraction)], check=True, cwd=PROJECT_ROOT)


def _model_worker(scene_dir: Path, fraction: float) -> None:
    from app.core.formats import read_point_cloud
    from app.core.localise import localise_changes
    from app.core.registration import apply_transform, register_scan

    reference = read_point_cloud(scene_dir / "reference.ply").points
    scan = read_point_cloud(scene_dir / "scan.ply").points
    scan = apply_transform(scan, register_scan(reference[::4], scan[::4]).transform)
    cut = np.quantile(reference[:, 0], fraction)
    reference = np.ascontiguousarray(reference[reference[:, 0] <= cut])
    scan = np.ascontiguousarray(scan[scan[:, 0] <= cut])
    before = _rss_bytes("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # resets the peak (VmHWM) to now
    started = time.perf_counter()
    localise_changes(reference, scan, threads=2)
    peak = _rss_bytes("VmHWM")
    points = len(reference) + len(scan)
    print(
        json.dumps(
            {
                "points": points,
                "bytes_per_point": round((peak - before) / points),
                "seconds": round(time.perf_counter() - started, 1),
            }
        ),
        flush=True,
    )


def stage_memory(scene_dir: Path, budget: str) -> None:
    """Print the peak RSS of each stage of the command's comparison (a child process)."""
    command = [sys.executable, "-m", "bench.tiled", "--stage-worker", str(scene_dir), budget]
    subprocess.run(command, check=True, cwd=PROJECT_ROOT)


def _stage_worker(scene_dir: Path, budget: str) -> None:
    """The command's read and comparison in this process, with the peak RSS (``VmHWM``, reset
    at each stage) of the stretch before each progress report: where the memory goes."""
    from app.core.formats import read_point_cloud
    from app.core.tiling.compare import compare_within_budget
    from app.core.tiling.lean import read_pair
    from app.kit.allocator import release_freed_memory_promptly

    release_freed_memory_promptly()  # as the command does
    stretches: list[dict[str, Any]] = []
    last = {"started": time.perf_counter()}

    def stretch(stage: str, _fraction: float = 0.0) -> None:
        stretches.append(
            {
                "before": f"{stage} {_fraction:.2f}",
                "peak_mb": round(_rss_bytes("VmHWM") / 1024**2),
                "rss_mb": round(_rss_bytes("VmRSS") / 1024**2),
                "seconds": round(time.perf_counter() - float(last["started"]), 1),
            }
        )
        print(json.dumps(stretches[-1]), flush=True)  # a long run shows how far it got
        last["started"] = time.perf_counter()
        Path("/proc/self/clear_refs").write_text("5")

    budget_bytes = round(float(budget.rstrip("GMK")) * 1024 ** "KMG".index(budget[-1]) * 1024)
    stretch("read")
    reference, scan, offset = read_pair(
        scene_dir / "reference.ply",
        scene_dir / "scan.ply",
        lambda side: read_point_cloud(scene_dir / f"{side}.ply"),
        budget_bytes,
    )
    stretch("compare")
    result = compare_within_budget(
        reference, scan, budget_bytes=budget_bytes, frame_offset=offset, progress=stretch
    )
    result.write_labels_npz(scene_dir / "labels_stages.npz")
    stretch("labels written")
    print(json.dumps({"lean": offset is not None, "stretches": stretches}))


def _rss_bytes(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no {field} in /proc/self/status")


def main() -> None:
    """Parse the command line and run the bench (or one of its children)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work-dir", type=Path, default=Path("/tmp/scandiff-tiled"))
    parser.add_argument("--points", type=int, default=2_000_000, help="points a scan")
    parser.add_argument("--memory-budget", default="2.5G")
    parser.add_argument("--one-process", action="store_true")
    parser.add_argument("--write-pair", nargs=2, metavar=("DIR", "POINTS"))
    parser.add_argument(
        "--write-pair-streamed",
        nargs=2,
        metavar=("DIR", "POINTS"),
        help="the same pair in station order, written in bounded memory (any size)",
    )
    parser.add_argument("--floor-worker", metavar="JSON")
    parser.add_argument("--measure-model", type=Path, metavar="DIR")
    parser.add_argument("--model-worker", nargs=2, metavar=("DIR", "FRACTION"))
    parser.add_argument(
        "--stage-memory",
        type=Path,
        metavar="DIR",
        help="print the peak RSS of each stage of the comparison of the pair in DIR",
    )
    parser.add_argument("--stage-worker", nargs=2, metavar=("DIR", "BUDGET"))
    parser.add_argument(
        "--densest-crop",
        type=Path,
        metavar="DIR",
        help="the most points a 1.5 x 1.3 m tile's crop of the pair in DIR can hold",
    )
    parser.add_argument(
        "--plan-only",
        type=Path,
        metavar="DIR",
        help="plan the streamed comparison of the pair in DIR at --memory-budget and stop",
    )
    args = parser.parse_args()
    if args.plan_only:
        plan_only(args.plan_only, args.memory_budget)
        return
    if args.densest_crop:
        densest_crop(args.densest_crop)
        return
    if args.stage_worker:
        _stage_worker(Path(args.stage_worker[0]), args.stage_worker[1])
        return
    if args.stage_memory:
        stage_memory(args.stage_memory, args.memory_budget)
        return
    if args.write_pair_streamed:
        _write_pair_streamed(Path(args.write_pair_streamed[0]), int(args.write_pair_streamed[1]))
        return
    if args.write_pair:
        _write_pair_here(Path(args.write_pair[0]), int(args.write_pair[1]))
        return
    if args.floor_worker:
        _floor_worker(json.loads(args.floor_worker))
        return
    if args.model_worker:
        _model_worker(Path(args.model_worker[0]), float(args.model_worker[1]))
        return
    if args.measure_model:
        measure_model(args.measure_model)
        return
    scene_dir = args.work_dir / f"{args.points // 1_000_000}M"
    started = time.perf_counter()
    paths = write_pair(scene_dir, args.points)
    print(f"pair ready in {time.perf_counter() - started:.0f} s: {scene_dir}", flush=True)
    tiled = run_compare(paths, scene_dir / "labels_tiled.npz", args.memory_budget)
    print(json.dumps({"compare": {k: v for k, v in tiled.items() if k != "tiles"}}), flush=True)
    if "error" in tiled:
        return
    tiles = tiled["tiles"]
    if tiles is None:
        print("the pair fit the budget: one process (give a smaller --memory-budget)")
        return
    per_tile = tiles["per_tile"]
    crop_points = sum(t["crop_reference_points"] + t["crop_scan_points"] for t in per_tile)
    core_points = sum(t["core_reference_points"] + t["core_scan_points"] for t in per_tile)
    largest = max(t["crop_reference_points"] + t["crop_scan_points"] for t in per_tile)
    print(
        f"crops hold {crop_points / core_points:.2f}x the pair's points (margins and rays); "
        f"largest crop {largest:,}",
        flush=True,
    )
    floors = run_tile_floors(paths, tiles)
    print(json.dumps({"tile_floors": floors}), flush=True)
    ratio = tiled["seconds"] / floors["seconds"] if "seconds" in floors else float("nan")
    print(
        f"tiles {tiles['count']}, peak RSS {tiled['peak_rss_mb']} MB (target <= "
        f"{RSS_TARGET_MB:.0f}: {'met' if tiled['peak_rss_mb'] <= RSS_TARGET_MB else 'NOT met'}), "
        f"wall {tiled['seconds']} s = {ratio:.2f}x the summed tile floors "
        f"{floors.get('seconds')} s (target <= {RATIO_TARGET}x: "
        f"{'met' if ratio <= RATIO_TARGET else 'NOT met'}); largest tile alignment residual "
        f"{tiles.get('alignment_residual_max')}",
        flush=True,
    )
    if args.one_process:
        one = run_compare(paths, scene_dir / "labels_one.npz", None)
        print(json.dumps({"one_process": one}), flush=True)
        if "error" not in one:
            iou = labels_iou(scene_dir / "labels_one.npz", scene_dir / "labels_tiled.npz")
            print(json.dumps({"labels_iou": iou}), flush=True)


if __name__ == "__main__":
    main()
