"""Scans: metadata and the original file."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import FileResponse

from app.api.deps import PrincipalDep, SessionDep, SettingsDep
from app.services import scans as scans_service
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
