"""The workers' memory budget (SCANDIFF_WORKER_MEMORY_BUDGET_BYTES): a comparison whose two
scans cannot even be held within it is refused with a 422 naming the setting, nothing queued;
a pair a worker reads in chunks (coordinates-only binary PLY, no origin) needs room for its
subsamples only.  The disk likewise: a pair compared in tiles whose points' crops and results
cannot fit beside what must stay free (SCANDIFF_MIN_FREE_DISK_BYTES) is refused."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from app.core.tiling.plan import (
    BASELINE_BYTES,
    LEAN_RESIDENT_BYTES_PER_POINT,
    RESIDENT_BYTES_PER_POINT,
)
from app.db.models import Job, Scan
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from tests.helpers.database import count_rows as count
from tests.helpers.http import assert_error, site_with_reference, upload
from tests.helpers.server import MAX_UPLOAD_BYTES, ApiServer, fresh_api

SCAN_POINTS = 2000
REFERENCE_POINTS = 3000  # site_with_reference's
PAIR_POINTS = REFERENCE_POINTS + SCAN_POINTS
BUDGET_BYTES = BASELINE_BYTES + PAIR_POINTS * LEAN_RESIDENT_BYTES_PER_POINT // 2
"""Room for half of the pair's points, even read lean in chunks: not even one tile fits."""
STREAMED_BUDGET_BYTES = (
    BASELINE_BYTES + PAIR_POINTS * (LEAN_RESIDENT_BYTES_PER_POINT + RESIDENT_BYTES_PER_POINT) // 2
)
"""Too small to hold the pair whole, enough for a worker reading it in chunks (whose
subsamples, at most 2M points a cloud, are here the whole clouds)."""


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


@pytest.fixture(scope="module")
def streamed_api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app with a budget that holds the test's pair only when it is read in chunks."""
    yield from fresh_api(
        tmp_path_factory,
        "streamed-budget-data",
        max_upload_bytes=MAX_UPLOAD_BYTES,
        worker_memory_budget_bytes=STREAMED_BUDGET_BYTES,
    )


def test_a_pair_read_in_chunks_needs_room_for_its_subsamples_only(
    streamed_api: ApiServer,
) -> None:
    writer = streamed_api.client(streamed_api.token("writer"))
    site, _ = site_with_reference(writer)
    scan = ply_bytes(room_points(SCAN_POINTS, seed=3))
    assert upload(writer, site["id"], scan).status_code == 202  # coordinates only: queued
    # an origin given at upload: the worker reads the scan whole, so the pair must fit whole
    jobs_before = count(streamed_api, Job)
    detail = assert_error(
        upload(writer, site["id"], scan, sensor_origin="0,0,1"), 422, "memory_budget_too_small"
    )
    assert "5,000 points" in detail
    # ascii PLY is not read in chunks either
    detail = assert_error(
        upload(writer, site["id"], ply_bytes(room_points(SCAN_POINTS, seed=3), "ascii")),
        422,
        "memory_budget_too_small",
    )
    assert count(streamed_api, Job) == jobs_before


@pytest.fixture(scope="module")
def small_disk_api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app comparing every pair in tiles, with more disk to keep free than any disk has."""
    yield from fresh_api(
        tmp_path_factory,
        "small-disk-data",
        max_upload_bytes=MAX_UPLOAD_BYTES,
        tile_crop_points=PAIR_POINTS // 2,
        min_free_disk_bytes=10**18,
    )


def test_a_tiled_pair_that_cannot_fit_the_disk_is_refused_with_the_setting_to_raise(
    small_disk_api: ApiServer,
) -> None:
    writer = small_disk_api.client(small_disk_api.token("writer"))
    site, _ = site_with_reference(writer)
    scans_before, jobs_before = count(small_disk_api, Scan), count(small_disk_api, Job)
    detail = assert_error(
        upload(writer, site["id"], ply_bytes(room_points(SCAN_POINTS, seed=3))),
        422,
        "insufficient_disk",
    )
    assert "5,000 points" in detail and "SCANDIFF_MIN_FREE_DISK_BYTES" in detail, detail
    assert "1,000,000,000.0 GB free" in detail, detail
    assert (count(small_disk_api, Scan), count(small_disk_api, Job)) == (scans_before, jobs_before)
