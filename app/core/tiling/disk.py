"""The disk a streamed comparison's files take, checked before any crop is written (issue 30).

A streamed comparison (:mod:`app.core.tiling.streamed`) writes every tile's crop of both
clouds before any tile runs (:mod:`app.core.tiling.crops`), then the tiles' results and the
per-point outputs.  The plan counts the points of each crop
(:attr:`~app.core.tiling.plan.TilePlan.crop_points`, as the passes write them: the box and the
other sensor's returns by direction), so the bytes follow before a byte is written:
:func:`needed_disk_bytes`.  :func:`check_disk` refuses a comparison whose files would not fit
the free disk beside what must stay free (:class:`DiskSpaceError`, saying how much it needs
and how much there is).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from app.core.errors import InputError
from app.core.tiling.plan import TilePlan

__all__ = [
    "CROP_COUNT_SLACK",
    "MIN_BYTES_PER_POINT",
    "RESULT_BYTES_PER_POINT",
    "DiskSpaceError",
    "FreeDisk",
    "check_disk",
    "free_disk_bytes",
    "needed_disk_bytes",
]

RESULT_BYTES_PER_POINT = 22
"""Bytes a point of both clouds takes once the tiles ran: its tile's result (index 8, label 1,
distance 4) and the per-point outputs (label 1, distance 4, region 4)."""

MIN_BYTES_PER_POINT = 16 + RESULT_BYTES_PER_POINT
"""The least a point of a pair compared in tiles takes: one crop record (float32 point,
uint32 index; :func:`~app.core.tiling.crops.record_dtype`) and its results; the crops'
margins and rays add to it (the plan counts them)."""

CROP_COUNT_SLACK = 1.05
"""The plan's crop points times this is what :func:`needed_disk_bytes` counts: the planner
counts on a subsample (measured written / planned: 0.982 on the 20M + 20M pair, 1.010 on the
100M + 100M one)."""

FreeDisk = Callable[[Path], int]
"""Free bytes of the file system holding a directory."""


class DiskSpaceError(InputError):
    """A comparison's files would not fit the free disk; the message says how much it needs
    and how much is free."""

    how_to_fix = "free_disk"


def free_disk_bytes(directory: Path) -> int:
    """Free bytes (for this user) of the file system holding ``directory`` (or its nearest
    existing parent)."""
    path = Path(directory).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return int(shutil.disk_usage(path).free)


def needed_disk_bytes(plan: TilePlan, record_bytes: int, n_points: int) -> int:
    """Bytes of a streamed comparison's files: every crop's records (``record_bytes`` a point
    of :attr:`~app.core.tiling.plan.TilePlan.crop_points`, :data:`CROP_COUNT_SLACK` more) and
    ``n_points`` points' results (:data:`RESULT_BYTES_PER_POINT`)."""
    crop_points = int(np.sum(plan.crop_points, dtype=np.int64))
    crops = int(np.ceil(crop_points * CROP_COUNT_SLACK)) * int(record_bytes)
    return crops + int(n_points) * RESULT_BYTES_PER_POINT


def _gb(count: int) -> str:
    return f"{count / 1e9:,.1f} GB"


def check_disk(
    directory: Path,
    needed: int,
    keep_free: int = 0,
    free: FreeDisk = free_disk_bytes,
) -> None:
    """Refuse (:class:`DiskSpaceError`) files of ``needed`` bytes under ``directory`` when
    they would leave less than ``keep_free`` bytes of its disk free."""
    available = free(Path(directory))
    if needed + keep_free <= available:
        return
    kept = f" and {_gb(keep_free)} must stay free" if keep_free > 0 else ""
    raise DiskSpaceError(
        f"not enough disk for this comparison: its tiles' inputs and results need about "
        f"{_gb(needed)} under {directory}, but only {_gb(available)} are free there{kept}; "
        f"free at least {_gb(needed + keep_free - available)} or compare smaller scans"
    )
