"""HTTP helpers for the API tests: sites, uploads, the error shape."""

from __future__ import annotations

import uuid
from typing import Any

import httpx

from app.testing.files import ply_bytes
from app.testing.scenes import room_points


def unique_name(prefix: str) -> str:
    """A name no other test (or earlier run on a persistent database) used."""
    return f"{prefix}-{uuid.uuid4().hex[:12]}"


def create_site(client: httpx.Client, name: str | None = None, **fields: Any) -> dict[str, Any]:
    """POST a site and return it (asserting 201)."""
    response = client.post(
        "/api/v1/sites", json={"name": name or f"site-{uuid.uuid4().hex[:6]}", **fields}
    )
    assert response.status_code == 201, response.text
    return response.json()


def upload(
    client: httpx.Client,
    site_id: str,
    content: bytes,
    *,
    filename: str | None = "scan.ply",
    reference: bool = False,
    multipart: bool = False,
    headers: dict[str, str] | None = None,
    **params: Any,
) -> httpx.Response:
    """Upload a scan as the raw body (default) or as the multipart field ``file``."""
    query: dict[str, Any] = {"reference": str(reference).lower(), **params}
    if multipart:
        return client.post(
            f"/api/v1/sites/{site_id}/scans",
            params=query,
            files={"file": (filename or "blob", content, "application/octet-stream")},
            headers=headers,
        )
    if filename is not None:
        query["filename"] = filename
    return client.post(
        f"/api/v1/sites/{site_id}/scans",
        params=query,
        content=content,
        headers={"Content-Type": "application/octet-stream", **(headers or {})},
    )


def upload_accepted(
    client: httpx.Client, site_id: str, filename: str, content: bytes, **query: str
) -> dict[str, Any]:
    """Upload the raw body, asserting 201/202; the JSON answer.

    ``reference="true"`` uploads a reference; a scan's job uses the fast PCA detector unless
    ``method`` says otherwise.
    """
    reference = query.pop("reference", "false") == "true"
    if not reference:
        query.setdefault("method", "pca")
    response = upload(client, site_id, content, filename=filename, reference=reference, **query)
    assert response.status_code in (201, 202), response.text
    return response.json()


def site_with_reference(client: httpx.Client) -> tuple[dict[str, Any], dict[str, Any]]:
    """A new site whose reference is a 3k-point PLY; ``(site, reference_scan)``."""
    site = create_site(client)
    response = upload(client, site["id"], ply_bytes(room_points(3000, seed=1)), reference=True)
    assert response.status_code == 201, response.text
    return site, response.json()["scan"]


def assert_error(response: httpx.Response, status_code: int, error: str | None = None) -> str:
    """Assert the JSON error shape and status; the detail."""
    assert response.status_code == status_code, response.text
    body = response.json()
    assert set(body) == {"error", "detail"}, body
    assert isinstance(body["error"], str) and isinstance(body["detail"], str)
    if error is not None:
        assert body["error"] == error, body
    return body["detail"]
