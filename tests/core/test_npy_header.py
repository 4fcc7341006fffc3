"""The .npy header is vetted before numpy parses it, so a corrupt header gives the project's own
message on every Python (on 3.12+ numpy's tokenizer reported a NUL byte as
"TokenError: source code cannot contain null bytes")."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
from numpy.lib import format as npy_format

from app.core.errors import PointCloudError
from app.core.formats import read_point_cloud
from app.testing.scenes import random_points


def npy_with_version(version: tuple[int, int]) -> tuple[bytes, int]:
    """A valid .npy file written in format ``version`` and the offset of its header text."""
    stream = io.BytesIO()
    npy_format.write_array(stream, random_points(20), version=version)
    header_start = 8 + (2 if version == (1, 0) else 4)
    return stream.getvalue(), header_start


def npz_holding(member: bytes) -> bytes:
    """An uncompressed .npz whose ``points.npy`` member is ``member`` as given."""
    stream = io.BytesIO()
    with zipfile.ZipFile(stream, "w") as archive:
        archive.writestr("points.npy", member)
    return stream.getvalue()


@pytest.mark.parametrize("version", [(1, 0), (2, 0), (3, 0)])
@pytest.mark.parametrize("control", [0x00, 0x01, 0x1B, 0x7F])
def test_a_control_byte_anywhere_in_the_header_names_its_position(version, control):
    content, header_start = npy_with_version(version)
    header_length = content.index(b"\n", header_start) - header_start
    for position in range(header_length):
        corrupt = bytearray(content)
        corrupt[header_start + position] = control
        with pytest.raises(PointCloudError) as caught:
            read_point_cloud(bytes(corrupt), filename="scan.npy")
        assert str(caught.value) == (
            f"scan.npy: malformed header in the .npy file: byte {position} of the header is "
            f"{control:#04x}, a control character; the file is corrupt (rewrite it with "
            "numpy.save)"
        )


def test_a_nul_in_an_npz_member_header_gets_the_same_message():
    content, header_start = npy_with_version((1, 0))
    corrupt = bytearray(content)
    corrupt[header_start + 3] = 0
    with pytest.raises(PointCloudError) as caught:
        read_point_cloud(npz_holding(bytes(corrupt)), filename="scan.npz")
    assert str(caught.value) == (
        "scan.npz: malformed header in the .npz member 'points.npy': byte 3 of the header is "
        "0x00, a control character; the file is corrupt (rewrite it with numpy.save)"
    )


def test_a_header_cut_short_or_claiming_too_much_is_refused_before_parsing():
    content, header_start = npy_with_version((2, 0))
    with pytest.raises(PointCloudError, match="the file ends inside the header"):
        read_point_cloud(content[: header_start + 5], filename="scan.npy")
    with pytest.raises(PointCloudError, match="the file ends inside the header"):
        read_point_cloud(content[:10], filename="scan.npy")
    huge = content[:8] + (1 << 30).to_bytes(4, "little") + content[header_start:]
    with pytest.raises(PointCloudError, match="claims 1,073,741,824 bytes"):
        read_point_cloud(huge, filename="scan.npy")


@pytest.mark.parametrize("version", [(1, 0), (2, 0), (3, 0)])
def test_every_header_version_still_reads(version):
    content, _ = npy_with_version(version)
    np.testing.assert_array_equal(
        read_point_cloud(content, filename="scan.npy").points, random_points(20)
    )
