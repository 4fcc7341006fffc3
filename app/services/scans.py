"""Scans: uploads (stream, store, parse, then register), reads and downloads of the originals.

An upload never holds a database transaction while it reads the body or parses the cloud:
a short read checks the site first (404, 409 without a reference, 422 for a bad detector) and
the storage quota (507 when ``Content-Length`` alone would pass it), the body streams to a
temporary file under the size cap and the storage left (507 as soon as it is passed), the
storage quota is checked again with the exact size, the core reader parses it (a malformed file
is a 4xx with the core's message, nothing is stored), the file is renamed into place, and only
then a short write transaction locks the organisation, checks the storage quota a last time and
inserts the scan and its job (:func:`app.services.jobs.new_job` checks the cap on unfinished
jobs there: 429) and the idempotency record.  Any refusal leaves no row, and the file goes with
the rolled-back transaction.
"""

from __future__ import annotations

import dataclasses
import functools
import threading
from collections.abc import AsyncIterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import anyio
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.config import Settings
from app.core.errors import InputError
from app.core.formats.rosbag import BAG_FORMATS, bag_options_from_strings
from app.db.models import IdempotencyRecord, Scan, new_id
from app.kit.scan_files import save_bag_options
from app.services import idempotency, jobs, quotas, sites, storage, trajectories
from app.services.auth import Principal
from app.services.errors import ConflictError, NotFoundError, ValidationFailedError
from app.services.idempotency import StoredResponse
from app.services.paging import newest_first_page
from app.services.schemas import JobRead, ScanRead, UploadRead
from app.services.scoping import get_owned, scoped
from app.services.sensor_origins import SensorOrigin, check_stations_match
from app.services.transaction import after_rollback, end_read_transaction

PARSE_SLOTS = threading.BoundedSemaphore(2)
"""At most this many clouds are parsed at once per process: checking a binary PLY/PCD, a
LAS/LAZ, a text or a ``.npy`` upload takes a few MB, but an E57 or ``.npz`` file, or a text
file with station columns, is decoded whole (gigabytes)."""


@dataclass(frozen=True)
class UploadOptions:
    """What an upload request asks for, besides its body."""

    site_id: str
    reference: bool
    filename: str | None
    method: str | None = None
    variant: str | None = None
    idempotency_key: str | None = None
    sensor_origin: SensorOrigin | None = None
    declared_size: int | None = None
    """The file's size when known before reading the body (a raw body's ``Content-Length``)."""
    trajectory_rate: float | None = None
    """KITTI poses' constant rate (poses a second), when the ``trajectory`` part is KITTI."""
    trajectory_format: str | None = None
    bag_parameters: dict[str, str] | None = None
    """How to read a ROS bag (``cloud_topic``, ``fixed_frame``, ``pose_topic``, ``voxel_size``,
    ``max_sweeps``), when the bag's own choices are ambiguous; kept beside the stored bag."""


class UploadBody(Protocol):
    """A request body being received: its bytes, then the client's file name once known."""

    def chunks(self) -> AsyncIterator[bytes]:
        """The bytes of the file, in order (may raise the service's errors)."""
        ...

    @property
    def filename(self) -> str | None:
        """The file name the client gave in the body (multipart), once ``chunks`` is consumed."""
        ...


@dataclass(frozen=True)
class ParsedScan:
    """What the core reader found in an upload."""

    format: str
    n_points: int
    n_dropped: int
    bbox_min: list[float]
    bbox_max: list[float]
    sensor_origin: SensorOrigin | None = None
    n_stations: int | None = None
    """Stations the file's per-point station index names (None: no index)."""


@dataclass(frozen=True)
class DownloadFile:
    """A stored file to send back."""

    path: Path
    filename: str
    media_type: str = "application/octet-stream"


def no_reference_message(site_id: str) -> str:
    """The 409 message for a comparison upload to a site without a reference."""
    return (
        f"site {site_id} has no reference scan yet: upload one first with "
        f"POST /api/v1/sites/{site_id}/scans?reference=true"
    )


def _key_was_used(session: Session, principal: Principal, key: str | None) -> bool:
    """Whether ``key`` has a stored response (its retry must replay, never be refused)."""
    if key is None:
        return False
    used = scoped(select(IdempotencyRecord.id).where(IdempotencyRecord.key == key), principal)
    return session.scalar(used) is not None


def check_upload_target(
    session: Session, settings: Settings, principal: Principal, options: UploadOptions
) -> int | None:
    """Site, reference, detector and storage quota before the body is read; the storage left."""
    site = sites.get_site(session, principal, options.site_id)
    if not options.reference:
        if site.reference_scan_id is None:
            raise ConflictError(no_reference_message(site.id), code="no_reference")
        sites.resolve_detector(site, options.method, options.variant)
        # Fail fast, before a robot sends a large body it would send in vain; the check that
        # counts is the one in jobs.new_job, under the organisation lock.
        quotas.check_queued_jobs(session, settings, principal)
    remaining = None
    if not _key_was_used(session, principal, options.idempotency_key):
        quotas.check_stored_bytes(session, settings, principal, options.declared_size)
        remaining = quotas.remaining_bytes(session, settings, principal)
    end_read_transaction(session)
    return remaining


def check_stored_bytes_before_parsing(
    session: Session, settings: Settings, principal: Principal, size: int
) -> None:
    """The storage quota with the exact size, before the cloud is parsed (a read, then the
    transaction ends: parsing is slow and holds no lock)."""
    quotas.check_stored_bytes(session, settings, principal, size)
    end_read_transaction(session)


async def _within_storage_left(
    chunks: AsyncIterator[bytes], remaining: int, cap: int
) -> AsyncIterator[bytes]:
    """``chunks``, or a 507 as soon as they pass the ``remaining`` bytes of the storage quota."""
    received = 0
    async for chunk in chunks:
        received += len(chunk)
        if received > remaining:
            raise quotas.storage_error(cap - remaining, cap, remaining, at_least=True)
        yield chunk


def _find_replay(
    session: Session, principal: Principal, key: str, fingerprint: str
) -> StoredResponse | None:
    stored = idempotency.find_response(session, principal, key, fingerprint)
    end_read_transaction(session)
    return stored


def scan_row(
    principal: Principal,
    *,
    scan_id: str,
    site_id: str,
    filename: str | None,
    storage_path: str,
    received: storage.ReceivedFile,
    parsed: ParsedScan,
    sensor_origin: SensorOrigin | None = None,
) -> Scan:
    """The ``Scan`` row of a stored file (a given ``sensor_origin`` overrides the file's)."""
    return Scan(
        id=scan_id,
        organisation_id=principal.organisation_id,
        site_id=site_id,
        filename=filename or f"scan.{parsed.format}",
        format=parsed.format,
        size_bytes=received.size_bytes,
        sha256=received.sha256,
        storage_path=storage_path,
        n_points=parsed.n_points,
        n_dropped=parsed.n_dropped,
        bbox_min=parsed.bbox_min,
        bbox_max=parsed.bbox_max,
        sensor_origin=sensor_origin or parsed.sensor_origin,
    )


def store_scan_file(
    session: Session,
    settings: Settings,
    principal: Principal,
    *,
    site_id: str,
    received: storage.ReceivedFile,
    filename: str | None,
    sensor_origin: SensorOrigin | None = None,
    trajectory: trajectories.TrajectoryUpload | None = None,
    bag_parameters: dict[str, str] | None = None,
) -> Scan:
    """Parse a received file with the core, rename it into place and build its row (not added).

    The one way a received scan is stored, for uploads and schedule runs alike: the file goes
    under the data layout's scan path, and is removed again if ``session`` rolls back.  Slow
    (parsing): call it with no transaction open.
    """
    parsed = parse_upload(
        received.path, filename, received.head, settings.max_points, bag_parameters
    )
    check_stations_match(sensor_origin, parsed.n_stations)
    # a trajectory sent with it is checked before anything is stored, then kept beside it
    checked = (
        None if trajectory is None else trajectory.checked_against(received.path, parsed.format)
    )
    scan_id = new_id()
    storage_path = settings.data_layout.scan_storage_path(site_id, scan_id, parsed.format)
    final_path = settings.data_layout.resolve(storage_path)
    storage.install_file(received.path, final_path)
    after_rollback(session, lambda: storage.remove_file(final_path))
    if bag_parameters and parsed.format in BAG_FORMATS:
        kept = save_bag_options(final_path, bag_parameters)
        after_rollback(session, lambda: storage.remove_file(kept))
    if checked is not None:
        saved = trajectories.trajectory_path(final_path)
        trajectories.save_trajectory(saved, checked)
        after_rollback(session, lambda: storage.remove_file(saved))
    return scan_row(
        principal,
        scan_id=scan_id,
        site_id=site_id,
        filename=filename,
        storage_path=storage_path,
        received=received,
        parsed=parsed,
        sensor_origin=sensor_origin,
    )


def parse_bag_parameters(values: Sequence[str] | None) -> dict[str, str] | None:
    """``bag=KEY=VALUE`` query values as a mapping, checked like the CLI's ``--bag-param``
    (422 naming the parameter when one is unknown or malformed)."""
    if not values:
        return None
    parameters: dict[str, str] = {}
    for value in values:
        key, separator, text = value.partition("=")
        if not separator or not key.strip():
            raise ValidationFailedError(
                f"bag parameter {value!r} is not KEY=VALUE: give e.g. bag=cloud_topic=/points"
            )
        parameters[key.strip()] = text.strip()
    try:
        bag_options_from_strings(parameters)
    except InputError as exc:
        raise ValidationFailedError(f"bag: {exc}") from exc
    return parameters


def parse_upload(
    path: Path,
    filename: str | None,
    head: bytes,
    max_points: int,
    bag_parameters: dict[str, str] | None = None,
) -> ParsedScan:
    """Detect the format and check the cloud with the core, without loading it (raises the
    core's errors)."""
    from app.core.formats import detect_format, summarise_point_cloud

    bag_options = None if not bag_parameters else bag_options_from_strings(bag_parameters)
    with PARSE_SLOTS:
        file_format = detect_format(filename, head)
        summary = summarise_point_cloud(
            path,
            file_format,
            filename=filename or "upload",
            max_points=max_points,
            bag_options=bag_options,
        )
        return ParsedScan(
            format=file_format,
            n_points=summary.n_points,
            n_dropped=summary.n_dropped,
            bbox_min=[float(value) for value in summary.low],
            bbox_max=[float(value) for value in summary.high],
            sensor_origin=None if summary.sensor_origin is None else summary.sensor_origin.tolist(),
            n_stations=summary.n_stations,
        )


def _register_upload(
    session: Session,
    settings: Settings,
    principal: Principal,
    options: UploadOptions,
    fingerprint: str,
    scan: Scan,
) -> tuple[StoredResponse, bool]:
    """Insert the scan (and its job) in the request's transaction; ``(response, created)``."""
    record = None
    if options.idempotency_key is not None:
        record, stored = idempotency.claim(session, principal, options.idempotency_key, fingerprint)
        if stored is not None:
            return stored, False
    quotas.lock_organisation(session, principal)
    quotas.check_stored_bytes(session, settings, principal, scan.size_bytes)
    site = sites.get_site(session, principal, options.site_id)
    if not options.reference and site.reference_scan_id is None:
        raise ConflictError(no_reference_message(site.id), code="no_reference")
    if not options.reference:  # its comparison must fit the workers' memory budget
        reference = session.get(Scan, site.reference_scan_id)
        if reference is not None:
            jobs.check_memory_budget(settings, reference, scan)
            jobs.check_disk_space(settings, reference, scan)
    session.add(scan)
    session.flush()
    if options.reference:
        sites.set_reference(session, site, scan)
        response = StoredResponse(
            201, UploadRead(scan=ScanRead.from_model(scan), job=None).model_dump(mode="json")
        )
    else:
        method, variant, params = sites.resolve_detector(site, options.method, options.variant)
        job = jobs.new_job(
            session,
            settings,
            principal,
            site_id=site.id,
            reference_scan_id=site.reference_scan_id,
            scan_id=scan.id,
            method=method,
            variant=variant,
            params=params,
        )
        response = StoredResponse(
            202,
            UploadRead(scan=ScanRead.from_model(scan), job=JobRead.from_model(job)).model_dump(
                mode="json"
            ),
        )
    return idempotency.remember(record, response), True


async def upload_scan(
    session: Session,
    settings: Settings,
    principal: Principal,
    options: UploadOptions,
    body: UploadBody,
) -> StoredResponse:
    """Receive a scan: 201 when it becomes the reference, else 202 with its comparison job."""
    key = idempotency.validate_key(options.idempotency_key)
    keyed_options = dataclasses.replace(options, idempotency_key=key)
    remaining = await anyio.to_thread.run_sync(
        check_upload_target, session, settings, principal, keyed_options
    )
    chunks = body.chunks()
    cap = settings.max_stored_bytes_per_organisation
    if cap is not None and remaining is not None and remaining < settings.max_upload_bytes:
        chunks = _within_storage_left(chunks, remaining, cap)
    received = await storage.receive_stream(chunks, settings, settings.max_upload_bytes)
    try:
        trajectory = trajectories.upload_of(
            body, options.trajectory_rate, options.trajectory_format
        )
        return await store_received_scan(
            session, settings, principal, keyed_options, received, body.filename, trajectory
        )
    finally:
        storage.remove_file(received.path)  # gone already when it was installed


async def store_received_scan(
    session: Session,
    settings: Settings,
    principal: Principal,
    options: UploadOptions,
    received: storage.ReceivedFile,
    body_filename: str | None = None,
    trajectory: trajectories.TrajectoryUpload | None = None,
) -> StoredResponse:
    """Make a received file a scan (and its job): quota, parse, install, register.

    The second half of every upload, the normal one and a completed resumable one; the caller
    removes ``received.path`` afterwards (it is gone already when it was installed).
    """
    key = options.idempotency_key
    filename = storage.sanitise_filename(options.filename or body_filename)
    fingerprint = idempotency.request_fingerprint(
        "POST",
        f"/api/v1/sites/{options.site_id}/scans",
        {
            "reference": options.reference,
            "filename": filename,
            "method": options.method,
            "variant": options.variant,
            "sensor_origin": options.sensor_origin,
            "sha256": received.sha256,
            **({"bag": options.bag_parameters} if options.bag_parameters else {}),
            **({} if trajectory is None else {"trajectory": trajectory.digest()}),
        },
    )
    if key is not None:
        stored = await anyio.to_thread.run_sync(_find_replay, session, principal, key, fingerprint)
        if stored is not None:
            return stored
    await anyio.to_thread.run_sync(
        check_stored_bytes_before_parsing, session, settings, principal, received.size_bytes
    )
    scan = await anyio.to_thread.run_sync(
        functools.partial(
            store_scan_file,
            session,
            settings,
            principal,
            site_id=options.site_id,
            received=received,
            filename=filename,
            sensor_origin=options.sensor_origin,
            trajectory=trajectory,
            bag_parameters=options.bag_parameters,
        )
    )
    response, created = await anyio.to_thread.run_sync(
        _register_upload, session, settings, principal, options, fingerprint, scan
    )
    if not created:
        for path in storage.scan_files(settings.data_layout.resolve(scan.storage_path)):
            storage.remove_file(path)
    return response


def get_scan(session: Session, principal: Principal, scan_id: str) -> Scan:
    """The principal's scan ``scan_id``; 404 when it does not exist or is another's."""
    return get_owned(session, principal, Scan, scan_id)


def list_site_scans(
    session: Session, principal: Principal, site_id: str, limit: int, cursor: str | None
) -> tuple[Sequence[Scan], str | None]:
    """A site's scans, newest first, one page."""
    site = sites.get_site(session, principal, site_id)
    statement = scoped(select(Scan).where(Scan.site_id == site.id), principal)
    return newest_first_page(session, statement, Scan, limit, cursor)


def scan_file(
    session: Session, settings: Settings, principal: Principal, scan_id: str
) -> DownloadFile:
    """The original bytes of a scan as uploaded."""
    scan = get_scan(session, principal, scan_id)
    path = storage.stored_file(settings, scan.storage_path)
    if not path.is_file():
        raise NotFoundError(f"the file of scan {scan_id} is missing from storage")
    return DownloadFile(path=path, filename=scan.filename)
