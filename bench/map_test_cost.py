"""What the map test costs at ~1M points a map (issue 29: the new tests add <= 20 % to a compare).

The swept warehouse aisle of :mod:`bench.trajectory_cost` (two epochs of a spinning lidar moved
along different paths, merged, about ``--points`` points a map; one box removed, one added) is
compared without trajectories, nothing given, two ways, alternately and ``--repeats`` times
each, in one process: with the default origin-free test (``auto``: the map test of
:mod:`app.core.localise.map_evidence`) and with the older coverage test
(``origin_free_test="coverage"``, the default before issue 29).  Printed per way: the median
CPU time of the compare (one thread: steady on a shared machine), the ratio to the older
path, the localise stage's wall time, the test each side got, and the IoU of changed points
against the truth.

Run: ``OMP_NUM_THREADS=1 python -m bench.map_test_cost [--points 1000000] [--repeats 1]``.
Writes nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

from bench.trajectory_cost import cpu_per_way, figures_per_way, pair

WAYS = {
    "coverage (older path)": {"localisation": {"origin_free_test": "coverage"}},
    "maps (default)": None,
}


def main() -> None:
    """Print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()
    started = time.perf_counter()
    scene = pair(args.points)
    reference, scan = (
        dataclasses.replace(scene[side], trajectory=None) for side in ("reference", "scan")
    )
    print(
        f"pair: reference {len(reference):,} points, scan {len(scan):,} points (built in "
        f"{time.perf_counter() - started:.1f} s); load {os.getloadavg()[0]:.1f}",
        flush=True,
    )
    given = {
        name: {"reference": reference, "scan": scan, "params": params}
        for name, params in WAYS.items()
    }
    cpu, last = cpu_per_way(given, args.repeats)
    base = cpu["coverage (older path)"]
    for name, way in figures_per_way(cpu, last, scene).items():
        print(
            f"{name:<22} CPU {way.seconds:6.1f} s (x{way.seconds / base:.3f} of the older path)  "
            f"localise wall {way.result.timings['localise']:5.1f} s  tests {way.tests:<13} "
            f"IoU {way.iou:.3f} (missed {way.missed}, false {way.false})  "
            f"regions {len(way.result.regions)}"
        )
    print(f"load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
