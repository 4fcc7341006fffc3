"""Large files read a block at a time (:mod:`app.core.formats.streamed`) and E57 scan by scan.

Rules checked:

* for every format, :func:`read_points_float32` with blocks far smaller than the file gives
  the points :func:`read_point_cloud` gives (to float32's resolution at the cloud's extent),
  the same file rows for them (non-finite rows dropped) and the same row count;
* georeferenced coordinates keep that resolution (an offset is subtracted before narrowing;
  plain float32 would not);
* memory: reading a ``.npy`` or binary PLY costs the float32 result plus a block (no float64
  copy, no resident map); an E57 is read a chunk of a scan at a time into one array, never
  holding a scan whole beside it, with the points, poses, stations and intensities of whole
  scans.
"""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pye57
import pytest

from app.core.formats import e57 as e57_module
from app.core.formats import read_point_cloud
from app.core.formats.streamed import open_point_blocks, read_points_float32
from app.testing.e57_times import e57_with_times_bytes
from app.testing.files import e57_bytes, las_bytes, npy_bytes, ply_bytes, text_bytes
from app.testing.scenes import random_points

SMALL_BLOCK = 37
"""Rows per block in the comparisons: many blocks, none aligned with anything."""


def _with_nan_rows(points: np.ndarray, rows: list[int]) -> np.ndarray:
    points = points.copy()
    points[rows, 2] = np.nan
    return points


def _write(folder: Path, name: str, content: bytes) -> Path:
    path = folder / name
    path.write_bytes(content)
    return path


def _files(folder: Path) -> dict[str, Path]:
    points = random_points(500, seed=11)
    holed = _with_nan_rows(points, [0, 36, 37, 38, 499])
    structured = np.empty(500, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("i", "<u2")])
    for axis, name in enumerate("xyz"):
        structured[name] = holed[:, axis]
    structured["i"] = np.arange(500)
    scans = [random_points(n, seed=n) for n in (120, 45, 333)]
    invalid = [np.arange(120) % 7 == 0, None, np.arange(333) % 11 == 0]
    poses = [((1, 0, 0, 0), (5, 0, 1)), ((1, 0, 0, 0), (0, 0, 0)), ((0, 0, 0, 1), (-3, 2, 0))]
    return {
        "npy64": _write(folder, "a.npy", npy_bytes(holed)),
        "npy32-fortran": _write(folder, "b.npy", npy_bytes(np.asfortranarray(holed, "f4"))),
        "npy-structured": _write(folder, "c.npy", npy_bytes(structured)),
        "ply-le32": _write(
            folder, "a.ply", ply_bytes(holed, extra={"intensity": np.arange(500, dtype="u2")})
        ),
        "ply-be64": _write(folder, "b.ply", ply_bytes(holed, "binary_big_endian", "f8")),
        "ply-ascii": _write(folder, "c.ply", ply_bytes(holed, "ascii", "f8")),
        "las": _write(folder, "a.las", las_bytes(points)),
        "laz": _write(folder, "a.laz", las_bytes(points, compress=True)),
        "e57": _write(folder, "a.e57", e57_bytes(scans, poses, invalid=invalid)),
        "xyz": _write(folder, "a.xyz", text_bytes(holed)),
    }


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    return _files(tmp_path_factory.mktemp("streamed"))


def _resolution(points: np.ndarray, offset: np.ndarray) -> float:
    """The largest float32 rounding error of ``points - offset`` (half a unit in the last place)."""
    return float(np.spacing(np.abs(points - offset).max().astype(np.float32)))


@pytest.mark.parametrize(
    "kind",
    [
        "npy64",
        "npy32-fortran",
        "npy-structured",
        "ply-le32",
        "ply-be64",
        "ply-ascii",
        "las",
        "laz",
        "e57",
        "xyz",
    ],
)
def test_float32_points_are_the_clouds_points(files, kind):
    cloud = read_point_cloud(files[kind])
    streamed = read_points_float32(files[kind], block_points=SMALL_BLOCK)
    assert streamed.points.dtype == np.float32
    assert streamed.points.shape == cloud.points.shape
    assert streamed.n_source == cloud.n_source
    error = np.abs(streamed.file_coordinates() - cloud.points).max()
    assert error <= _resolution(cloud.points, streamed.offset)
    if cloud.n_dropped:
        np.testing.assert_array_equal(streamed.source_rows, cloud.source_index)
    else:
        assert streamed.source_rows is None


@pytest.mark.parametrize("kind", ["npy64", "ply-le32", "laz", "e57"])
def test_blocks_come_in_file_order_and_cover_every_row(files, kind):
    cloud = read_point_cloud(files[kind])
    with open_point_blocks(files[kind], block_points=SMALL_BLOCK) as opened:
        assert opened.n_rows >= cloud.n_source
        got = [(start, block) for start, block in opened.blocks]
    starts = [start for start, _ in got]
    assert starts == sorted(starts) and starts[0] == 0
    rows = np.concatenate([block for _, block in got])
    assert len(rows) == cloud.n_source
    np.testing.assert_array_equal(rows[cloud.source_index], cloud.points)
    assert cloud.n_dropped == int((~np.isfinite(rows).all(axis=1)).sum())


def test_georeferenced_points_keep_their_resolution(tmp_path):
    local = random_points(2000, seed=4) * 50.0
    survey = local + np.array([512_345.678, 5_432_109.876, 312.5])
    path = _write(tmp_path, "survey.npy", npy_bytes(survey))
    streamed = read_points_float32(path, block_points=SMALL_BLOCK)
    error = np.abs(streamed.file_coordinates() - survey).max()
    assert error <= _resolution(survey, streamed.offset)
    plain = np.abs(survey.astype(np.float32).astype(np.float64) - survey).max()
    assert plain > 10 * error  # what the offset saves


@pytest.mark.parametrize("kind", ["npy", "ply"])
def test_reading_costs_the_float32_array_and_a_block(tmp_path, kind):
    n_points = 400_000
    points = random_points(n_points, seed=2)
    content = npy_bytes(points) if kind == "npy" else ply_bytes(points, coordinate_type="f8")
    path = _write(tmp_path, f"big.{kind}", content)
    block_points = n_points // 40
    tracemalloc.start()
    try:
        streamed = read_points_float32(path, block_points=block_points)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    result_bytes = streamed.points.nbytes
    # a float64 copy of the cloud alone would be twice the result
    assert peak < result_bytes + 8 * block_points * 24
    assert peak < 2 * result_bytes


def test_e57_scans_are_read_a_chunk_at_a_time(tmp_path, monkeypatch):
    scans = [random_points(30_000, seed=seed) for seed in range(12)]
    path = _write(tmp_path, "twelve.e57", e57_bytes(scans))
    monkeypatch.setattr(e57_module, "SCAN_CHUNK_POINTS", 4096)
    cloud_bytes = sum(len(scan) for scan in scans) * 3 * 8
    tracemalloc.start()
    try:
        cloud = read_point_cloud(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(cloud) == sum(len(scan) for scan in scans)
    # the cloud, its station index and a chunk: no scan held whole, no second copy
    assert peak < 1.5 * cloud_bytes


def test_e57_chunks_give_the_scans_pye57_reads_whole(tmp_path, monkeypatch):
    scans = [random_points(n, seed=n) for n in (300, 211)]
    invalid = [np.arange(300) % 3 == 0, np.arange(211) % 4 == 1]
    poses = [((0.6, 0.0, 0.0, 0.8), (5, 0, 1)), ((1, 0, 0, 0), (-3, 2, 0))]
    path = _write(tmp_path, "poses.e57", e57_bytes(scans, poses, intensity=True, invalid=invalid))
    with pye57.E57(str(path)) as reader:
        whole = [reader.read_scan(index, intensity=True) for index in range(len(scans))]
    monkeypatch.setattr(e57_module, "SCAN_CHUNK_POINTS", 17)
    chunked = read_point_cloud(path)
    expected = np.concatenate(
        [np.column_stack([scan[f"cartesian{axis}"] for axis in "XYZ"]) for scan in whole]
    )
    np.testing.assert_array_equal(chunked.points, expected)
    np.testing.assert_array_equal(
        chunked.attributes["intensity"], np.concatenate([scan["intensity"] for scan in whole])
    )
    np.testing.assert_array_equal(
        chunked.attributes["station_index"],
        np.repeat(np.arange(len(scans)), [len(scan["intensity"]) for scan in whole]),
    )
    np.testing.assert_array_equal(chunked.sensor_origin, [pose[1] for pose in poses])


def test_e57_times_come_through_the_chunks(tmp_path, monkeypatch):
    points = random_points(500, seed=8)
    times = np.linspace(100.0, 101.0, 500)
    path = _write(tmp_path, "timed.e57", e57_with_times_bytes(points, times))
    flagged = np.zeros(500, dtype=bool)
    flagged[433] = True  # one chunk of 17 among 30: the whole cloud then has no times
    flagged_path = _write(tmp_path, "flagged.e57", e57_with_times_bytes(points, times, flagged))
    monkeypatch.setattr(e57_module, "SCAN_CHUNK_POINTS", 17)
    np.testing.assert_array_equal(read_point_cloud(path).attributes["timeStamp"], times)
    assert "timeStamp" not in read_point_cloud(flagged_path).attributes
