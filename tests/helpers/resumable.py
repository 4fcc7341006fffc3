"""Raw tus requests for the resumable upload tests (httpx; the tuspy client is used directly)."""

from __future__ import annotations

import base64

import httpx

TUS = {"Tus-Resumable": "1.0.0"}
OCTETS = {**TUS, "Content-Type": "application/offset+octet-stream"}


def metadata_header(**values: str) -> str:
    """``Upload-Metadata`` of ``values`` (key base64, ...)."""
    return ",".join(
        f"{key} {base64.b64encode(value.encode()).decode()}" for key, value in values.items()
    )


def create_upload(client: httpx.Client, length: int, **metadata: str) -> httpx.Response:
    """POST a new upload of ``length`` bytes."""
    return client.post(
        "/api/v1/uploads",
        headers={
            **TUS,
            "Upload-Length": str(length),
            "Upload-Metadata": metadata_header(**metadata),
        },
    )


def new_upload(client: httpx.Client, length: int, **metadata: str) -> str:
    """Create an upload (asserting 201); its path."""
    response = create_upload(client, length, **metadata)
    assert response.status_code == 201, response.text
    return response.headers["Location"]


def patch(
    client: httpx.Client, location: str, offset: int, content: bytes, **headers: str
) -> httpx.Response:
    """PATCH ``content`` at ``offset``."""
    return client.patch(
        location, content=content, headers={**OCTETS, "Upload-Offset": str(offset), **headers}
    )


def offset_of(client: httpx.Client, location: str) -> int:
    """The upload's offset from HEAD (asserting 200)."""
    response = client.head(location, headers=TUS)
    assert response.status_code == 200, response.headers
    return int(response.headers["Upload-Offset"])
