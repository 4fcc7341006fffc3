"""The streamed tiled parent (issue 30, app.core.tiling.streamed): its peak RSS against the
pair's size, and against the lean parent that holds the whole pair, measured in one run.

Each variant runs in a child process on a pair written by ``python -m bench.tiled
--write-pair DIR POINTS`` (five-station warehouse, float32 binary PLY):

* ``streamed``: :func:`app.core.tiling.streamed.compare_streamed` (files read in chunks, the
  stages on subsamples, the crops written from the chunks, the merge range by range);
* ``lean``: what ``scandiff compare`` runs on a pair over its budget today (both clouds read
  lean, :func:`app.core.tiling.lean.read_pair`, then
  :func:`app.core.tiling.compare.compare_tiled`).

``--parent-only`` replaces localisation by a stand-in tile runner that reads each tile's crop
and labels its core points unchanged: what is left is the parent's own work (read, origins,
registration, stations, plan, crops, merge, detection), whose memory must not grow with the
pair beyond the subsamples.  Without it the tiles are localised in the same process in turn
(the CLI's way).

Printed per variant: CPU seconds (the child's, ``os.wait4``), peak RSS (``VmHWM``), the peak of
each stretch between progress reports (``VmHWM`` reset at each), the tiles, and a digest of the
labels (equal digests: identical labels).

Run: ``python -m bench.big100 --pair-dir /tmp/bigdata/4M --memory-budget 2.5G
[--parent-only] [--variants streamed,lean] [--crop-points N]`` (the work files go to the
system's temporary directory, ``TMPDIR``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

PROJECT_ROOT = Path(__file__).resolve().parents[1]


def _rss_bytes(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no {field} in /proc/self/status")


def _budget_bytes(budget: str) -> int:
    return round(float(budget.rstrip("GMK")) * 1024 ** ("KMG".index(budget[-1]) + 1))


def unchanged_tiles(
    plan: Any, source: Any, context: Any, threads: int, report: Any, *, directory: Path
) -> list:
    """A stand-in tile runner: each tile's crop read, its core points labelled unchanged, the
    result saved to a file and read back when merged (as the job's runner does)."""
    from app.core.tiling import TileResult
    from app.core.tiling.pair_files import StoredTileResults
    from app.core.tiling.tile import REGION_FIELDS

    del threads
    directory.mkdir(parents=True, exist_ok=True)
    results = []
    for tile_index in range(plan.n_tiles):
        crop = source.crop(plan, tile_index, context)
        cores = [
            plan.in_core(tile_index, points[:, :2])
            for points in (crop.reference_points, crop.scan_points)
        ]
        regions = {name: np.zeros(0) for name in REGION_FIELDS}
        regions.update(
            uncertain=np.zeros(0, bool),
            member_in_core=np.zeros(0, bool),
            core_count=np.zeros(0, np.int64),
            member_bounds=np.zeros(1, np.int64),
            members=np.zeros(0, np.int64),
            core_sum=np.zeros((0, 3)),
            core_min=np.zeros((0, 3)),
            core_max=np.zeros((0, 3)),
        )
        results.append(directory / f"tile-{tile_index:05d}.npz")
        TileResult(
            tile_index=tile_index,
            reference_index=crop.reference_index[cores[0]],
            scan_index=crop.scan_index[cores[1]],
            reference_label=np.zeros(int(cores[0].sum()), np.int8),
            scan_label=np.zeros(int(cores[1].sum()), np.int8),
            reference_distance=np.zeros(int(cores[0].sum()), np.float32),
            scan_distance=np.zeros(int(cores[1].sum()), np.float32),
            regions=regions,
            figures={"localised": True, "crop_points": len(crop.reference_index)},
        ).save(results[-1])
        report("localise", 0.35 + 0.5 * (tile_index + 1) / plan.n_tiles)
    return StoredTileResults(results)  # type: ignore[return-value]


def _child(
    variant: str, pair_dir: Path, budget: str, parent_only: bool, crop_points: int | None
) -> None:
    """One variant in this process; prints one JSON line."""
    from app.core.formats import read_point_cloud
    from app.core.tiling.compare import compare_tiled
    from app.core.tiling.lean import read_pair
    from app.core.tiling.streamed import compare_streamed
    from app.kit.allocator import release_freed_memory_promptly

    release_freed_memory_promptly()  # as the command and the workers do
    stretches: list[dict[str, Any]] = []
    last = {"started": time.perf_counter(), "cpu": time.process_time()}

    def stretch(stage: str, fraction: float = 0.0) -> None:
        stretches.append(
            {
                "before": f"{stage} {fraction:.2f}",
                "peak_mb": round(_rss_bytes("VmHWM") / 1024**2),
                "cpu_s": round(time.process_time() - last["cpu"], 1),
            }
        )
        last["cpu"] = time.process_time()
        Path("/proc/self/clear_refs").write_text("5")

    budget_bytes = _budget_bytes(budget)
    paths = [pair_dir / "reference.ply", pair_dir / "scan.ply"]
    options: dict[str, Any] = {
        "budget_bytes": budget_bytes,
        "progress": stretch,
        "max_crop_points": crop_points,
    }
    with tempfile.TemporaryDirectory(prefix="big100-") as work_dir:
        if parent_only:
            options["run_tiles"] = partial(unchanged_tiles, directory=Path(work_dir) / "stand-in")
        stretch("start")
        if variant == "streamed":
            result = compare_streamed(*paths, work_dir=work_dir, **options)
        else:
            reference, scan, offset = read_pair(
                paths[0],
                paths[1],
                lambda side: read_point_cloud(pair_dir / f"{side}.ply"),
                budget_bytes,
            )
            stretch("read")
            result = compare_tiled(reference, scan, frame_offset=offset, **options)
        digest = hashlib.sha256()
        for name in ("reference_label", "scan_label"):
            digest.update(np.ascontiguousarray(getattr(result, name)).tobytes())
        np.savez(
            _labels_file(variant),
            reference=np.asarray(result.reference_label),
            scan=np.asarray(result.scan_label),
        )
        stretch("end")
        print(
            json.dumps(
                {
                    "variant": variant,
                    "tiles": result.localisation["tiles"]["count"],
                    "points": [int(result.n_reference), int(result.n_scan)],
                    "regions": [(region.kind, region.n_points) for region in result.regions],
                    "labels_sha256": digest.hexdigest()[:16],
                    "stretches": stretches,
                }
            ),
            flush=True,
        )


def _labels_file(variant: str) -> Path:
    """Where a variant's child leaves its labels for the comparison of the variants (one
    file per run of the bench: ``BIG100_RUN``, the main process's id, set for its children)."""
    run = os.environ.get("BIG100_RUN", str(os.getpid()))
    return Path(tempfile.gettempdir()) / f"big100-{run}-{variant}-labels.npz"


def changed_iou(first: str, second: str) -> dict[str, float]:
    """IoU of the changed points of two variants' labels, and their share of equal labels."""
    figures = {}
    with np.load(_labels_file(first)) as one, np.load(_labels_file(second)) as other:
        for side in ("reference", "scan"):
            ours, theirs = one[side] == 1, other[side] == 1
            union = np.count_nonzero(ours | theirs)
            both = np.count_nonzero(ours & theirs)
            figures[f"{side}_iou"] = 1.0 if union == 0 else round(both / union, 4)
            figures[f"{side}_equal"] = round(float(np.mean(one[side] == other[side])), 5)
    return figures


def run_variant(
    variant: str, pair_dir: Path, budget: str, parent_only: bool, crop_points: int | None
) -> dict[str, Any]:
    """A variant in a child process: its JSON line, CPU seconds and peak RSS (``os.wait4``)."""
    command = [sys.executable, "-m", "bench.big100", "--child", variant]
    command += ["--pair-dir", str(pair_dir), "--memory-budget", budget]
    command += ["--parent-only"] if parent_only else []
    command += ["--crop-points", str(crop_points)] if crop_points else []
    started = time.perf_counter()
    environment = {**os.environ, "BIG100_RUN": str(os.getpid())}
    with subprocess.Popen(
        command, stdout=subprocess.PIPE, text=True, cwd=PROJECT_ROOT, env=environment
    ) as child:
        output = child.stdout.read() if child.stdout else ""
        _, status, usage = os.wait4(child.pid, 0)
        child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode:
        raise SystemExit(f"{variant} failed (exit {child.returncode})")
    report = json.loads(output.strip().splitlines()[-1])
    peaks = [stretch["peak_mb"] for stretch in report["stretches"]]
    report.update(
        cpu_s=round(usage.ru_utime + usage.ru_stime, 1),
        # VmHWM is reset at each stretch (ru_maxrss with it): the peak is the largest stretch's
        peak_rss_mb=max([round(usage.ru_maxrss / 1024), *peaks]),
        wall_s=round(time.perf_counter() - started, 1),
    )
    return report


def main() -> None:
    """Run the variants and print their figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pair-dir", type=Path, required=True)
    parser.add_argument("--memory-budget", default="2.5G")
    parser.add_argument("--parent-only", action="store_true")
    parser.add_argument("--variants", default="streamed,lean")
    parser.add_argument("--crop-points", type=int, help="points a crop may hold (not the budget's)")
    parser.add_argument("--child", choices=["streamed", "lean"])
    args = parser.parse_args()
    if args.child:
        _child(args.child, args.pair_dir, args.memory_budget, args.parent_only, args.crop_points)
        return
    reports = [
        run_variant(variant, args.pair_dir, args.memory_budget, args.parent_only, args.crop_points)
        for variant in args.variants.split(",")
    ]
    for report in reports:
        print(json.dumps(report))
    print("| variant | points | tiles | CPU s | peak RSS MB | labels sha256 | regions |")
    for report in reports:
        print(
            f"| {report['variant']} | {sum(report['points']):,} | {report['tiles']} | "
            f"{report['cpu_s']} | {report['peak_rss_mb']:,} | {report['labels_sha256']} | "
            f"{report['regions'][:3]} |"
        )
    if len(reports) == 2:
        first, second = reports
        cpu = first["cpu_s"] / second["cpu_s"]
        print(
            f"{first['variant']} / {second['variant']}: CPU {cpu:.2f}x, "
            f"peak RSS {first['peak_rss_mb'] / second['peak_rss_mb']:.2f}x, labels "
            f"{'identical' if first['labels_sha256'] == second['labels_sha256'] else 'differ'}"
        )
        print("changed points:", changed_iou(first["variant"], second["variant"]))
    for report in reports:
        _labels_file(report["variant"]).unlink(missing_ok=True)


if __name__ == "__main__":
    main()
