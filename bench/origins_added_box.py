"""The single-origin estimate on real Velodyne frames with and without a dense box added.

Each real frame of ../shared/data/real (KITTI HDL-64 street frames, Budapest HDL-64 frames; in
their sensor's frame, so the true origin is (0, 0, 0)) as it is and with a car-sized box (4 x
1.8 x 1.5 m, its six faces on an 81 x 81 grid: 39k points,
:func:`~app.core.datasets.added_objects.box_on_the_ground`) standing 10-14 m ahead, 2.1-3.9 m
to the left; :func:`~app.core.origins.estimate.estimate_origin` with ``--seeds`` seeds: how
many are confident and within 0.2 m of the sensor, the median confidence, the CPU seconds.

Run: ``.venv/bin/python -m bench.origins_added_box [--seeds 8]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from app.core.datasets.added_objects import box_on_the_ground
from app.core.formats import read_point_cloud
from app.core.origins import estimate_origin

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
TOLERANCE = 0.2
"""Metres from the sensor within which an estimate is right."""


def scored(points: np.ndarray, seeds: int) -> str:
    """``right/seeds, median confidence, CPU s`` of the estimate on ``points``."""
    right, confidence = 0, []
    started = time.process_time()
    for seed in range(seeds):
        found = estimate_origin(points, random_state=seed)
        right += int(found.confident and np.linalg.norm(found.origin) < TOLERANCE)
        confidence.append(found.confidence)
    seconds = (time.process_time() - started) / seeds
    return f"{right}/{seeds} | {np.median(confidence):.2f} | {seconds:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8)
    args = parser.parse_args()
    print(
        "| frame | points | box points | as is: right | median confidence | CPU s a seed "
        "| with the box: right | median confidence | CPU s a seed |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for path in sorted(REAL.glob("*/*.p[cl][dy]")):
        points = np.asarray(read_point_cloud(path).points, dtype=np.float64)
        box = box_on_the_ground(points, (10.0, 2.1), (14.0, 3.9), 1.5)
        with_box = np.vstack([points, box])
        print(
            f"| {path.parent.name}/{path.name} | {len(points)} | {len(box)} | "
            f"{scored(points, args.seeds)} | {scored(with_box, args.seeds)} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
