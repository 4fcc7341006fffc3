"""What finding the sensor origins costs at 1M points a scan (issue 15: <= 15 % of a compare).

Scenes from :func:`app.core.datasets.lidar.lidar_pair` at about ``--points`` points per scan
(denser rays: :func:`~app.core.datasets.lidar.steps_for_points`): single-station pairs
(nothing given, the origins estimated) and merged surveys of 3-5 stations per epoch (nothing
given: the stations are recovered by default).  Each pair goes through
:func:`app.core.pipeline.compare` once; per pair the bench prints the compare's wall time, the
time spent on origins (``timings["origins"]``: estimation, checks and station recovery of both
clouds), their ratios (``origins / compare`` and ``origins / (compare - origins)``, what
estimation adds), the IoU of changed points and, for merged surveys, the largest distance from
a true station to the nearest recovered one.  All numbers of a row come from the same run.

The machine may be shared: run with ``OMP_NUM_THREADS=1``; the load average is printed with the
results.  A small compare runs first (:func:`warm_up_process`), so that no pair is charged
with the process's imports.  ``--profile`` prints the top of a cProfile of the origins' stage
of the first pair.
``--against-given N`` also times each pair N times with nothing given and N times with its
true origins given, alternately, on ``--threads`` threads (2 by default: as ``scandiff
compare`` runs), and prints what not giving them adds to the wall time (fastest of each, and
the ratio of the medians: on a shared machine single runs of either side vary by 10-20 %).

Run: ``OMP_NUM_THREADS=1 .venv/bin/python -m bench.origins_speed [--points 1000000]
[--seeds 1] [--kinds single,merged] [--changes added,none]``.  Writes nothing.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import time

import numpy as np

from app.core.cloud import PointCloud
from app.core.comparison import SensorOriginEntry
from app.core.comparison import origins as origins_stage
from app.core.datasets.lidar import lidar_pair, steps_for_points
from app.core.pipeline import compare
from bench.merged_stations import nearest_station_error
from bench.scenes import changed_points_iou

KINDS = ("single", "merged")
LAYOUTS = ("room", "corridor", "warehouse")


def station_error(entries: list[SensorOriginEntry], truth: np.ndarray) -> float:
    """Largest distance (m) from a true station to the nearest reported one (inf: wrong count)."""
    found = np.array([entry.origin for entry in entries]).reshape(-1, 3)
    return nearest_station_error(found, truth)


class _CpuClock:
    """Process CPU seconds spent in the pipeline's origin stages (wrapped in place).

    On a shared machine wall times stretch with the load; the CPU time of one thread does not
    (the compare runs on one thread here, so nothing else runs during these stages).
    """

    def __init__(self) -> None:
        self.seconds = 0.0

    def wrap(self, function):
        def timed(*args, **kwargs):
            started = time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                self.seconds += time.process_time() - started

        return timed


def given_origins(pair) -> dict:
    """The true sensor origins as parameters (one per station; the scan's in its file's frame)."""
    return {
        name: (origins[0] if len(origins) == 1 else origins).tolist()
        for name, origins in (
            ("reference_origin", pair.reference_origins),
            ("scan_origin", pair.scan_origins),
        )
    }


def wall_against_given(pair, threads: int, repeats: int) -> dict:
    """What not giving the origins adds to a compare's wall time, on ``threads`` threads.

    The pair is compared with nothing given and with its true origins given, alternately,
    ``repeats`` times each; the fastest of each is kept (the machine may be shared).
    """
    times: dict[str, list[float]] = {"nothing": [], "given": []}
    for _ in range(repeats):
        for name, params in (("nothing", {}), ("given", given_origins(pair))):
            started = time.perf_counter()
            compare(
                PointCloud.from_array(pair.reference),
                PointCloud.from_array(pair.scan),
                params=params,
                threads=threads,
            )
            times[name].append(time.perf_counter() - started)
    nothing, given = min(times["nothing"]), min(times["given"])
    # the median too: on a shared machine one lucky run of either side swings the fastest
    median = float(np.median(times["nothing"]) / np.median(times["given"])) - 1.0
    return {
        "wall_nothing": nothing,
        "wall_given": given,
        "adds_wall": nothing / given - 1.0,
        "adds_wall_median": median,
    }


def run_pair(pair, merged: bool, profile: bool = False) -> dict:
    """One compare with nothing given (defaults); its timings, IoU and origin errors."""
    clock = _CpuClock()
    originals = origins_stage.resolve_stations, origins_stage.resolve_moved_cloud
    origins_stage.resolve_stations = clock.wrap(originals[0])
    origins_stage.resolve_moved_cloud = clock.wrap(originals[1])
    params: dict = {}  # merged surveys: stations recovered by default (recover_stations="auto")
    profiler = cProfile.Profile() if profile else None
    started = time.perf_counter()
    cpu_started = time.process_time()
    if profiler is not None:
        profiler.enable()
    result = compare(
        PointCloud.from_array(pair.reference),
        PointCloud.from_array(pair.scan),
        params=params,
        threads=1,
    )
    origins_stage.resolve_stations, origins_stage.resolve_moved_cloud = originals
    if profiler is not None:
        profiler.disable()
        pstats.Stats(profiler).sort_stats("cumulative").print_stats(40)
    total = time.perf_counter() - started
    cpu = time.process_time() - cpu_started
    origins = result.timings.get("origins", 0.0)
    errors = [
        station_error(result.sensor_origins[side], truth)
        for side, truth in (
            ("reference", pair.reference_origins),
            # the scan file is misaligned when asked: its origins are in its own frame
            ("scan", pair.scan_origins),
        )
    ]
    return {
        "seconds": total,
        "cpu_seconds": cpu,
        "origins": origins,
        "share": origins / total,
        "adds": origins / max(total - origins, 1e-9),
        "origins_cpu": clock.seconds,
        "adds_cpu": clock.seconds / max(cpu - clock.seconds, 1e-9),
        "iou": changed_points_iou(result, pair),
        "regions": len(result.regions),
        "decided": result.changed,
        "origin_error": max(errors),
        "sources": "/".join(
            ",".join(sorted({entry.source for entry in result.sensor_origins[side]}) or "-")
            for side in ("reference", "scan")
        ),
    }


def warm_up_process() -> None:
    """Import what a compare imports and run a small one, before anything is timed.

    A comparison imports the detectors' libraries on a thread of its own
    (:func:`app.core.detectors.warm_up`, about a second of CPU): in a fresh process that
    thread runs during the first pair's origin stage and was counted as origins (the first
    pair's origins took 2.0 s of CPU instead of 0.7).  A worker pays it once, not per compare.
    """
    from app.core.detectors import warm_up

    thread = warm_up()
    if thread is not None:
        thread.join()
    pair = lidar_pair(layout="room", change="added", n_stations=3, angular_step_deg=2.0)
    compare(PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan), threads=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=1_000_000, help="points per scan")
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--kinds", default=",".join(KINDS))
    parser.add_argument("--layouts", default=",".join(LAYOUTS))
    parser.add_argument("--changes", default="added,none")
    parser.add_argument("--profile", action="store_true", help="cProfile the first compare")
    parser.add_argument(
        "--against-given",
        type=int,
        default=0,
        metavar="REPEATS",
        help="also time each pair with nothing given against its true origins given, "
        "alternately REPEATS times each on --threads threads (wall time, fastest of each)",
    )
    parser.add_argument("--threads", type=int, default=2, help="threads for --against-given")
    args = parser.parse_args()
    print(f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}", flush=True)
    warm_up_process()
    rows = []
    profile = args.profile
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        for kind in args.kinds.split(","):
            for layout in args.layouts.split(","):
                for change in args.changes.split(","):
                    merged = kind == "merged"
                    n_stations = 3 + (seed + len(layout) + len(change)) % 3 if merged else 1
                    pair = lidar_pair(
                        layout=layout,
                        change=change,
                        n_stations=n_stations,
                        angular_step_deg=steps_for_points(args.points, n_stations),
                        misaligned=bool((seed + len(change)) % 2),
                        random_state=3000 + seed,
                    )
                    row = run_pair(pair, merged, profile)
                    profile = False
                    row.update(
                        kind=kind, layout=layout, change=change, seed=seed, stations=n_stations
                    )
                    row["points"] = len(pair.reference)
                    if args.against_given:
                        row.update(wall_against_given(pair, args.threads, args.against_given))
                    rows.append(row)
                    print(
                        f"{kind:6s} {layout:9s} {change:6s} seed {seed} k={n_stations} "
                        f"n={row['points']:8d} compare {row['seconds']:6.1f} s "
                        f"(cpu {row['cpu_seconds']:6.1f} s) origins {row['origins']:5.2f} s "
                        f"= {100 * row['share']:4.1f} % of compare, adds "
                        f"{100 * row['adds']:4.1f} % (cpu {row['origins_cpu']:5.2f} s, adds "
                        f"{100 * row['adds_cpu']:4.1f} %); IoU {row['iou']:.3f} "
                        f"regions {row['regions']:3d} origin error {row['origin_error']:.4f} m "
                        f"[{row['sources']}] load {os.getloadavg()[0]:.1f}",
                        flush=True,
                    )
                    if args.against_given:
                        print(
                            f"    {args.threads} threads: nothing given "
                            f"{row['wall_nothing']:6.2f} s, origins given "
                            f"{row['wall_given']:6.2f} s: not giving them adds "
                            f"{100 * row['adds_wall']:5.1f} % (fastest of each), "
                            f"{100 * row['adds_wall_median']:5.1f} % (medians)",
                            flush=True,
                        )
    for kind in args.kinds.split(","):
        mine = [row for row in rows if row["kind"] == kind]
        if not mine:
            continue
        changed = [row["iou"] for row in mine if row["change"] != "none"]
        print(
            f"{kind}: {len(mine)} pairs; origins adds to the compare: max "
            f"{100 * max(row['adds'] for row in mine):.1f} %, mean "
            f"{100 * np.mean([row['adds'] for row in mine]):.1f} % (wall); in CPU time max "
            f"{100 * max(row['adds_cpu'] for row in mine):.1f} %, mean "
            f"{100 * np.mean([row['adds_cpu'] for row in mine]):.1f} %; IoU min (changed) "
            f"{min(changed, default=float('nan')):.3f}; largest origin error "
            f"{max(row['origin_error'] for row in mine):.4f} m; quiet regions "
            f"{sum(row['regions'] for row in mine if row['change'] == 'none')}"
        )
        if args.against_given:
            for statistic in ("adds_wall", "adds_wall_median"):
                adds = [row[statistic] for row in mine]
                label = "fastest of each" if statistic == "adds_wall" else "medians"
                print(
                    f"{kind}: nothing given against origins given, {args.threads} threads, "
                    f"wall ({label}): adds max {100 * max(adds):.1f} %, mean "
                    f"{100 * np.mean(adds):.1f} %"
                )
    print(f"load average {os.getloadavg()}")


if __name__ == "__main__":
    main()
