"""Scans: metadata and the original file."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse

from app.api.deps import PrincipalDep, SessionDep, SettingsDep, WriterDep
from app.api.uploads import MAX_EXTRA_BYTES
from app.services import scans as scans_service
from app.services import trajectories as trajectories_service
from app.services.errors import PayloadTooLargeError
from app.services.schemas import ScanRead

router = APIRouter(tags=["scans"])


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
    filename: Annotated[str | None, Query(max_length=1000, description="Its name.")] = None,
    rate: Annotated[float | None, Query(gt=0, description="KITTI poses a second.")] = None,
    trajectory_format: Annotated[
        str | None, Query(max_length=16, description="tum, kitti or csv (default: detected).")
    ] = None,
) -> dict[str, Any]:
    """Add or replace a scan's trajectory: raw body, or parts trajectory/trajectory_times."""
    if request.headers.get("content-type", "").startswith("multipart/form-data"):
        async with request.form(max_part_size=MAX_EXTRA_BYTES) as form:
            parts = {
                name: await value.read() if hasattr(value, "read") else str(value).encode()
                for name, value in form.items()
                if name in ("trajectory", "trajectory_times")
            }
            names = {
                name: value.filename
                for name, value in form.items()
                if hasattr(value, "filename") and value.filename
            }
    else:
        body = await request.body()
        if len(body) > MAX_EXTRA_BYTES:
            raise PayloadTooLargeError(f"the trajectory is larger than {MAX_EXTRA_BYTES} bytes")
        parts, names = {"trajectory": body}, {"trajectory": filename} if filename else {}
    return await trajectories_service.attach_trajectory(
        session,
        settings,
        principal,
        scan_id,
        parts=parts,
        filename=names.get("trajectory") or filename,
        rate=rate,
        trajectory_format=trajectory_format,
    )
