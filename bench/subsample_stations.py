"""Which stations of a large merged survey the streamed parent can recover (issue 30, 100M row).

The streamed comparison (:mod:`app.core.tiling.streamed`) resolves the origins on a subsample
of each file (:func:`app.core.tiling.pair_files.survey`).  For a pair written by
``python -m bench.tiled --write-pair-streamed DIR N`` (station by station, ring by ring, with
``truth.npz`` beside it), this bench runs
:func:`~app.core.origins.station_recovery.recover_stations` on each side's points three ways:

- ``hashed``: the streamed subsample as it is drawn (one point in ``step`` by a hash of its
  index, :func:`~app.core.tiling.pair_files.subsample_offsets`);
- ``strided``: every ``step``-th point of the file (what the subsample was before s14);
- ``voxels``: the whole voxels at full density that the survey keeps for the lidar gate.

Per side and way it prints the points searched, the stations found against the true count, the
top-view distance of each found station to the nearest true one (metres) and the CPU seconds.

Run: ``OMP_NUM_THREADS=1 python -m bench.subsample_stations --pair-dir DIR [--subsample
2000000]``.  Reads the two PLY files twice each (about 30 CPU s a side at 100M); writes nothing.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from app.core.origins.station_recovery import recover_stations
from app.core.tiling.pair_files import StreamedCloud, survey
from app.core.tiling.streamed import SUBSAMPLE_POINTS


def strided_points(cloud: StreamedCloud) -> NDArray[np.float64]:
    """Every ``cloud.step``-th finite point of the file, shape (m, 3)."""
    parts = [points[(-first) % cloud.step :: cloud.step] for first, points in cloud.chunks()]
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def recovered(points: NDArray[np.float64], true: NDArray[np.float64]) -> dict[str, object]:
    """Stations recovered from ``points`` and their top-view distances to the true ones."""
    start = time.process_time()
    found = recover_stations(np.asarray(points, dtype=np.float64), random_state=0).origins
    offsets = found[:, None, :2] - true[None, :, :2]
    nearest = np.linalg.norm(offsets, axis=2).min(axis=1) if len(found) else np.zeros(0)
    return {
        "points": len(points),
        "found": len(found),
        "true": len(true),
        "nearest_true_m": nearest.round(3).tolist(),
        "cpu_s": round(time.process_time() - start, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pair-dir", type=Path, required=True)
    parser.add_argument("--subsample", type=int, default=SUBSAMPLE_POINTS)
    args = parser.parse_args()
    truth = np.load(args.pair_dir / "truth.npz")
    for side in ("reference", "scan"):
        cloud, subsample, voxels = survey(args.pair_dir / f"{side}.ply", None, args.subsample)
        true = truth[f"{side}_origins"]
        ways = {"hashed": subsample, "strided": strided_points(cloud)}
        if voxels is not None:
            ways["voxels"] = voxels
        for way, points in ways.items():
            row = {"side": side, "way": way, "step": cloud.step, **recovered(points, true)}
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
