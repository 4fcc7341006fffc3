"""A tiled job through the real service: 1 worker against 2 on this machine (issue 30 item 3).

One pair (a robot's fused map, nothing given, written as float32 binary PLY) is compared by
``scandiff serve`` with ``--workers 1`` and then ``--workers 2``, tiles forced with
``SCANDIFF_TILE_CROP_POINTS`` (a share of both clouds' points) so they are ``run_tile``
messages on the queue.  Timed: from the POST of the scan to the job's ``succeeded`` (the
reference already stored).  Checked: both runs' labels equal the in-process tiled comparison of
the same files (:func:`app.core.tiling.compare.compare_tiled`, what ``scandiff compare`` runs
for a pair over its budget), and which worker computed each tile.

Run: ``.venv/bin/python -m bench.tiled_service [--size 1.0] [--crop-share 0.2] [--repeats 1]``.
Target (issue 30): 2 workers >= 1.7x faster than 1 on 2 cores, the result identical.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import importlib
import json
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from app.core.datasets import map_pair
from app.core.formats import read_point_cloud, write_point_cloud
from app.core.formats.streamed import declared_rows
from app.core.tiling import TileBudgetError, compute_tile
from app.core.tiling.compare import compare_tiled
from app.jobs.consumer import first_use_libraries
from bench.service_process import Service, group_peak_rss, size_settings, upload, wait_for_job

TARGET_SPEEDUP = 1.7
JOB_TIMEOUT_SECONDS = 3600.0
PHASES = (
    "load_inputs",
    "origins",
    "align",
    "plan",
    "crop_pass_inputs_write",
    "crop_passes_parent_computing",
    "crop_passes_parent_computing_cpu",
    "crop_passes_parent_waiting",
    "crop_passes_other_workers",
    "tile_inputs_write",
    "tiles_parent_computing",
    "tiles_parent_computing_cpu",
    "tiles_parent_waiting",
    "tiles_other_workers",
    "tile_results_read",
    "localise",
    "detect",
    "write_outputs",
    "write_outputs_cpu",
    "stream_survey_cpu",
    "stream_stations_cpu",
    "stream_plan_cpu",
    "stream_marks_cpu",
    "stream_crops_cpu",
    "stream_tiles_cpu",
    "stream_merge_cpu",
    "stream_other_stages_cpu",
    "job_total",
    "compute_cpu",
    "streamed_seconds",
)
"""The job's timings printed for each run (app/jobs/execution.py, app/jobs/tiles.py,
app/jobs/crop_passes.py)."""


def run_service(
    work: Path,
    workers: int,
    crop_points: int,
    files: tuple[Path, Path],
    job_threads: int | None = None,
    memory_budget: int | None = None,
    timeout: float = JOB_TIMEOUT_SECONDS,
    job_params: dict[str, Any] | None = None,
) -> dict:
    """Seconds from the scan's POST to ``succeeded``, its labels, who computed the tiles and
    the peak RSS of every process of the service (``crop_points`` 0: not forced, the tiles
    follow ``memory_budget``)."""
    data_dir = work / f"service-{workers}-workers"
    data_dir.mkdir()
    env = {"SCANDIFF_TILE_CROP_POINTS": str(crop_points)} if crop_points else {}
    env.update(size_settings(files))
    if memory_budget:
        env["SCANDIFF_WORKER_MEMORY_BUDGET_BYTES"] = str(memory_budget)
    if job_threads:  # default: the CPUs shared by the workers (1 worker: both cores)
        env["SCANDIFF_JOB_THREADS"] = str(job_threads)
    service = Service(data_dir, workers, env)
    labels_path = work / f"labels-{workers}.npz"
    with service as client:
        detector = {"detector": {"method": "gmm", "params": job_params}} if job_params else {}
        created = client.post("/api/v1/sites", json={"name": "bench", **detector})
        created.raise_for_status()
        site = created.json()
        path = f"/api/v1/sites/{site['id']}/scans"
        upload(client, path, files[0], {"reference": "true", "filename": "reference.ply"})
        print(f"reference stored ({time.strftime('%H:%M:%S')})", flush=True)
        started = time.perf_counter()
        job_id = upload(client, path, files[1], {"filename": "scan.ply"})["job"]["id"]
        print(f"scan stored, job {job_id} ({time.strftime('%H:%M:%S')})", flush=True)
        job = wait_for_job(client, job_id, service.process.pid, timeout)
        seconds = time.perf_counter() - started
        peaks = group_peak_rss(service.process.pid, with_cpu=True)
        if job["status"] != "succeeded":
            print(json.dumps({"failed": job.get("error"), "processes": peaks}), flush=True)
            raise RuntimeError(f"job failed: {job['error']}")
        with (
            client.stream(
                "GET", f"/api/v1/jobs/{job_id}/labels", params={"format": "npz"}, timeout=None
            ) as labels,
            labels_path.open("wb") as output,
        ):
            labels.raise_for_status()
            for piece in labels.iter_bytes(1 << 24):
                output.write(piece)
        regions = client.get(f"/api/v1/jobs/{job_id}/regions", params={"limit": 100}).json()
    with np.load(labels_path) as data:
        arrays = {name: data[name] for name in ("reference_label", "scan_label")}
    with sqlite3.connect(data_dir / "scandiff.sqlite3") as connection:
        tile_rows = connection.execute(
            "SELECT tile_index, lease_owner, points, seconds, started_at, finished_at"
            " FROM job_tile WHERE job_id = ? ORDER BY started_at",
            (job_id,),
        ).fetchall()
    owners = [row[1].rsplit(":", 2)[1] for row in tile_rows]
    tile_log = [  # (tile, worker pid, crop points, wall s, started, finished), as started
        (row[0], row[1].rsplit(":", 2)[1], row[2], round(row[3] or 0.0, 1), row[4], row[5])
        for row in tile_rows
    ]
    return {
        "seconds": seconds,
        "labels": arrays,
        "tiles": job["tiles"],
        "tiles_per_worker": sorted(Counter(owners).values(), reverse=True),
        "tile_log": tile_log,
        "changed": job["changed"],
        "n_regions": job["n_regions"],
        "timings": job["timings"],
        "peak_rss_mb": peaks,
        "regions": regions["items"],
        "visibility": (job.get("calibration") or {}).get("visibility"),
        "warnings": job.get("warnings"),
        "labels_path": labels_path,
    }


def truth_check(pair_dir: Path | None, run: dict) -> dict[str, Any] | None:
    """Against ``truth.npz`` of a pair written by ``bench.tiled --write-pair-streamed``: the
    share of the added box's scan points labelled changed (and unobserved), the changed
    points elsewhere, and which regions lie on the added box (centroid within 0.5 m of it)."""
    if pair_dir is None or not (pair_dir / "truth.npz").exists():
        return None
    with np.load(pair_dir / "truth.npz") as truth, np.load(run["labels_path"]) as labels:
        rows = truth["scan_changed_rows"]
        scan_label = labels["scan_label"]
        reference_changed = int(np.count_nonzero(labels["reference_label"] == 1))
        known = {tuple(low) for low in truth["reference_box_low"]}
        added = [
            (low, high)
            for low, high in zip(truth["scan_box_low"], truth["scan_box_high"], strict=True)
            if tuple(low) not in known
        ]
        hits = int(np.count_nonzero(scan_label[rows] == 1))
        figures = {
            "added_box_points": len(rows),
            "added_box_seen_by_reference": int(truth["scan_changed_observed"].sum()),
            "labelled_changed": hits,
            "labelled_unobserved": int(np.count_nonzero(scan_label[rows] == -1)),
            "scan_changed_elsewhere": int(np.count_nonzero(scan_label == 1)) - hits,
            "reference_changed": reference_changed,
            "truth_reference_changed": len(truth["reference_changed_rows"]),
        }
    on_box = []
    for region in run["regions"]:
        centre = np.asarray(region["centroid"])
        if any(np.all((centre > low - 0.5) & (centre < high + 0.5)) for low, high in added):
            on_box.append((region["kind"], region["n_points"]))
    figures["regions_on_added_box"] = on_box
    return figures


def cli_labels(files: tuple[Path, Path], work: Path, memory_budget: int) -> dict:
    """``scandiff compare --labels`` of the pair under ``memory_budget``: its labels."""
    labels = work / "labels-cli.npz"
    command = [sys.executable, "-m", "app", "compare", str(files[0]), str(files[1])]
    command += ["--labels", str(labels), "--memory-budget", str(memory_budget), "--json"]
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    with np.load(labels) as data:
        return {name: data[name] for name in ("reference_label", "scan_label")}


class PhaseClock:
    """CPU seconds of each phase of one in-process ``compare_tiled`` (one thread).

    Phases are cut at its progress reports (``align`` after the reference's origins,
    ``localise`` 0.35 after registration and the scan's origins, ``detect`` after the merge,
    ``done`` after detection and the decision) and at the tile runner's start and end, which
    also times each tile.
    """

    def __init__(self) -> None:
        self.cpu: dict[str, float] = {}
        self.tiles: list[float] = []
        self._mark = time.process_time()

    def restart(self) -> None:
        """Forget every phase after reading the files (the comparison runs again)."""
        self.cpu = {"read both files": self.cpu["read both files"]}
        self.tiles, self._mark = [], time.process_time()

    def lap(self, phase: str) -> None:
        """Charge the CPU seconds since the last lap to ``phase``."""
        now = time.process_time()
        self.cpu[phase] = self.cpu.get(phase, 0.0) + now - self._mark
        self._mark = now

    def progress(self, stage: str, fraction: float) -> None:
        """``compare_tiled``'s progress callback."""
        ended = {"align": "reference origins", "detect": "merge", "done": "detect + decide"}
        if stage == "localise" and fraction == 0.35:
            self.lap("registration + scan origins")
        elif stage in ended:
            self.lap(ended[stage])

    def run_tiles(self, plan: Any, source: Any, context: Any, threads: int, report: Any) -> list:
        """Every tile in turn, each timed (the default runner's work)."""
        self.lap("tile inputs + plan")
        results = []
        for tile_index in range(plan.n_tiles):
            started = time.process_time()
            results.append(compute_tile(plan, tile_index, source, context, threads=threads))
            self.tiles.append(time.process_time() - started)
        self.lap("tiles")
        return results


def amdahl(serial: float, tiles: list[float], workers: int) -> float:
    """Best speed-up of ``workers`` over one: serial part plus the tiles packed largest first."""
    loads = [0.0] * workers
    for seconds in sorted(tiles, reverse=True):
        loads[loads.index(min(loads))] += seconds
    return (serial + sum(tiles)) / (serial + max(loads))


def print_phases(clock: PhaseClock, total_points: int, crop_points: int) -> None:
    """The phases' CPU seconds, the serial share and the 2-worker bound."""
    serial = sum(seconds for phase, seconds in clock.cpu.items() if phase != "tiles")
    whole = serial + sum(clock.tiles)
    print(
        f"In-process tiled comparison, one thread, {total_points:,} points, crops of at most "
        f"{crop_points:,} points (CPU s):\n"
    )
    print("| phase | CPU s | share |\n|---|---|---|")
    for phase, seconds in clock.cpu.items():
        print(f"| {phase} | {seconds:.1f} | {seconds / whole:.0%} |")
    print(
        f"\n{len(clock.tiles)} tiles: {min(clock.tiles):.2f}-{max(clock.tiles):.2f} s each; "
        f"serial share {serial / whole:.0%}; Amdahl bound for 2 workers "
        f"{amdahl(serial, clock.tiles, 2):.2f}x (the service adds writing the tiles' inputs "
        "and reading their results)\n"
    )


def parent_cpu_split(timings: dict[str, float]) -> dict[str, float]:
    """The parent's CPU seconds: ``serial`` (the job's CPU and its result files' writing, less
    the tiles it computed), ``tiles_here`` and, of the serial part, each streamed phase
    (``stream_*_cpu`` in the job's timings)."""
    tiles_here = timings.get("tiles_parent_computing_cpu", 0.0)
    serial = timings.get("compute_cpu", 0.0) + timings.get("write_outputs_cpu", 0.0) - tiles_here
    split = {"serial": serial, "tiles_here": tiles_here}
    for name, seconds in timings.items():
        if name.startswith("stream_") and name.endswith("_cpu") and name != "stream_tiles_cpu":
            split[name.removeprefix("stream_").removesuffix("_cpu")] = seconds
    split["write_outputs"] = timings.get("write_outputs_cpu", 0.0)
    split["crop_passes_here"] = timings.get("crop_passes_parent_computing_cpu", 0.0)
    return {name: round(seconds, 1) for name, seconds in split.items()}


def cpu_speedup(one: dict[str, float], two: dict[str, float]) -> float:
    """2 workers against 1 on an idle 2-core machine, from CPU seconds (one thread a job).

    The 1-worker job's CPU is its whole time; with 2 workers the job ends when the later of
    the parent (its serial part and its tiles) and the serial part plus the other worker's
    tiles (every tile's CPU, from the 1-worker run, less the parent's) ends.  The crops pass
    runs on both workers at once (one cloud's pass each): the parent waits for the other's
    pass when it is the longer (its CPU: both passes from the 1-worker run, less the
    parent's).  Wall seconds on a loaded machine measure the scheduler's shares; these do not.
    """
    serial = two["compute_cpu"] - two["tiles_parent_computing_cpu"]
    others = one["tiles_parent_computing_cpu"] - two["tiles_parent_computing_cpu"]
    passes_here = two.get("crop_passes_parent_computing_cpu", 0.0)
    other_pass = one.get("crop_passes_parent_computing_cpu", 0.0) - passes_here
    waiting = max(0.0, other_pass - passes_here)
    return one["compute_cpu"] / max(two["compute_cpu"] + waiting, serial + waiting + others)


def pair_files(work: Path, arguments: argparse.Namespace) -> tuple[Path, Path]:
    """``reference.ply`` and ``scan.ply``: from ``--pair-dir``, or a robot map written here."""
    if arguments.pair_dir is not None:
        return arguments.pair_dir / "reference.ply", arguments.pair_dir / "scan.ply"
    pair = map_pair(
        "robot",
        layout=arguments.layout,
        change="removed",
        size=arguments.size,
        random_state=arguments.seed,
    )
    files = (work / "reference.ply", work / "scan.ply")
    for path, cloud in zip(files, (pair.reference, pair.scan), strict=True):
        write_point_cloud(path, cloud.points.astype(np.float32))
    return files


def main(argv: list[str] | None = None) -> int:
    """Print the markdown section of the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--layout", default="warehouse", help="robot map layout (warehouse: widest)"
    )
    parser.add_argument("--size", type=float, default=1.0, help="map_pair size (rays cast)")
    parser.add_argument("--crop-share", type=float, default=0.2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--job-threads",
        type=int,
        default=None,
        help="threads a job may use in both runs (default: CPUs / workers, so one worker "
        "already uses both cores)",
    )
    parser.add_argument(
        "--pair-dir",
        type=Path,
        default=None,
        help="compare DIR/reference.ply and DIR/scan.ply instead of a robot map (e.g. the "
        "merged-station pair bench.tiled writes)",
    )
    parser.add_argument(
        "--phases-only",
        action="store_true",
        help="only the in-process comparison's CPU seconds per phase (no service)",
    )
    parser.add_argument(
        "--no-check",
        action="store_true",
        help="skip the in-process comparison (its phases and the labels check): the share "
        "is used as given and the 2 workers' labels are checked against the 1 worker's",
    )
    parser.add_argument(
        "--memory-budget",
        type=int,
        default=None,
        help="SCANDIFF_WORKER_MEMORY_BUDGET_BYTES of the service (bytes); with --crop-share 0 "
        "the tiles follow it, and --check-cli compares the labels with the command's",
    )
    parser.add_argument("--workers", default="1,2", help="the runs' worker counts")
    parser.add_argument(
        "--job-timeout",
        type=float,
        default=JOB_TIMEOUT_SECONDS,
        help="seconds a job may take before the run gives up (a 100M pair: hours)",
    )
    parser.add_argument(
        "--job-params",
        default=None,
        help="the site's detector params (JSON), e.g. '{\"recover_stations\": false}'",
    )
    parser.add_argument(
        "--work-dir",
        type=Path,
        default=None,
        help="keep the services' data directories, logs and labels here (default: a "
        "temporary directory, removed)",
    )
    parser.add_argument(
        "--check-cli",
        action="store_true",
        help="compare the runs' labels with `scandiff compare --memory-budget` of the files",
    )
    arguments = parser.parse_args(argv)

    with contextlib.ExitStack() as stack:
        if arguments.work_dir is None:
            work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="tiled-service-")))
        else:
            work = arguments.work_dir
            work.mkdir(parents=True, exist_ok=True)
        files = pair_files(work, arguments)
        for library in first_use_libraries():  # loaded before the jobs, as a worker does
            importlib.import_module(library)
        clock = PhaseClock()
        if arguments.no_check:  # counted from the headers: a 100M pair is never read here
            clouds = []
            total = sum(declared_rows(path) or 0 for path in files)
        else:
            clouds = [read_point_cloud(path) for path in files]
            total = sum(len(cloud) for cloud in clouds)
        clock.lap("read both files")
        share = arguments.crop_share
        expected, in_process = None, float("nan")
        if arguments.no_check:  # the share as given; the runs' labels checked against each other
            crop_points = int(share * total)
        else:
            while True:  # the smallest share from --crop-share whose tiles hold their margins
                crop_points = int(share * total)
                started = time.perf_counter()
                try:
                    expected = compare_tiled(
                        *clouds,
                        budget_bytes=1 << 40,
                        max_crop_points=crop_points,
                        threads=1,
                        progress=clock.progress,
                        run_tiles=clock.run_tiles,
                    )
                    break
                except TileBudgetError:
                    share += 0.05
                    clock.restart()
            in_process = time.perf_counter() - started
            print_phases(clock, total, crop_points)
        del clouds
        if arguments.phases_only:
            return 0
        runs = {}
        for workers in map(int, arguments.workers.split(",")):
            runs[workers] = run = run_service(
                work,
                workers,
                crop_points,
                files,
                arguments.job_threads,
                arguments.memory_budget,
                arguments.job_timeout,
                json.loads(arguments.job_params) if arguments.job_params else None,
            )
            # at once, so a long --check-cli after it cannot lose the run's figures
            print(f"{workers} worker(s): {run['seconds']:.1f} s, timings {run['timings']}")
            print(f"  parent CPU split {parent_cpu_split(run['timings'])}", flush=True)
        for run in runs.values():  # while the labels files are still there
            run["truth"] = truth_check(arguments.pair_dir, run)
        if arguments.check_cli:
            cli = cli_labels(files, work, arguments.memory_budget)
            for workers, run in runs.items():
                same = all(np.array_equal(run["labels"][name], cli[name]) for name in cli)
                verdict = "identical to" if same else "DIFFER from"
                print(f"{workers} worker(s): labels {verdict} the CLI's")

    first = next(iter(runs.values()))
    pair_name = (
        f"{arguments.pair_dir}"
        if arguments.pair_dir is not None
        else f"robot map ({arguments.layout}), size {arguments.size}"
    )
    print(f"## Tiled job through the service ({time.strftime('%Y-%m-%d %H:%M')})\n")
    print(
        f"Pair: {pair_name}, {total:,} points in both clouds; tiles of at "
        f"most {crop_points:,} points ({first['tiles']['total']} tiles); "
        f"in-process tiled comparison {in_process:.1f} s; job threads "
        f"{arguments.job_threads or 'CPUs / workers'}.\n"
    )
    against = "in-process" if expected is not None else "1 worker's"
    print(f"| workers | upload to succeeded s | tiles | tiles per worker | labels = {against} |")
    print("|---|---|---|---|---|")
    for workers, run in runs.items():
        same = all(
            np.array_equal(
                run["labels"][name],
                first["labels"][name] if expected is None else getattr(expected, name),
            )
            for name in ("reference_label", "scan_label")
        )
        print(
            f"| {workers} | {run['seconds']:.1f} | {run['tiles']['done']}/{run['tiles']['total']}"
            f" | {run['tiles_per_worker']} | {'yes' if same else 'NO'} |"
        )
    print("\nThe parent's job timings (wall s; `_cpu`: its CPU s):\n")
    for workers, run in runs.items():
        shown = {key: round(value, 1) for key, value in run["timings"].items() if key in PHASES}
        print(f"- {workers} worker(s): {shown}")
    print("\nThe parent's CPU s: serial (all but the tiles it computed) and its tiles:\n")
    for workers, run in runs.items():
        print(f"- {workers} worker(s): {parent_cpu_split(run['timings'])}")
    print("\nTiles as they started (index, worker pid, crop points, wall s, started, finished):\n")
    for workers, run in runs.items():
        print(f"- {workers} worker(s): {run['tile_log']}")
    print("\nPeak RSS (VmHWM, MB) of the service's processes, and the labels' digest:\n")
    for workers, run in runs.items():
        digest = hashlib.sha256()
        for name in ("reference_label", "scan_label"):  # as bench.big100 digests them
            digest.update(np.ascontiguousarray(run["labels"][name]).tobytes())
        print(f"- {workers} worker(s): {run['peak_rss_mb']}, labels {digest.hexdigest()[:16]}")
    print("\nRegions, stations and the truth (`truth.npz` of the pair, when there is one):\n")
    for workers, run in runs.items():
        regions = [(region["kind"], region["n_points"]) for region in run["regions"]]
        print(f"- {workers} worker(s): changed {run['changed']}, regions {regions}")
        print(f"  visibility {json.dumps(run['visibility'])}")
        print(f"  warnings {json.dumps(run['warnings'])}")
        print(f"  truth {run['truth']}")
    if not {1, 2} <= set(runs):
        return 0
    if arguments.job_threads == 1:
        figure = cpu_speedup(runs[1]["timings"], runs[2]["timings"])
        print(f"\nFrom CPU seconds (bench.tiled_service.cpu_speedup): {figure:.2f}x")
    speedup = runs[1]["seconds"] / runs[2]["seconds"]
    verdict = "PASS" if speedup >= TARGET_SPEEDUP else "FAIL"
    print(f"\n{verdict} 2 workers {speedup:.2f}x faster than 1 (target >= {TARGET_SPEEDUP}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
