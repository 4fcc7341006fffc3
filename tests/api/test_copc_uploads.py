"""COPC over HTTP: accepted as an upload (plain and resumable); a COPC or LAZ file whose header
and point count disagree is a 400 that says so, and nothing is stored."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from app.testing.files import las_bytes
from app.testing.scenes import room_points
from tests.helpers.copc import copc_bytes, with_point_count
from tests.helpers.http import assert_error, create_site, upload
from tests.helpers.resumable import new_upload, patch
from tests.helpers.server import ApiServer


@pytest.fixture(scope="module")
def room() -> np.ndarray:
    return room_points(3000, 21, noise=0.003)


def test_copc_is_accepted_as_a_reference_and_as_a_resumable_scan(api: ApiServer, room) -> None:
    client = api.client(api.token("writer"))
    site = create_site(client, detector={"method": "pca", "variant": "improved"})
    reference = copc_bytes(room)
    response = upload(client, site["id"], reference, filename="hall.copc.laz", reference=True)
    assert response.status_code == 201, response.text
    scan = response.json()["scan"]
    assert scan["format"] == "laz" and scan["n_points"] == len(room)
    assert scan["filename"] == "hall.copc.laz"

    content = copc_bytes(room_points(3000, 22, noise=0.003, with_box=True))
    location = new_upload(client, len(content), site=site["id"], filename="monday.copc.laz")
    assert patch(client, location, 0, content[: len(content) // 2]).status_code == 204
    response = patch(client, location, len(content) // 2, content[len(content) // 2 :])
    assert response.status_code == 202, response.text
    assert response.json()["scan"]["sha256"] == hashlib.sha256(content).hexdigest()


@pytest.mark.parametrize(
    ("kind", "declared_change"),
    [("copc", +40), ("copc", -40), ("laz", +40)],
)
def test_a_header_that_disagrees_with_the_points_is_a_400_and_nothing_is_stored(
    api: ApiServer, room, kind, declared_change
) -> None:
    client = api.client(api.token("writer"))
    site = create_site(client)
    if kind == "copc":
        content = copc_bytes(room)
    else:
        content = las_bytes(room, compress=True, point_format=6, version="1.4")
    edited = with_point_count(content, len(room) + declared_change)
    files_before = api.stored_files()
    response = upload(client, site["id"], edited, filename=f"hall.{kind}.laz", reference=True)
    detail = assert_error(response, 400)
    assert f"{len(room) + declared_change:,} points" in detail
    assert api.stored_files() == files_before
    assert client.get(f"/api/v1/sites/{site['id']}/scans").json()["items"] == []
    location = new_upload(client, len(edited), site=site["id"], reference="true")
    assert_error(patch(client, location, 0, edited), 400)
    assert client.get(location).json()["state"] == "failed"
    assert api.stored_files() == files_before
