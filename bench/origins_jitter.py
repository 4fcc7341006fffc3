"""Origin estimates of single-station lidars with and without azimuth jitter (issue 18).

The class: a spinning lidar (elevation -45 to 60 degrees, 1 cm range noise) 0.8-1.5 m above
the floor of a room, corridor or warehouse (:mod:`app.core.datasets.lidar`'s layouts), on a
regular grid or with a random azimuth phase per ring, a quarter-step azimuth jitter and 5 % of
a ring step of elevation error (as :func:`app.core.datasets.raycast_scene`'s lidar, whose 100k
pairs of seeds 100, 101 and 18 are included).  For each scan it prints what the column and ring
signals alone give (confidence, centre and height error, ring share there and from the true
centre) and what :func:`~app.core.origins.estimate.estimate_origin` returns (confidence, error,
the path taken: ``first``, ``sharp``ened or ``apex``, and its CPU seconds).

Run: ``OMP_NUM_THREADS=1 .venv/bin/python -m bench.origins_jitter [--seeds 2] [--steps 0.6 1.0]``
(prints, writes no file).  Against other code: ``PYTHONPATH=/path/to/checkout`` from there.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from numpy.typing import NDArray

from app.core.datasets.lidar import (
    ELEVATION_RANGE_DEG,
    LAYOUTS,
    RANGE_LIMITS,
    free_sensor_position,
    random_world,
)
from app.core.datasets.scenes import raycast_scene
from app.core.origins import estimate
from app.core.origins.columns import column_lines, fit_column_centre
from app.core.origins.rings import fit_ring_height
from app.core.origins.voxels import whole_voxels

RAYCAST_SEEDS = (100, 101, 18)
"""bench/perf_service.py's pair (100), a neighbour, bench/perf_round2.py's seed."""


def lidar_directions(
    elevation_step: float, azimuth_step: float, jitter: bool, rng: np.random.Generator
) -> NDArray[np.float64]:
    """Unit ray directions (r, 3) of one sweep: a regular grid, or with a random phase per
    ring, a quarter-step azimuth jitter and ring elevations off by 5 % of a step."""
    elevation = np.arange(ELEVATION_RANGE_DEG[0], ELEVATION_RANGE_DEG[1] + 1e-9, elevation_step)
    columns = round(360.0 / azimuth_step)
    if jitter:
        elevation = elevation + rng.normal(0.0, 0.05 * elevation_step, elevation.size)
        phase = rng.uniform(0.0, azimuth_step, elevation.size)
        azimuth = phase[:, None] + azimuth_step * np.arange(columns)[None, :]
        azimuth = azimuth + rng.uniform(-0.25, 0.25, azimuth.shape) * azimuth_step
    else:
        azimuth = rng.uniform(0.0, 360.0) + azimuth_step * np.arange(columns)
        azimuth = np.broadcast_to(azimuth, (elevation.size, columns))
    elevation_rad = np.deg2rad(np.broadcast_to(elevation[:, None], azimuth.shape).ravel())
    azimuth_rad = np.deg2rad(azimuth.ravel())
    return np.column_stack(
        [
            np.cos(elevation_rad) * np.cos(azimuth_rad),
            np.cos(elevation_rad) * np.sin(azimuth_rad),
            np.sin(elevation_rad),
        ]
    )


def single_scan(
    layout: str, seed: int, steps: tuple[float, float], jitter: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """One shuffled scan (n, 3) in a frame away from the building, and its sensor (3,)."""
    rng = np.random.default_rng(seed)
    world = random_world(layout, rng)
    station = free_sensor_position(rng, world)
    directions = lidar_directions(*steps, jitter, rng)
    distance, _ = world.cast(station, directions)
    keep = (distance >= RANGE_LIMITS[0]) & (distance <= RANGE_LIMITS[1])
    noisy = distance[keep] + rng.normal(0.0, 0.01, int(np.count_nonzero(keep)))
    points = station + noisy[:, None] * directions[keep]
    offset = np.round(np.array([*rng.uniform(-60.0, 60.0, 2), rng.uniform(-3.0, 3.0)]), 1)
    return (points + offset)[rng.permutation(len(points))], station + offset


def describe(points: NDArray[np.float64], truth: NDArray[np.float64]) -> str:
    """One line: the column and ring signals alone, then the whole estimate."""
    rng = np.random.default_rng(0)
    patch = whole_voxels(points, estimate.PATCH_POINTS, rng, thin_crowded=True)
    anchor, direction, walls = column_lines(patch, estimate.QUERY_POINTS, rng)
    low, high = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    columns = fit_column_centre(anchor, direction, low, high)
    rings = fit_ring_height(walls, columns.centre, rng)
    from_truth = fit_ring_height(walls, truth[:2], np.random.default_rng(0))
    first = min(
        estimate.confidence_ramp(columns.concurring_share, estimate.CONCURRING_RANGE),
        estimate.confidence_ramp(rings.ring_share, estimate.RING_SHARE_RANGE),
    )
    started = time.process_time()
    found = estimate.estimate_origin(points)
    seconds = time.process_time() - started
    evidence = found.evidence
    path = "apex" if "apex_spike" in evidence else "sharp" if "sharpened_spike" in evidence else ""
    centre_error = 1000 * np.linalg.norm(columns.centre - truth[:2])
    return (
        f"{len(points) // 1000:4d}k | columns+rings: conf {first:.2f}, concurring "
        f"{columns.concurring_share:.3f}, centre {centre_error:6.0f}"
        f" mm, height {1000 * (rings.height - truth[2]):6.1f} mm, ring share {rings.ring_share:.2f}"
        f" (from the sensor {from_truth.ring_share:.2f}) | estimate: conf {found.confidence:.2f}, "
        f"error {1000 * np.linalg.norm(found.origin - truth):7.1f} mm, {path or 'first':5s} "
        f"{seconds:.2f} s CPU"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=2, help="layouts drawn per kind")
    parser.add_argument(
        "--steps", type=float, nargs="+", default=[0.6, 1.0, 0.3], help="grid steps, degrees"
    )
    parser.add_argument("--no-raycast", action="store_true", help="skip raycast_scene's pairs")
    args = parser.parse_args()
    if not args.no_raycast:
        for seed in RAYCAST_SEEDS:
            pair = raycast_scene(n_points=100_000, change="box", random_state=seed)
            for side in ("reference", "scan"):
                points, truth = getattr(pair, side), getattr(pair, f"{side}_origin")
                print(f"raycast seed {seed} {side:9s} | {describe(points, truth)}", flush=True)
    steps = [(step, step) for step in args.steps] + [(0.66, 0.33)]  # raycast's 2:1 rings
    for layout in LAYOUTS:
        for seed in range(args.seeds):
            for step in steps:
                for jitter in (False, True):
                    points, truth = single_scan(layout, seed, step, jitter)
                    name = (
                        f"{layout} seed {seed} {step[0]}/{step[1]} {'jitter' if jitter else 'grid'}"
                    )
                    print(f"{name:32s} | {describe(points, truth)}", flush=True)


if __name__ == "__main__":
    main()
