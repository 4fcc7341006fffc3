"""Where a schedule's scans come from: uploads, a server-side directory, or an HTTP(S) URL.

* ``uploads`` (the default): scans pushed with ``POST /sites/{id}/scans``; nothing to fetch.
* ``{"directory": "/srv/drop/site-7"}``: only under a root the operator allowed
  (``SCANDIFF_SCHEDULE_DIRECTORY_ROOTS``).  A path with a ``..`` component, one that leaves the
  roots once symlinks are resolved, and a file that is a symlink out of the roots or larger
  than the upload cap are refused (422 / 413) when the schedule is created and when it runs.
* ``{"url": "https://..."}``: fetched by the run with plain GET, no redirects, within the
  upload cap and ``SCANDIFF_SCHEDULE_FETCH_TIMEOUT_SECONDS``.  The URL is checked by the rule
  webhooks use too (:func:`app.kit.net.check_url`: every address the host resolves to, refused
  address classes unless ``SCANDIFF_ALLOW_PRIVATE_ADDRESSES`` is set), and the connection goes
  to an address that was checked (a DNS answer that changes between check and connect cannot
  redirect it).

A fetched file is received exactly as an upload body (:func:`app.services.storage.receive_stream`:
the size cap, SHA-256 and temporary file) before :mod:`app.services.schedules.ingest` stores it.
"""

from __future__ import annotations

import http.client
import os
import time
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import anyio

from app.config import Settings
from app.kit import net
from app.kit.net import UrlTarget
from app.services import storage
from app.services.errors import PayloadTooLargeError, ValidationFailedError
from app.services.storage import ReceivedFile

CHUNK_BYTES = 1024 * 1024
IGNORED_SUFFIXES = (".part", ".tmp", ".partial")
"""Files still being written by the scanner's copy (by convention) are not taken."""

SourceMarker = dict[str, Any]


def source_error(message: str, code: str = "invalid_source") -> ValidationFailedError:
    """A 422 about a schedule's source."""
    return ValidationFailedError(message, code=code)


def normalise_source(settings: Settings, source: Any) -> dict[str, Any]:
    """The stored form of a requested source, checked; 422 saying what to fix otherwise."""
    if source is None or source == "uploads" or source == {"kind": "uploads"}:
        return {"kind": "uploads"}
    if isinstance(source, dict) and set(source) == {"directory"}:
        directory = check_directory(settings, str(source["directory"]))
        newest_directory_file(settings, directory, None)  # refuses a symlink out or a huge file
        return {"kind": "directory", "directory": str(directory)}
    if isinstance(source, dict) and set(source) == {"url"}:
        url = str(source["url"])
        check_url(settings, url)
        return {"kind": "url", "url": url}
    raise source_error(
        'source must be "uploads", {"directory": "<path under an allowed root>"} or '
        '{"url": "https://..."}'
    )


def _under_a_root(settings: Settings, path: Path) -> bool:
    return any(
        path == root or path.is_relative_to(root) for root in settings.schedule_directory_roots
    )


def check_directory(settings: Settings, text: str) -> Path:
    """The resolved directory ``text`` if it lies under an allowed root; 422 otherwise."""
    roots = settings.schedule_directory_roots
    if not roots:
        raise source_error(
            "directory sources are disabled: the operator allows directories by listing roots "
            "in SCANDIFF_SCHEDULE_DIRECTORY_ROOTS",
            code="directory_not_allowed",
        )
    allowed = ", ".join(str(root) for root in roots)
    path = Path(text)
    if not path.is_absolute() or ".." in path.parts or "\x00" in text:
        raise source_error(
            f"directory {text!r} must be an absolute path without '..' components under one of "
            f"the allowed roots: {allowed}",
            code="directory_not_allowed",
        )
    resolved = path.resolve()
    if not _under_a_root(settings, resolved):
        raise source_error(
            f"directory {text!r} is outside the allowed roots (symlinks followed: it leads to "
            f"{resolved}); use a directory under: {allowed}",
            code="directory_not_allowed",
        )
    if not resolved.is_dir():
        raise source_error(f"directory {text!r} does not exist or is not a directory")
    return resolved


@dataclass(frozen=True)
class DirectoryFile:
    """The newest file of a directory source, checked."""

    path: Path
    name: str
    marker: SourceMarker


def _candidates(directory: Path) -> Iterator[os.DirEntry[str]]:
    with os.scandir(directory) as entries:
        for entry in entries:
            if entry.name.startswith(".") or entry.name.endswith(IGNORED_SUFFIXES):
                continue
            if entry.is_file(follow_symlinks=True):
                yield entry


def newest_directory_file(
    settings: Settings, directory: Path, marker: SourceMarker | None
) -> DirectoryFile | None:
    """The newest file in ``directory`` newer than ``marker`` (None when there is none);
    422 when it is a symlink out of the roots, 413 when it is over the upload cap."""
    newest: tuple[int, str, os.DirEntry[str]] | None = None
    for entry in _candidates(directory):
        key = (entry.stat(follow_symlinks=True).st_mtime_ns, entry.name)
        if newest is None or key > newest[:2]:
            newest = (*key, entry)
    if newest is None:
        return None
    mtime_ns, name, entry = newest
    if marker is not None and (mtime_ns, name) <= (marker["mtime_ns"], marker["name"]):
        return None
    resolved = Path(entry.path).resolve()
    if not _under_a_root(settings, resolved):
        raise source_error(
            f"file {name!r} in {directory} is a symlink leading outside the allowed roots "
            f"(to {resolved}); replace it with the file itself",
            code="directory_not_allowed",
        )
    size = resolved.stat().st_size
    if size > settings.max_upload_bytes:
        raise PayloadTooLargeError(
            f"file {name!r} in {directory} is {size} bytes, over the upload limit of "
            f"{settings.max_upload_bytes} bytes (SCANDIFF_MAX_UPLOAD_BYTES)"
        )
    return DirectoryFile(path=resolved, name=name, marker={"mtime_ns": mtime_ns, "name": name})


async def _file_chunks(path: Path) -> AsyncIterator[bytes]:
    with open(path, "rb") as source:
        while chunk := source.read(CHUNK_BYTES):
            yield chunk


def receive_directory_file(settings: Settings, found: DirectoryFile) -> ReceivedFile:
    """Copy a directory source's file to a temporary file as an upload body is received."""
    return anyio.run(
        storage.receive_stream, _file_chunks(found.path), settings, settings.max_upload_bytes
    )


def check_url(settings: Settings, url: str) -> UrlTarget:
    """``url`` checked by the one outgoing-URL rule (:func:`app.kit.net.check_url`); else 422."""
    try:
        return net.check_url(url, allow_private=settings.allow_private_addresses)
    except net.RefusedAddressError as exc:
        raise source_error(f"url {url!r}: {exc}", code="forbidden_url_address") from exc
    except net.OutboundUrlError as exc:
        raise source_error(f"url {url!r}: {exc}", code="invalid_url") from exc


async def _response_chunks(
    response: http.client.HTTPResponse, deadline: float, url: str
) -> AsyncIterator[bytes]:
    while chunk := response.read(CHUNK_BYTES):
        if time.monotonic() > deadline:
            raise source_error(f"fetching {url!r} took too long", code="fetch_failed")
        yield chunk


def fetch_url(settings: Settings, url: str) -> ReceivedFile:
    """GET ``url`` (checked again now) into a temporary file; 422 / 413 saying why not."""
    target = check_url(settings, url)
    timeout = settings.schedule_fetch_timeout_seconds
    deadline = time.monotonic() + timeout
    connection = net.pinned_connection(target, timeout)
    try:
        try:
            connection.request("GET", target.path, headers={"User-Agent": "scandiff-schedule"})
            response = connection.getresponse()
        except (OSError, http.client.HTTPException) as exc:
            raise source_error(
                f"fetching {url!r} failed ({type(exc).__name__}: {exc})", code="fetch_failed"
            ) from exc
        if response.status != 200:
            raise source_error(
                f"fetching {url!r} answered HTTP {response.status} (redirects are not "
                "followed: give the final URL)",
                code="fetch_failed",
            )
        length = response.getheader("Content-Length")
        if length and length.isdigit() and int(length) > settings.max_upload_bytes:
            raise PayloadTooLargeError(storage.too_large_message(settings.max_upload_bytes))
        try:
            return anyio.run(
                storage.receive_stream,
                _response_chunks(response, deadline, url),
                settings,
                settings.max_upload_bytes,
            )
        except (OSError, http.client.HTTPException) as exc:
            raise source_error(
                f"fetching {url!r} failed ({type(exc).__name__}: {exc})", code="fetch_failed"
            ) from exc
    finally:
        connection.close()
