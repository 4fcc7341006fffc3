"""Ingest speed of ``bench/perf.py``: upload check and float64 load against ``numpy.fromfile``.

The same ray-cast cloud is written as binary PLY, binary PCD and LAZ (millimetre scale); each
file is flushed to disk (no writeback competes with the timed reads) and read once to warm the
page cache, then ``read_point_cloud`` and ``numpy.fromfile`` of the
file's bytes (the floor: no parsing) are timed alternately, ``repeats`` times each (alternating
keeps both under the same machine load). The share of the floor's speed uses the best times
(the least disturbed); the median times and their share are reported too.

Two readers are timed. ``summarise_point_cloud`` is what the service runs on every upload
before accepting it (the same parsing and checks as a read, the point count, the dropped
non-finite rows and the bounds, a block at a time in the file's float32, no float64 copy):
the ``*_upload_check`` figures. ``read_point_cloud`` loads the cloud the core computes on (a
job's load stage): it must also widen float32 coordinates to float64, i.e. write twice as many
bytes (24 MB for 1M points) as the floor does, into fresh pages the kernel first zeroes.

``read_point_cloud`` runs with its default thread budget (``threads``: for the PLY/PCD
widening two while the 1-minute load average leaves a core idle, else one; for LAZ every usable
CPU; ``OMP_NUM_THREADS`` overrides both) and, in the same rotation,
with one thread (the ``*_one_thread`` figures), so the single-threaded speed against the
single-threaded floor stays visible. ``load_average`` and ``threads`` are taken when the
format's timings start.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pypcd4
from numpy.typing import NDArray

from app.core.blocks import conversion_threads
from app.core.datasets.scenes import raycast_scene
from app.core.formats import read_point_cloud, summarise_point_cloud
from app.core.threads import available_threads
from bench.perf_workers import SCENE_SEED, write_binary_ply


def write_pcd(path: Path, points: NDArray[np.float64]) -> None:
    """A binary PCD with float32 x, y, z."""
    pypcd4.PointCloud.from_xyz_points(points.astype(np.float32)).save(str(path))


def write_laz(path: Path, points: NDArray[np.float64]) -> None:
    """A LAZ 1.2 file, point format 3, millimetre scale."""
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = points.min(axis=0)
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.write(str(path), do_compress=True)


def best_seconds(action: Callable[[], object], repeats: int) -> float:
    """Fastest of ``repeats`` timed calls of ``action``."""
    return min(timed_seconds(action, repeats))


def timed_seconds(action: Callable[[], object], repeats: int) -> list[float]:
    """Seconds of each of ``repeats`` calls of ``action``."""
    timings = []
    for _ in range(repeats):
        started = time.perf_counter()
        action()
        timings.append(time.perf_counter() - started)
    return timings


def rotate_seconds(actions: list[Callable[[], object]], repeats: int) -> list[list[float]]:
    """Seconds of ``repeats`` calls of each action, the actions taking turns."""
    times: list[list[float]] = [[] for _ in actions]
    for _ in range(repeats):
        for action, action_times in zip(actions, times, strict=True):
            action_times += timed_seconds(action, 1)
    return times


def measure_ingest(work_dir: Path, n_points: int, repeats: int = 3) -> dict[str, dict[str, Any]]:
    """Per format: file size, read and fromfile seconds (best and median), share of fromfile
    speed (best and median), MB/s and points/s (best); the same read figures with one thread
    (``*_one_thread``) and for the upload check (``*_upload_check``), the default thread count
    and the 1-minute load average."""
    points = raycast_scene(n_points=n_points, change="none", random_state=SCENE_SEED).reference
    ingest_dir = work_dir / "ingest"
    ingest_dir.mkdir(parents=True, exist_ok=True)
    writers = {"ply": write_binary_ply, "pcd": write_pcd, "laz": write_laz}
    results: dict[str, dict[str, Any]] = {}
    for name, writer in writers.items():
        path = ingest_dir / f"cloud.{name}"
        writer(path, points)
        _flush_to_disk(path)  # no writeback of the new file while the reads are timed
        cloud = read_point_cloud(path)  # warm the page cache and check the content
        if len(cloud) != len(points):
            raise RuntimeError(f"{name}: read {len(cloud)} of {len(points)} points")
        load_average = os.getloadavg()[0]
        # What the default read uses now: LAZ every usable CPU, the widening follows the load.
        threads = available_threads() if name == "laz" else conversion_threads()
        # Each read follows a fromfile (as in the two-way rotation before the one-thread
        # read was added): a read right after another finds its output memory hot in cache.
        timings = rotate_seconds(
            [
                lambda path=path: read_point_cloud(path),
                lambda path=path: np.fromfile(path, dtype=np.uint8),
                lambda path=path: read_point_cloud(path, threads=1),
                lambda path=path: np.fromfile(path, dtype=np.uint8),
                lambda path=path: summarise_point_cloud(path),
                lambda path=path: np.fromfile(path, dtype=np.uint8),
            ],
            repeats,
        )
        read_times, one_thread_times, check_times = timings[0], timings[2], timings[4]
        fromfile_times = timings[1] + timings[3] + timings[5]
        megabytes = path.stat().st_size / 1e6
        results[name] = {
            "megabytes": megabytes,
            "threads": threads,
            "load_average": load_average,
            **_read_figures(read_times, fromfile_times, megabytes, len(points), ""),
            **_read_figures(
                one_thread_times, fromfile_times, megabytes, len(points), "_one_thread"
            ),
            **_read_figures(check_times, fromfile_times, megabytes, len(points), "_upload_check"),
        }
    return results


def _flush_to_disk(path: Path) -> None:
    """Write the file's dirty pages out now (they stay in the page cache)."""
    with open(path, "rb") as file:
        os.fsync(file.fileno())


def _read_figures(
    read_times: list[float],
    fromfile_times: list[float],
    megabytes: float,
    n_points: int,
    suffix: str,
) -> dict[str, float]:
    """Best and median read seconds, their share of the floor's speed, MB/s and points/s."""
    read_seconds, fromfile_seconds = min(read_times), min(fromfile_times)
    read_median, fromfile_median = np.median(read_times), np.median(fromfile_times)
    figures = {
        "read_seconds": read_seconds,
        "fromfile_seconds": fromfile_seconds,
        "share_of_fromfile": fromfile_seconds / read_seconds,
        "read_seconds_median": float(read_median),
        "fromfile_seconds_median": float(fromfile_median),
        "share_of_fromfile_median": float(fromfile_median / read_median),
        "mb_per_second": megabytes / read_seconds,
        "points_per_second": n_points / read_seconds,
    }
    if suffix:  # the floor's own figures are reported once
        del figures["fromfile_seconds"], figures["fromfile_seconds_median"]
    return {f"{key}{suffix}": value for key, value in figures.items()}


def memory_figures(path: Path, small: Path) -> dict[str, dict[str, float]]:
    """Seconds and peak-RSS growth of one ``summarise_point_cloud`` and one ``read_point_cloud``
    (1 thread) of ``path``, each in a fresh process that first reads ``small``, a small file of
    the same format, so that the readers' own imports are not counted; the peak is then reset
    through ``/proc/self/clear_refs`` (Linux) and compared with the resident set."""
    import subprocess
    import sys

    script = (
        "import json, sys, time\n"
        "from app.core import formats\n"
        "def status_mb(field):\n"
        "    for line in open('/proc/self/status'):\n"
        "        if line.startswith(field + ':'):\n"
        "            return int(line.split()[1]) / 1024\n"
        "reader = getattr(formats, sys.argv[1])\n"
        "reader(sys.argv[3], threads=1)  # the readers' own imports, on a small file\n"
        "with open('/proc/self/clear_refs', 'w') as refs:\n"
        "    refs.write('5')  # VmHWM := VmRSS: the peak from here on\n"
        "before = status_mb('VmRSS')\n"
        "started = time.perf_counter()\n"
        "reader(sys.argv[2], threads=1)\n"
        "seconds = time.perf_counter() - started\n"
        "growth = status_mb('VmHWM') - before\n"
        "print(json.dumps({'seconds': seconds, 'peak_rss_growth_mb': growth}))\n"
    )
    figures = {}
    for reader in ("summarise_point_cloud", "read_point_cloud"):
        completed = subprocess.run(
            [sys.executable, "-c", script, reader, str(path), str(small)],
            capture_output=True,
            text=True,
            check=True,
            cwd=Path(__file__).resolve().parent.parent,
        )
        figures[reader] = json.loads(completed.stdout)
    return figures


def main() -> None:
    """``python -m bench.perf_ingest``: the ingest figures alone, in a fresh quiet process."""
    import argparse
    import tempfile

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=40, help="rounds of the rotation")
    parser.add_argument(
        "--memory",
        action="store_true",
        help="instead: time and peak-RSS growth of one upload check and one load of a binary "
        "PLY and a LAZ of --points random points, each in a fresh process",
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as directory:
        if args.memory:
            points = np.random.default_rng(SCENE_SEED).normal(size=(args.points, 3)) * 50.0
            for name, writer in (("ply", write_binary_ply), ("laz", write_laz)):
                path, small = Path(directory) / f"cloud.{name}", Path(directory) / f"small.{name}"
                writer(path, points)
                writer(small, points[:1000])
                _flush_to_disk(path)
                for reader, row in memory_figures(path, small).items():
                    print(
                        f"{name} {reader}: {1e3 * row['seconds']:.1f} ms, "
                        f"peak RSS +{row['peak_rss_growth_mb']:.0f} MB"
                    )
            return
        results = measure_ingest(Path(directory), args.points, repeats=args.repeats)
    for name, row in results.items():
        print(
            f"{name}: fromfile {1e3 * row['fromfile_seconds']:.3f} ms; "
            f"upload check {1e3 * row['read_seconds_upload_check']:.3f} ms "
            f"({100 * row['share_of_fromfile_upload_check']:.1f} %, median "
            f"{100 * row['share_of_fromfile_median_upload_check']:.1f} %); "
            f"float64 load with {row['threads']} thread(s) {1e3 * row['read_seconds']:.3f} ms "
            f"({100 * row['share_of_fromfile']:.1f} %), with 1 "
            f"{1e3 * row['read_seconds_one_thread']:.3f} ms "
            f"({100 * row['share_of_fromfile_one_thread']:.1f} %); "
            f"load average {row['load_average']:.1f}"
        )


if __name__ == "__main__":
    main()
