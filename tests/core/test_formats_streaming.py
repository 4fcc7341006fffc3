"""Text and ``.npy`` uploads are checked a chunk at a time, with the reader's results and errors.

``summarise_point_cloud`` parses a text file in chunks of whole lines
(:func:`app.core.formats.text.summarise_text`) and visits a ``.npy`` file's coordinates as a
view of the file: here with chunks far smaller than the file, the summary must equal the cloud
``read_point_cloud`` returns (counts, NaN rows dropped, bounds), and every refusal must carry
the reading's message (row and line numbers counted over the whole file); memory must stay at
a chunk.
"""

from __future__ import annotations

import codecs
import tracemalloc

import numpy as np
import pytest

from app.core.errors import PointCloudError
from app.core.formats import read_point_cloud, summarise_point_cloud
from app.core.formats import text as text_module
from app.testing.files import npy_bytes, text_bytes
from app.testing.scenes import random_points
from tests.helpers.clouds import assert_summary_of

N_NPY_POINTS = 1_000_000
"""Points of the ``.npy`` files whose summary's memory is measured (12-40 MB arrays)."""
SMALL_CHUNK_BYTES = 97
"""Far smaller than the files below: dozens of chunks, cut mid-way through lines."""


@pytest.fixture
def small_chunks(monkeypatch):
    """Text summaries parse ``SMALL_CHUNK_BYTES`` at a time (the header found in 300 bytes)."""
    monkeypatch.setattr(text_module, "CHUNK_BYTES", SMALL_CHUNK_BYTES)
    monkeypatch.setattr(text_module, "HEAD_BYTES", 300)


def _outcome(function, *args, **kwargs):
    """``("ok", result)`` or ``("error", message)`` of a call that may raise PointCloudError."""
    try:
        return "ok", function(*args, **kwargs)
    except PointCloudError as exc:
        return "error", str(exc)


def _with_nan_rows(points: np.ndarray, rows: list[int]) -> np.ndarray:
    points = points.copy()
    points[rows, 1] = np.nan
    return points


def _text_variants() -> dict[str, bytes]:
    points = _with_nan_rows(random_points(400, seed=5), [0, 57, 58, 399])
    plain = text_bytes(points)
    commented = b"# exported\n\n" + plain.replace(b"\n", b"\n# a comment\n\n", 40)
    decimal_comma = plain.replace(b".", b",").replace(b" ", b";")
    with_attribute = b"x,y,z,intensity\n" + b"".join(
        f"{float(x)!r},{float(y)!r},{float(z)!r},{index}\n".encode()
        for index, (x, y, z) in enumerate(points)
    )
    return {
        "space": plain,
        "comma header": text_bytes(points, delimiter=",", header="x,y,z"),
        "comments and blank lines": commented,
        "crlf": plain.replace(b"\n", b"\r\n"),
        "byte-order mark": codecs.BOM_UTF8 + plain,
        "byte-order mark and header": codecs.BOM_UTF8 + b"x y z\n" + plain,
        "decimal comma": decimal_comma,
        "attribute column": with_attribute,
        "no final newline": plain.rstrip(b"\n"),
    }


TEXT_VARIANTS = _text_variants()


@pytest.mark.parametrize("from_disk", [False, True], ids=["bytes", "file"])
@pytest.mark.parametrize("variant", sorted(TEXT_VARIANTS))
def test_text_summary_in_small_chunks_equals_the_read_cloud(
    small_chunks, tmp_path, variant, from_disk
):
    content = TEXT_VARIANTS[variant]
    assert len(content) > 20 * SMALL_CHUNK_BYTES
    source = content
    if from_disk:  # read with pread from the file, not through its memory map
        source = tmp_path / "scan.xyz"
        source.write_bytes(content)
    cloud = read_point_cloud(content, filename="scan.xyz")
    summary = summarise_point_cloud(source, filename="scan.xyz")
    assert_summary_of(summary, cloud)
    assert summary.n_dropped == 4


def test_text_summary_parses_chunk_by_chunk(small_chunks, monkeypatch):
    """numpy parses pieces of about a chunk, never the whole file."""
    parsed_sizes: list[int] = []
    original = np.loadtxt

    def recording_loadtxt(stream, *args, **kwargs):
        text = stream.getvalue()
        parsed_sizes.append(len(text))
        return original(stream, *args, **kwargs)

    monkeypatch.setattr(np, "loadtxt", recording_loadtxt)
    content = TEXT_VARIANTS["space"]
    summary = summarise_point_cloud(content, filename="scan.xyz")
    assert summary.n_source == 400
    longest_line = max(len(line) for line in content.splitlines()) + 1
    assert len(parsed_sizes) > 20
    assert max(parsed_sizes) <= SMALL_CHUNK_BYTES + longest_line
    assert sum(parsed_sizes) == len(content)


def _late(content: bytes, row: int, replacement: bytes) -> bytes:
    lines = content.split(b"\n")
    lines[row] = replacement
    return b"\n".join(lines)


def _refusals() -> dict[str, bytes]:
    plain = text_bytes(random_points(300, seed=9))
    header = b"# survey\nx y z\n" + plain
    all_nan = text_bytes(np.full((50, 3), np.nan))
    return {
        "non-numeric value late": _late(plain, 250, b"1.0 abc 3.0"),
        "non-numeric value after comments": _late(header, 200, b"1.0 2.0 x3"),
        "missing column late": _late(plain, 180, b"1.0 2.0"),
        "not UTF-8 late": _late(plain, 260, b"1.0 2.0 \xff3.0"),
        "NUL byte late": _late(plain, 270, b"1.0 2.0\x00 3.0"),
        "not UTF-8 after a NUL byte": _late(_late(plain, 20, b"1 2\x00 3"), 280, b"\xfe 2 3"),
        "every row NaN": all_nan,
        "too few finite rows": _late(text_bytes(np.full((50, 3), np.nan)), 3, b"1 2 3"),
        "header only": b"x y z\n# nothing\n\n",
        "one very long line": b"1 2 3\n" + b"9" * (3 * text_module.MAX_LINE_BYTES),
    }


REFUSALS = _refusals()


@pytest.mark.parametrize("case", sorted(REFUSALS))
def test_text_summary_in_small_chunks_refuses_with_the_reading_message(
    small_chunks, tmp_path, case
):
    content = REFUSALS[case]
    path = tmp_path / "scan.xyz"
    path.write_bytes(content)
    read = _outcome(read_point_cloud, content, filename="scan.xyz")
    summary = _outcome(summarise_point_cloud, path)
    if case == "one very long line":  # the reader takes it whole; a summary stops at a line
        assert read[0] == "error" and summary[0] == "error"
        assert "longer than" in summary[1]
        return
    assert read[0] == "error", read
    assert summary == read
    assert summary[1].startswith("scan.xyz: ")


def test_text_summary_row_numbers_count_over_the_whole_file(small_chunks):
    content = REFUSALS["non-numeric value late"]
    status, message = _outcome(summarise_point_cloud, content, filename="scan.xyz")
    assert status == "error"
    assert "in data row 251" in message and "abc" in message


def test_text_summary_checks_the_line_count_first(small_chunks):
    content = _late(TEXT_VARIANTS["space"], 300, b"1.0 abc 3.0")
    read = _outcome(read_point_cloud, content, filename="scan.xyz", max_points=100)
    summary = _outcome(summarise_point_cloud, content, filename="scan.xyz", max_points=100)
    assert summary == read
    assert "more than the limit of 100" in summary[1]


def test_text_summary_with_station_fields_equals_the_read_cloud(small_chunks):
    points = random_points(200, seed=4)
    rows = [f"{x} {y} {z} {index % 3}" for index, (x, y, z) in enumerate(points.tolist())]
    content = ("x y z station\n" + "\n".join(rows) + "\n").encode()
    summary = summarise_point_cloud(content, filename="scan.xyz")
    assert_summary_of(summary, read_point_cloud(content, filename="scan.xyz"))
    assert summary.n_stations == 3


def peak_traced_bytes(action) -> int:
    """Peak bytes of Python and numpy allocations while ``action()`` runs."""
    tracemalloc.start()
    try:
        action()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_text_summary_memory_stays_at_a_chunk(monkeypatch, tmp_path):
    monkeypatch.setattr(text_module, "CHUNK_BYTES", 64 * 1024)
    monkeypatch.setattr(text_module, "HEAD_BYTES", 64 * 1024)
    path = tmp_path / "scan.xyz"
    path.write_bytes(text_bytes(random_points(120_000, seed=2)))
    summary_peak = peak_traced_bytes(lambda: summarise_point_cloud(path))
    assert summary_peak < path.stat().st_size / 3  # reading it takes several times its size


@pytest.mark.parametrize(
    "array",
    [
        random_points(N_NPY_POINTS, seed=1).astype(np.float32),
        np.asfortranarray(random_points(N_NPY_POINTS, seed=2)),
        np.hstack([random_points(N_NPY_POINTS, seed=3), np.ones((N_NPY_POINTS, 2))]),
    ],
    ids=["float32 (n, 3)", "Fortran order", "(n, 5)"],
)
def test_npy_summary_from_disk_is_a_view_of_the_file(tmp_path, array):
    """No copy of the coordinates: memory far below the array's, the read cloud's counts."""
    array = array.copy()
    array[[3, 4000]] = np.nan
    path = tmp_path / "scan.npy"
    path.write_bytes(npy_bytes(array))
    summary_peak = peak_traced_bytes(lambda: summarise_point_cloud(path))
    float64_copy = len(array) * 3 * 8  # what reading takes: a float64 copy of x, y, z
    assert summary_peak < float64_copy / 2  # a chunk and a per-point flag at most
    assert_summary_of(summarise_point_cloud(path), read_point_cloud(path))
