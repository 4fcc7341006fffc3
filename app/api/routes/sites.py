"""Sites, their scans (uploads), reference and job timeline."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.responses import JSONResponse

from app.api.deps import PrincipalDep, SessionDep, SettingsDep, WriterDep
from app.api.errors import QUEUED_JOBS_RESPONSE, STORAGE_QUOTA_RESPONSE
from app.api.uploads import RawBody, UploadBodyDep, declared_length
from app.db.models import JobStatus
from app.services import jobs as jobs_service
from app.services import scans as scans_service
from app.services import sensor_origins as sensor_origins_service
from app.services import sites as sites_service
from app.services.paging import DEFAULT_LIMIT, MAX_LIMIT
from app.services.schemas import (
    ErrorRead,
    JobRead,
    Page,
    ReferencePromote,
    ScanRead,
    SiteCreate,
    SiteRead,
    SiteUpdate,
    UploadRead,
)

router = APIRouter(tags=["sites"])

Limit = Annotated[int, Query(ge=1, le=MAX_LIMIT, description="Items per page.")]
Cursor = Annotated[str | None, Query(description="`next_cursor` of the previous page.")]

UPLOAD_BODY_SCHEMA: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "content": {
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "properties": {"file": {"type": "string", "format": "binary"}},
                    "required": ["file"],
                }
            },
        },
    }
}


@router.post("/sites", status_code=201, response_model=SiteRead)
def create_site(payload: SiteCreate, session: SessionDep, principal: WriterDep) -> SiteRead:
    """Create a site."""
    return SiteRead.from_model(sites_service.create_site(session, principal, payload))


@router.get("/sites", response_model=Page[SiteRead])
def list_sites(
    session: SessionDep,
    principal: PrincipalDep,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> Page[SiteRead]:
    """List the organisation's sites, newest first."""
    rows, next_cursor = sites_service.list_sites(session, principal, limit, cursor)
    return Page[SiteRead](items=[SiteRead.from_model(row) for row in rows], next_cursor=next_cursor)


@router.get("/sites/{site_id}", response_model=SiteRead)
def get_site(site_id: str, session: SessionDep, principal: PrincipalDep) -> SiteRead:
    """Read a site."""
    return SiteRead.from_model(sites_service.get_site(session, principal, site_id))


@router.patch("/sites/{site_id}", response_model=SiteRead)
def update_site(
    site_id: str,
    payload: SiteUpdate,
    session: SessionDep,
    settings: SettingsDep,
    principal: WriterDep,
) -> SiteRead:
    """Change a site's name, description or detector."""
    return SiteRead.from_model(
        sites_service.update_site(session, settings, principal, site_id, payload)
    )


@router.delete("/sites/{site_id}", status_code=204, response_class=Response)
def delete_site(
    site_id: str, session: SessionDep, settings: SettingsDep, principal: WriterDep
) -> Response:
    """Delete a site with its scans, jobs and their files."""
    sites_service.delete_site(session, settings, principal, site_id)
    return Response(status_code=204)


@router.post("/sites/{site_id}/reference", response_model=SiteRead)
def promote_reference(
    site_id: str, payload: ReferencePromote, session: SessionDep, principal: WriterDep
) -> SiteRead:
    """Make an existing scan of the site its reference."""
    site = sites_service.promote_reference(session, principal, site_id, payload.scan_id)
    return SiteRead.from_model(site)


@router.post(
    "/sites/{site_id}/scans",
    status_code=202,
    response_model=UploadRead,
    responses={
        201: {"model": UploadRead, "description": "Stored as the site's new reference (no job)."},
        202: {"model": UploadRead, "description": "Stored; its comparison job is queued."},
        409: {"model": ErrorRead, "description": "The site has no reference yet."},
        413: {"model": ErrorRead},
        415: {"model": ErrorRead},
        429: QUEUED_JOBS_RESPONSE,
        507: STORAGE_QUOTA_RESPONSE,
    },
    openapi_extra=UPLOAD_BODY_SCHEMA,
)
async def upload_scan(
    site_id: str,
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    principal: WriterDep,
    body: UploadBodyDep,
    reference: Annotated[bool, Query(description="Make this scan the site's reference.")] = False,
    filename: Annotated[str | None, Query(max_length=1000, description="Original name.")] = None,
    method: Annotated[str | None, Query(max_length=64, description="Detector override.")] = None,
    variant: Annotated[str | None, Query(max_length=64, description="Variant override.")] = None,
    sensor_origin: Annotated[
        str | None,
        Query(
            max_length=65_536,
            description="Sensor position 'x,y,z' in the file's frame (0,0,0 for a scan in its "
            "sensor's frame), or for a cloud merged from several stations a JSON list "
            "'[[x,y,z],...]' in the order of the file's per-point station index; enables the "
            "visibility test. Default: the file's own (PCD VIEWPOINT, E57 scan poses, per-point "
            "origin_x/y/z), else estimated from the points.",
        ),
    ] = None,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
    trajectory_rate: Annotated[
        float | None,
        Query(
            description="Poses a second of a KITTI poses 'trajectory' part (or send its "
            "times as the part 'trajectory_times').",
            gt=0,
        ),
    ] = None,
    trajectory_format: Annotated[
        str | None, Query(max_length=16, description="tum, kitti or csv (default: detected).")
    ] = None,
    bag: Annotated[
        list[str] | None,
        Query(
            max_length=1000,
            description="For a ROS bag whose topics or frames are ambiguous: KEY=VALUE, "
            "repeatable, KEY one of cloud_topic, fixed_frame, pose_topic, voxel_size (metres), "
            "max_sweeps. Kept with the scan, so its jobs read the same map.",
        ),
    ] = None,
) -> JSONResponse:
    """Upload a scan as the raw body or multipart field `file` (and optionally its
    `trajectory`); compare it to the reference."""
    options = scans_service.UploadOptions(
        site_id=site_id,
        reference=reference,
        filename=filename,
        method=method,
        variant=variant,
        idempotency_key=idempotency_key,
        sensor_origin=sensor_origins_service.parse_sensor_origin(sensor_origin),
        declared_size=declared_length(request) if isinstance(body, RawBody) else None,
        trajectory_rate=trajectory_rate,
        trajectory_format=trajectory_format,
        bag_parameters=scans_service.parse_bag_parameters(bag),
    )
    stored = await scans_service.upload_scan(session, settings, principal, options, body)
    return JSONResponse(stored.body, status_code=stored.status_code)


@router.get("/sites/{site_id}/scans", response_model=Page[ScanRead])
def list_site_scans(
    site_id: str,
    session: SessionDep,
    principal: PrincipalDep,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> Page[ScanRead]:
    """List a site's scans, newest first."""
    rows, next_cursor = scans_service.list_site_scans(session, principal, site_id, limit, cursor)
    return Page[ScanRead](items=[ScanRead.from_model(row) for row in rows], next_cursor=next_cursor)


@router.get("/sites/{site_id}/jobs", response_model=Page[JobRead])
def list_site_jobs(
    site_id: str,
    session: SessionDep,
    principal: PrincipalDep,
    changed: Annotated[bool | None, Query(description="Only jobs with this decision.")] = None,
    status: Annotated[JobStatus | None, Query(description="Only jobs in this state.")] = None,
    since: Annotated[datetime | None, Query(description="Only jobs created at/after.")] = None,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> Page[JobRead]:
    """The site's timeline of comparison jobs, newest first."""
    rows, next_cursor = jobs_service.list_site_jobs(
        session,
        principal,
        site_id,
        changed=changed,
        status=status,
        since=since,
        limit=limit,
        cursor=cursor,
    )
    return Page[JobRead](items=[JobRead.from_model(row) for row in rows], next_cursor=next_cursor)
