"""Resumable uploads (tus 1.0.0): create, read the offset, append, terminate, see the outcome."""

from __future__ import annotations

from collections.abc import AsyncIterator
from email.utils import format_datetime
from typing import Annotated

import anyio
from fastapi import APIRouter, Depends, Header, Request, Response
from fastapi.responses import JSONResponse
from starlette.requests import ClientDisconnect

from app.api.deps import PrincipalDep, SessionDep, SettingsDep, WriterDep
from app.api.uploads import declared_length
from app.services import resumable_uploads as uploads_service
from app.services import tus_protocol
from app.services.errors import AppError
from app.services.resumable_upload_schemas import ResumableUploadRead

TUS_HEADERS = {"Tus-Resumable": tus_protocol.TUS_VERSION}


async def tus_headers(
    request: Request, tus_resumable: Annotated[str | None, Header()] = None
) -> AsyncIterator[None]:
    """Every answer carries ``Tus-Resumable``; requests but OPTIONS and GET must send it (412)."""
    try:
        if request.method not in ("OPTIONS", "GET"):
            tus_protocol.check_tus_version(tus_resumable)
        yield
    except AppError as exc:
        exc.headers.update(TUS_HEADERS)
        raise


router = APIRouter(tags=["resumable uploads"], dependencies=[Depends(tus_headers)])


def _progress_headers(progress: uploads_service.UploadProgress) -> dict[str, str]:
    return {
        **TUS_HEADERS,
        "Upload-Offset": str(progress.offset),
        "Upload-Expires": format_datetime(progress.expires_at, usegmt=True),
        "Cache-Control": "no-store",
    }


class PatchBody:
    """The PATCH body as it arrives; a client that disconnects only ends it."""

    def __init__(self, request: Request) -> None:
        self._request = request
        self.disconnected = False

    async def chunks(self) -> AsyncIterator[bytes]:
        """The body's bytes until its end or the client's disconnection."""
        try:
            async for chunk in self._request.stream():
                if chunk:
                    yield chunk
        except ClientDisconnect:
            self.disconnected = True


@router.options("/uploads", status_code=204)
def upload_capabilities(principal: PrincipalDep, settings: SettingsDep) -> Response:
    """The tus version, extensions, size limit and checksum algorithms of this server."""
    return Response(
        status_code=204,
        headers={
            **TUS_HEADERS,
            "Tus-Version": tus_protocol.TUS_VERSION,
            "Tus-Extension": tus_protocol.TUS_EXTENSIONS,
            "Tus-Max-Size": str(settings.max_upload_bytes),
            "Tus-Checksum-Algorithm": ",".join(tus_protocol.CHECKSUM_ALGORITHMS),
        },
    )


@router.post("/uploads", status_code=201)
def create_upload(
    session: SessionDep,
    settings: SettingsDep,
    principal: WriterDep,
    upload_length: Annotated[str | None, Header()] = None,
    upload_metadata: Annotated[str | None, Header(max_length=65_536)] = None,
) -> Response:
    """Create a resumable upload (`Upload-Length`, `Upload-Metadata` with `site`); 201 Location."""
    length = tus_protocol.parse_non_negative(upload_length, "Upload-Length")
    progress = uploads_service.create_upload(
        session, settings, principal, length, upload_metadata or ""
    )
    return Response(
        status_code=201,
        headers={**_progress_headers(progress), "Location": f"/api/v1/uploads/{progress.id}"},
    )


@router.head("/uploads/{upload_id}")
def upload_offset(upload_id: str, session: SessionDep, principal: PrincipalDep) -> Response:
    """The upload's offset and length (`Upload-Offset`, `Upload-Length`): resume from there."""
    progress = uploads_service.upload_progress(session, principal, upload_id)
    headers = {**_progress_headers(progress), "Upload-Length": str(progress.length)}
    if progress.upload_metadata:
        headers["Upload-Metadata"] = progress.upload_metadata
    return Response(status_code=200, headers=headers)


@router.patch("/uploads/{upload_id}", status_code=204)
async def append_to_upload(
    upload_id: str,
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    principal: WriterDep,
    upload_offset: Annotated[str | None, Header()] = None,
    upload_length: Annotated[str | None, Header()] = None,
    upload_checksum: Annotated[str | None, Header()] = None,
    content_type: Annotated[str, Header()] = "",
) -> Response:
    """Append bytes at `Upload-Offset`; the last ones make the scan (201/202 with its answer)."""
    body = PatchBody(request)
    progress = await uploads_service.append(
        session,
        settings,
        principal,
        upload_id,
        offset=tus_protocol.parse_non_negative(upload_offset, "Upload-Offset"),
        content_type=content_type.split(";")[0].strip().lower(),
        content_length=declared_length(request),
        declared_length=tus_protocol.parse_non_negative(upload_length, "Upload-Length"),
        checksum=tus_protocol.parse_checksum(upload_checksum),
        chunks=body.chunks(),
        disconnected=lambda: body.disconnected,
    )
    if progress.response is not None:
        stored = progress.response
        return JSONResponse(
            stored.body, status_code=stored.status_code, headers=_progress_headers(progress)
        )
    return Response(status_code=204, headers=_progress_headers(progress))


@router.delete("/uploads/{upload_id}", status_code=204)
async def terminate_upload(
    upload_id: str, session: SessionDep, settings: SettingsDep, principal: WriterDep
) -> Response:
    """Terminate an unfinished upload: its bytes are deleted and its quota released."""
    await anyio.to_thread.run_sync(
        uploads_service.terminate_upload, session, settings, principal, upload_id
    )
    return Response(status_code=204, headers=TUS_HEADERS)


@router.get("/uploads/{upload_id}", response_model=ResumableUploadRead)
def get_upload(upload_id: str, session: SessionDep, principal: PrincipalDep) -> ResumableUploadRead:
    """A resumable upload's state and, once completed, its scan and job."""
    return ResumableUploadRead.from_model(uploads_service.get_upload(session, principal, upload_id))
