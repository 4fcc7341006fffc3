"""Reading, writing and detecting point-cloud formats (app.core.formats).

Files are written with the reference libraries (plyfile, pypcd4, laspy, numpy) and read back
with ours; the malformed corpus checks that every broken input raises PointCloudError with a
message that says what is wrong.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Callable
from pathlib import Path

import numpy as np
import plyfile
import pytest

from app.core.errors import PointCloudError, UnsupportedFormatError
from app.core.formats import (
    SUPPORTED_FORMATS,
    detect_format,
    read_point_cloud,
    write_point_cloud,
)
from app.testing.files import las_bytes, npy_bytes, npz_bytes, pcd_bytes, ply_bytes, text_bytes
from app.testing.scenes import random_points
from tests.helpers.corpus import FUZZ_SEEDS, MALFORMED, N_POINTS, mutate_bytes

# ----------------------------------------------------------------------------------------------
# round trips


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_round_trip_keeps_points_and_extra_properties(encoding):
    points = random_points()
    extra = {
        "red": np.arange(N_POINTS, dtype=np.uint8),
        "intensity": np.linspace(0, 1, N_POINTS).astype(np.float32),
        "label": np.arange(N_POINTS, dtype=np.int32) - 5,
    }
    cloud = read_point_cloud(ply_bytes(points, encoding, extra=extra), filename="scan.ply")
    assert cloud.points.dtype == np.float64
    np.testing.assert_array_equal(cloud.points, points)
    assert set(cloud.attributes) == set(extra)
    for name, values in extra.items():
        np.testing.assert_array_equal(cloud.attributes[name], values)
        assert cloud.attributes[name].dtype == values.dtype
        assert cloud.attributes[name].dtype.isnative


@pytest.mark.parametrize("coordinate_type", ["f8", "f4", "i2", "u1", "i4"])
def test_ply_coordinates_of_any_numeric_type(coordinate_type):
    points = np.random.default_rng(1).integers(0, 100, size=(N_POINTS, 3)).astype(np.float64)
    cloud = read_point_cloud(ply_bytes(points, coordinate_type=coordinate_type), format="ply")
    np.testing.assert_array_equal(cloud.points, points)


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian"])
def test_ply_mesh_faces_are_ignored_and_list_elements_before_vertices_are_skipped(encoding):
    points = random_points()
    faces = np.empty(3, dtype=[("vertex_indices", "i4", (3,))])
    faces["vertex_indices"] = [[0, 1, 2], [1, 2, 3], [2, 3, 4]]
    face_element = plyfile.PlyElement.describe(faces, "face")
    after = read_point_cloud(
        ply_bytes(points, encoding, other_elements=(face_element,)), format="ply"
    )
    np.testing.assert_array_equal(after.points, points)
    before = read_point_cloud(
        ply_bytes(points, encoding, elements_before=(face_element,)), format="ply"
    )
    np.testing.assert_array_equal(before.points, points)


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_pcd_round_trip_with_packed_rgb_normals_curvature_intensity(encoding):
    points = random_points()
    rgb = (np.arange(N_POINTS, dtype=np.uint32) * 0x010203) & 0xFFFFFF
    extra = {
        "rgb": rgb.view(np.float32),  # PCL's habit: packed colour declared as float32
        "normal_x": np.linspace(-1, 1, N_POINTS).astype(np.float32),
        "curvature": np.linspace(0, 0.1, N_POINTS).astype(np.float32),
        "intensity": np.arange(N_POINTS, dtype=np.uint16),
    }
    if encoding == "ascii":
        extra["rgb"] = rgb  # pypcd4 prints floats with 10 decimals: colours only survive as U4
    cloud = read_point_cloud(pcd_bytes(points, encoding, extra), filename="scan.pcd")
    np.testing.assert_allclose(cloud.points, points, atol=1e-6)
    assert cloud.attributes["rgb"].dtype == np.uint32
    np.testing.assert_array_equal(cloud.attributes["rgb"], rgb)
    np.testing.assert_allclose(cloud.attributes["normal_x"], extra["normal_x"], atol=1e-6)
    np.testing.assert_allclose(cloud.attributes["curvature"], extra["curvature"], atol=1e-6)
    np.testing.assert_array_equal(cloud.attributes["intensity"], extra["intensity"])
    assert cloud.sensor_origin is None  # default viewpoint means "unknown"


def test_pcd_viewpoint_becomes_sensor_origin():
    content = pcd_bytes(random_points(), "binary", viewpoint=(1.5, -2.0, 0.25, 1, 0, 0, 0))
    cloud = read_point_cloud(content, format="pcd")
    np.testing.assert_array_equal(cloud.sensor_origin, [1.5, -2.0, 0.25])


def test_pcd_field_with_count_above_one_becomes_a_2d_attribute():
    points = random_points()
    header = (
        "VERSION 0.7\nFIELDS x y z hist\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 3\n"
        f"WIDTH {N_POINTS}\nHEIGHT 1\nPOINTS {N_POINTS}\nDATA binary\n"
    ).encode()
    records = np.zeros((N_POINTS, 6), dtype=np.float32)
    records[:, :3] = points
    records[:, 3:] = np.arange(3 * N_POINTS).reshape(-1, 3)
    cloud = read_point_cloud(header + records.tobytes(), format="pcd")
    assert cloud.attributes["hist"].shape == (N_POINTS, 3)
    np.testing.assert_array_equal(cloud.attributes["hist"], records[:, 3:])


def test_pcd_binary_zero_padding_after_the_points_is_accepted():
    content = pcd_bytes(random_points(), "binary") + bytes(4000)  # PCL pads its binary files
    assert len(read_point_cloud(content, format="pcd")) == N_POINTS


@pytest.mark.parametrize(("compress", "point_format"), [(False, 3), (True, 3), (True, 6)])
def test_las_and_laz_round_trip(compress, point_format):
    points = np.round(random_points(), 3)
    version = "1.4" if point_format >= 6 else "1.2"
    content = las_bytes(points, compress=compress, point_format=point_format, version=version)
    name = "scan.laz" if compress else "scan.las"
    assert detect_format(name, content[:4096]) == ("laz" if compress else "las")
    cloud = read_point_cloud(content, filename=name)
    np.testing.assert_allclose(cloud.points, points, atol=1e-9)
    np.testing.assert_array_equal(cloud.attributes["intensity"], np.arange(N_POINTS))
    np.testing.assert_array_equal(cloud.attributes["classification"], 2)
    if point_format == 3:
        np.testing.assert_array_equal(cloud.attributes["red"], np.arange(N_POINTS) * 100)


@pytest.mark.parametrize("point_format", [3, 6])
def test_laz_decoded_in_parallel_equals_sequential(point_format):
    """Several LAZ chunks (50,000 points each): the parallel decoder gives the sequential
    cloud."""
    points = np.round(random_points(120_000, seed=4), 3)
    version = "1.4" if point_format >= 6 else "1.2"
    content = las_bytes(points, compress=True, point_format=point_format, version=version)
    sequential = read_point_cloud(content, filename="scan.laz", threads=1)
    parallel = read_point_cloud(content, filename="scan.laz", threads=2)
    np.testing.assert_allclose(sequential.points, points, atol=1e-9)
    np.testing.assert_array_equal(parallel.points, sequential.points)
    assert parallel.attributes.keys() == sequential.attributes.keys()
    for name, values in sequential.attributes.items():
        np.testing.assert_array_equal(parallel.attributes[name], values)


def test_georeferenced_las_keeps_millimetres():
    rng = np.random.default_rng(3)
    utm = np.column_stack(
        [
            512_345.0 + rng.uniform(0, 300, 500),
            5_412_345.0 + rng.uniform(0, 300, 500),
            240.0 + rng.uniform(0, 30, 500),
        ]
    )
    utm = np.round(utm, 3)  # the file's resolution: 1 mm
    for compress in (False, True):
        cloud = read_point_cloud(las_bytes(utm, compress=compress), format="laz")
        assert np.abs(cloud.points - utm).max() < 1e-6  # float32 would be off by ~0.25 m
    assert np.abs(utm.astype(np.float32).astype(np.float64) - utm).max() > 0.1


@pytest.mark.parametrize(
    ("delimiter", "header"),
    [
        (" ", None),
        ("\t", None),
        (",", None),
        (";", None),
        (",", "x,y,z"),
        (" ", "X Y Z"),
        (";", "x;y;z"),
        (",", "//X,Y,Z"),
        (" ", "# x y z"),
    ],
)
def test_text_round_trip_with_any_delimiter_and_optional_header(delimiter, header):
    points = random_points()
    cloud = read_point_cloud(text_bytes(points, delimiter, header), filename="scan.txt")
    np.testing.assert_array_equal(cloud.points, points)
    assert cloud.attributes == {}


def test_text_named_columns_become_attributes_and_order_is_free():
    points = random_points()
    intensity = np.arange(N_POINTS, dtype=np.float64)
    rows = [
        f"{i},{float(p[2])!r},{float(p[0])!r},{float(p[1])!r},name{i}"
        for i, p in zip(intensity, points, strict=True)
    ]
    content = ("intensity,Z[m],X[m],Y[m],comment\n" + "\n".join(rows)).encode()
    cloud = read_point_cloud(content, filename="scan.csv")
    np.testing.assert_array_equal(cloud.points, points)
    assert set(cloud.attributes) == {"intensity"}  # the text column is not numeric: skipped
    np.testing.assert_array_equal(cloud.attributes["intensity"], intensity)


def test_text_without_header_uses_first_three_numeric_columns():
    points = random_points()
    rows = [
        f"p{i} {float(p[0])!r} {float(p[1])!r} {float(p[2])!r} 7 8" for i, p in enumerate(points)
    ]
    cloud = read_point_cloud(("\n".join(rows)).encode(), filename="scan.xyz")
    np.testing.assert_array_equal(cloud.points, points)


def test_text_semicolons_with_decimal_commas():
    content = "\n".join(f"{i},5;{i},25;-{i},0" for i in range(20)).encode()
    cloud = read_point_cloud(content, filename="scan.csv")
    np.testing.assert_array_equal(cloud.points[3], [3.5, 3.25, -3.0])


def test_text_with_utf8_bom_crlf_and_comments():
    points = random_points()
    body = text_bytes(points, ",", "x,y,z").decode().replace("\n", "\r\n")
    content = ("\ufeff# exported by a scanner\r\n" + body).encode()
    cloud = read_point_cloud(content, filename="scan.csv")
    np.testing.assert_array_equal(cloud.points, points)


@pytest.mark.parametrize("dtype", ["f8", "f4", "i4"])
def test_npy_plain_array(dtype):
    points = np.round(random_points()).astype(dtype)
    cloud = read_point_cloud(npy_bytes(points), filename="scan.npy")
    np.testing.assert_array_equal(cloud.points, points.astype(np.float64))


def test_npy_wide_fortran_and_structured_arrays():
    points = random_points()
    wide = np.asfortranarray(np.column_stack([points, np.ones((N_POINTS, 2))]))
    np.testing.assert_array_equal(read_point_cloud(npy_bytes(wide), "npy").points, points)
    structured = np.zeros(N_POINTS, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("i", "u2")])
    for axis, name in enumerate("xyz"):
        structured[name] = points[:, axis]
    structured["i"] = np.arange(N_POINTS)
    cloud = read_point_cloud(npy_bytes(structured), "npy")
    np.testing.assert_array_equal(cloud.points, points)
    np.testing.assert_array_equal(cloud.attributes["i"], np.arange(N_POINTS))


@pytest.mark.parametrize("layout", ["points", "xyz", "columns", "single"])
def test_npz_layouts_and_per_point_attributes(layout):
    points = random_points()
    label = np.arange(N_POINTS, dtype=np.int8)
    arrays = {
        "points": {"points": points, "label": label},
        "xyz": {"xyz": points, "label": label},
        "columns": {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2], "label": label},
        "single": {"anything": points},
    }[layout]
    cloud = read_point_cloud(npz_bytes(**arrays), filename="scan.npz")
    np.testing.assert_array_equal(cloud.points, points)
    if layout != "single":
        np.testing.assert_array_equal(cloud.attributes["label"], label)


# ----------------------------------------------------------------------------------------------
# writers


@pytest.mark.parametrize("suffix", ["ply", "las", "laz"])
def test_labelled_writer_round_trip(tmp_path, suffix):
    rng = np.random.default_rng(4)
    points = np.column_stack(
        [
            500_000 + rng.uniform(0, 100, 300),
            5_000_000 + rng.uniform(0, 100, 300),
            rng.uniform(0, 10, 300),
        ]
    )
    fields = {
        "label": rng.integers(-1, 2, 300).astype(np.int8),
        "distance": rng.uniform(0, 2, 300).astype(np.float32),
        "region": rng.integers(-1, 5, 300).astype(np.int32),
    }
    path = tmp_path / f"labels.{suffix}"
    write_point_cloud(path, points, fields)
    assert not [p for p in tmp_path.iterdir() if p.name != path.name]  # no temporary left
    cloud = read_point_cloud(path)
    tolerance = 0 if suffix == "ply" else 5e-5  # LAS stores 0.1 mm integers
    np.testing.assert_allclose(cloud.points, points, rtol=0, atol=tolerance)
    for name, values in fields.items():
        assert cloud.attributes[name].dtype == values.dtype
        np.testing.assert_array_equal(cloud.attributes[name], values)


def test_writer_rejects_bad_input(tmp_path):
    with pytest.raises(UnsupportedFormatError, match="writable formats"):
        write_point_cloud(tmp_path / "out.pcd", random_points())
    with pytest.raises(PointCloudError, match="one value per point"):
        write_point_cloud(tmp_path / "out.ply", random_points(), {"label": np.zeros(3)})
    bad = random_points()
    bad[0] = np.nan
    with pytest.raises(PointCloudError, match="NaN"):
        write_point_cloud(tmp_path / "out.las", bad)
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------------------------
# sources, NaN handling, limits


def test_every_kind_of_source(tmp_path):
    content = ply_bytes(random_points())
    path = tmp_path / "scan.ply"
    path.write_bytes(content)
    for source in (path, str(path), content, bytearray(content), io.BytesIO(content)):
        assert len(read_point_cloud(source)) == N_POINTS
    with open(path, "rb") as handle:
        assert len(read_point_cloud(handle)) == N_POINTS
    with pytest.raises(PointCloudError, match="file not found"):
        read_point_cloud(tmp_path / "missing.ply")


@pytest.mark.parametrize(
    "build",
    [
        lambda p: ply_bytes(p),
        lambda p: ply_bytes(p, "ascii"),
        lambda p: pcd_bytes(p, "binary_compressed"),
        lambda p: text_bytes(p),
        lambda p: npy_bytes(p),
    ],
    ids=["ply", "ply-ascii", "pcd", "xyz", "npy"],
)
def test_non_finite_rows_are_dropped_and_counted(build: Callable[[np.ndarray], bytes]):
    points = random_points()
    bad_rows = [0, 5, 17, N_POINTS - 1]
    points[bad_rows[0], 0] = np.nan
    points[bad_rows[1], 1] = np.inf
    points[bad_rows[2], 2] = -np.inf
    points[bad_rows[3]] = np.nan
    cloud = read_point_cloud(build(points))
    assert cloud.n_source == N_POINTS
    assert cloud.n_dropped == len(bad_rows)
    expected_index = np.setdiff1d(np.arange(N_POINTS), bad_rows)
    np.testing.assert_array_equal(cloud.source_index, expected_index)
    np.testing.assert_array_equal(cloud.points, points[expected_index])


def test_max_points_refuses_before_reading():
    content = ply_bytes(random_points())
    with pytest.raises(PointCloudError, match="more than the limit of 10"):
        read_point_cloud(content, "ply", max_points=10)
    assert len(read_point_cloud(content, "ply", max_points=None)) == N_POINTS


# ----------------------------------------------------------------------------------------------
# detection


POINTS_FOR_SNIFFING = random_points()
SNIFF_CASES = {
    "ply": ply_bytes(POINTS_FOR_SNIFFING),
    "ply-ascii": ply_bytes(POINTS_FOR_SNIFFING, "ascii"),
    "pcd": pcd_bytes(POINTS_FOR_SNIFFING),
    "pcd-commented": b"# .PCD v0.7 - Point Cloud Data\n" + pcd_bytes(POINTS_FOR_SNIFFING),
    "las": las_bytes(POINTS_FOR_SNIFFING),
    "laz": las_bytes(POINTS_FOR_SNIFFING, compress=True),
    "npy": npy_bytes(POINTS_FOR_SNIFFING),
    "npz": npz_bytes(points=POINTS_FOR_SNIFFING),
    "csv": text_bytes(POINTS_FOR_SNIFFING, ",", "x,y,z"),
    "xyz": text_bytes(POINTS_FOR_SNIFFING, " "),
}
SNIFF_EXPECTED = {"ply-ascii": "ply", "pcd-commented": "pcd"}


@pytest.mark.parametrize("kind", sorted(SNIFF_CASES))
@pytest.mark.parametrize("filename", [None, "upload", "upload.bin", "upload.PLY", "upload.txt"])
def test_content_decides_when_suffix_is_missing_unknown_or_contradicted(kind, filename):
    content = SNIFF_CASES[kind]
    expected = SNIFF_EXPECTED.get(kind, kind)
    if filename == "upload.txt" and expected in ("xyz", "csv"):
        expected = "txt"  # the suffix agrees with the content's family: it decides
    if filename == "upload.PLY" and kind.startswith("ply"):
        expected = "ply"
    assert detect_format(filename, content[:4096]) == expected
    cloud = read_point_cloud(content, filename=filename)
    np.testing.assert_allclose(cloud.points, POINTS_FOR_SNIFFING, atol=1e-3)


def test_las_suffix_with_laz_content_is_read_as_laz():
    content = SNIFF_CASES["laz"]
    assert detect_format("scan.las", content[:512]) == "laz"
    assert detect_format("scan.laz", SNIFF_CASES["las"][:512]) == "las"


def test_suffix_decides_when_the_content_matches_nothing():
    assert detect_format("scan.ply", b"\x00\x01garbage") == "ply"


@pytest.mark.parametrize("filename", [None, "scan.dat", "notes"])
def test_undetectable_content_is_unsupported_and_lists_formats(filename):
    with pytest.raises(UnsupportedFormatError) as caught:
        detect_format(filename, b"\x89PNG\r\n\x1a\n\x00\x00")
    for name in SUPPORTED_FORMATS:
        assert name in str(caught.value)
    with pytest.raises(UnsupportedFormatError, match="supported formats"):
        read_point_cloud(b"\x89PNG\r\n\x1a\n\x00\x00", filename=filename)


def test_unknown_explicit_format_is_unsupported():
    with pytest.raises(UnsupportedFormatError, match="supported formats"):
        read_point_cloud(b"whatever", format="rcp")


# ----------------------------------------------------------------------------------------------
# malformed corpus


@pytest.mark.parametrize("case", sorted(MALFORMED))
@pytest.mark.parametrize("threads", [1, 2])  # sequential and parallel decoders (LAZ, widening)
def test_malformed_input_raises_point_cloud_error_with_a_useful_message(case, threads):
    filename, build, fragment = MALFORMED[case]
    with pytest.raises(PointCloudError) as caught:
        read_point_cloud(build(), filename=filename, threads=threads)
    message = str(caught.value)
    assert fragment in message, message
    assert message.startswith(f"{filename}: ")


@pytest.mark.parametrize("case", ["ply-truncated-binary", "pcd-truncated-binary", "las-truncated"])
def test_malformed_files_on_disk_too(tmp_path: Path, case):
    filename, build, fragment = MALFORMED[case]
    path = tmp_path / filename
    path.write_bytes(build())
    with pytest.raises(PointCloudError, match=fragment):
        read_point_cloud(path)


@pytest.mark.parametrize("kind", sorted(FUZZ_SEEDS))
def test_corrupted_files_raise_only_point_cloud_error(kind):
    """Random byte flips, truncations and insertions (found a LAZ chunk-table abort in lazrs
    and a 10**9-VLR loop in laspy, both now refused up front)."""
    content = FUZZ_SEEDS[kind](random_points(200))
    rng = np.random.default_rng(sorted(FUZZ_SEEDS).index(kind))
    # LAZ also through the parallel decoder (lazrs's ParLasZipDecompressor)
    thread_counts = (1, 2) if kind.startswith("laz") else (None,)
    for _ in range(40):
        data = mutate_bytes(bytearray(content), rng, int(rng.integers(4)))
        for filename in (None, f"scan.{kind.split('-')[0]}"):
            for threads in thread_counts:
                with contextlib.suppress(PointCloudError):  # anything else fails the test
                    read_point_cloud(bytes(data), filename=filename, threads=threads)
