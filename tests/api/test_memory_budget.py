"""The workers' memory budget (SCANDIFF_WORKER_MEMORY_BUDGET_BYTES): a comparison whose two
scans cannot even be held within it is refused with a 422 naming the setting, nothing queued."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from app.core.tiling.plan import BASELINE_BYTES, RESIDENT_BYTES_PER_POINT
from app.db.models import Job, Scan
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from tests.helpers.database import count_rows as count
from tests.helpers.http import assert_error, site_with_reference, upload
from tests.helpers.server import MAX_UPLOAD_BYTES, ApiServer, fresh_api

SCAN_POINTS = 2000
REFERENCE_POINTS = 3000  # site_with_reference's
BUDGET_BYTES = BASELINE_BYTES + (REFERENCE_POINTS + SCAN_POINTS) * RESIDENT_BYTES_PER_POINT // 2
"""Room for half of the pair's points: not even one tile fits."""


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app with a memory budget too small for the test's pair."""
    yield from fresh_api(
        tmp_path_factory,
        "budget-data",
        max_upload_bytes=MAX_UPLOAD_BYTES,
        worker_memory_budget_bytes=BUDGET_BYTES,
    )


def test_a_pair_over_the_workers_budget_is_refused_with_the_setting_to_raise(
    api: ApiServer,
) -> None:
    writer = api.client(api.token("writer"))
    site, reference = site_with_reference(writer)
    scans_before, jobs_before = count(api, Scan), count(api, Job)
    # a comparison upload: refused, neither the scan nor a job stored
    detail = assert_error(
        upload(writer, site["id"], ply_bytes(room_points(SCAN_POINTS, seed=3))),
        422,
        "memory_budget_too_small",
    )
    assert "SCANDIFF_WORKER_MEMORY_BUDGET_BYTES" in detail and "5,000 points" in detail
    assert (count(api, Scan), count(api, Job)) == (scans_before, jobs_before)
    # a job on two stored scans (the second uploaded as the new reference): refused too
    response = upload(
        writer, site["id"], ply_bytes(room_points(SCAN_POINTS, seed=3)), reference=True
    )
    assert response.status_code == 201, response.text
    detail = assert_error(
        writer.post(
            "/api/v1/jobs",
            json={"reference_scan_id": reference["id"], "scan_id": response.json()["scan"]["id"]},
        ),
        422,
        "memory_budget_too_small",
    )
    assert "5,000 points" in detail
    assert count(api, Job) == jobs_before
