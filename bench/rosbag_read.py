"""Reading a ROS bag as a scan: time and peak Python memory of ``read_point_cloud`` on a bag.

    .venv/bin/python -m bench.rosbag_read                       # 60 sweeps of 5,760 points
    .venv/bin/python -m bench.rosbag_read --sweeps 60 --azimuth-step 0.5 --storage mcap

Writes a bag (``app/testing/bags.py``: a 16-ring lidar on a robot driving through a box room,
poses on ``/tf``) in a temporary directory, then reads it ``--repeat`` times and prints the bag
size, raw points, map points, the median wall time, raw points per second and the peak memory
tracemalloc saw during one read (numpy buffers included). The map is voxel-thinned a chunk of
sweeps at a time, so memory follows the map and one chunk, not the raw points.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
import tracemalloc
from pathlib import Path

from app.core.formats import BagOptions, read_point_cloud
from app.testing.bags import write_lidar_bag


def main() -> None:
    """Write one bag, read it, print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--storage", choices=("bag", "db3", "mcap"), default="bag")
    parser.add_argument("--sweeps", type=int, default=60, help="sweeps (at most 200)")
    parser.add_argument("--azimuth-step", type=float, default=1.0, help="degrees (>= 0.2)")
    parser.add_argument("--voxel-size", type=float, default=0.05, help="metres")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    sweeps = min(max(args.sweeps, 2), 200)
    step = max(args.azimuth_step, 0.2)
    with tempfile.TemporaryDirectory() as directory:
        written = write_lidar_bag(
            Path(directory), args.storage, n_sweeps=sweeps, period=6.0 / sweeps,
            azimuth_step_deg=step,
        )  # fmt: skip
        options = BagOptions(voxel_size=args.voxel_size)
        wall = []
        for _ in range(max(args.repeat, 1)):
            started = time.perf_counter()
            cloud = read_point_cloud(written.path, bag_options=options)
            wall.append(time.perf_counter() - started)
        tracemalloc.start()
        read_point_cloud(written.path, bag_options=options)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        median = statistics.median(wall)
        print(f"storage {args.storage}, {sweeps} sweeps, azimuth step {step} deg")
        print(f"bag size          {written.path.stat().st_size / 1e6:.1f} MB")
        print(f"raw points        {written.n_raw_points:,}")
        print(f"map points        {len(cloud):,} (voxel {args.voxel_size} m)")
        print(
            f"read wall median  {median:.2f} s over {len(wall)} "
            f"({written.n_raw_points / median / 1e6:.2f} M raw points/s)"
        )
        print(f"read peak memory  {peak / 1e6:.0f} MB (tracemalloc)")


if __name__ == "__main__":
    main()
