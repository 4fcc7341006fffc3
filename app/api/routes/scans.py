"""Scans: metadata, the original file and trajectories (of a stored scan, or held with an
unfinished resumable upload)."""

from __future__ import annotations

import functools
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse

from app.api.deps import PrincipalDep, SessionDep, SettingsDep, WriterDep
from app.api.uploads import trajectory_parts
from app.services import scans as scans_service
from app.services import trajectories as trajectories_service
from app.services import upload_trajectories
from app.services.schemas import ScanRead

router = APIRouter(tags=["scans"])

TrajectoryName = Annotated[str | None, Query(max_length=1000, description="Its name.")]
TrajectoryRate = Annotated[float | None, Query(gt=0, description="KITTI poses a second.")]
TrajectoryFormat = Annotated[
    str | None, Query(max_length=16, description="tum, kitti or csv (default: detected).")
]


@router.get("/scans/{scan_id}", response_model=ScanRead)
def get_scan(scan_id: str, session: SessionDep, principal: PrincipalDep) -> ScanRead:
    """Read a scan's metadata."""
    return ScanRead.from_model(scans_service.get_scan(session, principal, scan_id))


@router.get("/scans/{scan_id}/file", response_class=FileResponse)
def get_scan_file(
    scan_id: str, session: SessionDep, settings: SettingsDep, principal: PrincipalDep
) -> FileResponse:
    """Download the scan's original bytes as uploaded."""
    download = scans_service.scan_file(session, settings, principal, scan_id)
    return FileResponse(download.path, media_type=download.media_type, filename=download.filename)


@router.put("/scans/{scan_id}/trajectory")
async def put_scan_trajectory(
    scan_id: str,
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    principal: WriterDep,
    filename: TrajectoryName = None,
    rate: TrajectoryRate = None,
    trajectory_format: TrajectoryFormat = None,
) -> dict[str, Any]:
    """Add or replace a scan's trajectory: raw body, or parts trajectory/trajectory_times."""
    parts, sent_name = await trajectory_parts(request, filename)
    return await trajectories_service.attach_trajectory(
        session,
        settings,
        principal,
        scan_id,
        parts=parts,
        filename=sent_name,
        rate=rate,
        trajectory_format=trajectory_format,
    )


@router.put("/uploads/{upload_id}/trajectory")
async def put_upload_trajectory(
    upload_id: str,
    request: Request,
    session: SessionDep,
    principal: WriterDep,
    filename: TrajectoryName = None,
    rate: TrajectoryRate = None,
    trajectory_format: TrajectoryFormat = None,
) -> dict[str, Any]:
    """Hold a trajectory with an unfinished resumable upload; its scan is stored with it."""
    parts, sent_name = await trajectory_parts(request, filename)
    return await anyio.to_thread.run_sync(
        functools.partial(
            upload_trajectories.hold_trajectory,
            session,
            principal,
            upload_id,
            parts=parts,
            filename=sent_name,
            rate=rate,
            trajectory_format=trajectory_format,
        )
    )
