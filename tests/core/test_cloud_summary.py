"""Summaries (what an upload is checked with) agree with the clouds they stand for.

``summarise_point_cloud`` must accept exactly what ``read_point_cloud`` accepts, refuse what
it refuses with the same message, and report the counts, bounds and sensor origin of the
cloud it would return, for every format and for corrupted files too; and it must do so
without a float64 copy of the coordinates.
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from app.core import blocks as blocks_module
from app.core import cloud_summary as summary_module
from app.core.cloud import MIN_POINTS, PointCloud
from app.core.cloud_summary import summarise_array
from app.core.errors import PointCloudError
from app.core.formats import las, read_point_cloud, summarise_point_cloud
from app.testing.files import las_bytes, pcd_bytes, ply_bytes
from app.testing.scenes import random_points
from tests.helpers.clouds import assert_summary_of
from tests.helpers.corpus import FUZZ_SEEDS, MALFORMED, mutate_bytes


def peak_traced_bytes(action) -> int:
    """Peak bytes of Python and numpy allocations while ``action()`` runs (numpy reports its
    buffers to ``tracemalloc``)."""
    tracemalloc.start()
    try:
        action()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def _outcome(function, *args, **kwargs):
    """``("ok", result)`` or ``("error", message)`` of a call that may raise PointCloudError."""
    try:
        return "ok", function(*args, **kwargs)
    except PointCloudError as exc:
        return "error", str(exc)


@pytest.fixture(
    params=[(16, 4, 1), (16, 4, 3), (1 << 16, 2048, 1)],
    ids=["16-row blocks", "16-row blocks, 3 threads", "default blocks"],
)
def block_points(monkeypatch, request):
    """Many small blocks of whole and partial 4-row lines (a partial last block, blocks of NaN
    rows only), in one thread or shared by three; or the default sizes."""
    block_points, rows_per_line, threads = request.param
    monkeypatch.setattr(summary_module, "SUMMARY_BLOCK_POINTS", block_points)
    monkeypatch.setattr(summary_module, "SUMMARY_ROWS_PER_LINE", rows_per_line)
    monkeypatch.setattr(blocks_module, "PARALLEL_MIN_POINTS", 64)
    monkeypatch.setattr(blocks_module, "conversion_threads", lambda: threads)
    return block_points


@pytest.mark.parametrize(
    "dtype", ["<f4", ">f4", "<f8", ">f8", "<f2", "<i4", ">i2", "<u1", "?"], ids=str
)
@pytest.mark.parametrize("with_non_finite", [False, True], ids=["finite", "non-finite rows"])
def test_array_summary_equals_the_cloud_for_any_dtype(block_points, dtype, with_non_finite):
    rng = np.random.default_rng(3)
    values = rng.uniform(-100, 100, size=(301, 3)).astype(dtype)
    if with_non_finite and np.dtype(dtype).kind == "f":
        values[[0, 17, 18, 300], [0, 1, 2, 1]] = [np.nan, np.inf, -np.inf, np.nan]
        values[32:48] = np.nan  # a whole 16-row block of dropped rows
    assert_summary_of(summarise_array(values), PointCloud.from_array(values))


@pytest.mark.parametrize("offset", [0, 1, 2, 5], ids=lambda offset: f"offset {offset}")
def test_array_summary_of_padded_unaligned_records(block_points, offset):
    """Records with other fields between the points, starting at any byte (a PLY body after a
    header of any length)."""
    layout = np.dtype([("a", "u1"), ("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("b", "<f8")])
    raw = np.zeros(offset + 200 * layout.itemsize, np.uint8)
    records = raw[offset:].view(layout)
    values = np.random.default_rng(4).normal(size=(200, 3)) * 1e3
    values[7, 2] = np.nan
    for axis, name in enumerate("xyz"):
        records[name] = values[:, axis]
    view = np.ndarray((200, 3), ">f4", raw, offset + 1, (layout.itemsize, 4))
    assert not view.flags.c_contiguous
    assert_summary_of(summarise_array(view), PointCloud.from_array(view))


@pytest.mark.parametrize(
    ("points", "attributes", "sensor_origin"),
    [
        (np.zeros((0, 3)), None, None),
        (np.full((30, 3), np.nan), None, None),
        (np.zeros((MIN_POINTS - 1, 3), np.float32), None, None),
        (np.zeros((30, 2)), None, None),
        (np.array([["a", "b", "c"]] * 20), None, None),
        (np.zeros((20, 3)), {"rgb": np.zeros(19)}, None),
        (np.zeros((20, 3)), None, [0.0, np.nan, 0.0]),
    ],
    ids=["empty", "all NaN", "too few", "2 columns", "strings", "attribute rows", "origin"],
)
def test_array_summary_refuses_what_the_cloud_refuses(points, attributes, sensor_origin):
    with pytest.raises(PointCloudError) as expected:
        PointCloud.from_array(points, attributes, sensor_origin)
    with pytest.raises(PointCloudError) as got:
        summarise_array(points, attributes, sensor_origin)
    assert str(got.value) == str(expected.value)


def test_array_summary_memory_stays_at_a_block_whatever_the_cloud(monkeypatch):
    """The point of summaries: a 1M-point float32 cloud (12 MB) is checked with a few blocks of
    new arrays (here 245 blocks of 4096 points: nothing may grow with their number), where
    building the cloud allocates its 24 MB float64 copy."""
    monkeypatch.setattr(summary_module, "SUMMARY_BLOCK_POINTS", 4096)
    values = np.random.default_rng(5).normal(size=(1_000_000, 3)).astype(np.float32)
    values[123_456] = np.nan

    summary_peak = peak_traced_bytes(lambda: summarise_array(values, threads=1))
    cloud_peak = peak_traced_bytes(lambda: PointCloud.from_array(values, threads=1))
    assert_summary_of(summarise_array(values, threads=2), PointCloud.from_array(values))
    block_bytes = 4096 * 3 * 4
    line_bytes = summary_module.SUMMARY_ROWS_PER_LINE * 3 * 4
    assert cloud_peak >= values.size * 8  # the float64 copy
    assert summary_peak < 4 * (block_bytes + line_bytes), (summary_peak, block_bytes)


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_file_summary_refuses_malformed_input_with_the_reading_message(case):
    filename, build, _ = MALFORMED[case]
    content = build()
    expected = _outcome(read_point_cloud, content, filename=filename)
    assert expected[0] == "error"
    assert _outcome(summarise_point_cloud, content, filename=filename) == expected


@pytest.mark.parametrize("kind", sorted(FUZZ_SEEDS))
def test_file_summary_agrees_with_reading_on_corrupted_files(kind):
    """Each corruption is either refused by both with the same message or accepted by both
    with the same counts and bounds (some flips only change coordinates)."""
    content = FUZZ_SEEDS[kind](random_points(200))
    rng = np.random.default_rng(100 + sorted(FUZZ_SEEDS).index(kind))
    for _ in range(25):
        data = bytes(mutate_bytes(bytearray(content), rng, int(rng.integers(4))))
        filename = f"scan.{kind.split('-')[0]}"
        read = _outcome(read_point_cloud, data, filename=filename)
        summary = _outcome(summarise_point_cloud, data, filename=filename)
        assert read[0] == summary[0], (read, summary)
        if read[0] == "error":
            assert summary[1] == read[1]
        else:
            assert_summary_of(summary[1], read[1])


@pytest.mark.parametrize("kind", sorted(FUZZ_SEEDS))
def test_file_summary_equals_the_read_cloud_from_bytes_and_from_disk(tmp_path, kind):
    points = random_points(500)
    points[[3, 250]] = np.nan
    if kind.startswith(("las", "laz")):
        points = random_points(500)  # LAS holds integers: no NaN to write
    content = FUZZ_SEEDS[kind](points)
    filename = f"scan.{kind.split('-')[0]}"
    cloud = read_point_cloud(content, filename=filename)
    assert_summary_of(summarise_point_cloud(content, filename=filename), cloud)
    path = tmp_path / filename
    path.write_bytes(content)
    assert_summary_of(summarise_point_cloud(path), cloud)


def test_file_summary_keeps_the_sensor_origin_and_the_point_limit():
    points = random_points(100)
    content = pcd_bytes(points, "binary", viewpoint=(1.5, -2.0, 0.25, 1, 0, 0, 0))
    summary = summarise_point_cloud(content, filename="scan.pcd")
    np.testing.assert_array_equal(summary.sensor_origin, [1.5, -2.0, 0.25])
    with pytest.raises(PointCloudError, match="more than the limit of 10"):
        summarise_point_cloud(ply_bytes(points), filename="scan.ply", max_points=10)


@pytest.mark.parametrize("compress", [False, True], ids=["las", "laz"])
@pytest.mark.parametrize("threads", [1, 2])
def test_las_summary_over_many_chunks_equals_the_read_cloud(monkeypatch, compress, threads):
    """LAS/LAZ are summarised a decoded chunk at a time (here 16 chunks of 64 points, each of
    whole and partial 4-row lines), by the sequential and the parallel LAZ decoder."""
    monkeypatch.setattr(las, "SUMMARY_CHUNK_POINTS", 64)
    monkeypatch.setattr(summary_module, "SUMMARY_ROWS_PER_LINE", 4)
    content = las_bytes(random_points(1000, seed=7) * 40.0, compress=compress)
    filename = "scan.laz" if compress else "scan.las"
    cloud = read_point_cloud(content, filename=filename, threads=threads)
    summary = summarise_point_cloud(content, filename=filename, threads=threads)
    assert_summary_of(summary, cloud)
    with pytest.raises(PointCloudError, match=r"truncated|corrupt") as expected:
        read_point_cloud(content[: len(content) - 200], filename=filename, threads=threads)
    with pytest.raises(PointCloudError) as got:
        summarise_point_cloud(content[: len(content) - 200], filename=filename, threads=threads)
    assert str(got.value) == str(expected.value)


@pytest.mark.parametrize("compress", [False, True], ids=["las", "laz"])
def test_las_summary_memory_stays_at_a_chunk(monkeypatch, tmp_path, compress):
    """A 200k-point LAS/LAZ file summarised 4096 points at a time allocates a few chunks of
    arrays (nothing grows with the 49 chunks), where reading it allocates every point's
    coordinates and fields. (Bytes, not a file, would be copied whole for laspy's stream.)"""
    monkeypatch.setattr(las, "SUMMARY_CHUNK_POINTS", 4096)
    points = np.random.default_rng(8).uniform(-500, 500, size=(200_000, 3))
    path = tmp_path / ("scan.laz" if compress else "scan.las")
    path.write_bytes(las_bytes(points, compress=compress))

    summary_peak = peak_traced_bytes(lambda: summarise_point_cloud(path))
    read_peak = peak_traced_bytes(lambda: read_point_cloud(path))
    record_bytes = 34  # point format 3
    assert read_peak >= len(points) * 24  # the float64 coordinates alone
    assert summary_peak < 8 * 4096 * (24 + record_bytes), (summary_peak, read_peak)
