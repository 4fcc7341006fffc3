"""Resumable uploads (the tus protocol 1.0.0): a scan sent in pieces over a flaky link.

Extensions: ``creation``, ``expiration``, ``termination`` and ``checksum``. An upload is created
with its ``Upload-Length`` and ``Upload-Metadata`` (``site`` and what the normal upload takes:
``filename``, ``reference``, ``method``, ``variant``, ``sensor_origin``, a ROS bag's parameters
as ``bag.KEY`` keys; optionally the whole file's ``checksum`` as ``sha256:<hex>``), then
receives ``PATCH`` requests at its offset.  Its bytes live in ``uploads/<id>.part`` under the
data directory; each PATCH appends, fsyncs, and only then commits the new offset in the
``resumable_upload`` row, so a killed server loses no accepted byte (bytes written after the
last committed offset are cut off by the next PATCH).

The organisation's storage quota counts the accepted bytes of its active uploads
(:func:`app.services.quotas.stored_bytes`): a PATCH that would pass it is refused with 413,
and an expired or terminated upload releases them.  When the last byte arrives, the whole-file
checksum (when declared) is verified and the file becomes a scan through
:func:`app.services.scans.store_received_scan`, exactly as a normal upload: validation,
summary, atomic store, 201 (reference) or 202 with the job.  Any refusal there leaves nothing
stored and the upload ``failed``.

States: ``active`` (receiving; ``expired`` once ``expires_at`` passed), ``completing`` (all
bytes in, becoming a scan), ``completed``, ``failed``, ``terminated``, ``expired``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import os
import re
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, BinaryIO

import anyio
from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from app.clock import as_utc, utc_now
from app.config import Settings
from app.core.errors import InputError
from app.db.models import ResumableUpload
from app.db.session import transaction
from app.services import quotas, scans, storage, trajectories
from app.services.auth import Principal
from app.services.errors import (
    AppError,
    BadRequestError,
    ConflictError,
    PayloadTooLargeError,
    UnsupportedMediaError,
    ValidationFailedError,
)
from app.services.idempotency import StoredResponse
from app.services.scoping import get_owned
from app.services.sensor_origins import parse_sensor_origin
from app.services.transaction import end_read_transaction, rollback
from app.services.tus_protocol import CHECKSUM_ALGORITHMS, PATCH_CONTENT_TYPE, parse_metadata

BAG_PREFIX = "bag."
"""Metadata keys ``bag.cloud_topic``, ``bag.voxel_size``...: how to read an uploaded ROS bag."""
FILE_CHECKSUM = re.compile(r"^sha256:([0-9a-fA-F]{64})$")
UPLOAD_SUFFIX = ".part"
HASH_BLOCK_BYTES = 1 << 20
TOMBSTONE_FACTOR = 2
"""Finished, failed or expired uploads are forgotten (404) after this many expiry periods."""


class ChecksumMismatchError(AppError, status_code=460, code="checksum_mismatch"):
    """The chunk's ``Upload-Checksum`` does not match its bytes (tus: 460)."""


class UploadGoneError(AppError, status_code=410, code="upload_gone"):
    """The upload expired, was terminated or failed: its bytes are gone."""


@dataclass(frozen=True)
class UploadProgress:
    """What the tus headers of an upload say: its offset, length, expiry and metadata."""

    id: str
    offset: int
    length: int
    expires_at: datetime
    upload_metadata: str
    response: StoredResponse | None = None
    """The scan (201) or scan and job (202) once the upload completed in this request."""


@dataclass(frozen=True)
class UploadView:
    """An upload's row as plain values, usable after its transaction ended."""

    id: str
    site_id: str
    offset: int
    length: int
    state: str
    options: dict[str, Any]
    upload_metadata: str
    expires_at: datetime
    result_status: int | None
    result: dict[str, Any] | None

    @classmethod
    def of(cls, upload: ResumableUpload) -> UploadView:
        """The values of ``upload``."""
        return cls(
            id=upload.id,
            site_id=upload.site_id,
            offset=upload.offset,
            length=upload.length,
            state=upload.state,
            options=dict(upload.options),
            upload_metadata=upload.upload_metadata,
            expires_at=as_utc(upload.expires_at),
            result_status=upload.result_status,
            result=upload.result,
        )


def _upload_options(metadata: dict[str, str]) -> dict[str, Any]:
    """The normal upload's options from the metadata (stored with the upload); 4xx if bad."""
    site_id = metadata.get("site")
    if not site_id:
        raise BadRequestError(
            "Upload-Metadata needs 'site' (the site id, base64) to know where the scan goes",
            code="missing_site",
        )
    reference = metadata.get("reference", "false").strip().lower()
    if reference not in ("true", "false", "1", "0"):
        raise ValidationFailedError(
            f"metadata 'reference' must be true or false (got {reference!r})"
        )
    checksum = metadata.get("checksum")
    if checksum is not None and not FILE_CHECKSUM.match(checksum.strip()):
        raise ValidationFailedError(
            "metadata 'checksum' must be 'sha256:' and the file's 64 hex digits",
            code="malformed_checksum",
        )
    return {
        "site_id": site_id,
        "bag_parameters": _bag_parameters(metadata),
        "reference": reference in ("true", "1"),
        "filename": metadata.get("filename") or metadata.get("name"),
        "method": metadata.get("method"),
        "variant": metadata.get("variant"),
        "sensor_origin": parse_sensor_origin(metadata.get("sensor_origin")),
        "checksum": None if checksum is None else checksum.strip().split(":", 1)[1].lower(),
    }


def _bag_parameters(metadata: dict[str, str]) -> dict[str, str] | None:
    """The ``bag.KEY`` metadata (how to read a ROS bag) as ``?bag=KEY=VALUE`` would give them,
    checked the same way (422 naming the bad one); None without."""
    values = [
        f"{key[len(BAG_PREFIX) :]}={value}"
        for key, value in metadata.items()
        if key.startswith(BAG_PREFIX)
    ]
    if "bag" in metadata:
        raise ValidationFailedError(
            "metadata 'bag' is not a parameter: give each bag parameter as its own key "
            "'bag.KEY' (e.g. bag.cloud_topic with the topic's name, base64)"
        )
    return scans.parse_bag_parameters(values)


def _scan_options(upload: UploadView) -> scans.UploadOptions:
    options = upload.options
    return scans.UploadOptions(
        site_id=upload.site_id,
        reference=bool(options["reference"]),
        filename=options.get("filename"),
        method=options.get("method"),
        variant=options.get("variant"),
        sensor_origin=options.get("sensor_origin"),
        bag_parameters=options.get("bag_parameters"),
    )


def upload_path(settings: Settings, upload_id: str) -> Path:
    """Where the upload's bytes are kept between requests (under the data directory)."""
    return settings.data_layout.resolve(f"uploads/{upload_id}{UPLOAD_SUFFIX}")


def _progress(
    upload: ResumableUpload | UploadView, response: StoredResponse | None = None
) -> UploadProgress:
    return UploadProgress(
        id=upload.id,
        offset=upload.offset,
        length=upload.length,
        expires_at=as_utc(upload.expires_at),
        upload_metadata=upload.upload_metadata,
        response=response,
    )


def _is_expired(upload: ResumableUpload, now: datetime) -> bool:
    expired = upload.state == "active" and as_utc(upload.expires_at) <= now
    return upload.state == "expired" or expired


def owned_upload(session: Session, principal: Principal, upload_id: str) -> ResumableUpload:
    """The principal's upload; 404 if unknown or another's, 410 if its bytes are gone."""
    upload = get_owned(session, principal, ResumableUpload, upload_id)
    if _is_expired(upload, utc_now()):
        raise UploadGoneError(
            f"upload {upload_id} expired (SCANDIFF_RESUMABLE_UPLOAD_EXPIRY_SECONDS after its last "
            "bytes) and its bytes were released: start a new upload"
        )
    if upload.state == "terminated":
        raise UploadGoneError(f"upload {upload_id} was terminated: start a new upload")
    if upload.state == "failed":
        raise UploadGoneError(
            f"upload {upload_id} failed and nothing was stored ({upload.error}): fix the file "
            "and start a new upload"
        )
    return upload


def create_upload(
    session: Session, settings: Settings, principal: Principal, length: int | None, metadata: str
) -> UploadProgress:
    """Create an upload after the checks a normal upload makes before its body (4xx)."""
    if length is None:
        raise BadRequestError(
            "send Upload-Length (the file's size in bytes): deferred lengths are not supported",
            code="missing_upload_length",
        )
    if length == 0:
        raise BadRequestError(
            "Upload-Length is 0: a scan file cannot be empty", code="empty_upload"
        )
    if length > settings.max_upload_bytes:
        raise PayloadTooLargeError(storage.too_large_message(settings.max_upload_bytes))
    options = _upload_options(parse_metadata(metadata))
    target = scans.UploadOptions(
        site_id=options["site_id"],
        reference=options["reference"],
        filename=options["filename"],
        method=options["method"],
        variant=options["variant"],
        declared_size=length,
    )
    scans.check_upload_target(session, settings, principal, target)  # ends its read
    remove_expired_uploads(session, settings)
    upload = ResumableUpload(
        organisation_id=principal.organisation_id,
        site_id=options["site_id"],
        length=length,
        offset=0,
        options=options,
        upload_metadata=metadata,
        state="active",
        expires_at=utc_now() + timedelta(seconds=settings.resumable_upload_expiry_seconds),
    )
    session.add(upload)
    session.flush()
    return _progress(upload)


def upload_progress(session: Session, principal: Principal, upload_id: str) -> UploadProgress:
    """The upload's offset, length and expiry (404 unknown, 410 gone)."""
    return _progress(owned_upload(session, principal, upload_id))


def get_upload(session: Session, principal: Principal, upload_id: str) -> ResumableUpload:
    """The upload's row whatever its state (404 when unknown or another's)."""
    return get_owned(session, principal, ResumableUpload, upload_id)


def terminate_upload(
    session: Session, settings: Settings, principal: Principal, upload_id: str
) -> None:
    """Drop an unfinished upload and its bytes (releases its quota); 409 once completed."""
    upload = owned_upload(session, principal, upload_id)
    if upload.state in ("completing", "completed"):
        raise ConflictError(
            f"upload {upload_id} is complete: it is a scan now (GET /api/v1/uploads/{upload_id})"
        )
    path = upload_path(settings, upload.id)
    with _locked(path, upload_id, create=False):
        upload.state = "terminated"
        session.flush()
        storage.remove_file(path)


@contextlib.contextmanager
def _locked(path: Path, upload_id: str, *, create: bool = True) -> Any:
    """The upload's file opened for appending under an exclusive lock (409 while another request
    holds it); None when ``create`` is false and there is no file."""
    if not create and not path.exists():
        yield None
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "ab+") as handle:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as exc:
            raise ConflictError(
                f"another request is writing upload {upload_id}: wait for it, then HEAD the "
                "upload for its offset",
                code="upload_locked",
            ) from exc
        yield handle


def _begin_append(
    session: Session,
    settings: Settings,
    principal: Principal,
    upload_id: str,
    offset: int,
    content_length: int | None,
    declared_length: int | None,
) -> tuple[UploadView, int | None]:
    """The checks before a PATCH's body is read; the upload and the bytes the quota leaves."""
    upload = UploadView.of(owned_upload(session, principal, upload_id))
    if declared_length is not None and declared_length != upload.length:
        raise ConflictError(
            f"Upload-Length is {declared_length} but upload {upload_id} was created for "
            f"{upload.length} bytes: a different file needs a new upload",
            code="different_file",
        )
    if upload.offset != offset:
        raise ConflictError(
            f"Upload-Offset is {offset} but upload {upload_id} has {upload.offset} bytes: "
            "resume from there (HEAD the upload for its offset)",
            code="offset_mismatch",
        )
    if content_length is not None and offset + content_length > upload.length:
        raise BadRequestError(_past_length_message(upload), code="past_upload_length")
    left = quotas.remaining_bytes(session, settings, principal)
    if left is not None and content_length is not None and content_length > left:
        raise _quota_error(settings, left, content_length)
    end_read_transaction(session)
    return upload, left


def _past_length_message(upload: UploadView) -> str:
    return (
        f"this PATCH carries bytes past the Upload-Length of {upload.length} declared for upload "
        f"{upload.id}: is it the same file? A different file needs a new upload"
    )


def _quota_error(settings: Settings, left: int, adding: int) -> PayloadTooLargeError:
    """The 413 of a PATCH that would pass the storage quota (``left`` bytes were free)."""
    cap = settings.max_stored_bytes_per_organisation or 0
    return PayloadTooLargeError(
        quotas.storage_message(cap - left, cap, adding, at_least=True)
        + "; the accepted bytes of unfinished resumable uploads count until they expire "
        "(DELETE /api/v1/uploads/{id} releases them)",
        code="storage_quota_exceeded",
    )


async def _write_body(
    handle: BinaryIO,
    chunks: AsyncIterator[bytes],
    upload: UploadView,
    settings: Settings,
    left: int | None,
    checksum: tuple[str, bytes] | None,
) -> int:
    """Append the body at the upload's offset; the bytes written (the file is cut back on error)."""
    handle.truncate(upload.offset)  # bytes after the committed offset were never accepted
    handle.seek(upload.offset)
    hasher = None if checksum is None else CHECKSUM_ALGORITHMS[checksum[0]]()
    written = 0
    try:
        async for chunk in chunks:
            written += len(chunk)
            if upload.offset + written > upload.length:
                raise BadRequestError(_past_length_message(upload), code="past_upload_length")
            if left is not None and written > left:
                raise _quota_error(settings, left, written)
            if hasher is not None:
                hasher.update(chunk)
            handle.write(chunk)
        if checksum is not None and hasher is not None and hasher.digest() != checksum[1]:
            raise ChecksumMismatchError(
                f"Upload-Checksum ({checksum[0]}) does not match the {written} bytes received: "
                "they were discarded; send the chunk again from the same offset"
            )
        handle.flush()
        await anyio.to_thread.run_sync(os.fsync, handle.fileno())
    except BaseException:
        handle.truncate(upload.offset)
        raise
    return written


def _commit_offset(settings: Settings, upload_id: str, offset: int, completing: bool) -> UploadView:
    """Record accepted bytes (after the fsync) in a transaction of their own; the new values."""
    with transaction(settings.sqlalchemy_url) as session:
        upload = session.get(ResumableUpload, upload_id)
        if upload is None or upload.state != "active":
            raise UploadGoneError(f"upload {upload_id} was terminated meanwhile")
        upload.offset = offset
        upload.expires_at = utc_now() + timedelta(seconds=settings.resumable_upload_expiry_seconds)
        if completing:
            upload.state = "completing"
        session.flush()
        return UploadView.of(upload)


def _recorded_state(settings: Settings, upload_id: str) -> tuple[str, int]:
    """The upload's state and committed offset as the database has them now."""
    with transaction(settings.sqlalchemy_url) as session:
        upload = session.get(ResumableUpload, upload_id)
        return ("gone", -1) if upload is None else (upload.state, upload.offset)


def _mark_failed(settings: Settings, upload_id: str, message: str) -> None:
    with transaction(settings.sqlalchemy_url) as session:
        upload = session.get(ResumableUpload, upload_id)
        if upload is not None:
            upload.state = "failed"
            upload.error = message[:2000]


async def append(
    session: Session,
    settings: Settings,
    principal: Principal,
    upload_id: str,
    *,
    offset: int | None,
    content_type: str,
    content_length: int | None,
    declared_length: int | None,
    checksum: tuple[str, bytes] | None,
    chunks: AsyncIterator[bytes],
    disconnected: Callable[[], bool],
) -> UploadProgress:
    """A PATCH: append its body at ``offset`` (409 elsewhere), then complete the upload if full.

    A client that disconnects keeps the bytes that arrived (unless it sent a checksum, which
    they could not match): it resumes from the offset HEAD gives.
    """
    if content_type != PATCH_CONTENT_TYPE:
        raise UnsupportedMediaError(
            f"a PATCH body must be sent as Content-Type: {PATCH_CONTENT_TYPE} "
            f"(got {content_type!r})"
        )
    if offset is None:
        raise BadRequestError("send Upload-Offset (HEAD the upload for it)", code="missing_offset")
    upload, left = await anyio.to_thread.run_sync(
        _begin_append,
        session,
        settings,
        principal,
        upload_id,
        offset,
        content_length,
        declared_length,
    )
    if upload.state == "completed" and upload.result_status is not None:
        return _progress(upload, StoredResponse(upload.result_status, upload.result or {}))
    path = upload_path(settings, upload.id)
    with _locked(path, upload.id) as handle:
        current = await anyio.to_thread.run_sync(_recorded_state, settings, upload.id)
        if current != (upload.state, upload.offset):  # another PATCH ended meanwhile
            raise ConflictError(
                f"upload {upload.id} changed while this PATCH waited (now {current[0]} at "
                f"{current[1]} bytes): HEAD the upload for its offset and resume from there",
                code="offset_mismatch",
            )
        if upload.state == "completing" or upload.offset == upload.length:
            # the completion of an earlier PATCH was interrupted: an empty PATCH retries it
            return await _complete(session, settings, principal, upload, path)
        written = await _write_body(handle, chunks, upload, settings, left, checksum)
        if disconnected() and checksum is not None:
            handle.truncate(upload.offset)  # a partial chunk cannot be checked: not accepted
            return _progress(upload)
        completing = upload.offset + written == upload.length
        upload = await anyio.to_thread.run_sync(
            _commit_offset, settings, upload.id, upload.offset + written, completing
        )
        if not completing:
            return _progress(upload)
        return await _complete(session, settings, principal, upload, path)


def _file_digest(path: Path) -> tuple[str, bytes]:
    """The SHA-256 (hex) of the whole file and its first bytes (for format sniffing)."""
    hasher = hashlib.sha256()
    with open(path, "rb") as source:
        head = source.read(storage.HEAD_BYTES)
        hasher.update(head)
        while block := source.read(HASH_BLOCK_BYTES):
            hasher.update(block)
    return hasher.hexdigest(), head


async def _complete(
    session: Session, settings: Settings, principal: Principal, upload: UploadView, path: Path
) -> UploadProgress:
    """The full file becomes a scan as a normal upload does; on a refusal nothing is stored."""
    try:
        if not path.is_file() or path.stat().st_size != upload.length:
            raise ConflictError(
                f"the bytes of upload {upload.id} are incomplete on the server: start a new upload"
            )
        sha256, head = await anyio.to_thread.run_sync(_file_digest, path)
        declared = upload.options.get("checksum")
        if declared is not None and declared != sha256:
            raise ValidationFailedError(
                f"the whole file's SHA-256 is {sha256} but the upload declared {declared}: the "
                "bytes received are not the file that was announced (resumed with a different "
                "file?); nothing was stored, start a new upload",
                code="file_checksum_mismatch",
            )
        received = storage.ReceivedFile(
            path=path, size_bytes=upload.length, sha256=sha256, head=head
        )
        response = await scans.store_received_scan(
            session,
            settings,
            principal,
            _scan_options(upload),
            received,
            trajectory=trajectories.from_held(upload.options.get("trajectory")),
        )
    except (AppError, InputError) as exc:
        await anyio.to_thread.run_sync(rollback, session)
        await anyio.to_thread.run_sync(_mark_failed, settings, upload.id, str(exc))
        storage.remove_file(path)
        raise
    await anyio.to_thread.run_sync(_record_result, session, upload.id, response)
    storage.remove_file(path)  # moved into scans/ already
    return _progress(dataclasses.replace(upload, offset=upload.length), response)


def _record_result(session: Session, upload_id: str, response: StoredResponse) -> None:
    """Mark the upload completed in the transaction that stores its scan."""
    upload = session.get(ResumableUpload, upload_id)
    if upload is not None:
        upload.state = "completed"
        upload.offset = upload.length
        upload.result_status = response.status_code
        upload.result = response.body
        session.flush()


def remove_expired_uploads(session: Session, settings: Settings) -> int:
    """Release expired uploads (their bytes and quota), forget old finished ones and delete the
    bytes of uploads whose site was deleted; how many expired (run on each creation)."""
    now = utc_now()
    expired = session.scalars(
        select(ResumableUpload).where(
            ResumableUpload.state.in_(("active", "completing")), ResumableUpload.expires_at <= now
        )
    ).all()
    for upload in expired:
        upload.state = "expired"
        storage.remove_file(upload_path(settings, upload.id))
    forget_before = now - timedelta(
        seconds=TOMBSTONE_FACTOR * settings.resumable_upload_expiry_seconds
    )
    session.execute(
        delete(ResumableUpload)
        .where(
            ResumableUpload.state.not_in(("active", "completing")),
            ResumableUpload.expires_at <= forget_before,
        )
        .execution_options(synchronize_session=False)
    )
    session.flush()
    receiving = select(ResumableUpload.id).where(
        ResumableUpload.state.in_(("active", "completing"))
    )
    kept = {f"{upload_id}{UPLOAD_SUFFIX}" for upload_id in session.scalars(receiving)}
    if settings.uploads_dir.is_dir():
        for path in settings.uploads_dir.glob(f"*{UPLOAD_SUFFIX}"):
            if path.name not in kept:  # its site was deleted with its uploads
                storage.remove_file(path)
    return len(expired)
