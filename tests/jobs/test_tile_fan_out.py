"""A job compared tile by tile on several workers (issue 30's fan-out), through the real service.

``SCANDIFF_TILE_CROP_POINTS`` forces small tiles so a small pair crosses many tile borders; the
tiles are ``run_tile`` messages on the same queue the workers consume.  Checked: the fanned-out
result equals the in-process tiled comparison of the same files (labels identical), more than
one worker computed tiles, the job reports tiles done/total, a worker killed inside a tile
leaves that tile to be retried while the tiles already stored are never computed again, and a
job that stops cancels its tiles.  The streamed parent's crops pass is queue work too, one pass
a cloud: run by both workers, retried when the worker running one is killed, cancelled with
its job.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sqlalchemy import delete, select, update

from app.config import Settings
from app.core.datasets import map_pair
from app.core.formats import read_point_cloud
from app.core.tiling.compare import compare_tiled
from app.db.models import Job, JobCropPass, JobStatus, JobTile, TileStatus
from app.db.session import transaction
from app.jobs.crop_passes import run_crop_pass_message
from app.jobs.leases import TileOutcome, lease_owner_pid
from app.jobs.tiles import run_tile_message
from app.testing.files import ply_bytes
from app.testing.service import ServiceProcess
from app.testing.waiting import wait_until
from tests.helpers.jobs import create_job

CROP_SHARE = 0.5
"""Share of both clouds' points a tile's crop may hold: the map below gets four tiles."""


def _pair() -> tuple[np.ndarray, np.ndarray, int]:
    """A robot's fused map with a box removed (points only: nothing given), and the crop size."""
    pair = map_pair("robot", change="removed", size=0.25, random_state=0)
    reference, scan = pair.reference.points, pair.scan.points
    return reference, scan, int(CROP_SHARE * (len(reference) + len(scan)))


def _tiles(data_dir: Path, job_id: str) -> list[dict]:
    with sqlite3.connect(data_dir / "scandiff.sqlite3") as connection:
        connection.row_factory = sqlite3.Row
        rows = connection.execute(
            "SELECT * FROM job_tile WHERE job_id = ? ORDER BY tile_index", (job_id,)
        ).fetchall()
    return [dict(row) for row in rows]


def _run_job(service: ServiceProcess, reference: np.ndarray, scan: np.ndarray) -> dict:
    job = _finished_job(service, reference, scan)
    with service.client() as client:
        labels = client.get(f"/api/v1/jobs/{job['id']}/labels", params={"format": "npz"})
        assert labels.status_code == 200, labels.text
    return {**job, "labels_npz": labels.content}


def _finished_job(service: ServiceProcess, reference: np.ndarray, scan: np.ndarray) -> dict:
    """Upload the pair (the reference first) and wait for its job to end."""
    with service.client() as client:
        site = client.post("/api/v1/sites", json={"name": "hall"}).json()
        path = f"/api/v1/sites/{site['id']}/scans"
        response = client.post(
            path,
            params={"reference": "true", "filename": "monday.ply"},
            content=ply_bytes(reference),
        )
        assert response.status_code == 201, response.text
        response = client.post(path, params={"filename": "tuesday.ply"}, content=ply_bytes(scan))
        assert response.status_code == 202, response.text
        return service.wait_for_job(client, response.json()["job"]["id"], timeout=300)


def _crop_passes(data_dir: Path, job_id: str) -> list[dict]:
    with sqlite3.connect(data_dir / "scandiff.sqlite3") as connection:
        connection.row_factory = sqlite3.Row
        rows = connection.execute(
            "SELECT * FROM job_crop_pass WHERE job_id = ? ORDER BY pass_index", (job_id,)
        ).fetchall()
    return [dict(row) for row in rows]


def _expected(tmp_path: Path, reference: np.ndarray, scan: np.ndarray, crop_points: int) -> Any:
    """The in-process tiled comparison of the files the service stored."""
    clouds = []
    for name, points in (("reference.ply", reference), ("scan.ply", scan)):
        (tmp_path / name).write_bytes(ply_bytes(points))  # the bytes the service stored
        clouds.append(read_point_cloud(tmp_path / name))
    return compare_tiled(*clouds, budget_bytes=1 << 40, max_crop_points=crop_points, threads=1)


def _assert_same_labels(job: dict, expected: Any, tmp_path: Path) -> None:
    assert job["changed"] == expected.changed
    assert job["n_regions"] == len(expected.regions)
    stored = _labels(job["labels_npz"], tmp_path)
    np.testing.assert_array_equal(stored["reference_label"], expected.reference_label)
    np.testing.assert_array_equal(stored["scan_label"], expected.scan_label)


def _labels(npz: bytes, tmp_path: Path) -> dict[str, np.ndarray]:
    path = tmp_path / "labels.npz"
    path.write_bytes(npz)
    with np.load(path) as data:
        return {name: data[name] for name in data.files}


def _service_with_short_leases(
    service_factory: Callable[..., ServiceProcess], workers: int, crop_points: int, hooks: str
) -> ServiceProcess:
    """A service whose job and tile leases expire 3 s after a kill (``hooks``: the test hooks)."""
    return service_factory(
        workers=workers,
        env={
            "SCANDIFF_TILE_CROP_POINTS": str(crop_points),
            "SCANDIFF_JOB_LEASE_SECONDS": "3",
            "SCANDIFF_JOB_HEARTBEAT_SECONDS": "0.5",
            "SCANDIFF_TEST_JOB_HOOKS": hooks,
        },
    )


def test_tiles_and_crop_passes_run_on_every_worker_and_equal_the_in_process_tiled_result(
    service_factory: Callable[..., ServiceProcess], tmp_path: Path
) -> None:
    reference, scan, crop_points = _pair()
    service = service_factory(
        workers=2,
        env={
            "SCANDIFF_TILE_CROP_POINTS": str(crop_points),
            # a pass long enough for the other worker to take the second pass's message under load
            "SCANDIFF_TEST_JOB_HOOKS": (
                '{"tile_sleep_seconds": 0.3, "crop_pass_sleep_seconds": 3.0}'
            ),
        },
    )
    job = _run_job(service, reference, scan)
    assert job["status"] == JobStatus.SUCCEEDED, job
    tiles = _tiles(service.data_dir, job["id"])
    assert len(tiles) >= 3
    assert job["tiles"] == {"done": len(tiles), "total": len(tiles)}
    assert {tile["status"] for tile in tiles} == {"succeeded"}
    assert all(tile["attempts"] == 1 for tile in tiles), "no tile computed twice"
    workers = {lease_owner_pid(tile["lease_owner"]) for tile in tiles}
    assert len(workers) == 2, f"tiles computed by {workers}: the second worker took none"
    tiles_directory = service.data_dir / "results" / job["id"] / "tiles"
    # the parent deletes the tile files just after storing the job (a heavily loaded machine
    # can show the job succeeded first); they must be gone soon after
    wait_until(lambda: not tiles_directory.exists(), 30.0, "the finished job's tile files deleted")
    timings = job["timings"]  # the parent's phases, for operators
    assert timings["tiles_computed_here"] + timings["tiles_computed_elsewhere"] == len(tiles)
    seconds_by_owner: dict[str, list[float]] = {}
    for tile in tiles:
        seconds_by_owner.setdefault(tile["lease_owner"], []).append(tile["seconds"])
    everything = sum(tile["seconds"] for tile in tiles)
    assert any(  # the parent's own tiles (one lease owner) and the others' seconds add up
        len(seconds) == timings["tiles_computed_here"]
        and sum(seconds) + timings["tiles_other_workers"] == pytest.approx(everything)
        for seconds in seconds_by_owner.values()
    ), (timings, seconds_by_owner)
    assert timings["tile_inputs_write"] > 0 and timings["tile_results_read"] > 0
    assert "streamed_seconds" in timings, "coordinates-only files: the parent streams them"
    passes = _crop_passes(service.data_dir, job["id"])  # the crops pass: one a cloud
    assert [row["pass_index"] for row in passes] == [0, 1]
    assert {row["status"] for row in passes} == {"succeeded"}
    assert all(row["attempts"] == 1 and row["points"] > 0 for row in passes)
    workers = {lease_owner_pid(row["lease_owner"]) for row in passes}
    assert len(workers) == 2, f"crop passes run by {workers}: the second worker took none"
    assert timings["crop_passes_computed_here"] == timings["crop_passes_computed_elsewhere"] == 1
    assert timings["crop_passes_other_workers"] > 0

    _assert_same_labels(job, _expected(tmp_path, reference, scan, crop_points), tmp_path)


def test_a_job_whose_crops_do_not_fit_the_disk_fails_saying_so_before_writing_them(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    # the workers see a disk with 2 MB free (the API the real one: the pair alone fits)
    reference, scan, crop_points = _pair()
    service = service_factory(
        workers=1,
        env={
            "SCANDIFF_TILE_CROP_POINTS": str(crop_points),
            "SCANDIFF_TEST_JOB_HOOKS": '{"free_disk_bytes": 2000000}',
        },
    )
    job = _finished_job(service, reference, scan)
    assert job["status"] == JobStatus.FAILED, job
    assert job["attempts"] == 1, "refused, not retried"
    error = job["error"]
    assert "not enough disk for this comparison" in error, error
    assert "only 0.0 GB are free" in error and "SCANDIFF_MIN_FREE_DISK_BYTES" in error, error
    assert _crop_passes(service.data_dir, job["id"]) == [], "no crop pass started"
    assert not list((service.data_dir / "results").rglob("crop-*.bin")), "no crop written"


@pytest.mark.slow  # a lease to expire: ~40 s
def test_a_worker_killed_in_a_crop_pass_leaves_it_retried_with_the_same_result(
    service_factory: Callable[..., ServiceProcess], tmp_path: Path
) -> None:
    reference, scan, crop_points = _pair()
    service = _service_with_short_leases(
        service_factory,
        2,
        crop_points,
        ('{"crop_pass_sleep_seconds": 3.0, "kill_in_crop_pass": "helper"}'),
    )
    job = _run_job(service, reference, scan)
    assert job["status"] == JobStatus.SUCCEEDED, job
    assert job["attempts"] == 1, "the job's own worker lived: only the pass was retried"
    passes = _crop_passes(service.data_dir, job["id"])
    assert {row["status"] for row in passes} == {"succeeded"}
    # the pass the other worker died in ran again (on the job's worker); the other ran once
    assert sorted(row["attempts"] for row in passes) == [1, 2]
    assert len({row["lease_owner"] for row in passes}) == 1, "the job's worker stored both"
    assert job["timings"]["crop_passes_computed_here"] == 2
    _assert_same_labels(job, _expected(tmp_path, reference, scan, crop_points), tmp_path)


@pytest.mark.slow  # two attempts of a real job with a lease to expire: ~1 minute
def test_a_worker_killed_in_a_tile_leaves_it_retried_and_stored_tiles_are_kept(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    reference, scan, crop_points = _pair()
    service = _service_with_short_leases(
        service_factory, 1, crop_points, '{"kill_in_tile": 2, "on_attempts": [1]}'
    )
    job = _run_job(service, reference, scan)
    assert job["status"] == JobStatus.SUCCEEDED, job
    assert job["attempts"] == 2, "the first worker died in a tile"
    tiles = _tiles(service.data_dir, job["id"])
    assert {tile["status"] for tile in tiles} == {"succeeded"}
    attempts = sorted(tile["attempts"] for tile in tiles)
    # the tile the worker died in ran twice; every tile stored before was not computed again
    assert attempts == [1] * (len(tiles) - 1) + [2], attempts
    assert job["tiles"] == {"done": len(tiles), "total": len(tiles)}


@pytest.mark.parametrize("ending", ["failed", "deleted"])
def test_tiles_of_a_job_that_stopped_are_cancelled(job_settings: Settings, ending: str) -> None:
    job_id = create_job(job_settings)
    with transaction(job_settings.sqlalchemy_url) as session:
        session.execute(update(Job).where(Job.id == job_id).values(status=JobStatus.RUNNING))
        session.add_all(JobTile(job_id=job_id, tile_index=index) for index in range(3))
    # a job waiting in the queue for its next attempt keeps its tiles for that attempt
    with transaction(job_settings.sqlalchemy_url) as session:
        session.execute(update(Job).where(Job.id == job_id).values(status=JobStatus.QUEUED))
    assert run_tile_message(job_id, 1, job_settings) is TileOutcome.SKIPPED
    assert _statuses(job_settings, job_id) == {TileStatus.QUEUED}
    with transaction(job_settings.sqlalchemy_url) as session:
        if ending == "failed":
            session.execute(update(Job).where(Job.id == job_id).values(status=JobStatus.FAILED))
        else:
            session.execute(delete(Job).where(Job.id == job_id))
    assert run_tile_message(job_id, 1, job_settings) is TileOutcome.CANCELLED
    assert _statuses(job_settings, job_id) == (
        {TileStatus.CANCELLED} if ending == "failed" else set()
    )


@pytest.mark.slow  # two attempts of a real job with a lease to expire: ~1 minute
def test_a_parent_killed_in_a_crop_pass_is_followed_by_an_attempt_writing_the_crops_afresh(
    service_factory: Callable[..., ServiceProcess], tmp_path: Path
) -> None:
    reference, scan, crop_points = _pair()
    service = _service_with_short_leases(
        service_factory, 1, crop_points, '{"kill_in_crop_pass": "parent", "on_attempts": [1]}'
    )
    job = _run_job(service, reference, scan)
    assert job["status"] == JobStatus.SUCCEEDED, job
    assert job["attempts"] == 2, "the first worker died in its crop pass"
    passes = _crop_passes(service.data_dir, job["id"])
    assert {row["status"] for row in passes} == {"succeeded"}
    # the pass it died in (its first: the reference's) ran again in the second attempt (the
    # other too, maybe twice: the restarted worker may take its message from the first)
    assert passes[0]["attempts"] >= 2
    _assert_same_labels(job, _expected(tmp_path, reference, scan, crop_points), tmp_path)


def test_crop_passes_of_a_job_that_stopped_are_cancelled(job_settings: Settings) -> None:
    job_id = create_job(job_settings)
    with transaction(job_settings.sqlalchemy_url) as session:
        session.execute(update(Job).where(Job.id == job_id).values(status=JobStatus.QUEUED))
        session.add_all(JobCropPass(job_id=job_id, pass_index=index) for index in range(2))
    assert run_crop_pass_message(job_id, 1, job_settings) is TileOutcome.SKIPPED
    with transaction(job_settings.sqlalchemy_url) as session:
        session.execute(update(Job).where(Job.id == job_id).values(status=JobStatus.FAILED))
    assert run_crop_pass_message(job_id, 1, job_settings) is TileOutcome.CANCELLED
    with transaction(job_settings.sqlalchemy_url) as session:
        statuses = set(
            session.scalars(select(JobCropPass.status).where(JobCropPass.job_id == job_id))
        )
    assert statuses == {TileStatus.CANCELLED}


def _statuses(settings: Settings, job_id: str) -> set[str]:
    with transaction(settings.sqlalchemy_url) as session:
        return set(session.scalars(select(JobTile.status).where(JobTile.job_id == job_id)))
