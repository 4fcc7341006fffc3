"""What the trajectory visibility test costs at ~1M points a map (issue 29: <= 20 % of a compare).

A swept warehouse aisle (40 x 8 x 4 m, racks and boxes): each epoch is a spinning lidar stopping
every 0.5 m along its own path (the scan's path 0.6 m to the side, one box removed, one added),
the sweeps merged (about ``--points`` points a map), each point with its time, each epoch with
its trajectory (a pose at the start and the end of each 0.1 s sweep).  The same pair is compared
(:func:`app.core.pipeline.compare`, one thread) three ways, ``--repeats`` times each,
alternately: without trajectories (the default origin-free path), with the trajectories and
per-point times, and with the trajectories without times (line-of-sight poses).  Printed per
way: the median CPU time of the compare (one thread: steady on a shared machine) and what it
adds to the default way's, the wall time of the origins and localise stages, the test each side
got, and the IoU of changed points against the truth (more than 10 cm from every surface of the
other epoch's world) with the changed points missed and the false ones.

Run: ``OMP_NUM_THREADS=1 python -m bench.trajectory_cost [--points 1000000] [--repeats 1]``.
Writes nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from typing import Any

import numpy as np

from app.core.cloud import PointCloud
from app.core.datasets.lidar import CHANGE_DISTANCE, LidarWorld, lidar_directions
from app.core.pipeline import compare
from app.core.trajectory import Trajectory

SHELL_HIGH = np.array([40.0, 8.0, 4.0])
RACKS = [((x, 0.0, 0.0), (x + 2.0, 1.2, 3.0)) for x in (3.0, 12.0, 21.0, 30.0)]
BOXES = [((8.0, 5.5, 0.0), (8.8, 6.3, 0.8)), ((25.0, 6.0, 0.0), (26.0, 6.9, 1.2))]
REMOVED = ((17.0, 5.8, 0.0), (17.9, 6.6, 1.0))
ADDED = ((34.0, 2.5, 0.0), (34.8, 3.2, 0.9))
OFFSET = np.array([500.0, 300.0, 20.0])
SWEEP_SECONDS = 0.1


def world(boxes: list) -> LidarWorld:
    """The aisle with ``boxes`` (low, high corners)."""
    return LidarWorld(
        shell_low=np.zeros(3),
        shell_high=SHELL_HIGH,
        box_low=np.array([low for low, _ in boxes], dtype=np.float64),
        box_high=np.array([high for _, high in boxes], dtype=np.float64),
    )


def sweep(
    scene: LidarWorld, path: np.ndarray, points: int, seed: int, start: float
) -> tuple[PointCloud, np.ndarray]:
    """The merged sweeps from each pose of ``path`` (cloud with time and trajectory, exact)."""
    rng = np.random.default_rng(seed)
    step = float(np.sqrt(105.0 * 360.0 / (points / len(path))))
    clouds, exact, times, pose_times, pose_positions = [], [], [], [], []
    for number, position in enumerate(path):
        directions = lidar_directions(step, step, yaw_deg=rng.uniform(0, 360))
        distance, _ = scene.cast(position, directions)
        keep = distance >= 0.3
        directions, distance = directions[keep], distance[keep]
        exact.append(position + distance[:, None] * directions)
        noisy = distance + rng.normal(0.0, 0.005, distance.shape)
        clouds.append(position + noisy[:, None] * directions)
        azimuth = np.arctan2(directions[:, 1], directions[:, 0])
        sweep_start = start + number
        times.append(sweep_start + SWEEP_SECONDS * (azimuth + np.pi) / (2 * np.pi))
        pose_times += [sweep_start, sweep_start + SWEEP_SECONDS + 1e-3]
        pose_positions += [position, position]
    trajectory = Trajectory(np.array(pose_times), np.array(pose_positions) + OFFSET)
    cloud = PointCloud.from_array(np.vstack(clouds) + OFFSET, {"time": np.concatenate(times)})
    return dataclasses.replace(cloud, trajectory=trajectory), np.vstack(exact)


def pair(points: int) -> dict:
    """Both epochs and their truth."""
    xs = np.arange(1.0, 39.01, 0.5)
    reference_world = world([*RACKS, *BOXES, REMOVED])
    scan_world = world([*RACKS, *BOXES, ADDED])
    reference, reference_exact = sweep(
        reference_world,
        np.column_stack([xs, np.full(xs.size, 3.5), np.full(xs.size, 1.0)]),
        points,
        1,
        1000.0,
    )
    scan, scan_exact = sweep(
        scan_world,
        np.column_stack([xs, np.full(xs.size, 4.1), np.full(xs.size, 1.1)]),
        points,
        2,
        9000.0,
    )
    return {
        "reference": reference,
        "scan": scan,
        "reference_changed": scan_world.surface_distance(reference_exact) > CHANGE_DISTANCE,
        "scan_changed": reference_world.surface_distance(scan_exact) > CHANGE_DISTANCE,
    }


def scores(result, truth: dict) -> tuple[float, int, int]:
    """IoU of changed points over both clouds, changed points missed, false changed points."""
    found = np.concatenate([result.reference_label == 1, result.scan_label == 1])
    true = np.concatenate([truth["reference_changed"], truth["scan_changed"]])
    union = np.count_nonzero(found | true)
    missed, false = np.count_nonzero(true & ~found), np.count_nonzero(found & ~true)
    return (np.count_nonzero(found & true) / union if union else 1.0), missed, false


def cpu_per_way(given: dict[str, dict], repeats: int) -> tuple[dict[str, float], dict[str, object]]:
    """``compare(**given[name], threads=1)`` ``repeats`` times per way, taking turns; the median
    CPU seconds (one thread: CPU time is steady on a shared machine) and the last result of each.
    """
    cpu: dict[str, list[float]] = {name: [] for name in given}
    last: dict[str, object] = {}
    for _ in range(repeats):
        for name, arguments in given.items():
            started = time.process_time()
            last[name] = compare(**arguments, threads=1)
            cpu[name].append(time.process_time() - started)
    return {name: float(np.median(seconds)) for name, seconds in cpu.items()}, last


@dataclasses.dataclass(frozen=True)
class WayFigures:
    """One way's figures: median CPU seconds, last result, visibility tests run, scores."""

    seconds: float
    result: Any
    tests: str
    iou: float
    missed: int
    false: int


def figures_per_way(
    cpu: dict[str, float], last: dict[str, Any], truth: dict
) -> dict[str, WayFigures]:
    """The figures of each way of :func:`cpu_per_way` against ``truth`` (see :func:`scores`)."""
    figures = {}
    for name, result in last.items():
        tests = "/".join(str(result.visibility[side].test) for side in ("reference", "scan"))
        figures[name] = WayFigures(cpu[name], result, tests, *scores(result, truth))
    return figures


def ways(scene: dict) -> dict[str, tuple[PointCloud, PointCloud]]:
    """The three ways the pair is given."""
    untimed = {
        side: dataclasses.replace(
            scene[side], attributes={k: v for k, v in scene[side].attributes.items() if k != "time"}
        )
        for side in ("reference", "scan")
    }
    return {
        "default": tuple(
            dataclasses.replace(scene[s], trajectory=None) for s in ("reference", "scan")
        ),
        "trajectory+times": (scene["reference"], scene["scan"]),
        "trajectory, no times": (untimed["reference"], untimed["scan"]),
    }


def main() -> None:
    """Print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()
    started = time.perf_counter()
    scene = pair(args.points)
    print(
        f"pair: reference {len(scene['reference']):,} points, scan {len(scene['scan']):,} "
        f"points, {len(scene['reference'].trajectory)} poses each (built in "
        f"{time.perf_counter() - started:.1f} s); load {os.getloadavg()[0]:.1f}"
    )
    given = {
        name: {"reference": reference, "scan": scan}
        for name, (reference, scan) in ways(scene).items()
    }
    cpu, last = cpu_per_way(given, args.repeats)
    base = cpu["default"]
    for name, way in figures_per_way(cpu, last, scene).items():
        timings = way.result.timings
        print(
            f"{name:<21} CPU {way.seconds:6.1f} s (adds {100 * (way.seconds / base - 1):+5.1f} %)  "
            f"wall: origins {timings.get('origins', 0):5.1f} s, localise "
            f"{timings['localise']:5.1f} s  tests {way.tests:<21} IoU {way.iou:.3f} (missed "
            f"{way.missed}, false {way.false})  regions {len(way.result.regions)}"
        )
    print(f"load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
