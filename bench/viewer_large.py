"""Opening the 3D view of a large job: seconds and peak memory, streamed vs loading whole.

Generates a job of ``--points`` points per scan (default 20M): an 80 x 50 x 10 m hall, the
reference a binary PLY (float32) and the scan a LAZ in its own frame (turned and shifted), a
2 x 2 x 2 m pallet changed in each, 5 % unobserved, with the ``labels.npz`` and
``details.npz`` a worker writes. Then, each in a fresh child process:

- ``open``: :func:`app.viewer.large_scene.budget_scene` at the default point budget (the scene
  a browser opens with);
- ``box``: :func:`app.viewer.large_scene.box_scene` of a 10 x 10 m box around the change, at
  full density up to the budget;
- ``whole`` (``--whole``): what the view did before for every job: both clouds read whole
  (``read_point_cloud``) and :func:`app.viewer.scene.build_scene_data`.

Printed: the seconds, the child's peak RSS (``VmHWM`` of ``/proc/self/status``; ``ru_maxrss``
would carry the generating parent's over ``exec``), its growth over
the RSS after the imports, the points drawn, and the growth over the two files' size.

Run: ``.venv/bin/python -m bench.viewer_large [--points 20000000] [--whole] [--ways open,box]``
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.child_memory import measure_child
from bench.read_memory import WRITE_POINTS, status_kb

HALL = np.array([80.0, 50.0, 10.0])
CHANGE_LOW = np.array([40.0, 25.0, 0.0])
CHANGE_HIGH = CHANGE_LOW + 2.0
BOX_LOW = CHANGE_LOW - 4.0
BOX_HIGH = CHANGE_HIGH + 4.0
SCAN_TO_REFERENCE = np.array(
    [
        [np.cos(0.2), -np.sin(0.2), 0.0, 3.0],
        [np.sin(0.2), np.cos(0.2), 0.0, -1.5],
        [0.0, 0.0, 1.0, 0.2],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def write_job(folder: Path, n_points: int) -> dict[str, str]:
    """The job's files in ``folder``, written a chunk at a time."""
    import laspy

    rng = np.random.default_rng(5)
    labels = {side: np.zeros(n_points, np.int8) for side in ("reference", "scan")}
    distances = {side: np.zeros(n_points, np.float32) for side in ("reference", "scan")}
    ply = folder / "reference.ply"
    laz = folder / "scan.laz"
    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales = np.full(3, 0.001)
    header.offsets = np.array([-100.0, -100.0, -10.0])
    to_scan = np.linalg.inv(SCAN_TO_REFERENCE)
    with (
        open(ply, "wb") as output,
        laspy.open(laz, mode="w", header=header, do_compress=True) as writer,
    ):
        output.write(
            (
                "ply\nformat binary_little_endian 1.0\n"
                f"element vertex {n_points}\nproperty float x\nproperty float y\n"
                "property float z\nend_header\n"
            ).encode()
        )
        for start in range(0, n_points, WRITE_POINTS):
            rows = slice(start, min(start + WRITE_POINTS, n_points))
            for side in ("reference", "scan"):
                points = rng.random((rows.stop - start, 3)) * HALL
                inside = ((points >= CHANGE_LOW) & (points <= CHANGE_HIGH)).all(axis=1)
                unobserved = rng.random(len(points)) < 0.05
                labels[side][rows] = np.where(inside, 1, np.where(unobserved, -1, 0))
                distances[side][rows] = np.where(inside, 0.4, rng.random(len(points)) * 0.05)
                if side == "reference":
                    output.write(points.astype("<f4").tobytes())
                else:
                    in_scan = points @ to_scan[:3, :3].T + to_scan[:3, 3]
                    record = laspy.ScaleAwarePointRecord.zeros(len(points), header=header)
                    record.x, record.y, record.z = in_scan[:, 0], in_scan[:, 1], in_scan[:, 2]
                    writer.write_points(record)
    np.savez_compressed(
        folder / "labels.npz", reference_label=labels["reference"], scan_label=labels["scan"]
    )
    np.savez(
        folder / "details.npz",
        reference_distance=distances["reference"],
        scan_distance=distances["scan"],
    )
    return {"reference": str(ply), "scan": str(laz), "folder": str(folder)}


def child(folder: str, way: str) -> None:
    """Build the scene one ``way`` and print the result as JSON (the parent reads the RSS)."""
    from app.core.formats import read_point_cloud
    from app.viewer.large_scene import SceneContext, StoredSide, box_scene, budget_scene
    from app.viewer.scene import build_scene_data
    from app.viewer.stored_results import stored_distances, stored_labels

    before = status_kb("VmRSS")
    root = Path(folder)
    paths = {"reference": root / "reference.ply", "scan": root / "scan.laz"}
    start = time.perf_counter()
    labels = stored_labels(root / "labels.npz")
    context = SceneContext(SCAN_TO_REFERENCE)
    if way == "whole":
        reference = read_point_cloud(paths["reference"])
        scan = read_point_cloud(paths["scan"])
        with np.load(root / "details.npz") as details:
            data = build_scene_data(
                reference.points,
                scan.points,
                reference_labels=reference.from_source_order(labels["reference"]),
                scan_labels=scan.from_source_order(labels["scan"]),
                reference_distances=reference.from_source_order(details["reference_distance"]),
                scan_distances=scan.from_source_order(details["scan_distance"]),
                transform=SCAN_TO_REFERENCE,
            )
    else:
        distances = stored_distances(
            root / "details.npz", {side: len(values) for side, values in labels.items()}
        )
        sides = {side: StoredSide(paths[side], labels[side], distances[side]) for side in paths}
        if way == "open":
            data = budget_scene(sides, context)
        else:
            data = box_scene(sides, context, BOX_LOW, BOX_HIGH)
    seconds = time.perf_counter() - start
    capped = any(warning["code"] == "box_capped" for warning in data.warnings)
    print(
        json.dumps(
            {
                "seconds": seconds,
                "shown": data.n_shown,
                "total": data.n_total,
                "capped": capped,
                "rss_after_imports_kb": before,
                "peak_rss_kb": status_kb("VmHWM"),
            }
        )
    )


def measure(folder: str, way: str) -> dict:
    """Run :func:`child` in a fresh interpreter; its output plus its peak RSS."""
    return measure_child("bench.viewer_large", folder, way)


def main() -> None:
    """Generate the job, open it each way and print."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20_000_000)
    parser.add_argument("--whole", action="store_true", help="also load the clouds whole")
    parser.add_argument("--ways", default="open,box", help="of open, box (default both)")
    parser.add_argument("--child", nargs=2, metavar=("FOLDER", "WAY"), help=argparse.SUPPRESS)
    arguments = parser.parse_args()
    if arguments.child:
        child(*arguments.child)
        return
    with tempfile.TemporaryDirectory(prefix="viewer-large-") as folder:
        started = time.perf_counter()
        files = write_job(Path(folder), arguments.points)
        size_mb = sum(Path(files[side]).stat().st_size for side in ("reference", "scan")) / 2**20
        print(
            f"{arguments.points:,} points per scan; files {size_mb:.0f} MB (PLY + LAZ); "
            f"generated in {time.perf_counter() - started:.0f} s"
        )
        print("way    seconds  peak RSS MB  growth MB  growth / files  shown / total")
        ways = [way for way in arguments.ways.split(",") if way in ("open", "box")]
        for way in (*ways, *(("whole",) if arguments.whole else ())):
            result = measure(folder, way)
            capped = " (capped)" if result["capped"] else ""
            print(
                f"{way:5}  {result['seconds']:7.1f}  {result['peak_rss_mb']:11.0f}  "
                f"{result['growth_mb']:9.0f}  {result['growth_mb'] / size_mb:14.2f}  "
                f"{result['shown']:,} / {result['total']:,}{capped}",
                flush=True,
            )


if __name__ == "__main__":
    main()
