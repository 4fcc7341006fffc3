"""Label digests of the shared real pairs and a synthetic suite: do two versions label alike?

Issue 18 asks that memory and float32 changes leave the labels as they were.  This script runs
``compare`` (gmm, defaults, ``OMP_NUM_THREADS`` as set) on

* the real pairs of ``../shared/data/real`` (KITTI frames 0-1, 1-2, 0-2; Lidar-SCU Velo1-2,
  Velo2-3, compared without alignment: those street scans do not overlap enough to align),
  when present;
* a synthetic suite: :func:`app.core.datasets.lidar.lidar_pair` (three layouts, two seeds
  each, misaligned scans, 60k points) and :func:`app.core.datasets.scenes.raycast_scene` (two
  change kinds, 50k points);

and prints one line per pair: the SHA-256 of both label arrays, the changed / unobserved
counts and the verdict.  ``--save FILE`` writes them as JSON; ``--against FILE`` compares
with a saved run (exit status 1 on any difference).  Run the code before a change with
``PYTHONPATH=<checkout>``.

``--float32-local`` rounds each cloud, in the comparison's local frame (the reference's
rounded centre subtracted, :func:`app.core.cloud.choose_local_origin`), to float32 before
comparing: the labels a pipeline storing float32 local coordinates would give.  On files that
hold float32 coordinates (the real pairs) this changes nothing by construction; on the
synthetic suite (float64) it shows what float32 storage would change.

Run: ``.venv/bin/python -m bench.label_digests --save /tmp/after.json [--against
/tmp/before.json]``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from app.core.cloud import PointCloud, choose_local_origin
from app.core.datasets.lidar import lidar_pair, steps_for_points
from app.core.datasets.scenes import raycast_scene
from app.core.formats import read_point_cloud
from app.core.pipeline import compare

PROJECT_ROOT = Path(__file__).resolve().parent.parent

REAL_DATA = Path(os.environ.get("SCANDIFF_SHARED_DATA", PROJECT_ROOT.parent / "shared" / "data"))
REAL_PAIRS = (
    ("kitti_2011_09_26_drive_0002_pointcloudset", "frame0.ply", "frame1.ply", True),
    ("kitti_2011_09_26_drive_0002_pointcloudset", "frame1.ply", "frame2.ply", True),
    ("kitti_2011_09_26_drive_0002_pointcloudset", "frame0.ply", "frame2.ply", True),
    ("lidar_scu_velodyne_budapest", "Velo1.pcd", "Velo2.pcd", False),
    ("lidar_scu_velodyne_budapest", "Velo2.pcd", "Velo3.pcd", False),
)
"""(folder, reference, scan, align)."""
SYNTHETIC_POINTS = 60_000


def pairs() -> Iterator[tuple[str, PointCloud, PointCloud, bool]]:
    """(name, reference, scan, align) of every pair of the suite."""
    for folder, first, second, align in REAL_PAIRS:
        directory = REAL_DATA / "real" / folder
        if (directory / first).is_file() and (directory / second).is_file():
            yield (
                f"real {folder[:5]} {first}-{second}",
                read_point_cloud(directory / first),
                read_point_cloud(directory / second),
                align,
            )
    for layout in ("room", "corridor", "warehouse"):
        for seed in (1, 2):
            pair = lidar_pair(
                layout=layout,
                change="mixed",
                angular_step_deg=steps_for_points(SYNTHETIC_POINTS),
                misaligned=True,
                random_state=seed,
            )
            yield (
                f"lidar_pair {layout} seed {seed}",
                PointCloud.from_array(pair.reference),
                PointCloud.from_array(pair.scan),
                True,
            )
    for change in ("none", "mixed"):
        scene = raycast_scene(n_points=50_000, change=change, random_state=3)
        yield (
            f"raycast_scene {change}",
            PointCloud.from_array(scene.reference),
            PointCloud.from_array(scene.scan),
            True,
        )


def float32_local(cloud: PointCloud, local_origin: np.ndarray) -> PointCloud:
    """``cloud`` with its coordinates rounded to float32 relative to ``local_origin``."""
    rounded = (cloud.points - local_origin).astype(np.float32).astype(np.float64) + local_origin
    return PointCloud.from_array(rounded, sensor_origin=cloud.sensor_origin)


def digest(name: str, reference: PointCloud, scan: PointCloud, align: bool) -> dict[str, object]:
    """The comparison's label digest and counts."""
    result = compare(reference, scan, align=align)
    labels = np.concatenate([result.reference_label, result.scan_label]).astype(np.int8)
    counts = result.label_counts()
    return {
        "name": name,
        "sha256": hashlib.sha256(labels.tobytes()).hexdigest()[:16],
        "changed": [counts["reference"]["changed"], counts["scan"]["changed"]],
        "unobserved": [counts["reference"]["unobserved"], counts["scan"]["unobserved"]],
        "n_regions": len(result.regions),
        "verdict": bool(result.changed),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--save", type=Path)
    parser.add_argument("--against", type=Path)
    parser.add_argument("--float32-local", action="store_true")
    args = parser.parse_args()
    rows = []
    for name, reference, scan, align in pairs():
        if args.float32_local:
            origin = choose_local_origin(reference.points)
            reference, scan = float32_local(reference, origin), float32_local(scan, origin)
        row = digest(name, reference, scan, align)
        rows.append(row)
        print(json.dumps(row), flush=True)
    if args.save:
        args.save.write_text(json.dumps(rows, indent=1))
    if args.against:
        before = {row["name"]: row for row in json.loads(args.against.read_text())}
        different = [row["name"] for row in rows if before.get(row["name"]) != row]
        print(f"{len(rows) - len(different)} of {len(rows)} pairs labelled as in {args.against}")
        for name in different:
            print(f"  differs: {name}: {before.get(name)}")
        return 1 if different else 0
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
