"""The binary PLY/PCD ingest fast paths give exactly the clouds of the slow paths.

Fast: the readers hand ``PointCloud.from_array`` an (n, 3) view of the file's records
(``xyz_points``), which converts it to float64 block by block and checks finiteness on the way
(``dot`` per block, row-by-row check only when that fails), in one thread or split between
several (every test here runs both ways). Slow: ``xyz_from_columns`` fills a
float64 array column by column and ``from_array`` then checks it. Both must agree bit for bit
on points, dropped rows, source_index and attributes, for every layout and byte order.
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import tempfile
from pathlib import Path

import numpy as np
import pytest

from app.core import blocks as blocks_module
from app.core import cloud as cloud_module
from app.core import cloud_summary as summary_module
from app.core.cloud import PointCloud
from app.core.errors import PointCloudError
from app.core.formats import pcd, ply, read_point_cloud, summarise_point_cloud
from app.core.formats._common import file_rows_of, open_source, xyz_from_columns, xyz_view
from app.core.threads import available_threads
from app.testing.files import pcd_bytes, ply_bytes
from tests.helpers.clouds import assert_summary_of

N_POINTS = 257  # not a multiple of the (patched) block size: the last block is partial
VIEWPOINT = (1, 2, 3, 1, 0, 0, 0)  # the sensor at (1, 2, 3)


@pytest.fixture(autouse=True, params=[1, 3], ids=["1 thread", "3 threads"])
def _small_blocks(monkeypatch, request):
    """Many blocks, including a partial last one, even for small test clouds; converted by
    one thread, or shared by three (from 192 rows on)."""
    monkeypatch.setattr(blocks_module, "CHECK_BLOCK_POINTS", 16)
    monkeypatch.setattr(summary_module, "SUMMARY_BLOCK_POINTS", 16)
    monkeypatch.setattr(summary_module, "SUMMARY_ROWS_PER_LINE", 4)
    monkeypatch.setattr(blocks_module, "PARALLEL_MIN_POINTS", 64)
    monkeypatch.setattr(blocks_module, "MAX_CONVERSION_THREADS", 3)
    monkeypatch.setattr(blocks_module, "conversion_threads", lambda: request.param)
    return request.param


def _values(n: int = N_POINTS, seed: int = 0, with_non_finite: bool = True) -> np.ndarray:
    rng = np.random.default_rng(seed)
    values = rng.uniform(-1000.0, 1000.0, size=(n, 3))
    if with_non_finite:
        values[3, 0] = np.nan
        values[40, 2] = np.inf
        values[41, 1] = -np.inf
        values[n - 1] = np.nan  # in the partial last block
    return values


def _structured(layout: list[tuple[str, str]], values: np.ndarray) -> np.ndarray:
    records = np.zeros(len(values), dtype=layout)
    for axis, name in enumerate("xyz"):
        records[name] = values[:, axis]
    for name, _ in layout:
        if name not in "xyz":
            records[name] = np.arange(len(values)) % 7 + 1
    return records


def _assert_same_cloud(fast: PointCloud, slow: PointCloud) -> None:
    assert fast.points.dtype == np.float64 and fast.points.flags.c_contiguous
    assert fast.points.flags.owndata and fast.points.flags.writeable
    np.testing.assert_array_equal(fast.points, slow.points)
    assert fast.n_source == slow.n_source and fast.n_dropped == slow.n_dropped
    np.testing.assert_array_equal(fast.source_index, slow.source_index)
    assert fast.attributes.keys() == slow.attributes.keys()
    for name, values in slow.attributes.items():
        assert fast.attributes[name].dtype == values.dtype
        np.testing.assert_array_equal(fast.attributes[name], values)
    if slow.sensor_origin is None:
        assert fast.sensor_origin is None
    else:
        np.testing.assert_array_equal(fast.sensor_origin, slow.sensor_origin)


def _fast_and_slow(monkeypatch, module, content: bytes, filename: str):
    """The cloud read from bytes (fast path), and through the slow path; the same content read
    from a file (its rows then come by ``pread``, see ``FileRows``) must equal the first, and
    the summaries of both (what uploads are checked with) must describe the slow one."""
    fast = read_point_cloud(content, filename=filename)
    with monkeypatch.context() as patch:
        patch.setattr(module, "xyz_points", xyz_from_columns)
        slow = read_point_cloud(content, filename=filename)
    assert_summary_of(summarise_point_cloud(content, filename=filename), slow)
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / filename
        path.write_bytes(content)
        _assert_same_cloud(read_point_cloud(path), fast)
        assert_summary_of(summarise_point_cloud(path), slow)
    return fast, slow


PLY_ENCODINGS = {"<": "binary_little_endian", ">": "binary_big_endian"}

PLY_LAYOUTS = {
    "f4 packed": [("x", "f4"), ("y", "f4"), ("z", "f4")],
    "f8 packed": [("x", "f8"), ("y", "f8"), ("z", "f8")],
    "property before": [("intensity", "u2"), ("x", "f4"), ("y", "f4"), ("z", "f4")],
    "properties around": [("a", "u1"), ("x", "f4"), ("y", "f4"), ("z", "f4"), ("b", "f8")],
    "property between": [("x", "f4"), ("y", "f4"), ("nx", "f4"), ("z", "f4")],
    "z y x": [("z", "f4"), ("y", "f4"), ("x", "f4")],
    "mixed types": [("x", "f8"), ("y", "f4"), ("z", "f4")],
    "int32": [("x", "i4"), ("y", "i4"), ("z", "i4")],
}


@pytest.mark.parametrize("layout", PLY_LAYOUTS, ids=list(PLY_LAYOUTS))
@pytest.mark.parametrize("byte_order", ["<", ">"])
@pytest.mark.parametrize("comment", ["", "c", "ab", "abc", "abcdefg"])  # body alignment 0..7
def test_binary_ply_fast_path_equals_slow_path(monkeypatch, layout, byte_order, comment):
    integer = PLY_LAYOUTS[layout][0][1] == "i4"
    values = np.round(_values(with_non_finite=not integer))
    records = _structured(PLY_LAYOUTS[layout], values)
    content = ply_bytes(records, PLY_ENCODINGS[byte_order], comments=[comment] if comment else [])
    fast, slow = _fast_and_slow(monkeypatch, ply, content, "cloud.ply")
    _assert_same_cloud(fast, slow)
    finite = np.isfinite(values).all(axis=1)
    expected = np.column_stack([records[name].astype(np.float64) for name in "xyz"])[finite]
    np.testing.assert_array_equal(fast.points, expected)
    assert fast.n_dropped == (0 if integer else 4)


PCD_LAYOUTS = {
    "f4 packed": [("x", "F", 4, 1), ("y", "F", 4, 1), ("z", "F", 4, 1)],
    "f8 packed": [("x", "F", 8, 1), ("y", "F", 8, 1), ("z", "F", 8, 1)],
    "padding and rgb": [
        ("x", "F", 4, 1),
        ("y", "F", 4, 1),
        ("z", "F", 4, 1),
        ("_", "U", 1, 4),
        ("rgb", "F", 4, 1),
    ],
    "count > 1 before": [("hist", "F", 4, 3), ("x", "F", 4, 1), ("y", "F", 4, 1), ("z", "F", 4, 1)],
    "field between": [
        ("x", "F", 4, 1),
        ("intensity", "U", 2, 1),
        ("y", "F", 4, 1),
        ("z", "F", 4, 1),
    ],
}


def _pcd_records(fields, values):
    kinds = {"F": "f", "U": "u", "I": "i"}
    layout = [
        (name, f"<{kinds[type_code]}{size}", (count,))
        if count > 1
        else (name, f"<{kinds[type_code]}{size}")
        for name, type_code, size, count in fields
    ]
    records = np.zeros(len(values), dtype=layout)
    for axis, name in enumerate("xyz"):
        records[name] = values[:, axis]
    for name, *_ in fields:
        if name not in "xyz":
            records[name] = (np.arange(len(values)) % 5 + 1).reshape(
                (-1,) + (1,) * (records[name].ndim - 1)
            )
    return records


@pytest.mark.parametrize("layout", PCD_LAYOUTS, ids=list(PCD_LAYOUTS))
@pytest.mark.parametrize("encoding", ["binary", "binary_compressed"])
def test_pcd_fast_path_equals_slow_path(monkeypatch, layout, encoding):
    values = _values()
    content = pcd_bytes(_pcd_records(PCD_LAYOUTS[layout], values), encoding, viewpoint=VIEWPOINT)
    fast, slow = _fast_and_slow(monkeypatch, pcd, content, "cloud.pcd")
    _assert_same_cloud(fast, slow)
    assert fast.n_dropped == 4
    np.testing.assert_array_equal(fast.sensor_origin, [1.0, 2.0, 3.0])
    assert "_" not in fast.attributes and not any(k.startswith("#") for k in fast.attributes)


def test_xyz_view_only_for_equally_spaced_columns_of_one_buffer():
    records = np.zeros(5, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("w", "<f4")])
    view = xyz_view(records["x"], records["y"], records["z"])
    assert view is not None and view.shape == (5, 3) and not view.flags.writeable
    assert np.shares_memory(view, records)
    assert xyz_view(records["x"], records["y"], records["w"]) is None  # uneven spacing
    assert xyz_view(records["z"], records["y"], records["x"]) is None  # backwards
    assert xyz_view(records["x"], records["y"], records["z"].copy()) is None  # two buffers
    assert xyz_view(np.zeros(5), np.zeros(5), np.zeros(5)) is None
    mixed = np.zeros(5, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<i4")])
    assert xyz_view(mixed["x"], mixed["y"], mixed["z"]) is None


@pytest.mark.parametrize("dtype", ["<f4", ">f4", "<f8", ">f8", "<i4", "<u2", "<f2"])
@pytest.mark.parametrize("aligned", [True, False])
def test_from_array_converts_any_view_like_a_float64_copy(dtype, aligned):
    values = _values(with_non_finite=np.dtype(dtype).kind == "f")
    raw = values.astype(dtype)
    buffer = (b"" if aligned else b"\x00") + raw.tobytes()
    view = np.frombuffer(buffer, dtype=dtype, offset=0 if aligned else 1).reshape(-1, 3)
    assert view.flags.aligned == aligned or np.dtype(dtype).itemsize == 1
    fast = PointCloud.from_array(view, attributes={"i": np.arange(len(view))})
    slow = PointCloud.from_array(
        np.array(raw, dtype=np.float64), attributes={"i": np.arange(len(view))}
    )
    _assert_same_cloud(fast, slow)
    assert not np.shares_memory(fast.points, view)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_huge_finite_values_are_kept(dtype):
    """dot(v, v) overflows to inf for huge values: the row check then keeps every row."""
    big = np.finfo(dtype).max / 4
    values = np.full((40, 3), big, dtype=dtype)
    values[::2] *= -1
    cloud = PointCloud.from_array(values)
    assert len(cloud) == 40 and cloud.n_dropped == 0
    np.testing.assert_array_equal(cloud.points, values.astype(np.float64))


def test_signalling_nan_rows_are_dropped_silently():
    values = np.ones((20, 3), dtype=np.float32)
    values.view(np.uint32)[5, 1] = 0x7F800001  # signalling NaN
    with np.errstate(all="raise"):
        cloud = PointCloud.from_array(values.copy())
        view_cloud = PointCloud.from_array(np.frombuffer(values.tobytes(), "<f4").reshape(-1, 3))
    assert cloud.n_dropped == view_cloud.n_dropped == 1
    assert 5 not in view_cloud.source_index


def test_all_non_finite_and_too_few_points_give_the_same_errors():
    with pytest.raises(PointCloudError, match="none of the 30 points"):
        PointCloud.from_array(
            np.frombuffer(np.full(90, np.nan, "<f4").tobytes(), "<f4").reshape(-1, 3)
        )
    few = np.zeros((30, 3), dtype=np.float32)
    few[5:] = np.nan
    with pytest.raises(PointCloudError, match=r"only 5 finite points \(of 30\)"):
        PointCloud.from_array(few)


def test_owned_float64_points_are_not_copied_and_read_only_ones_are():
    points = np.random.default_rng(1).uniform(size=(50, 3))
    assert PointCloud.from_array(points).points is points
    frozen = points.copy()
    frozen.flags.writeable = False
    kept = PointCloud.from_array(frozen).points
    assert kept.flags.writeable and not np.shares_memory(kept, frozen)
    np.testing.assert_array_equal(kept, frozen)


def test_lazy_source_index_behaves_like_an_arange():
    cloud = PointCloud.from_array(np.zeros((30, 3)))
    labels = np.arange(30) * 2
    np.testing.assert_array_equal(cloud.to_source_order(labels, fill=-1), labels)
    np.testing.assert_array_equal(cloud.from_source_order(labels), labels)
    assert cloud.from_source_order(labels) is not labels
    np.testing.assert_array_equal(cloud.source_index, np.arange(30))
    assert cloud.source_index.dtype == np.int64 and cloud.source_index is cloud.source_index
    restored = pickle.loads(pickle.dumps(PointCloud.from_array(np.zeros((30, 3)))))
    np.testing.assert_array_equal(restored.source_index, np.arange(30))
    moved = dataclasses.replace(cloud, sensor_origin=np.ones(3))
    np.testing.assert_array_equal(moved.source_index, np.arange(30))
    explicit = PointCloud(np.zeros((3, 3)), np.array([0, 2, 5]), 6)
    np.testing.assert_array_equal(explicit.source_index, [0, 2, 5])
    assert explicit.to_source_order(np.array([1, 2, 3]), fill=0).tolist() == [1, 0, 2, 0, 0, 3]
    with pytest.raises(TypeError):
        PointCloud(np.zeros((3, 3)))  # source_index and n_source stay required


def test_ply_header_longer_than_the_peek_or_ending_at_its_edge(tmp_path):
    values = _values(with_non_finite=False)
    records = _structured(PLY_LAYOUTS["f4 packed"], values)
    plain = ply_bytes(records)
    header_length = plain.index(b"end_header\n") + len(b"end_header\n")
    comment_line = len(b"comment \n")
    for target in (
        ply.HEADER_PEEK_BYTES - 1,
        ply.HEADER_PEEK_BYTES,
        ply.HEADER_PEEK_BYTES + 1,
        3 * ply.HEADER_PEEK_BYTES,
    ):
        comment = "c" * (target - header_length - comment_line)
        content = ply_bytes(records, comments=[comment])
        assert content.index(b"end_header\n") + len(b"end_header\n") == target
        path = tmp_path / f"long_{target}.ply"
        path.write_bytes(content)
        cloud = read_point_cloud(path)
        np.testing.assert_array_equal(cloud.points, values.astype(np.float32).astype(np.float64))


@pytest.mark.parametrize(
    ("build", "expect_view"),
    [
        (lambda: _ply_content("f4 packed", "<"), True),
        (lambda: _ply_content("f8 packed", ">"), True),
        (lambda: _ply_content("properties around", "<"), True),
        (lambda: _ply_content("property between", "<"), False),
        (lambda: _pcd_content("padding and rgb", "binary"), True),
        (lambda: _pcd_content("count > 1 before", "binary_compressed"), True),
        (lambda: _pcd_content("field between", "binary"), False),
    ],
)
def test_readers_hand_over_a_view_when_the_layout_allows(build, expect_view):
    content, reader = build()
    with open_source(content) as source:
        raw = reader(source, None)
        assert (raw.points.dtype != np.float64 or not raw.points.flags.owndata) == expect_view
        assert raw.points.shape == (N_POINTS, 3)


def _ply_content(layout: str, byte_order: str):
    records = _structured(PLY_LAYOUTS[layout], _values())
    return ply_bytes(records, PLY_ENCODINGS[byte_order]), ply.read_ply


def _pcd_content(layout: str, encoding: str):
    fields = PCD_LAYOUTS[layout]
    return pcd_bytes(_pcd_records(fields, _values()), encoding, viewpoint=VIEWPOINT), pcd.read_pcd


@pytest.mark.parametrize("n", [1, 255, 256, 257, 1000, 5 * 256])
@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int32])
def test_column_extreme_equals_the_plain_reduction(n, dtype):
    points = (np.random.default_rng(n).normal(size=(n, 3)) * 1000).astype(dtype)
    for ufunc in (np.minimum, np.maximum):
        np.testing.assert_array_equal(
            cloud_module.column_extreme(points, ufunc), ufunc.reduce(points, axis=0)
        )
        strided = np.asfortranarray(points)
        np.testing.assert_array_equal(
            cloud_module.column_extreme(strided, ufunc), ufunc.reduce(points, axis=0)
        )
    if dtype is not np.int32:
        points[n // 2, 1] = np.nan
        low = cloud_module.column_extreme(points, np.minimum)
        assert np.isnan(low[1]) and not np.isnan(low[[0, 2]]).any()
    with pytest.raises(ValueError, match="zero-size"):
        cloud_module.column_extreme(points[:0], np.minimum)


def test_bounds_and_local_origin_use_the_fast_extremes():
    points = np.random.default_rng(2).uniform(-5, 5, size=(1000, 3)) + np.array([5e5, 5e6, 100.0])
    cloud = PointCloud.from_array(points)
    low, high = cloud.bounds()
    np.testing.assert_array_equal(low, points.min(axis=0))
    np.testing.assert_array_equal(high, points.max(axis=0))
    centre = (points.min(axis=0) + points.max(axis=0)) / 2
    np.testing.assert_array_equal(cloud_module.choose_local_origin(points), np.round(centre))


@pytest.mark.parametrize("threads", [1, 2, 3, 4, 16])
@pytest.mark.parametrize("n_points", [63, 64, 65, 128, 129, 200, 257, 1000])
@pytest.mark.parametrize("aligned", [True, False])
def test_threaded_conversion_equals_one_thread(threads, n_points, aligned):
    """Any number of threads (more than there are blocks included) gives the one-thread
    cloud, non-finite rows in any block included."""
    values = _values(n=n_points, seed=n_points)
    values[n_points // 2, 1] = np.nan  # in a later part
    buffer = (b"" if aligned else b"\x00") + values.astype("<f4").tobytes()
    view = np.frombuffer(buffer, "<f4", offset=0 if aligned else 1).reshape(-1, 3)
    attributes = {"i": np.arange(n_points)}
    split = PointCloud.from_array(view, attributes=attributes, threads=threads)
    single = PointCloud.from_array(view, attributes=attributes, threads=1)
    _assert_same_cloud(split, single)
    finite_values = values.astype(np.float32).astype(np.float64)
    np.testing.assert_array_equal(split.points, finite_values[np.isfinite(values).all(axis=1)])


def test_all_finite_clouds_need_no_row_check_whatever_the_threads(monkeypatch):
    values = _values(n=300, with_non_finite=False).astype(np.float32)
    monkeypatch.setattr(np, "isfinite", _refuse_row_check(np.isfinite))
    for threads in (1, 2, 3):
        cloud = PointCloud.from_array(values, threads=threads)
        assert cloud.n_dropped == 0 and cloud.source_index.tolist() == list(range(300))


def _refuse_row_check(isfinite):
    def guarded(values, *args, **kwargs):
        if np.ndim(values) == 2:
            raise AssertionError("row-by-row check on an all-finite cloud")
        return isfinite(values, *args, **kwargs)

    return guarded


def test_an_error_in_a_helper_thread_reaches_the_caller(monkeypatch):
    original = blocks_module._convert_blocks
    calls = []

    def failing(array, out, block_numbers, file_rows=None):
        calls.append(len(array))
        if len(calls) == 2:
            raise MemoryError("no room for this part")
        return original(array, out, block_numbers, file_rows)

    monkeypatch.setattr(blocks_module, "_convert_blocks", failing)
    values = _values(n=200).astype(np.float32)
    with pytest.raises(MemoryError, match="no room"):
        PointCloud.from_array(values, threads=2)


def test_conversion_threads_follow_omp_num_threads_and_the_cap(monkeypatch):
    monkeypatch.undo()  # the real conversion_threads and cap
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert blocks_module.conversion_threads() == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "64")
    assert blocks_module.conversion_threads() == blocks_module.MAX_CONVERSION_THREADS
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert 1 <= blocks_module.conversion_threads() <= blocks_module.MAX_CONVERSION_THREADS


@pytest.mark.parametrize(
    ("cpus", "load", "expected"),
    [(2, 0.1, 2), (2, 1.3, 2), (2, 1.6, 1), (2, 3.5, 1), (1, 0.0, 1), (8, 5.0, 2), (8, 7.8, 1)],
)
def test_conversion_threads_leave_busy_cpus_alone(monkeypatch, cpus, load, expected):
    monkeypatch.undo()  # the real conversion_threads and cap
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(blocks_module.os, "sched_getaffinity", lambda pid: set(range(cpus)))
    monkeypatch.setattr(blocks_module.os, "getloadavg", lambda: (load, load, load))
    assert blocks_module.conversion_threads() == expected


def test_conversion_without_a_spare_thread_happens_in_the_caller(monkeypatch):
    def refuse(self):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(blocks_module.threading.Thread, "start", refuse)
    values = _values(n=200).astype(np.float32)
    _assert_same_cloud(
        PointCloud.from_array(values, threads=3), PointCloud.from_array(values, threads=1)
    )


def test_available_threads_ignore_the_load(monkeypatch):
    """The LAZ default: lazrs's threads do not hold the GIL, so only OMP_NUM_THREADS and the
    affinity mask count."""
    monkeypatch.undo()
    monkeypatch.setattr(blocks_module.os, "sched_getaffinity", lambda pid: {0, 1, 2})
    monkeypatch.setattr(blocks_module.os, "getloadavg", lambda: (9.0, 9.0, 9.0))
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert available_threads() == 3
    assert blocks_module.conversion_threads() == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "5")
    assert available_threads() == 5
    assert blocks_module.conversion_threads() == blocks_module.MAX_CONVERSION_THREADS


def test_file_rows_are_read_with_pread_and_a_file_changed_meanwhile_is_an_error(
    monkeypatch, tmp_path
):
    content, _ = _ply_content("properties around", "<")  # 17-byte records: unaligned rows
    path = tmp_path / "cloud.ply"
    path.write_bytes(content)
    with open_source(path) as source:
        raw = ply.read_ply(source, None)
        rows = file_rows_of(raw.points, source)
        assert rows is not None and rows.file_descriptor == source.file_descriptor
        assert content[rows.offset : rows.offset + 4] == raw.points[:1, 0].tobytes()
    with open_source(content) as source:  # bytes: no file to read from
        assert file_rows_of(ply.read_ply(source, None).points, source) is None

    reads = []
    original_read = blocks_module._BlockReader.read

    def counted(reader, start, rows):
        reads.append(rows)
        return original_read(reader, start, rows)

    monkeypatch.setattr(blocks_module._BlockReader, "read", counted)
    cloud = read_point_cloud(path)
    assert sum(reads) == N_POINTS and len(cloud) == N_POINTS - 4

    # the file shrank after it was mapped: say so instead of converting garbage
    monkeypatch.setattr(blocks_module.os, "preadv", lambda fd, buffers, offset: 5)
    with pytest.raises(PointCloudError, match="changed while it was read"):
        read_point_cloud(path)
    assert os.path.getsize(path) == len(content)
