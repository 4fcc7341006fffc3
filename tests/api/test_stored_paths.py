"""Stored paths over HTTP: a scan row whose path leads outside the data directory is not
served (404 saying why), even when a file is there."""

from __future__ import annotations

from pathlib import Path

import httpx
from sqlalchemy import update

from app.db.models import Scan
from app.db.session import transaction
from tests.helpers.http import assert_error, site_with_reference
from tests.helpers.server import ApiServer


def test_a_scan_file_outside_the_data_directory_is_not_served(
    api: ApiServer, writer: httpx.Client, tmp_path: Path
) -> None:
    _site, scan = site_with_reference(writer)
    assert writer.get(f"/api/v1/scans/{scan['id']}/file").status_code == 200
    outside = tmp_path / "secret.ply"
    outside.write_text("someone else's file")
    for stored in ("../" * 8 + str(outside).lstrip("/"), str(outside)):
        with transaction(api.settings.sqlalchemy_url) as session:
            session.execute(update(Scan).where(Scan.id == scan["id"]).values(storage_path=stored))
        detail = assert_error(writer.get(f"/api/v1/scans/{scan['id']}/file"), 404, "not_found")
        assert "outside the data directory" in detail
