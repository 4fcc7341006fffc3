"""A pair too large for one process, read lean: float32 points near a common offset.

A tiled comparison holds both clouds whole while its tiles run (the crops are cut from them).
As read, a cloud is float64 in the file's frame, 24 bytes a point; the comparison needs its
points only in a local frame near the data, where float32 keeps them to well under a
millimetre over a building (about 4 micrometres at 64 m).  :func:`read_pair` reads each cloud
in turn and keeps it as float32 minus the reference's local origin (12 bytes a point: the
float64 copy of one cloud is alive only while that cloud is converted), when the files' headers
say the pair will be tiled under the budget.  :func:`~app.core.tiling.compare.compare_tiled`
takes such clouds with ``frame_offset`` (the offset they were shifted by).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import PointCloud, choose_local_origin
from app.core.formats.streamed import declared_rows
from app.core.tiling.plan import crop_point_limit

__all__ = ["LEAN_CHUNK", "float32_cloud", "read_pair"]

LEAN_CHUNK = 1 << 20
"""Points per step of the conversion (its float64 temporaries)."""


def float32_cloud(cloud: PointCloud, offset: NDArray[np.float64]) -> PointCloud:
    """``cloud`` with its points as float32 minus ``offset``, the rest shared.

    Parameters
    ----------
    cloud : PointCloud
    offset : ndarray, shape (3,)
        Subtracted from every point (in float64, before the rounding to float32).

    Returns
    -------
    PointCloud
        ``points`` shape (n, 3) float32 in the frame ``file - offset``; ``sensor_origin``,
        ``trajectory``, attributes and the source rows as in ``cloud`` (file frame).
    """
    offset = np.asarray(offset, dtype=np.float64).reshape(3)
    points = np.empty((len(cloud), 3), dtype=np.float32)
    for start in range(0, len(cloud), LEAN_CHUNK):
        points[start : start + LEAN_CHUNK] = cloud.points[start : start + LEAN_CHUNK] - offset
    return PointCloud(
        points,
        cloud.__dict__.get("_source_index"),  # None (no row dropped) stays unbuilt
        cloud.n_source,
        cloud.attributes,
        cloud.sensor_origin,
        cloud.trajectory,
    )


def read_pair(
    reference_path: Path,
    scan_path: Path,
    read: Callable[[str], PointCloud],
    budget_bytes: int | None,
    *,
    allowed: bool = True,
) -> tuple[PointCloud, PointCloud, NDArray[np.float64] | None]:
    """Both clouds of a comparison, lean when the pair will be tiled under ``budget_bytes``.

    Parameters
    ----------
    reference_path, scan_path : Path
    read : callable
        ``read("reference")`` / ``read("scan") -> PointCloud``: the caller's reader of each
        file, with its options.
    budget_bytes : int or None
        The comparison's memory budget; None: no limit.
    allowed : bool
        False: both as read whatever their size (a cloud with a trajectory: the tiled
        comparison resolves its poses in float64).

    Returns
    -------
    reference, scan : PointCloud
    frame_offset : ndarray, shape (3,), or None
        Not None: both clouds are float32 minus it (:func:`float32_cloud`), to be compared by
        :func:`~app.core.tiling.compare.compare_tiled` with ``frame_offset``.  None: both as
        read (the headers do not declare the counts, or the pair fits the budget whole).
    """
    rows = [declared_rows(path) for path in (reference_path, scan_path)]
    tiled = (
        allowed
        and budget_bytes is not None
        and None not in rows
        and crop_point_limit(budget_bytes, sum(rows)) < sum(rows)  # type: ignore[arg-type]
    )
    reference = read("reference")
    if not tiled:
        return reference, read("scan"), None
    offset = choose_local_origin(reference.points)
    reference = float32_cloud(reference, offset)
    return reference, float32_cloud(read("scan"), offset), offset
