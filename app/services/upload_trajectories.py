"""A trajectory for a resumable (tus) upload, sent before its last bytes (issue 29).

A robot that uploads its map by tus sends the trajectory with ``PUT /api/v1/uploads/{id}/
trajectory`` while the upload is active: the file is parsed at once (a bad one is a 422 and
nothing is kept) and held with the upload; when the last bytes arrive, the scan is stored with
it exactly as a multipart upload with a ``trajectory`` part is (checked against the points'
times first: a trajectory that does not fit fails the upload and nothing is stored), so the
comparison job the upload queues already has it.  Once the upload is complete, the trajectory
goes to the scan instead (``PUT /api/v1/scans/{scan_id}/trajectory``).
"""

from __future__ import annotations

from typing import Any

from app.core.trajectory import TrajectoryError
from app.services.errors import ConflictError, PayloadTooLargeError
from app.services.resumable_uploads import owned_upload
from app.services.trajectories import (
    TrajectoryUpload,
    check_times_without_trajectory,
    held,
    parse_trajectory,
    summary,
)

MAX_PENDING_TRAJECTORY_BYTES = 4 * 1024 * 1024
"""Largest trajectory (with its times file) held with an unfinished upload (kept in its row,
read on every PATCH: some 50,000 TUM poses).  A larger one goes to the scan once stored."""


def hold_trajectory(
    session: Any,
    principal: Any,
    upload_id: str,
    *,
    parts: dict[str, bytes],
    filename: str | None,
    rate: float | None,
    trajectory_format: str | None,
) -> dict[str, Any]:
    """Parse a trajectory and hold it with an active upload; its summary (4xx if bad)."""
    upload = owned_upload(session, principal, upload_id)
    if upload.state != "active":
        raise ConflictError(
            f"upload {upload_id} is complete: add the trajectory to its scan with PUT "
            "/api/v1/scans/{scan_id}/trajectory (GET /api/v1/uploads/"
            f"{upload_id} names the scan), then re-run its job"
        )
    data, times = parts.get("trajectory"), parts.get("trajectory_times")
    check_times_without_trajectory(data is not None, times, rate)
    if data is None:
        raise TrajectoryError(
            "no trajectory was sent: send it as the body or the multipart part 'trajectory'"
        )
    if len(data) + len(times or b"") > MAX_PENDING_TRAJECTORY_BYTES:
        raise PayloadTooLargeError(
            f"a trajectory held with an unfinished upload is at most "
            f"{MAX_PENDING_TRAJECTORY_BYTES // 2**20} MB: finish the upload, then PUT the "
            "trajectory to its scan (/api/v1/scans/{scan_id}/trajectory) and re-run its job"
        )
    sent = TrajectoryUpload(
        data=data, filename=filename, times=times, rate=rate, trajectory_format=trajectory_format
    )
    trajectory = parse_trajectory(
        data, filename, times=times, rate=rate, trajectory_format=trajectory_format
    )
    upload.options = {**upload.options, "trajectory": held(sent)}
    session.flush()
    return {"upload_id": upload.id, **summary(trajectory, held_until="the upload completes")}
