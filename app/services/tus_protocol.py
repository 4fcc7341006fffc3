"""The tus 1.0.0 protocol's headers: version, metadata, byte counts and chunk checksums."""

from __future__ import annotations

import base64
import binascii
import hashlib
from collections.abc import Callable
from typing import Any

from app.services.errors import AppError, BadRequestError

TUS_VERSION = "1.0.0"
TUS_EXTENSIONS = "creation,expiration,termination,checksum"
PATCH_CONTENT_TYPE = "application/offset+octet-stream"
CHECKSUM_ALGORITHMS: dict[str, Callable[[], Any]] = {
    "sha1": hashlib.sha1,
    "sha256": hashlib.sha256,
    "md5": hashlib.md5,
}
"""Algorithms of the ``Upload-Checksum`` header (tuspy sends sha1 by default)."""


class TusVersionError(AppError, status_code=412, code="unsupported_tus_version"):
    """The request's ``Tus-Resumable`` is not 1.0.0."""


def check_tus_version(value: str | None) -> None:
    """412 unless the client speaks tus 1.0.0."""
    if value != TUS_VERSION:
        raise TusVersionError(
            f"send the header Tus-Resumable: {TUS_VERSION} (got {value!r}): this server speaks "
            f"tus {TUS_VERSION}"
        )


def parse_metadata(header: str | None) -> dict[str, str]:
    """``Upload-Metadata`` (``key base64,key base64``) as text; 400 when malformed."""
    metadata: dict[str, str] = {}
    for pair in (header or "").split(","):
        if not pair.strip():
            continue
        key, _, encoded = pair.strip().partition(" ")
        try:
            metadata[key] = base64.b64decode(encoded.strip(), validate=True).decode("utf-8")
        except (binascii.Error, UnicodeDecodeError) as exc:
            raise BadRequestError(
                f"Upload-Metadata: the value of {key!r} is not base64 of UTF-8 text",
                code="malformed_upload_metadata",
            ) from exc
    return metadata


def parse_non_negative(value: str | None, header: str) -> int | None:
    """A header that holds a byte count; 400 when it is not a non-negative integer."""
    if value is None:
        return None
    if not value.strip().isdigit():
        raise BadRequestError(f"{header} must be a non-negative integer (got {value!r})")
    return int(value)


def parse_checksum(header: str | None) -> tuple[str, bytes] | None:
    """``Upload-Checksum: <algorithm> <base64>``; 400 when malformed or the algorithm unknown."""
    if header is None:
        return None
    algorithm, _, encoded = header.strip().partition(" ")
    if algorithm not in CHECKSUM_ALGORITHMS:
        raise BadRequestError(
            f"Upload-Checksum algorithm {algorithm!r} is not supported: use one of "
            f"{', '.join(CHECKSUM_ALGORITHMS)}",
            code="unsupported_checksum",
        )
    try:
        return algorithm, base64.b64decode(encoded.strip(), validate=True)
    except binascii.Error as exc:
        raise BadRequestError("Upload-Checksum: the digest is not base64") from exc
