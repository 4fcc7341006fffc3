"""Files of the service: streamed uploads, atomic installation, clean-up and the start-up sweep.

Uploads stream into ``tmp/`` (same filesystem as ``scans/``) while their size is counted against
the cap and their SHA-256 computed; the file is fsynced and renamed into place only once it
parsed.  A killed server leaves at most a temporary file (removed by
:func:`sweep_temporary_files` at the next start) or, in the instant between the rename and the
commit of the row, an unreferenced scan file (removed by the same sweep); a job worker killed
while writing its results leaves a temporary result file (removed by the same sweep too).

The layout of the data directory (``tmp/``, ``scans/<site_id>/``, ``results/<job_id>/``...) is
:class:`app.kit.data_layout.DataLayout` (``settings.data_layout``), which also reads stored paths
back, refusing one outside the data directory.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import re
import shutil
import time
import unicodedata
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import anyio
from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError

from app.config import Settings
from app.core.files import fsync_directory
from app.db.models import Job, Scan, new_id
from app.db.session import transaction
from app.jobs.geometry import CACHE_SUFFIX as GEOMETRY_CACHE_SUFFIX
from app.jobs.results import remove_stale_temp_files
from app.kit.data_layout import StoredPathError
from app.kit.scan_files import bag_options_path, trajectory_path
from app.services.errors import BadRequestError, NotFoundError, PayloadTooLargeError

logger = logging.getLogger("scandiff.storage")

HEAD_BYTES = 4096
"""How much of the start of an upload is kept for format sniffing."""

TEMPORARY_SUFFIX = ".part"
MAX_FILENAME_BYTES = 255
_HEX_ID = re.compile(r"^[0-9a-f]{32}$")
_SAFE_PUNCTUATION = frozenset("._-+ ()[]")


@dataclass(frozen=True)
class ReceivedFile:
    """An upload fully written to a temporary file (fsynced)."""

    path: Path
    size_bytes: int
    sha256: str
    head: bytes


def ensure_directories(settings: Settings) -> None:
    """Create the data, scans, results and temporary directories if missing."""
    for directory in (
        settings.data_dir,
        settings.scans_dir,
        settings.results_dir,
        settings.tmp_dir,
    ):
        directory.mkdir(parents=True, exist_ok=True)


def too_large_message(max_bytes: int) -> str:
    """The 413 message for a cap of ``max_bytes``."""
    return f"the upload is larger than the limit of {max_bytes} bytes (SCANDIFF_MAX_UPLOAD_BYTES)"


async def receive_stream(
    chunks: AsyncIterator[bytes], settings: Settings, max_bytes: int
) -> ReceivedFile:
    """Write ``chunks`` to a new temporary file, counting bytes against ``max_bytes``.

    Raises :class:`PayloadTooLargeError` as soon as the cap is passed (the rest of the body is
    not read) and :class:`BadRequestError` for an empty body; the temporary file is removed on
    any failure, including a client that disconnects.
    """
    settings.tmp_dir.mkdir(parents=True, exist_ok=True)
    path = settings.tmp_dir / f"{os.getpid()}-{new_id()}{TEMPORARY_SUFFIX}"
    hasher = hashlib.sha256()
    head = bytearray()
    size = 0
    try:
        with open(path, "xb") as output:
            async for chunk in chunks:
                if not chunk:
                    continue
                size += len(chunk)
                if size > max_bytes:
                    raise PayloadTooLargeError(too_large_message(max_bytes))
                hasher.update(chunk)
                if len(head) < HEAD_BYTES:
                    head.extend(chunk[: HEAD_BYTES - len(head)])
                output.write(chunk)
            if size == 0:
                raise BadRequestError(
                    "the upload is empty: send the scan file as the request body "
                    "or as the multipart field 'file'",
                    code="empty_upload",
                )
            output.flush()
            await anyio.to_thread.run_sync(os.fsync, output.fileno())
    except BaseException:
        remove_file(path)
        raise
    return ReceivedFile(path=path, size_bytes=size, sha256=hasher.hexdigest(), head=bytes(head))


def install_file(source: Path, destination: Path) -> None:
    """Atomically move a complete (fsynced) file into place and make the rename durable."""
    destination.parent.mkdir(parents=True, exist_ok=True)
    os.replace(source, destination)
    with contextlib.suppress(OSError):  # the file is in place; only the rename's durability is lost
        fsync_directory(destination.parent)


def remove_file(path: Path) -> None:
    """Delete ``path`` if it exists (errors are logged, never raised)."""
    try:
        path.unlink(missing_ok=True)
    except OSError:
        logger.warning("could not remove %s", path, exc_info=True)


def remove_tree(path: Path) -> None:
    """Delete the directory ``path`` and everything in it if it exists (errors are logged)."""
    if path.exists():
        shutil.rmtree(path, ignore_errors=True)


def stored_file(settings: Settings, stored_path: str) -> Path:
    """A file stored in the database, read back through the data layout; 404 if it is outside."""
    try:
        return settings.data_layout.resolve(stored_path)
    except StoredPathError as exc:
        raise NotFoundError(
            f"{exc}: the file is not served (an operator should check the row)"
        ) from exc


def sanitise_filename(name: str | None) -> str | None:
    """A display-safe file name: no directories, controls or undecodable bytes; None if empty.

    ``"../../etc/passwd"`` becomes ``"passwd"``, ``"C:\\scans\\a.ply"`` becomes ``"a.ply"``,
    undecodable bytes (surrogate escapes) become ``"_"``; at most 255 UTF-8 bytes, suffix kept.
    """
    if name is None:
        return None
    text = name.encode("utf-8", "replace").decode("utf-8", "replace")
    text = unicodedata.normalize("NFC", text).replace("\\", "/").rsplit("/", 1)[-1]
    cleaned = "".join(
        char if char.isprintable() and (char.isalnum() or char in _SAFE_PUNCTUATION) else "_"
        for char in text
    )
    cleaned = cleaned.strip(" .")
    if not cleaned or set(cleaned) <= {"_"}:
        return None
    if len(cleaned.encode("utf-8")) > MAX_FILENAME_BYTES:
        stem, dot, suffix = cleaned.rpartition(".")
        if not dot or len(suffix) > 16:
            stem, suffix = cleaned, ""
        budget = MAX_FILENAME_BYTES - len(suffix.encode("utf-8")) - (1 if suffix else 0)
        stem = stem.encode("utf-8")[:budget].decode("utf-8", "ignore")
        cleaned = f"{stem}.{suffix}" if suffix else stem
    return cleaned


def _older_than(path: Path, min_age_seconds: float, now: float) -> bool:
    if min_age_seconds <= 0:
        return True
    try:
        return now - path.stat().st_mtime >= min_age_seconds
    except OSError:
        return False


def scan_files(path: Path) -> tuple[Path, ...]:
    """A stored scan's file and the files that belong to it beside it: a reference's geometry
    cache (checked before use, :mod:`app.jobs.geometry`), the trajectory sent with it
    (:mod:`app.kit.scan_files`) and the parameters its ROS bag is read with
    (:func:`app.kit.scan_files.bag_options_path`)."""
    return (
        path,
        path.with_suffix(GEOMETRY_CACHE_SUFFIX),
        trajectory_path(path),
        bag_options_path(path),
    )


def sweep_temporary_files(settings: Settings, *, min_age_seconds: float = 0.0) -> int:
    """Remove what an interrupted upload or deletion left behind; the number of paths removed.

    Call it at start-up, before serving (``min_age_seconds=0``); periodic calls while uploads
    run must pass a generous ``min_age_seconds`` (say 3600).  Removes temporary upload files,
    temporary result files of job workers killed while writing (``results/<job>/.*.tmp*``),
    files beside the scans that no scan row references (a reference's ``.geometry`` cache is
    its scan's), and result directories of jobs that no longer exist.  Never raises (a
    database that is not migrated yet only skips the last two).
    """
    now = time.time()
    removed = 0
    if settings.tmp_dir.is_dir():
        for path in settings.tmp_dir.iterdir():
            if path.is_file() and _older_than(path, min_age_seconds, now):
                remove_file(path)
                removed += 1
    removed += remove_stale_temp_files(settings, min_age_seconds)
    try:
        with transaction(settings.sqlalchemy_url) as session:
            scan_paths = set(session.scalars(select(Scan.storage_path)))
            job_ids = set(session.scalars(select(Job.id)))
    except SQLAlchemyError:
        logger.warning("sweep: database not readable, orphaned files not checked", exc_info=True)
        return removed
    stored = []
    for stored_path in scan_paths:
        try:
            stored.append(settings.data_layout.resolve(stored_path))
        except StoredPathError:  # a row pointing outside: its jobs fail saying so; serve anyway
            logger.warning("sweep: scan path %r is outside the data directory", stored_path)
    referenced = {companion for path in stored for companion in scan_files(path)}
    if settings.scans_dir.is_dir():
        for site_directory in settings.scans_dir.iterdir():
            if not site_directory.is_dir() or not _HEX_ID.match(site_directory.name):
                continue
            for path in site_directory.iterdir():
                if (
                    path.is_file()
                    and path.resolve() not in referenced
                    and _older_than(path, min_age_seconds, now)
                ):
                    remove_file(path)
                    removed += 1
            if _older_than(site_directory, min_age_seconds, now):
                with contextlib.suppress(OSError):
                    site_directory.rmdir()  # only succeeds when empty
    if settings.results_dir.is_dir():
        for path in settings.results_dir.iterdir():
            if (
                path.is_dir()
                and _HEX_ID.match(path.name)
                and path.name not in job_ids
                and _older_than(path, min_age_seconds, now)
            ):
                remove_tree(path)
                removed += 1
    if removed:
        logger.info("sweep removed %d leftover file(s) or directories", removed)
    return removed
