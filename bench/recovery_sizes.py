"""Station recovery alone at increasing density (issue 30): stations recovered and seconds.

The pair of bench/tiled.py (a five-station warehouse survey per epoch,
:func:`app.core.datasets.lidar.lidar_pair` with ``n_stations=5``, seed 18) at several point
counts a scan (the angular step from :func:`~app.core.datasets.lidar.steps_for_points`); for
each cloud, :func:`~app.core.origins.station_recovery.recover_stations` alone: the stations
found, how many lie within ``--tolerance`` metres (top view) of a true station, the points the
whole-voxel subset kept and the seconds taken.  Generated clouds are cached as ``.npy`` in
``--work-dir`` (generation takes minutes at 10M points and more).

Run: ``OMP_NUM_THREADS=1 .venv/bin/python -m bench.recovery_sizes --sizes 1M,4M,10M
[--work-dir /tmp/recovery_sizes] [--max-points 100000] [--output FILE]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from app.core.datasets.lidar import lidar_pair, steps_for_points
from app.core.origins import station_recovery
from app.core.origins.voxels import whole_voxels

SCENE_SEED = 18
N_STATIONS = 5


def parse_size(text: str) -> int:
    """``4M`` -> 4_000_000, ``500k`` -> 500_000."""
    text = text.strip().lower()
    scale = {"k": 1_000, "m": 1_000_000}.get(text[-1], 1)
    return int(float(text[:-1] if scale > 1 else text) * scale)


def load_pair(work_dir: Path, n_points: int, seed: int) -> dict[str, np.ndarray]:
    """The pair's clouds and true stations, generated once into ``work_dir``."""
    path = work_dir / f"merged-{seed}-{n_points}.npz"
    if not path.exists():
        work_dir.mkdir(parents=True, exist_ok=True)
        pair = lidar_pair(
            layout="warehouse",
            change="added",
            n_stations=N_STATIONS,
            angular_step_deg=steps_for_points(n_points, N_STATIONS),
            random_state=seed,
        )
        np.savez(
            path,
            reference=pair.reference.astype(np.float32),
            scan=pair.scan.astype(np.float32),
            reference_origins=pair.reference_origins,
            scan_origins=pair.scan_origins,
        )
    with np.load(path) as stored:
        return {name: stored[name] for name in stored.files}


def matched(found: np.ndarray, truth: np.ndarray, tolerance: float) -> int:
    """True stations with a found one within ``tolerance`` metres in the top view."""
    if found.shape[0] == 0:
        return 0
    distance = np.linalg.norm(truth[:, None, :2] - found[None, :, :2], axis=2)
    return int((distance.min(axis=1) <= tolerance).sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1M,4M,10M")
    parser.add_argument("--seeds", default=str(SCENE_SEED))
    parser.add_argument("--work-dir", type=Path, default=Path("/tmp/recovery_sizes"))
    parser.add_argument("--tolerance", type=float, default=0.1)
    parser.add_argument("--output", type=Path)
    parser.add_argument(
        "--max-points",
        type=int,
        help="the recovery's subset size (default MAX_POINTS, 200k): a smaller one takes the "
        "share of a denser cloud (100k of 10M points: 20M points' 1 %%)",
    )
    args = parser.parse_args()
    if args.max_points:
        station_recovery.MAX_POINTS = args.max_points
    rows = []
    header = "| points a scan | seed | side | n | subset | found | true within tol | seconds |"
    print(header)
    print("|---|---|---|---|---|---|---|---|")
    for size in (parse_size(text) for text in args.sizes.split(",")):
        for seed in (int(text) for text in args.seeds.split(",")):
            pair = load_pair(args.work_dir, size, seed)
            for side in ("reference", "scan"):
                points = pair[side].astype(np.float64)
                rng = np.random.default_rng(0)
                subset = whole_voxels(points, station_recovery.MAX_POINTS, rng)
                started = time.perf_counter()
                found = station_recovery.recover_stations(points)
                seconds = time.perf_counter() - started
                hits = matched(found.origins, pair[f"{side}_origins"], args.tolerance)
                row = (
                    f"| {size / 1e6:g}M | {seed} | {side} | {points.shape[0]:,} | "
                    f"{subset.shape[0]:,} | {found.origins.shape[0]} | {hits}/{N_STATIONS} | "
                    f"{seconds:.2f} |"
                )
                print(row, flush=True)
                rows.append(row)
    if args.output:
        rule = "|---|---|---|---|---|---|---|---|"
        args.output.write_text("\n".join([header, rule, *rows]) + "\n")


if __name__ == "__main__":
    main()
