"""Peak memory of reading a large point cloud per format: streamed float32 vs the whole cloud.

For each format (``.npy`` float64, binary little-endian PLY float32, LAS, LAZ, E57 of four
scans) a file of ``--points`` points (default 20M) is generated a chunk at a time, then read in
a fresh child process twice:

- ``streamed``: :func:`app.core.formats.streamed.read_points_float32` (float32 near an offset,
  a block at a time);
- ``whole``: :func:`app.core.formats.read_point_cloud` (the float64 ``PointCloud`` the
  comparison uses).

Printed per format and way: the seconds, the child's peak RSS (``VmHWM`` of
``/proc/self/status``, its own high-water mark: anonymous and file-backed pages both count;
``ru_maxrss`` would carry the generating parent's over ``exec``), its growth over the RSS after the
imports, and that growth over the float32 (n, 3) array's size (12 bytes a point): 1.0 means
the reading cost nothing besides its result.

Run: ``.venv/bin/python -m bench.read_memory [--points 20000000] [--formats npy,ply,las,laz,e57]``
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.child_memory import measure_child

WRITE_POINTS = 1_000_000
"""Points generated and written at a time (the bench's own memory stays small)."""

FORMATS = ("npy", "ply", "las", "laz", "e57")


def _chunks(n_points: int, seed: int = 3):
    """Uniform points in an 80 x 50 x 10 m hall, ``WRITE_POINTS`` at a time."""
    rng = np.random.default_rng(seed)
    for start in range(0, n_points, WRITE_POINTS):
        count = min(WRITE_POINTS, n_points - start)
        yield rng.random((count, 3)) * [80.0, 50.0, 10.0] + [512_000.0, 5_400_000.0, 300.0]


def write_file(path: Path, kind: str, n_points: int) -> None:
    """A ``kind`` file of ``n_points`` points, written a chunk at a time."""
    if kind == "npy":
        array = np.lib.format.open_memmap(path, mode="w+", dtype=np.float64, shape=(n_points, 3))
        start = 0
        for chunk in _chunks(n_points):
            array[start : start + len(chunk)] = chunk
            start += len(chunk)
        array.flush()
        del array
    elif kind == "ply":
        header = (
            "ply\nformat binary_little_endian 1.0\n"
            f"element vertex {n_points}\nproperty float x\nproperty float y\nproperty float z\n"
            "end_header\n"
        )
        with open(path, "wb") as output:
            output.write(header.encode())
            for chunk in _chunks(n_points):
                output.write((chunk - [512_000.0, 5_400_000.0, 300.0]).astype("<f4").tobytes())
    elif kind in ("las", "laz"):
        import laspy

        header = laspy.LasHeader(point_format=0, version="1.2")
        header.scales = np.full(3, 0.001)
        header.offsets = np.array([512_000.0, 5_400_000.0, 300.0])
        with laspy.open(path, mode="w", header=header, do_compress=kind == "laz") as writer:
            for chunk in _chunks(n_points):
                record = laspy.ScaleAwarePointRecord.zeros(len(chunk), header=header)
                record.x, record.y, record.z = chunk[:, 0], chunk[:, 1], chunk[:, 2]
                writer.write_points(record)
    elif kind == "e57":
        import pye57

        per_scan = -(-n_points // 4)
        with pye57.E57(str(path), mode="w") as writer:
            for index in range(4):
                count = min(per_scan, n_points - index * per_scan)
                scan = np.concatenate(list(_chunks(count, seed=index)))
                data = {
                    "cartesianX": scan[:, 0],
                    "cartesianY": scan[:, 1],
                    "cartesianZ": scan[:, 2],
                }
                writer.write_scan_raw(data, name=f"scan {index}")
                del scan, data
    else:
        raise ValueError(kind)


def status_kb(field: str) -> int:
    """A ``kB`` field of ``/proc/self/status`` (``VmRSS``, ``VmHWM``)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1])
    raise RuntimeError(f"no {field} in /proc/self/status")


def child(path: str, way: str) -> None:
    """Read ``path`` one ``way`` and print the timing as JSON (the parent reads the RSS)."""
    from app.core.formats import read_point_cloud
    from app.core.formats.streamed import read_points_float32

    before = status_kb("VmRSS")
    start = time.perf_counter()
    if way == "streamed":
        n_points = len(read_points_float32(path).points)
    else:
        n_points = len(read_point_cloud(path, max_points=None))
    seconds = time.perf_counter() - start
    result = {"seconds": seconds, "n_points": n_points, "rss_after_imports_kb": before}
    print(json.dumps({**result, "peak_rss_kb": status_kb("VmHWM")}))


def measure(path: Path, way: str) -> dict:
    """Run :func:`child` in a fresh interpreter; its output plus its peak RSS."""
    return measure_child("bench.read_memory", str(path), way)


def main() -> None:
    """Generate, read and print."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20_000_000)
    parser.add_argument("--formats", default=",".join(FORMATS))
    parser.add_argument("--child", nargs=2, metavar=("PATH", "WAY"), help=argparse.SUPPRESS)
    arguments = parser.parse_args()
    if arguments.child:
        child(*arguments.child)
        return
    array_mb = arguments.points * 12 / 2**20
    print(f"{arguments.points:,} points; float32 (n, 3) array: {array_mb:.0f} MB")
    print("format  file MB  way       seconds  peak RSS MB  growth MB  growth / array")
    with tempfile.TemporaryDirectory(prefix="read-memory-") as folder:
        for kind in arguments.formats.split(","):
            path = Path(folder) / f"cloud.{kind}"
            write_file(path, kind, arguments.points)
            size_mb = path.stat().st_size / 2**20
            for way in ("streamed", "whole"):
                result = measure(path, way)
                print(
                    f"{kind:6}  {size_mb:7.0f}  {way:8}  {result['seconds']:7.1f}  "
                    f"{result['peak_rss_mb']:11.0f}  {result['growth_mb']:9.0f}  "
                    f"{result['growth_mb'] / array_mb:14.2f}",
                    flush=True,
                )
            path.unlink()


if __name__ == "__main__":
    main()
