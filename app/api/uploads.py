"""Request bodies of uploads, streamed: the raw body, or the ``file`` field of a multipart form.

Neither form is buffered: bytes are handed on as they arrive, so the size cap trips (413) before
the rest is read.  ``Content-Length`` is checked first, before any byte is read.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import Depends, Request
from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header

from app.api.deps import SettingsDep
from app.services.errors import BadRequestError, PayloadTooLargeError, ValidationFailedError
from app.services.scans import UploadBody
from app.services.storage import too_large_message

FILE_FIELD = "file"
EXTRA_FIELDS = ("trajectory", "trajectory_times")
"""Small parts kept in memory besides the file (a scan's trajectory and its pose times)."""
MAX_EXTRA_BYTES = 32 * 1024 * 1024
"""Largest such part."""
MULTIPART_OVERHEAD_BYTES = 1024 * 1024
"""Room for boundaries, part headers and small extra fields around the file in a form."""


class RawBody:
    """The request body is the file (``application/octet-stream`` or anything not multipart)."""

    filename: str | None = None

    def __init__(self, request: Request) -> None:
        self._request = request
        self.parts: dict[str, bytearray] = {}
        self.part_filenames: dict[str, str] = {}

    async def chunks(self) -> AsyncIterator[bytes]:
        """The body as it arrives."""
        async for chunk in self._request.stream():
            yield chunk


class MultipartBody:
    """The file is the multipart field ``file``; :data:`EXTRA_FIELDS` are kept in ``parts``
    (with their file names in ``part_filenames``); other fields are skipped (within the cap)."""

    def __init__(self, request: Request, boundary: bytes, max_upload_bytes: int) -> None:
        self._request = request
        self._boundary = boundary
        self._max_upload_bytes = max_upload_bytes
        self._max_total_bytes = (
            max_upload_bytes + MULTIPART_OVERHEAD_BYTES + len(EXTRA_FIELDS) * MAX_EXTRA_BYTES
        )
        self.parts: dict[str, bytearray] = {}
        self.part_filenames: dict[str, str] = {}
        self._extra: str | None = None
        self.filename: str | None = None
        self._header_name = b""
        self._header_value = b""
        self._disposition = b""
        self._in_file = False
        self._file_seen = False
        self._pending: list[bytes] = []

    def _on_part_begin(self) -> None:
        self._disposition = b""
        self._in_file = False
        self._extra = None

    def _on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_name += data[start:end]

    def _on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def _on_header_end(self) -> None:
        if self._header_name.strip().lower() == b"content-disposition":
            self._disposition = self._header_value
        self._header_name = b""
        self._header_value = b""

    def _on_headers_finished(self) -> None:
        _, options = parse_options_header(self._disposition)
        if options.get(b"name") == FILE_FIELD.encode() and not self._file_seen:
            self._in_file = True
            self._file_seen = True
            raw_name = options.get(b"filename")
            if raw_name is not None:
                self.filename = raw_name.decode("utf-8", "surrogateescape")
        name = (options.get(b"name") or b"").decode("utf-8", "replace")
        if name in EXTRA_FIELDS and name not in self.parts:
            self._extra = name
            self.parts[name] = bytearray()
            raw_name = options.get(b"filename")
            if raw_name is not None:
                self.part_filenames[name] = raw_name.decode("utf-8", "replace")

    def _on_part_data(self, data: bytes, start: int, end: int) -> None:
        if self._in_file:
            self._pending.append(bytes(data[start:end]))
        elif self._extra is not None:
            self.parts[self._extra] += data[start:end]
            if len(self.parts[self._extra]) > MAX_EXTRA_BYTES:
                raise PayloadTooLargeError(
                    f"the '{self._extra}' part is larger than {MAX_EXTRA_BYTES // 2**20} MB"
                )

    def _on_part_end(self) -> None:
        self._in_file = False
        self._extra = None

    async def chunks(self) -> AsyncIterator[bytes]:
        """The bytes of the ``file`` field as the body arrives."""
        parser = MultipartParser(
            self._boundary,
            {
                "on_part_begin": self._on_part_begin,
                "on_header_field": self._on_header_field,
                "on_header_value": self._on_header_value,
                "on_header_end": self._on_header_end,
                "on_headers_finished": self._on_headers_finished,
                "on_part_data": self._on_part_data,
                "on_part_end": self._on_part_end,
            },
        )
        received = 0
        async for chunk in self._request.stream():
            received += len(chunk)
            if received > self._max_total_bytes:
                raise PayloadTooLargeError(too_large_message(self._max_upload_bytes))
            try:
                parser.write(chunk)
            except FormParserError as exc:
                raise BadRequestError(
                    f"malformed multipart body: {exc}", code="malformed_multipart"
                ) from exc
            pending, self._pending = self._pending, []
            for piece in pending:
                yield piece
        try:
            parser.finalize()
        except FormParserError as exc:
            raise BadRequestError(
                f"malformed multipart body: {exc}", code="malformed_multipart"
            ) from exc
        for piece in self._pending:
            yield piece
        if not self._file_seen:
            raise ValidationFailedError(
                f"the multipart form has no field named '{FILE_FIELD}': send the scan as "
                f"-F '{FILE_FIELD}=@scan.ply' (or as the raw request body)",
                code="missing_file_field",
            )


def declared_length(request: Request) -> int | None:
    """The ``Content-Length`` the client declared (400 when it is not a number)."""
    value = request.headers.get("content-length")
    if value is None:
        return None
    try:
        length = int(value)
    except ValueError as exc:
        raise BadRequestError("Content-Length is not a number") from exc
    if length < 0:
        raise BadRequestError("Content-Length is negative")
    return length


def get_upload_body(request: Request, settings: SettingsDep) -> UploadBody:
    """The upload's body, after checking its declared length against the cap (413 at once)."""
    length = declared_length(request)
    content_type, options = parse_options_header(request.headers.get("content-type", ""))
    if content_type == b"multipart/form-data":
        boundary = options.get(b"boundary")
        if not boundary:
            raise BadRequestError("multipart body without a boundary", code="malformed_multipart")
        extra = len(EXTRA_FIELDS) * MAX_EXTRA_BYTES
        if (
            length is not None
            and length > settings.max_upload_bytes + MULTIPART_OVERHEAD_BYTES + extra
        ):
            raise PayloadTooLargeError(too_large_message(settings.max_upload_bytes))
        return MultipartBody(request, boundary, settings.max_upload_bytes)
    if length is not None and length > settings.max_upload_bytes:
        raise PayloadTooLargeError(too_large_message(settings.max_upload_bytes))
    return RawBody(request)


UploadBodyDep = Annotated[UploadBody, Depends(get_upload_body)]


async def trajectory_parts(
    request: Request, filename: str | None
) -> tuple[dict[str, bytes], str | None]:
    """A trajectory sent on its own: the multipart parts :data:`EXTRA_FIELDS`, or the raw body
    as the ``trajectory`` part; and the trajectory file's name (the part's, else
    ``filename``).  A part or body over :data:`MAX_EXTRA_BYTES` is a 413."""
    if request.headers.get("content-type", "").startswith("multipart/form-data"):
        async with request.form(max_part_size=MAX_EXTRA_BYTES) as form:
            parts = {
                name: await value.read() if hasattr(value, "read") else str(value).encode()
                for name, value in form.items()
                if name in EXTRA_FIELDS
            }
            names = {
                name: value.filename
                for name, value in form.items()
                if hasattr(value, "filename") and value.filename
            }
        return parts, names.get("trajectory") or filename
    body = await request.body()
    if len(body) > MAX_EXTRA_BYTES:
        raise PayloadTooLargeError(f"the trajectory is larger than {MAX_EXTRA_BYTES} bytes")
    return {"trajectory": body}, filename
