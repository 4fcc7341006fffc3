"""COPC (cloud-optimised point cloud): a LAZ 1.4 file whose chunks are the nodes of an octree.

A COPC file is read whole like any LAZ (:func:`app.core.formats.las.read_las`: laspy and lazrs
decode it chunk by chunk); :func:`read_copc_bounds` reads only the octree nodes that overlap a
box (laspy's ``CopcReader``), so a tile of a large survey decodes its part only.  Before any
point is decoded, :func:`check_copc_hierarchy` verifies that the octree's hierarchy (its pages
of node entries) is inside the file and counts as many points as the header declares: a file
whose header and point count disagree is refused.

Layout (COPC 1.0): the LAS 1.4 header (375 bytes), then the ``copc`` info VLR (record 1, 160
bytes: centre, half size, spacing, root hierarchy page offset and size, GPS time range), the
LASzip VLR, the chunks, and the hierarchy pages in an EVLR (``copc`` record 1000); each page
entry is 32 bytes: the node's key (depth, x, y, z as int32), the byte offset (uint64) and size
(int32) of its chunk, and its point count (int32; -1 marks an entry that points to a child
page instead).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from app.core.errors import PointCloudError
from app.core.formats._common import RawCloud, check_point_count, open_source
from app.core.formats.las import (
    COPC_INFO_VLR_OFFSET,
    KEPT_STANDARD_DIMENSIONS,
    POINT_COUNT_OFFSET,
    VLR_HEADER_BYTES,
    check_copc_hierarchy,
    is_copc,
)

__all__ = ["check_copc_hierarchy", "is_copc", "read_copc_bounds"]


def read_copc_bounds(
    path: str | Path,
    low: ArrayLike,
    high: ArrayLike,
    max_points: int | None = None,
) -> RawCloud:
    """The points of a COPC file inside a box, decoding only the octree nodes that overlap it.

    Parameters
    ----------
    path : str or Path
        A COPC file (``.copc.laz``).
    low, high : array_like, shape (3,)
        Corners of the axis-aligned box, in the file's coordinates (bounds included).
    max_points : int or None
        Refuse a box holding more points than this.

    Returns
    -------
    RawCloud
        ``points`` (m, 3) float64 in file order within each node, and the attributes
        :func:`~app.core.formats.las.read_las` keeps (intensity, classification, ..., extra
        bytes), each of length m.

    Raises
    ------
    PointCloudError
        Not a COPC file, a malformed box, a hierarchy that disagrees with the header, too many
        points, corrupt data.
    """
    import laspy
    from laspy.copc import Bounds

    low_corner = np.asarray(low, dtype=np.float64).reshape(-1)
    high_corner = np.asarray(high, dtype=np.float64).reshape(-1)
    if low_corner.shape != (3,) or high_corner.shape != (3,):
        raise PointCloudError("a COPC box needs three low and three high coordinates")
    if not (np.isfinite(low_corner).all() and np.isfinite(high_corner).all()):
        raise PointCloudError("a COPC box needs finite corners")
    if (low_corner > high_corner).any():
        raise PointCloudError(f"a COPC box's low corner {low_corner} is above its high corner")
    with open(path, "rb") as handle:
        head = handle.read(COPC_INFO_VLR_OFFSET + VLR_HEADER_BYTES)
    if not is_copc(head):
        raise PointCloudError(
            f"{Path(path).name}: not a COPC file (its first VLR is not the 'copc' info record); "
            "read it whole as LAS/LAZ instead"
        )
    with open_source(Path(path)) as source:
        declared = struct.unpack_from("<Q", source.buffer, POINT_COUNT_OFFSET)[0]
        check_copc_hierarchy(source, declared)
    try:
        with laspy.CopcReader.open(str(path)) as reader:
            found = reader.query(Bounds(mins=low_corner, maxs=high_corner))
    except (OSError, ValueError, laspy.LaspyException) as exc:
        raise PointCloudError(f"{Path(path).name}: corrupt COPC data: {exc}") from exc
    points = np.column_stack(
        [np.asarray(found.x), np.asarray(found.y), np.asarray(found.z)]
    ).astype(np.float64, copy=False)
    inside = ((points >= low_corner) & (points <= high_corner)).all(axis=1)
    check_point_count(int(inside.sum()), max_points, "the COPC box")
    point_format = found.point_format
    kept = [name for name in KEPT_STANDARD_DIMENSIONS if name in point_format.dimension_names]
    kept += list(point_format.extra_dimension_names)
    attributes: dict[str, NDArray] = {name: np.asarray(found[name])[inside] for name in kept}
    return RawCloud(np.ascontiguousarray(points[inside]), attributes)
