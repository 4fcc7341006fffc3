"""The corpus of broken point-cloud files: what each reader must refuse, and with which message.

:data:`MALFORMED` maps a case to ``(filename, content builder, expected message fragment)``;
:data:`FUZZ_SEEDS` builds a valid file of each format from points, which
:func:`mutate_bytes` corrupts at random.  The format tests read them; the upload tests send them.
"""

from __future__ import annotations

import functools
import io
import struct
import zipfile
from collections.abc import Callable

import numpy as np

from app.testing.files import las_bytes, npy_bytes, npz_bytes, pcd_bytes, ply_bytes, text_bytes
from app.testing.scenes import random_points

N_POINTS = 64
"""Points of each corpus file (what :func:`random_points` gives by default)."""


def replace_once(content: bytes, old: bytes, new: bytes) -> bytes:
    """``content`` with the first ``old`` (which must be there) replaced by ``new``."""
    assert old in content, old
    return content.replace(old, new, 1)


def edit_header(format_name: str, old: bytes, new: bytes) -> bytes:
    """A valid ``ply`` or ``pcd`` corpus file with ``old`` in its header replaced by ``new``."""
    build = {"ply": corpus_ply, "pcd": corpus_pcd}[format_name]
    return replace_once(build(), old, new)


def corpus_ply(encoding: str = "binary_little_endian", n: int = N_POINTS) -> bytes:
    """A valid PLY of ``n`` random points."""
    return ply_bytes(random_points(n), encoding)


def corpus_pcd(encoding: str = "binary") -> bytes:
    """A valid PCD of the random points."""
    return pcd_bytes(random_points(), encoding)


def pcd_with_compressed_sizes(
    compressed: int, uncompressed: int, payload: bytes, n_points: int = N_POINTS
) -> bytes:
    """A compressed PCD of ``n_points`` whose block declares the given sizes, then ``payload``."""
    content = corpus_pcd("binary_compressed")
    for keyword in (b"POINTS", b"WIDTH"):
        content = replace_once(
            content, b"%s %d" % (keyword, N_POINTS), b"%s %d" % (keyword, n_points)
        )
    start = content.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    return content[:start] + struct.pack("<II", compressed, uncompressed) + payload


def pcd_ascii_with_extra_column() -> bytes:
    """An ASCII PCD whose rows hold one value more than its FIELDS."""
    header, body = corpus_pcd("ascii").split(b"DATA ascii\n")
    rows = [row + b" 7" for row in body.splitlines()]
    return header + b"DATA ascii\n" + b"\n".join(rows) + b"\n"


def las_with_point_count(content: bytes, count: int) -> bytes:
    """A LAS/LAZ file whose header declares ``count`` points (legacy count field)."""
    return content[:107] + struct.pack("<I", count) + content[111:]


def patch_bytes(content: bytes, offset: int, new: bytes) -> bytes:
    """``content`` with ``new`` written over it at ``offset``."""
    return content[:offset] + new + content[offset + len(new) :]


def laz_with_chunk_count(n_chunks: int) -> bytes:
    """A LAZ file whose chunk table declares ``n_chunks`` chunks (lazrs would abort)."""
    content = las_bytes(random_points(), compress=True)
    point_offset = struct.unpack_from("<I", content, 96)[0]
    table_offset = struct.unpack_from("<q", content, point_offset)[0]
    return patch_bytes(content, table_offset, struct.pack("<II", 0, n_chunks))


def npy_header(shape: tuple[int, ...], dtype: str = "<f8") -> bytes:
    """The header of an NPY file of ``shape`` and ``dtype`` (no data)."""
    stream = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        stream, {"descr": dtype, "fortran_order": False, "shape": shape}
    )
    return b"\x93NUMPY\x01\x00" + stream.getvalue()[8:]


def npz_with_member(name: str, member: bytes) -> bytes:
    """An (uncompressed) NPZ archive with one raw ``member`` called ``name``."""
    stream = io.BytesIO()
    with zipfile.ZipFile(stream, "w") as archive:
        archive.writestr(name, member)
    return stream.getvalue()


VERTEX_LINE = f"vertex {N_POINTS}".encode()
NAN_ONLY = np.full((N_POINTS, 3), np.nan)
ROWS_3 = b"1 2 3\n4 5 6\n7 8 9\n"

MALFORMED: dict[str, tuple[str, Callable[[], bytes], str]] = {
    # name: (filename, content builder, expected message fragment)
    "empty-file": ("scan.ply", lambda: b"", "empty (0 bytes)"),
    "ply-bad-magic": ("scan.ply", lambda: b"plx\n" + corpus_ply()[4:], "not a PLY file"),
    "ply-truncated-binary": ("scan.ply", lambda: corpus_ply()[:-7], "truncated body"),
    "ply-truncated-big-endian": (
        "scan.ply",
        lambda: corpus_ply("binary_big_endian")[:-40],
        "truncated body",
    ),
    "ply-truncated-ascii": ("scan.ply", lambda: corpus_ply("ascii")[:-200], "truncated body"),
    "ply-ascii-surplus-rows": (
        "scan.ply",
        lambda: replace_once(corpus_ply("ascii"), f"vertex {N_POINTS}".encode(), b"vertex 20"),
        "fix the 'element' counts",
    ),
    "ply-no-vertex": (
        "scan.ply",
        lambda: replace_once(
            replace_once(corpus_ply(), b"element vertex", b"element thing"),
            b"float x",
            b"float a",
        ),
        "no 'vertex' element",
    ),
    "ply-no-end-header": (
        "scan.ply",
        lambda: b"ply\nformat ascii 1.0\nelement vertex 3\n",
        "truncated PLY header",
    ),
    "ply-ascii-non-numeric": (
        "scan.ply",
        lambda: (
            replace_once(corpus_ply("ascii"), b"end_header\n", b"end_header\nfoo bar baz\n").rsplit(
                b"\n", 2
            )[0]
            + b"\n"
        ),
        "malformed ascii PLY vertex data",
    ),
    "ply-ascii-missing-column": (
        "scan.ply",
        lambda: (
            b"ply\nformat ascii 1.0\nelement vertex 12\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n" + b"1.0 2.0\n" * 12
        ),
        "malformed ascii PLY vertex data",
    ),
    "ply-zero-vertices": ("scan.ply", lambda: corpus_ply(n=0), "empty (0 points)"),
    "ply-nan-only": ("scan.ply", lambda: ply_bytes(NAN_ONLY), "none of the 64 points"),
    "pcd-truncated-binary": ("scan.pcd", lambda: corpus_pcd()[:-5], "truncated body"),
    "pcd-points-fewer-than-body": (
        "scan.pcd",
        lambda: replace_once(
            replace_once(corpus_pcd(), f"POINTS {N_POINTS}".encode(), b"POINTS 10"),
            f"WIDTH {N_POINTS}".encode(),
            b"WIDTH 10",
        ),
        "count mismatch",
    ),
    "pcd-header-bomb": (
        "scan.pcd",
        lambda: replace_once(
            replace_once(corpus_pcd(), f"POINTS {N_POINTS}".encode(), b"POINTS 2147483648"),
            f"WIDTH {N_POINTS}".encode(),
            b"WIDTH 2147483648",
        ),
        "more than the limit",
    ),
    "pcd-compressed-bomb": (
        "scan.pcd",
        lambda: pcd_with_compressed_sizes(8, 10**7 * 12, bytes(8), n_points=10**7),
        "absurd compressed PCD block",
    ),
    "pcd-compressed-size-mismatch": (
        "scan.pcd",
        lambda: pcd_with_compressed_sizes(8, 2**31, bytes(8)),
        "count mismatch",
    ),
    "pcd-compressed-truncated": (
        "scan.pcd",
        lambda: corpus_pcd("binary_compressed")[:-20],
        "truncated body",
    ),
    "pcd-compressed-corrupt": (
        "scan.pcd",
        lambda: pcd_with_compressed_sizes(64, N_POINTS * 12, b"\xff" * 64),
        "corrupt compressed PCD data",
    ),
    "pcd-no-data-line": ("scan.pcd", lambda: corpus_pcd().split(b"DATA")[0], "no 'DATA' line"),
    "pcd-ascii-non-numeric": (
        "scan.pcd",
        lambda: corpus_pcd("ascii").rsplit(b"\n", 2)[0] + b"\n1.0 abc 3.0\n",
        "malformed ascii PCD data",
    ),
    "pcd-ascii-fewer-rows": (
        "scan.pcd",
        lambda: corpus_pcd("ascii").rsplit(b"\n", 4)[0] + b"\n",
        "count mismatch",
    ),
    "pcd-ascii-extra-column": (
        "scan.pcd",
        lambda: pcd_ascii_with_extra_column(),
        "values per point",
    ),
    "las-truncated": ("scan.las", lambda: las_bytes(random_points())[:-30], "truncated body"),
    "las-header-bomb": (
        "scan.las",
        lambda: las_with_point_count(las_bytes(random_points()), 2**31),
        "more than the limit",
    ),
    "laz-absurd-count": (
        "scan.laz",
        lambda: las_with_point_count(las_bytes(random_points(), compress=True), 10**8),
        "absurd LAZ header",
    ),
    "laz-truncated": (
        "scan.laz",
        lambda: las_bytes(random_points(1000), compress=True)[:-2000],
        "truncated",
    ),
    "las-bad-magic": (
        "scan.las",
        lambda: b"LASX" + las_bytes(random_points())[4:],
        "not a LAS/LAZ file",
    ),
    "las-short-header": ("scan.las", lambda: b"LASF" + bytes(50), "truncated LAS header"),
    "las-vlr-count-bomb": (
        "scan.las",
        lambda: patch_bytes(las_bytes(random_points()), 100, struct.pack("<I", 10**9)),
        "VLRs cannot fit",
    ),
    "las-point-offset-beyond-file": (
        "scan.las",
        lambda: patch_bytes(las_bytes(random_points()), 96, struct.pack("<I", 10**7)),
        "inconsistent",
    ),
    "laz-chunk-table-bomb": ("scan.laz", lambda: laz_with_chunk_count(10**9), "chunk table"),
    "text-non-utf8": ("scan.xyz", lambda: b"1 2 3\n" * 20 + b"4 5 \xff\xfe\n", "not UTF-8 text"),
    "text-non-numeric": ("scan.xyz", lambda: ROWS_3 * 5 + b"1 two 3\n", "non-numeric text"),
    "text-two-columns": ("scan.csv", lambda: b"1,2\n3,4\n" * 10, "at least 3 numeric columns"),
    "text-inconsistent-columns": (
        "scan.xyz",
        lambda: ROWS_3 * 5 + b"1 2\n",
        "inconsistent number of columns",
    ),
    "text-header-without-xyz": (
        "scan.csv",
        lambda: b"a,b,c\n" + b"1,2,3\n" * 20,
        "has no 'x' column",
    ),
    "text-header-only": ("scan.csv", lambda: b"x,y,z\n", "zero points"),
    "text-nan-only": ("scan.xyz", lambda: b"nan nan nan\n" * 20, "none of the 20 points"),
    "text-too-few-points": ("scan.xyz", lambda: ROWS_3, "at least 10 are needed"),
    "text-binary-garbage": ("scan.txt", lambda: b"\x00\x01\x02" * 50, "NUL bytes"),
    "npy-truncated": ("scan.npy", lambda: npy_bytes(random_points())[:-9], "truncated data"),
    "npy-header-bomb": ("scan.npy", lambda: npy_header((2**31, 3)), "more than the limit"),
    "npy-wrong-shape": ("scan.npy", lambda: npy_bytes(np.zeros((20, 2))), "expected (n, 3)"),
    "npy-object-array": (
        "scan.npy",
        lambda: npy_bytes(np.array([object()] * 3)),
        "object (pickled) array",
    ),
    "npy-bad-header": (
        "scan.npy",
        lambda: b"\x93NUMPY\x01\x00\x10\x00{'descr': zzz}\n" + bytes(64),
        "malformed header in the .npy file",
    ),
    "npy-strings": (
        "scan.npy",
        lambda: npy_bytes(np.array([["a", "b", "c"]] * 20)),
        "expected numbers",
    ),
    "npz-no-points-key": (
        "scan.npz",
        lambda: npz_bytes(a=np.zeros((20, 3)), b=np.zeros((20, 3))),
        "no 'points' or 'xyz' array",
    ),
    "npz-bad-zip": ("scan.npz", lambda: b"PK\x03\x04" + bytes(100), "not a valid .npz"),
    "npz-member-bomb": (
        "scan.npz",
        lambda: npz_with_member("points.npy", npy_header((2**31, 3))),
        "more than the limit",
    ),
    "npz-member-truncated": (
        "scan.npz",
        lambda: npz_with_member("points.npy", npy_header((100, 3)) + bytes(80)),
        "truncated data",
    ),
}


HEADER_EDITS: dict[str, tuple[bytes, bytes, str]] = {
    # name (its format first): (header text of a valid file, its replacement, message fragment)
    "ply-header-count-too-small": (VERTEX_LINE, b"vertex 10", "fix the 'element vertex' count"),
    "ply-unknown-property-type": (b"property float z", b"property quad z", "field type 'quad'"),
    "ply-no-xyz": (b"property float z", b"property float w", "no 'z' field"),
    "ply-header-bomb": (VERTEX_LINE, b"vertex 2147483648", "more than the limit"),
    "ply-count-beyond-body": (VERTEX_LINE, b"vertex 1000000", "truncated body"),
    "ply-non-ascii-header": (b"format", b"comment \xe9t\xe9\nformat", "not ASCII"),
    "ply-bad-format-line": (b"binary_little_endian", b"binary", "don't understand format"),
    "pcd-width-height-mismatch": (b"HEIGHT 1", b"HEIGHT 2", "count mismatch"),
    "pcd-unknown-type": (b"TYPE F F F", b"TYPE F F X", "unknown PCD field type 'X'"),
    "pcd-half-float": (b"SIZE 4 4 4", b"SIZE 4 4 2", "unsupported PCD field type"),
    "pcd-field-list-mismatch": (b"SIZE 4 4 4", b"SIZE 4 4", "FIELDS lists 3"),
    "pcd-no-xyz": (b"FIELDS x y z", b"FIELDS a b c", "no 'x' field"),
    "pcd-unknown-encoding": (b"DATA binary", b"DATA zipped", "unknown PCD DATA encoding"),
    "pcd-unknown-header-line": (b"HEIGHT 1", b"HEIGHT 1\nCOLOUR red", "unknown line"),
}
MALFORMED.update(
    {
        case: (f"scan.{case[:3]}", functools.partial(edit_header, case[:3], old, new), fragment)
        for case, (old, new, fragment) in HEADER_EDITS.items()
    }
)

FUZZ_SEEDS = {
    "ply": lambda p: ply_bytes(p),
    "ply-ascii": lambda p: ply_bytes(p, "ascii"),
    "ply-big-endian": lambda p: ply_bytes(p, "binary_big_endian"),
    "pcd": lambda p: pcd_bytes(p),
    "pcd-ascii": lambda p: pcd_bytes(p, "ascii"),
    "pcd-compressed": lambda p: pcd_bytes(p, "binary_compressed"),
    "las": lambda p: las_bytes(p),
    "laz": lambda p: las_bytes(p, compress=True),
    "npy": lambda p: npy_bytes(p),
    "npz": lambda p: npz_bytes(points=p),
    "csv": lambda p: text_bytes(p, ",", "x,y,z"),
}


def mutate_bytes(
    data: bytearray, rng: np.random.Generator, mutation: int, min_length: int = 0
) -> bytearray:
    """One corruption of a valid file: 0 header bytes flipped, 1 truncated (to at least
    ``min_length`` bytes), 2 body bytes flipped, 3 random bytes inserted."""
    if mutation == 0:  # header bytes
        for _ in range(rng.integers(1, 4)):
            data[rng.integers(0, min(len(data), 400))] = rng.integers(256)
    elif mutation == 1:
        data = data[: rng.integers(min_length, len(data))]
    elif mutation == 2:
        for _ in range(rng.integers(1, 20)):
            data[rng.integers(0, len(data))] = rng.integers(256)
    else:
        at = rng.integers(0, len(data))
        data[at:at] = rng.integers(0, 256, rng.integers(1, 50)).astype(np.uint8).tobytes()
    return data
