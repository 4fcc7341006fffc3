"""What reading an E57 scan's per-point times (``timeStamp``) costs (issue 29).

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.e57_point_times --points 1000000

Writes one scan of ``--points`` points twice, without times (pye57) and with ``timeStamp``
(libE57Format, ``app.testing.e57_times``), then reads each with ``read_point_cloud`` in turn,
``--repeat`` times, and prints the best CPU seconds of each and their difference (the second
pass that reads the times and the validity flags).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from app.core.formats import read_point_cloud
from app.testing.e57_times import e57_with_times_bytes
from app.testing.files import e57_bytes


def main() -> None:
    """Print the best CPU seconds of reading each file."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    points = rng.uniform(0.0, 50.0, (args.points, 3))
    files = {
        "without times": e57_bytes([points]),
        "with timeStamp": e57_with_times_bytes(points, 100.0 + points[:, 0]),
    }
    best = {name: float("inf") for name in files}
    for _ in range(args.repeat):  # interleaved: the machine's load hits both alike
        for name, content in files.items():
            started = time.process_time()
            cloud = read_point_cloud(content, filename="scan.e57")
            best[name] = min(best[name], time.process_time() - started)
            assert ("time" in cloud.attributes) == (name == "with timeStamp")
    for name, seconds in best.items():
        print(f"{name:>15}: {seconds:.3f} CPU s for {args.points:,} points")
    print(f"{'times cost':>15}: {best['with timeStamp'] - best['without times']:+.3f} CPU s")


if __name__ == "__main__":
    main()
