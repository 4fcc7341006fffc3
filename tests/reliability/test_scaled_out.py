"""The reliability suite against the scaled-out shape: kill -9 of an API, a worker and Redis.

The deployment of issue 17 as real processes (``app/testing/topology.py``): a fresh
PostgreSQL database, a private Redis, 2 API processes and 3 job consumers (one worker each,
real pipeline, PCA detector on 20,000-point rooms: about half a second a job) on one data
directory, lease 2 s, recovery sweep every 0.5 s.

50 client threads each upload one scan with an ``Idempotency-Key``, half of them to each API
process, starting at random moments over 20 s.  A client that gets a connection error or a 5xx
retries against the other API process with the same key (backing off from 0.2 s to 2 s).
Meanwhile, each with ``kill -9`` (SIGKILL to the process group) and a restart in the background
(the next kill does not wait for it):

1. API process 0, after a random 5-15 uploads were answered (uploads to it in flight);
2. the job consumer whose worker holds a running job (the job's lease names its pid; tried
   again, up to 3 times, if the job finished just before the kill);
3. Redis itself, restarted empty on the same port 1 s later (it keeps nothing): the messages of
   queued jobs die with it and uploads during the outage cannot send theirs.

Pass (what ``test_crash_recovery`` and ``test_worker_kills`` assert, on this shape):

* no 5xx from a live API process (only connection errors from the killed one);
* 0 accepted scans lost: every upload got a 2xx; each has exactly one scan row (by SHA-256)
  whose file is on disk with that size and hash, and exactly one job; all answers for one key
  name the same scan and job (a retried upload created no second scan);
* 0 jobs stuck: every job ``succeeded`` within ``SETTLE_TIMEOUT_SECONDS`` (the recovery sweep
  re-sends queued jobs whose message died with Redis; a killed worker's job is recovered when
  its lease expires), with its result files and ``attempts`` within the cap;
* 0 jobs run twice to completion: every worker logs ``job succeeded`` once per completed run
  (after ``store_results`` committed under its lease); no job id appears twice across the
  logs of all consumers.
"""

from __future__ import annotations

import hashlib
import json
import random
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

from app.jobs.leases import lease_owner_pid
from app.testing.files import room_ply
from app.testing.topology import ManagedProcess, Topology, WorkerProcess, scaled_out
from app.testing.waiting import wait_until
from tests.helpers.figures import record_figure
from tests.helpers.http import upload as send_upload
from tests.helpers.topology import require_topology

N_UPLOADS = 50
N_APIS = 2
N_WORKERS = 3
POINTS = 20_000
MAX_ATTEMPTS = 3
UPLOAD_SPREAD_SECONDS = 20.0
CLIENT_DEADLINE_SECONDS = 120.0
SETTLE_TIMEOUT_SECONDS = 180.0
REDIS_DOWN_SECONDS = 1.0
MAX_WORKER_KILLS = 3
"""Tries to land the worker kill on a running job (a job may finish just before the kill)."""
SCALED_OUT_ENV = {
    "SCANDIFF_JOB_LEASE_SECONDS": "2",
    "SCANDIFF_JOB_HEARTBEAT_SECONDS": "0.25",
    "SCANDIFF_RECOVERY_INTERVAL_SECONDS": "0.5",
    "SCANDIFF_JOB_MAX_ATTEMPTS": str(MAX_ATTEMPTS),
    "SCANDIFF_JOB_THREADS": "1",
}


@dataclass
class Upload:
    """One client's scan and every answer it got (status code or exception name)."""

    index: int
    body: bytes
    answers: list[tuple[int, int | str]] = field(default_factory=list)
    scan_ids: set[str] = field(default_factory=set)
    job_ids: set[str] = field(default_factory=set)

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.body).hexdigest()

    @property
    def key(self) -> str:
        return f"scaled-out-{self.index:02d}"

    @property
    def acknowledged(self) -> bool:
        return any(isinstance(status, int) and status < 300 for _, status in self.answers)


def send_until_accepted(topology: Topology, site_id: str, upload: Upload, delay: float) -> None:
    """Upload to API ``index % 2``; on a connection error or 5xx retry on the other, same key."""
    time.sleep(delay)
    deadline = time.monotonic() + CLIENT_DEADLINE_SECONDS
    api = upload.index % N_APIS
    while not upload.acknowledged and time.monotonic() < deadline:
        try:
            with topology.client(api) as client:
                response = send_upload(
                    client,
                    site_id,
                    upload.body,
                    filename=f"scan-{upload.index:02d}.ply",
                    headers={"Idempotency-Key": upload.key},
                    method="pca",
                )
        except httpx.HTTPError as error:
            upload.answers.append((api, type(error).__name__))
        else:
            upload.answers.append((api, response.status_code))
            if response.status_code in (201, 202):
                answer = response.json()
                upload.scan_ids.add(answer["scan"]["id"])
                upload.job_ids.add(answer["job"]["id"])
                return
            if response.status_code < 500:
                return  # a refusal is an answer: the assertions report it
        api = (api + 1) % N_APIS
        time.sleep(min(2.0, 0.2 * 2 ** (len(upload.answers) - 1)))  # back off: 0.2, 0.4 ... 2 s


def worker_holding_a_running_job(topology: Topology) -> tuple[WorkerProcess, str] | None:
    """A consumer whose worker holds a running, not yet storing, job; with that job's id."""
    for job in topology.rows("job"):
        if job["status"] != "running" or job["stage"] in ("claimed", "storing"):
            continue
        pid = lease_owner_pid(job["lease_owner"] or "")
        for worker in topology.workers:
            if pid is not None and pid in worker.worker_pids():
                return worker, job["id"]
    return None


def restart_later(process: ManagedProcess, after: float, fault: dict[str, Any]) -> threading.Thread:
    """Start ``process`` again ``after`` seconds from now, in a thread (the next kill need not
    wait for its start-up); ``fault["down_seconds"]`` notes how long it was down."""
    killed_at = time.monotonic()

    def restart() -> None:
        time.sleep(after)
        process.start()
        fault["down_seconds"] = round(time.monotonic() - killed_at, 1)

    thread = threading.Thread(target=restart, daemon=True)
    thread.start()
    return thread


def inject_faults(
    topology: Topology, uploads: list[Upload], rng: random.Random, faults: list[dict[str, Any]]
) -> list[threading.Thread]:
    """kill -9 an API process, a worker holding a job and Redis, in turn, while uploads go on;
    each is restarted (in a thread); the restarting threads."""

    def answered() -> int:
        return sum(upload.acknowledged for upload in uploads)

    target = rng.randint(5, 15)
    wait_until(lambda: answered() >= target, 120, f"{target} uploads answered")
    topology.apis[0].kill()
    faults.append({"fault": "api-0", "answered": answered()})
    restarts = [restart_later(topology.apis[0], rng.uniform(0.5, 2.0), faults[-1])]

    holder: list[tuple[WorkerProcess, str]] = []

    def found() -> bool:
        hit = worker_holding_a_running_job(topology)
        if hit is not None:
            holder.append(hit)
        return hit is not None

    held: list[str] = []
    for _ in range(MAX_WORKER_KILLS):  # a job may finish between the read and the kill
        wait_until(found, 120, "a worker running a job")
        worker = holder[-1][0]
        pids = set(worker.worker_pids())
        running = [
            (job["id"], pid)
            for job in topology.rows("job")
            if job["status"] == "running"
            and (pid := lease_owner_pid(job["lease_owner"] or "")) in pids
        ]
        worker.kill()
        completed = completions_by_pid(worker.log_text())
        held = [job_id for job_id, pid in running if (job_id, pid) not in completed]
        faults.append({"fault": worker.name, "held": held, "answered": answered()})
        restarts.append(restart_later(worker, 0.0, faults[-1]))
        if held:
            break
        wait_until(worker.is_running, 120, f"{worker.name} restarted")

    target = min(answered() + rng.randint(3, 8), N_UPLOADS)
    wait_until(lambda: answered() >= target, 120, f"{target} uploads answered")
    counts = topology.job_status_counts()
    topology.redis.kill()
    faults.append(
        {
            "fault": "redis",
            "answered": answered(),
            "queued": counts["queued"],
            "running": counts["running"],
        }
    )
    restarts.append(restart_later(topology.redis, REDIS_DOWN_SECONDS, faults[-1]))
    return restarts


def first_error(log: str) -> str:
    """The last line of the first exception an API process logged ("" if none)."""
    for line in log.splitlines():
        if line.startswith("{") and '"exception"' in line:
            exception = json.loads(line)["exception"].strip().splitlines()
            raised = [i for i, part in enumerate(exception) if "Error" in part[:80].split(" ")[0]]
            return " ".join(exception[raised[-1] if raised else 0 :][:6])
    return ""


def completions_by_pid(log: str) -> set[tuple[str, int]]:
    """``(job id, worker pid)`` of every ``job succeeded`` line in ``log``."""
    completed = set()
    for line in log.splitlines():
        if '"job succeeded"' in line:
            entry = json.loads(line)
            if entry.get("message") == "job succeeded":
                completed.add((entry["job_id"], entry["pid"]))
    return completed


def success_lines(log: str) -> Counter[str]:
    """How many times each job id was logged ``job succeeded`` (one per completed run)."""
    counts: Counter[str] = Counter()
    for line in log.splitlines():
        if '"job succeeded"' not in line:
            continue
        entry = json.loads(line)
        if entry.get("message") == "job succeeded":
            counts[entry["job_id"]] += 1
    return counts


@pytest.mark.slow
@pytest.mark.timeout(900)  # start-up, three faults and settling on a loaded machine
def test_scaled_out_kills_of_api_worker_and_redis_lose_nothing(tmp_path: Path) -> None:
    require_topology()
    seed = random.randrange(2**32)
    rng = random.Random(seed)
    print(f"\nscaled-out seed {seed}")
    uploads = [
        Upload(index, room_ply(100 + index, with_box=True, n_points=POINTS))
        for index in range(N_UPLOADS)
    ]
    started = time.monotonic()
    with scaled_out(tmp_path, n_api=N_APIS, n_workers=N_WORKERS, env=SCALED_OUT_ENV) as topology:
        start_up_seconds = time.monotonic() - started
        with topology.client(1) as client:
            site = client.post("/api/v1/sites", json={"name": "scaled-out"}).json()
            reference = client.post(
                f"/api/v1/sites/{site['id']}/scans",
                params={"filename": "reference.ply", "reference": "true"},
                content=room_ply(1, n_points=POINTS),
                headers={"Content-Type": "application/octet-stream"},
            )
            assert reference.status_code == 201, reference.text
            reference_id = reference.json()["scan"]["id"]

        uploads_started = time.monotonic()
        threads = [
            threading.Thread(
                target=send_until_accepted,
                args=(topology, site["id"], upload, rng.uniform(0, UPLOAD_SPREAD_SECONDS)),
                daemon=True,  # a failing test must not wait for its clients' retries
            )
            for upload in uploads
        ]
        for thread in threads:
            thread.start()
        faults: list[dict[str, Any]] = []
        try:
            restarts = inject_faults(topology, uploads, rng, faults)
        except TimeoutError as error:  # say why the uploads stalled
            answers = Counter(str(status) for upload in uploads for _, status in upload.answers)
            logs = "".join(api.log_text() for api in topology.apis)
            raise AssertionError(
                f"{error}; answers so far {dict(answers)}; faults {faults}; first error "
                f"logged by an API: {first_error(logs)}"
            ) from error
        for thread in [*threads, *restarts]:
            thread.join()
        assert all(process.is_running() for process in topology.processes), faults
        print(f"faults: {faults}")

        def settled() -> bool:
            counts = topology.job_status_counts()
            return counts["queued"] + counts["running"] == 0 and sum(counts.values()) >= len(
                [upload for upload in uploads if upload.acknowledged]
            )

        wait_until(settled, SETTLE_TIMEOUT_SECONDS, "every job finished")
        settled_seconds = time.monotonic() - uploads_started
        scans, jobs = topology.rows("scan"), topology.rows("job")
        data_dir = topology.data_dir
        worker_log = topology.worker_logs()
        api_log = "".join(api.log_text() for api in topology.apis)

    # a live API process answers every upload with a 2xx: a 5xx is a bug, not a fault we made
    server_errors = {
        upload.index: upload.answers
        for upload in uploads
        if any(isinstance(status, int) and status >= 500 for _, status in upload.answers)
    }
    assert server_errors == {}, (
        f"{len(server_errors)} uploads got a 5xx from a live API process: {server_errors}; "
        f"first error logged: {first_error(api_log)}"
    )

    # 0 accepted scans lost; a retried upload created no second scan
    not_acknowledged = {
        upload.index: upload.answers for upload in uploads if not upload.acknowledged
    }
    assert not_acknowledged == {}, f"uploads never accepted: {not_acknowledged}"
    scans_by_sha = Counter(scan["sha256"] for scan in scans)
    scan_by_sha = {scan["sha256"]: scan for scan in scans}
    jobs_by_scan = Counter(job["scan_id"] for job in jobs)
    job_by_scan = {job["scan_id"]: job for job in jobs}
    for upload in uploads:
        assert scans_by_sha[upload.sha256] == 1, f"upload {upload.index}: {upload.answers}"
        scan = scan_by_sha[upload.sha256]
        assert upload.scan_ids == {scan["id"]}, f"upload {upload.index}: {upload.scan_ids}"
        content = (data_dir / scan["storage_path"]).read_bytes()
        assert (len(content), hashlib.sha256(content).hexdigest()) == (
            scan["size_bytes"],
            scan["sha256"],
        ), f"scan {scan['id']}: file differs from its row"
        assert jobs_by_scan[scan["id"]] == 1, f"scan {scan['id']}: {jobs_by_scan[scan['id']]}"
        assert upload.job_ids == {job_by_scan[scan["id"]]["id"]}, upload.job_ids
    assert (len(scans), len(jobs)) == (N_UPLOADS + 1, N_UPLOADS)
    assert jobs_by_scan[reference_id] == 0

    # 0 jobs stuck: all succeeded (no input here is a legitimate failure), results on disk
    for job in jobs:
        assert (job["status"], job["error"]) == ("succeeded", None), job
        assert 1 <= job["attempts"] <= MAX_ATTEMPTS, job
        for name in ("labels.npz", "details.npz"):
            assert (data_dir / "results" / job["id"] / name).is_file(), (job["id"], name)

    # 0 jobs run twice to completion
    completions = success_lines(worker_log)
    twice = {job_id: count for job_id, count in completions.items() if count > 1}
    assert twice == {}, f"jobs completed more than once: {twice}"
    unlogged = [job["id"] for job in jobs if completions[job["id"]] == 0]
    # a worker killed between its commit and its log line is the one way to miss a line
    assert len(unlogged) <= 1, f"succeeded without a completion logged: {unlogged}"
    assert set(completions) <= {job["id"] for job in jobs}

    assert faults[0]["fault"] == "api-0" and faults[-1]["fault"] == "redis", faults
    killed_jobs = [job for job in jobs if job["id"] in faults[-2]["held"]]
    assert killed_jobs, f"no worker kill landed on a running job: {faults}"
    for job in killed_jobs:
        assert job["attempts"] >= 2, job  # its first attempt died with the worker
    resent = worker_log.count("queued job had no message; enqueued again")
    answers = Counter(str(status) for upload in uploads for _, status in upload.answers)
    attempts = Counter(job["attempts"] for job in jobs)
    retried = sum(len(upload.answers) > 1 for upload in uploads)
    enqueue_failures = sum("callback" in line and "failed" in line for line in api_log.splitlines())
    record_figure(
        "scaled-out",
        load=(
            f"{N_UPLOADS} concurrent uploads ({POINTS}-point rooms, real pipeline, PCA) over "
            f"{N_APIS} API processes; {N_WORKERS} consumers x 1 worker; PostgreSQL + Redis; "
            "lease 2 s, sweep 0.5 s"
        ),
        faults=(
            "kill -9 + restart of API process 0 mid-uploads, of the consumer running a job, and "
            f"of Redis ({REDIS_DOWN_SECONDS:g} s down, restarted empty); clients retry on the "
            "other API with their Idempotency-Key"
        ),
        inputs=f"{N_UPLOADS} uploads, {sum(answers.values())} requests, {retried} retried",
        result=(
            f"{N_UPLOADS}/{N_UPLOADS} accepted, each 1 scan + 1 job, {N_UPLOADS} succeeded, "
            f"0 completed twice; answers {dict(sorted(answers.items()))}; attempts "
            f"{dict(sorted(attempts.items()))}; {resent} queued jobs re-sent by the sweep; "
            f"{enqueue_failures} enqueue failures logged by the APIs; start-up "
            f"{start_up_seconds:.0f} s, settled {settled_seconds:.0f} s after the first upload"
        ),
        seed=seed,
        faults_detail=faults,
    )
