"""kill -9 of the whole service, three times, under 50 concurrent uploads (issue 5, item 1).

The real ``scandiff serve`` (API, consumer, 2 job workers; real pipeline, PCA detector) on a
temporary data directory.  50 client threads each upload one 1-5 MB binary PLY (10,000 points
in a room with a box, plus float64 attribute columns that make up the size, so every job is a
real comparison of about a second) with an ``Idempotency-Key``.  The whole process group gets
SIGKILL three times at random moments, and the service is restarted on the same data directory
each time:

1. after a random number (8-30) of uploads were answered: uploads in flight, jobs running;
2. and 3. after a random number (2-6) of jobs finished since the restart, a random 0-0.5 s
   later: jobs running, the retried uploads possibly still in flight.

After each restart (the start-up sweeps ran before the API answers) nothing half-written may
be left: no file in ``tmp/``, no scan file without its row, no scan row without its file (same
size and SHA-256) or without exactly one job, no temporary result file; an upload that got no
answer left either nothing or a complete scan + job (committed just before the kill).  Clients
whose upload got no 2xx retry it with the same ``Idempotency-Key`` after the restart.

At the end, every upload got a 2xx, all answers for one key name the same job, each upload has
exactly one scan row and one job, every job ``succeeded`` (none ``queued``/``running``) with
its result files.  ``SCANDIFF_JOB_MAX_ATTEMPTS`` is 4: each kill may cost the jobs running at
that moment one attempt (a power cut is indistinguishable from a crashing input), so with three
kills a job hit every time must still have one attempt left.
"""

from __future__ import annotations

import hashlib
import random
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from app.config import Settings
from app.core.files import write_atomically
from app.db.migrate import upgrade_to_head
from app.db.session import get_engine
from app.services.storage import ensure_directories, sweep_temporary_files
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from app.testing.service import ServiceProcess
from app.testing.waiting import wait_until
from tests.helpers.database import database_rows, job_status_counts
from tests.helpers.figures import record_figure
from tests.helpers.jobs import create_job

N_UPLOADS = 50
N_KILLS = 3
N_WORKERS = 2
POINTS_PER_SCAN = 10_000
MIN_SCAN_BYTES = 1_000_000
MAX_SCAN_BYTES = 5_000_000
MAX_ATTEMPTS = N_KILLS + 1
SETTLE_TIMEOUT_SECONDS = 240.0
CRASH_ENV = {
    "SCANDIFF_JOB_LEASE_SECONDS": "2",
    "SCANDIFF_JOB_HEARTBEAT_SECONDS": "0.25",
    "SCANDIFF_RECOVERY_INTERVAL_SECONDS": "0.5",
    "SCANDIFF_JOB_MAX_ATTEMPTS": str(MAX_ATTEMPTS),
    "SCANDIFF_MAX_UPLOAD_BYTES": str(2 * MAX_SCAN_BYTES),
}


def room_with_attributes(seed: int, *, with_box: bool, n_bytes: int) -> bytes:
    """A binary PLY of a floor and two walls (a box on the floor when ``with_box``).

    ``POINTS_PER_SCAN`` points with float64 x, y, z plus as many float64 attribute columns
    (``a0``, ``a1``, ... random values) as make the file about ``n_bytes`` long.
    """
    rng = np.random.default_rng(seed)
    points = room_points(POINTS_PER_SCAN, rng, noise=0.003, with_box=with_box)
    n_attributes = max(0, round(n_bytes / (8 * len(points))) - 3)
    attributes = {f"a{index}": rng.random(len(points)) for index in range(n_attributes)}
    return ply_bytes(points, coordinate_type="f8", extra=attributes)


@dataclass
class Upload:
    """One client's scan and what the service answered to each try."""

    index: int
    body: bytes
    sha256: str = ""
    answers: list[int | str] = field(default_factory=list)
    job_ids: set[str] = field(default_factory=set)
    scan_ids: set[str] = field(default_factory=set)

    def __post_init__(self) -> None:
        self.sha256 = hashlib.sha256(self.body).hexdigest()

    @property
    def acknowledged(self) -> bool:
        return any(isinstance(answer, int) and 200 <= answer < 300 for answer in self.answers)

    @property
    def key(self) -> str:
        return f"crash-recovery-{self.index:02d}"


def send(client: httpx.Client, site_id: str, upload: Upload) -> None:
    """POST the upload once; note the answer (status or exception name)."""
    try:
        response = client.post(
            f"/api/v1/sites/{site_id}/scans",
            params={"filename": f"scan-{upload.index:02d}.ply", "method": "pca"},
            content=upload.body,
            headers={
                "Content-Type": "application/octet-stream",
                "Idempotency-Key": upload.key,
            },
        )
    except httpx.HTTPError as error:
        upload.answers.append(type(error).__name__)
        return
    upload.answers.append(response.status_code)
    if response.status_code == 202:
        answer = response.json()
        upload.job_ids.add(answer["job"]["id"])
        upload.scan_ids.add(answer["scan"]["id"])


def send_all(
    service: ServiceProcess, site_id: str, uploads: list[Upload]
) -> list[threading.Thread]:
    """One thread (and connection) per upload, all started at once."""

    def run(upload: Upload) -> None:
        with service.client(timeout=60.0) as client:
            send(client, site_id, upload)

    threads = [threading.Thread(target=run, args=(upload,)) for upload in uploads]
    for thread in threads:
        thread.start()
    return threads


def check_nothing_half_written(
    data_dir: Path, reference_id: str, uploads: list[Upload]
) -> dict[str, int]:
    """The invariants every restart must restore (see the module docstring); some counts."""
    scans, jobs = database_rows(data_dir, "scan"), database_rows(data_dir, "job")
    leftovers = [path.name for path in (data_dir / "tmp").glob("*")]
    assert leftovers == [], f"temporary upload files left: {leftovers}"
    referenced = {scan["storage_path"] for scan in scans}
    caches = {Path(path).with_suffix(".geometry").as_posix() for path in referenced}
    stored_files = {
        path.relative_to(data_dir).as_posix() for path in data_dir.glob("scans/*/*")
    } - caches  # a reference's k-NN geometry cache beside it is its scan's (app/jobs/geometry.py)
    assert stored_files == referenced, (
        f"files without a row: {stored_files - referenced}; rows without a file: "
        f"{referenced - stored_files}"
    )
    for scan in scans:
        content = (data_dir / scan["storage_path"]).read_bytes()
        assert (len(content), hashlib.sha256(content).hexdigest()) == (
            scan["size_bytes"],
            scan["sha256"],
        ), f"scan {scan['id']}: file differs from its row"
    jobs_per_scan = Counter(job["scan_id"] for job in jobs)
    scan_ids = {scan["id"] for scan in scans}
    assert set(jobs_per_scan) <= scan_ids, "jobs without their scan"
    for scan in scans:
        expected = 0 if scan["id"] == reference_id else 1
        assert jobs_per_scan[scan["id"]] == expected, f"scan {scan['id']}: {jobs_per_scan}"
    by_sha = Counter(scan["sha256"] for scan in scans)
    committed_unanswered = 0
    for upload in uploads:
        assert by_sha[upload.sha256] <= 1, f"upload {upload.index} stored twice"
        if upload.acknowledged:
            assert by_sha[upload.sha256] == 1, f"acknowledged upload {upload.index} lost"
            assert upload.scan_ids <= scan_ids
        elif by_sha[upload.sha256] == 1:
            committed_unanswered += 1  # stored (complete) just before the kill
    return {
        "scans": len(scans) - 1,
        "jobs": len(jobs),
        "committed_unanswered": committed_unanswered,
    }


def leftovers(data_dir: Path) -> dict[str, list[Path]]:
    """What a kill may leave: temporary uploads, temporary result files, unreferenced scans.

    A reference's geometry cache (``<scan>.geometry`` beside its file, app/jobs/geometry.py)
    belongs to its scan: checked before every use, rebuilt when damaged.
    """
    stored = [scan["storage_path"] for scan in database_rows(data_dir, "scan")]
    referenced = {*stored, *(Path(path).with_suffix(".geometry").as_posix() for path in stored)}
    return {
        "tmp": sorted((data_dir / "tmp").glob("*")),
        "result_tmp": sorted(data_dir.glob("results/*/.*.tmp*")),
        "unreferenced_scans": sorted(
            path
            for path in data_dir.glob("scans/*/*")
            if path.relative_to(data_dir).as_posix() not in referenced
        ),
    }


@pytest.mark.slow
def test_three_power_cuts_lose_nothing_and_leave_nothing_half_written(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    seed = random.randrange(2**32)
    rng = random.Random(seed)
    print(f"\ncrash-recovery seed {seed}")
    started = time.monotonic()
    uploads = [
        Upload(
            index,
            room_with_attributes(
                100 + index,
                with_box=True,
                n_bytes=rng.randrange(MIN_SCAN_BYTES, MAX_SCAN_BYTES - 200_000),
            ),
        )
        for index in range(N_UPLOADS)
    ]
    sizes = [len(upload.body) for upload in uploads]
    assert MIN_SCAN_BYTES <= min(sizes) and max(sizes) <= MAX_SCAN_BYTES
    service = service_factory(workers=N_WORKERS, env=CRASH_ENV)
    data_dir = service.data_dir
    with service.client() as client:
        site = client.post("/api/v1/sites", json={"name": "crash-yard"}).json()
        reference = client.post(
            f"/api/v1/sites/{site['id']}/scans",
            params={"filename": "reference.ply", "reference": "true"},
            content=room_with_attributes(1, with_box=False, n_bytes=3_000_000),
            headers={"Content-Type": "application/octet-stream"},
        )
        assert reference.status_code == 201, reference.text
        reference_id = reference.json()["scan"]["id"]
    service.wait_for_workers()

    kills: list[dict[str, Any]] = []
    checks: list[dict[str, int]] = []
    uploads_started = time.monotonic()
    for round_number in range(N_KILLS + 1):
        pending = [upload for upload in uploads if not upload.acknowledged]
        threads = send_all(service, site["id"], pending)
        if round_number == N_KILLS:  # the last round: no kill, let everything settle
            for thread in threads:
                thread.join()
            break
        if round_number == 0:
            answered = rng.randint(8, 30)
            wait_until(
                lambda target=answered: sum(upload.acknowledged for upload in uploads) >= target,
                120,
                f"{answered} uploads answered",
            )
            time.sleep(rng.uniform(0, 0.1))
        else:
            done_before = job_status_counts(data_dir)["succeeded"]
            more = rng.randint(2, 6)
            wait_until(
                lambda target=done_before + more: (
                    job_status_counts(data_dir)["succeeded"] >= target
                ),
                120,
                f"{more} more jobs succeeded",
            )
            time.sleep(rng.uniform(0, 0.5))
        in_flight = sum(thread.is_alive() for thread in threads)
        at_kill = job_status_counts(data_dir)
        service.kill()  # SIGKILL to the process group: API, consumer, scheduler, workers
        for thread in threads:
            thread.join()
        left = leftovers(data_dir)
        kills.append(
            {
                "uploads_in_flight": in_flight,
                "running": at_kill["running"],
                "queued": at_kill["queued"],
                "succeeded": at_kill["succeeded"],
                **{f"left_{kind}": len(paths) for kind, paths in left.items()},
            }
        )
        print(f"kill {round_number + 1}: {kills[-1]}")
        service.start()  # same data directory and port; the start-up sweeps run first
        still_there = [str(path) for paths in left.values() for path in paths if path.exists()]
        assert still_there == [], f"left by kill {round_number + 1}, kept by the sweep"
        checks.append(check_nothing_half_written(data_dir, reference_id, uploads))
        print(f"after restart {round_number + 1}: {checks[-1]}")

    uploads_seconds = time.monotonic() - uploads_started
    wait_until(
        lambda: (
            (counts := job_status_counts(data_dir))["queued"] + counts["running"] == 0
            and sum(counts.values()) == N_UPLOADS
        ),
        SETTLE_TIMEOUT_SECONDS,
        "every job finished",
    )
    settled_seconds = time.monotonic() - uploads_started
    final = check_nothing_half_written(data_dir, reference_id, uploads)
    assert leftovers(data_dir) == {"tmp": [], "result_tmp": [], "unreferenced_scans": []}
    scans, jobs = database_rows(data_dir, "scan"), database_rows(data_dir, "job")
    job_by_scan = {job["scan_id"]: job for job in jobs}
    scan_by_sha = {scan["sha256"]: scan for scan in scans}

    not_acknowledged = [upload.index for upload in uploads if not upload.acknowledged]
    assert not_acknowledged == [], f"uploads never answered with a 2xx: {not_acknowledged}"
    for upload in uploads:
        scan = scan_by_sha[upload.sha256]
        job = job_by_scan[scan["id"]]
        assert upload.job_ids == {job["id"]}, f"upload {upload.index}: {upload.job_ids}"
        assert upload.scan_ids == {scan["id"]}
        assert (job["status"], job["error"]) == ("succeeded", None), job
        assert 1 <= job["attempts"] <= MAX_ATTEMPTS
        for name in ("labels.npz", "details.npz"):
            assert (data_dir / "results" / job["id"] / name).is_file()
    assert (final["scans"], final["jobs"]) == (N_UPLOADS, N_UPLOADS)
    log = service.log_path.read_text(errors="replace")
    assert "database is locked" not in log

    answers = Counter(
        answer if isinstance(answer, int) else "no answer"
        for upload in uploads
        for answer in upload.answers
    )
    attempts = Counter(job["attempts"] for job in jobs)
    retried = sum(len(upload.answers) > 1 for upload in uploads)
    committed_unanswered = sum(check["committed_unanswered"] for check in checks)
    total_seconds = time.monotonic() - started
    record_figure(
        "crash-recovery",
        load=(
            f"{N_UPLOADS} concurrent uploads of {min(sizes) / 1e6:.1f}-{max(sizes) / 1e6:.1f} MB "
            f"PLYs ({POINTS_PER_SCAN} points each), real pipeline, `serve` with {N_WORKERS} "
            "workers, lease 2 s, sweep 0.5 s"
        ),
        faults=(
            f"SIGKILL of the whole process group x{N_KILLS}, restart on the same data dir; "
            "kill 1 mid-upload, kills 2-3 mid-job; unanswered uploads retried with their "
            "Idempotency-Key"
        ),
        inputs=f"{N_UPLOADS} uploads, {sum(answers.values())} requests",
        result=(
            f"{N_UPLOADS}/{N_UPLOADS} uploads answered 2xx, each exactly 1 scan + 1 job, "
            f"{N_UPLOADS} succeeded, 0 queued/running, 0 half-written rows or files after "
            f"each restart; at the kills {[k['uploads_in_flight'] for k in kills]} uploads in "
            f"flight and {[k['running'] for k in kills]} jobs running; the kills left "
            f"{sum(k['left_tmp'] for k in kills)} temporary uploads, "
            f"{sum(k['left_unreferenced_scans'] for k in kills)} unreferenced scan files and "
            f"{sum(k['left_result_tmp'] for k in kills)} temporary result files, all removed by "
            "the start-up sweep; "
            f"{committed_unanswered} stored-but-unanswered uploads replayed by their key; "
            f"answers {dict(sorted(answers.items(), key=str))}; attempts "
            f"{dict(sorted(attempts.items()))}; all settled {settled_seconds:.0f} s after the "
            f"first upload; {total_seconds:.0f} s"
        ),
        seed=seed,
        kills=kills,
        checks=checks,
        retried_uploads=retried,
        uploads_seconds=round(uploads_seconds, 1),
        settled_seconds=round(settled_seconds, 1),
    )


def test_the_start_up_sweep_removes_result_files_a_killed_worker_was_writing(
    tmp_path: Path,
) -> None:
    """A worker killed inside ``write_atomically`` leaves ``results/<job>/.labels.<hex>.tmp.npz``;
    the start-up sweep (``scandiff serve`` runs it before any worker starts) removes it at once,
    not an hour later, and leaves the finished files alone."""
    settings = Settings(data_dir=tmp_path / "data")
    ensure_directories(settings)
    upgrade_to_head(settings.sqlalchemy_url)
    job_directory = settings.results_dir / create_job(settings, n_points=50)
    interrupted: list[Path] = []

    def killed_mid_write(temp_path: Path) -> None:
        temp_path.write_bytes(b"half an npz")
        interrupted.append(temp_path)
        raise KeyboardInterrupt  # stands in for SIGKILL: the rename never happens

    with pytest.raises(KeyboardInterrupt):
        write_atomically(job_directory / "labels.npz", killed_mid_write)
    interrupted[0].write_bytes(b"half an npz")  # SIGKILL runs no finally: the file stays
    write_atomically(job_directory / "details.npz", lambda path: path.write_bytes(b"done"))
    try:
        # a periodic sweep keeps fresh files (a live worker may be writing them)
        assert sweep_temporary_files(settings, min_age_seconds=3600) == 0
        assert interrupted[0].exists()
        sweep_temporary_files(settings)  # start-up
    finally:
        get_engine(settings.sqlalchemy_url).dispose()
    assert not interrupted[0].exists()
    assert [path.name for path in job_directory.iterdir()] == ["details.npz"]
