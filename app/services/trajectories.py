"""A scan's trajectory: sent with the scan (multipart part ``trajectory``) or added to it later.

The trajectory file (TUM, KITTI poses with a times file or rate, CSV with a header:
:mod:`app.core.formats.trajectory_files`) is parsed and checked against the scan's per-point
times before anything is stored; it is kept beside the scan's file as ``<scan file>.trajectory
.npz`` (times, positions, orientations, has_times) and loaded with the scan by its comparisons.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from app.core.trajectory import Trajectory, TrajectoryError
from app.kit.scan_files import save_trajectory, trajectory_path

__all__ = ["save_trajectory", "trajectory_path"]  # (re-exported: the upload stores with them)

MAX_TRAJECTORY_BYTES = 64 * 1024 * 1024
"""Largest trajectory (or times) file accepted with an upload."""


def parse_trajectory(
    data: bytes,
    filename: str | None,
    *,
    times: bytes | None = None,
    rate: float | None = None,
    trajectory_format: str | None = None,
) -> Trajectory:
    """The trajectory of an upload (raises TrajectoryError: a 422 saying what to fix)."""
    from app.core.formats.trajectory_files import read_trajectory

    if not data:
        raise TrajectoryError("the trajectory part is empty: send the trajectory file's bytes")
    return read_trajectory(
        data, filename=filename or "trajectory", format=trajectory_format, times=times, rate=rate
    )


def check_times_without_trajectory(has_trajectory: bool, times: bytes | None, rate: Any) -> None:
    """Pose times (a times file or rate) without a trajectory: TrajectoryError."""
    if not has_trajectory and (times is not None or rate is not None):
        raise TrajectoryError(
            "pose times (trajectory_times or trajectory_rate) were given without a trajectory: "
            "send the poses as the 'trajectory' part too, or leave the times out"
        )


def check_fits(scan_path: Path, scan_format: str | None, trajectory: Trajectory) -> dict[str, Any]:
    """Check the trajectory against the scan's points; its summary (raises TrajectoryError).

    With per-point times (the cloud is read whole for them) they must lie within the
    trajectory's span, most of them, and the trajectory must have times
    (:func:`~app.core.trajectory_poses.interpolate_positions`).
    """
    from app.core.formats import read_point_cloud
    from app.core.trajectory_poses import interpolate_positions
    from app.kit.scan_files import stored_bag_options

    cloud = read_point_cloud(
        scan_path, format=scan_format, bag_options=stored_bag_options(scan_path)
    )
    times = cloud.attributes.get("time")
    outside = 0
    if times is not None:
        _, outside_mask = interpolate_positions(trajectory, np.asarray(times, dtype=np.float64))
        outside = int(outside_mask.sum())
    return summary(trajectory, points_outside=outside, point_times=times is not None)


def summary(trajectory: Trajectory, **extra: Any) -> dict[str, Any]:
    """``{"poses", "time_span", "has_orientations", ...}`` of a trajectory (JSON)."""
    return {
        "poses": len(trajectory),
        "time_span": [float(trajectory.times[0]), float(trajectory.times[-1])]
        if trajectory.has_times
        else None,
        "has_orientations": trajectory.orientations is not None,
        **extra,
    }


async def attach_trajectory(
    session: Any,
    settings: Any,
    principal: Any,
    scan_id: str,
    *,
    parts: dict[str, bytes],
    filename: str | None,
    rate: float | None,
    trajectory_format: str | None,
) -> dict[str, Any]:
    """Parse, check and store a trajectory for a stored scan; its summary."""
    import anyio

    from app.db.models import Scan
    from app.services import storage
    from app.services.scoping import get_owned

    scan = await anyio.to_thread.run_sync(get_owned, session, principal, Scan, scan_id)
    data, times = parts.get("trajectory"), parts.get("trajectory_times")
    check_times_without_trajectory(data is not None, times, rate)
    if data is None:
        raise TrajectoryError(
            "no trajectory was sent: send it as the body or the multipart part 'trajectory'"
        )
    trajectory = parse_trajectory(
        data, filename, times=times, rate=rate, trajectory_format=trajectory_format
    )
    scan_path = storage.stored_file(settings, scan.storage_path)
    fits = await anyio.to_thread.run_sync(check_fits, scan_path, scan.format, trajectory)
    await anyio.to_thread.run_sync(save_trajectory, trajectory_path(scan_path), trajectory)
    return {"scan_id": scan.id, **fits}


@dataclass(frozen=True)
class TrajectoryUpload:
    """A trajectory sent with a scan: the file's bytes, its name, its pose times or rate."""

    data: bytes
    filename: str | None = None
    times: bytes | None = None
    rate: float | None = None
    trajectory_format: str | None = None

    def digest(self) -> str:
        """A digest of everything sent (for the upload's idempotency fingerprint)."""
        import hashlib

        digest = hashlib.sha256(repr((self.rate, self.trajectory_format)).encode())
        for part in (self.data, self.times or b""):
            digest.update(hashlib.sha256(part).digest())
        return digest.hexdigest()

    def checked_against(self, scan_path: Path, scan_format: str | None) -> Trajectory:
        """The parsed trajectory, checked against the scan's points (TrajectoryError: 422)."""
        trajectory = parse_trajectory(
            self.data,
            self.filename,
            times=self.times,
            rate=self.rate,
            trajectory_format=self.trajectory_format,
        )
        check_fits(scan_path, scan_format, trajectory)
        return trajectory


def upload_of(
    body: Any, rate: float | None, trajectory_format: str | None
) -> TrajectoryUpload | None:
    """The trajectory parts of an upload's body (multipart ``trajectory`` and
    ``trajectory_times``), or None without them; pose times without a trajectory: 422."""
    parts = getattr(body, "parts", {})
    data, times = parts.get("trajectory"), parts.get("trajectory_times")
    check_times_without_trajectory(data is not None, times, rate)
    if data is None:
        return None
    return TrajectoryUpload(
        data=bytes(data),
        filename=getattr(body, "part_filenames", {}).get("trajectory"),
        times=None if times is None else bytes(times),
        rate=rate,
        trajectory_format=trajectory_format,
    )


def held(upload: TrajectoryUpload) -> dict[str, Any]:
    """A trajectory upload as JSON (the files base64), to hold with an unfinished upload."""

    def encoded(data: bytes | None) -> str | None:
        return None if data is None else base64.b64encode(data).decode("ascii")

    return {
        "data": encoded(upload.data),
        "times": encoded(upload.times),
        "filename": upload.filename,
        "rate": upload.rate,
        "trajectory_format": upload.trajectory_format,
    }


def from_held(stored: dict[str, Any] | None) -> TrajectoryUpload | None:
    """The trajectory upload :func:`held` gave, or None."""
    if not stored:
        return None
    times = stored.get("times")
    return TrajectoryUpload(
        data=base64.b64decode(stored["data"]),
        filename=stored.get("filename"),
        times=None if times is None else base64.b64decode(times),
        rate=stored.get("rate"),
        trajectory_format=stored.get("trajectory_format"),
    )
