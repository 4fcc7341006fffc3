"""Job workers killed with SIGKILL, again and again, across 20 jobs; a poison input (item 2).

``tests/jobs/test_consumer_processes.py`` kills one worker once (fake pipeline) and runs one
poison job; this test does it at scale against the real ``scandiff serve`` (API, consumer, 2
workers; real pipeline, PCA detector on 12,000-point rooms, about a second a job) with a 3 s
lease and a 0.5 s recovery sweep:

* 20 jobs are uploaded over HTTP; while they run, a killer picks a random job whose attempt has
  been running for a random 0.1-0.8 s (loading, comparing or writing its result files, not yet
  storing) and SIGKILLs its worker process (only processes of this
  service's worker pid files), every 0.15-0.6 s, at most twice per job (a third kill would use
  the job's last attempt: failing it then is the attempt cap working, tested with the poison);
* one more upload, ``poison.ply``, kills its own worker on every attempt (test hook).

Pass: the 20 jobs succeed with ``attempts`` = 1 + the kills they took (<= 3: a kill costs one
attempt, nothing else does); the poison job ends ``failed`` after 3 attempts with a reason that
names the lost worker; every kill is recovered (the job leaves the dead worker's lease: requeued
or taken over) within lease + sweep interval; both workers are alive at the end (replaced).
Recovery time: from the SIGKILL to the job row no longer naming the dead worker as lease owner
(polled every 20 ms); also reported, until the next attempt is running (that includes waiting
for a free worker).
"""

from __future__ import annotations

import json
import os
import random
import signal
import statistics
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import pytest

from app.jobs.leases import lease_owner_pid
from app.testing.files import room_ply
from app.testing.service import ServiceProcess
from tests.helpers.database import database_rows
from tests.helpers.figures import record_figure
from tests.helpers.http import upload_accepted

N_JOBS = 20
N_WORKERS = 2
POINTS = 30_000  # a job runs ~1-2 s on 2 cores: long enough to be killed mid-run
LEASE_SECONDS = 3.0
SWEEP_SECONDS = 0.5
MAX_ATTEMPTS = 3
MAX_KILLS_PER_JOB = MAX_ATTEMPTS - 1
POISON_FILENAME = "poison.ply"
TIMEOUT_SECONDS = 240.0
WORKER_KILL_ENV = {
    "SCANDIFF_JOB_LEASE_SECONDS": str(LEASE_SECONDS),
    "SCANDIFF_JOB_HEARTBEAT_SECONDS": "0.25",
    "SCANDIFF_RECOVERY_INTERVAL_SECONDS": str(SWEEP_SECONDS),
    "SCANDIFF_JOB_MAX_ATTEMPTS": str(MAX_ATTEMPTS),
    "SCANDIFF_TEST_JOB_HOOKS": json.dumps({"kill_worker": True, "scan_filename": POISON_FILENAME}),
}


@dataclass
class Kill:
    """One SIGKILL of a worker running a job, and when the job got away from it."""

    job_id: str
    lease_owner: str
    attempt: int
    killed_at: float
    recovered_at: float | None = None
    rerunning_at: float | None = None

    @property
    def recovery_seconds(self) -> float:
        assert self.recovered_at is not None
        return self.recovered_at - self.killed_at

    @property
    def rerun_seconds(self) -> float:
        assert self.rerunning_at is not None
        return self.rerunning_at - self.killed_at


def follow_kills(kills: list[Kill], jobs: dict[str, dict[str, Any]], now: float) -> None:
    """Note when each killed job left the dead worker's lease and when it ran again."""
    for kill in kills:
        job = jobs[kill.job_id]
        if kill.recovered_at is None and job["lease_owner"] != kill.lease_owner:
            kill.recovered_at = now
        if kill.rerunning_at is None and (
            job["status"] == "succeeded"
            or (job["status"] == "running" and job["attempts"] > kill.attempt)
        ):
            kill.rerunning_at = now


@pytest.mark.slow
def test_workers_killed_twenty_jobs_all_succeed_and_a_poison_input_fails(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    seed = random.randrange(2**32)
    rng = random.Random(seed)
    print(f"\nworker-kills seed {seed}")
    service = service_factory(workers=N_WORKERS, env=WORKER_KILL_ENV)
    data_dir = service.data_dir
    with service.client() as client:
        site = client.post("/api/v1/sites", json={"name": "worker-kills"}).json()
        upload_accepted(
            client, site["id"], "reference.ply", room_ply(0, n_points=POINTS), reference="true"
        )
        service.wait_for_workers()
        started = time.monotonic()
        job_ids = [
            upload_accepted(
                client,
                site["id"],
                f"scan-{index:02d}.ply",
                room_ply(10 + index, with_box=True, n_points=POINTS),
            )["job"]["id"]
            for index in range(N_JOBS)
        ]
        poison_id = upload_accepted(
            client, site["id"], POISON_FILENAME, room_ply(99, with_box=True)
        )["job"]["id"]

    kills: list[Kill] = []
    idle_kills = 0
    seen_running: dict[tuple[str, int], float] = {}
    next_kill_at = time.monotonic() + rng.uniform(0.15, 0.6)
    settled = False
    while time.monotonic() - started < TIMEOUT_SECONDS:
        now = time.monotonic()
        jobs = {job["id"]: job for job in database_rows(data_dir, "job")}
        follow_kills(kills, jobs, now)
        if all(job["status"] in ("succeeded", "failed") for job in jobs.values()):
            settled = all(kill.rerunning_at is not None for kill in kills)
            if settled:
                break
        kills_per_job = Counter(kill.job_id for kill in kills)
        candidates = []
        for job in jobs.values():
            if job["status"] != "running" or job["id"] == poison_id:
                continue
            first_seen = seen_running.setdefault((job["id"], job["attempts"]), now)
            if (
                job["stage"] not in ("claimed", "storing")
                and now - first_seen >= rng.uniform(0.05, 0.4)
                and kills_per_job[job["id"]] < MAX_KILLS_PER_JOB
                and job["attempts"] < MAX_ATTEMPTS
                and all(kill.recovered_at is not None for kill in kills)
            ):
                candidates.append(job)
        if candidates and now >= next_kill_at:
            victim = rng.choice(candidates)
            pid = lease_owner_pid(victim["lease_owner"])
            if pid is not None and pid in service.worker_pids():
                os.kill(pid, signal.SIGKILL)
                killed_at = time.monotonic()
                # The worker may have moved on in the last milliseconds: blame what it held.
                after = {job["id"]: job for job in database_rows(data_dir, "job")}
                held = [
                    job
                    for job in after.values()
                    if job["status"] == "running" and lease_owner_pid(job["lease_owner"]) == pid
                ]
                for job in held:
                    kills.append(Kill(job["id"], job["lease_owner"], job["attempts"], killed_at))
                idle_kills += not held
                next_kill_at = killed_at + rng.uniform(0.15, 0.6)
        time.sleep(0.02)
    assert settled, (
        f"not settled after {TIMEOUT_SECONDS} s: {Counter(j['status'] for j in jobs.values())}"
    )
    elapsed = time.monotonic() - started

    jobs = {job["id"]: job for job in database_rows(data_dir, "job")}
    kills_per_job = Counter(kill.job_id for kill in kills)
    for job_id in job_ids:
        job = jobs[job_id]
        assert (job["status"], job["error"]) == ("succeeded", None), job
        assert job["attempts"] == 1 + kills_per_job[job_id] <= MAX_ATTEMPTS, job
    poison = jobs[poison_id]
    assert (poison["status"], poison["attempts"]) == ("failed", MAX_ATTEMPTS), poison
    assert poison["error"].startswith(f"gave up after {MAX_ATTEMPTS} attempts"), poison["error"]
    assert "worker killed or lost" in poison["error"]
    recoveries = [kill.recovery_seconds for kill in kills]
    reruns = [kill.rerun_seconds for kill in kills]
    assert len(kills) >= N_JOBS // 2, f"only {len(kills)} kills landed on a job"
    assert max(recoveries) <= LEASE_SECONDS + SWEEP_SECONDS, sorted(recoveries)
    assert len(service.wait_for_workers(N_WORKERS)) == N_WORKERS
    assert "database is locked" not in service.log_text()

    attempts = Counter(jobs[job_id]["attempts"] for job_id in job_ids)
    record_figure(
        "worker-kills",
        load=(
            f"{N_JOBS} jobs ({POINTS}-point rooms, real pipeline) + 1 poison input, `serve` with "
            f"{N_WORKERS} workers, lease {LEASE_SECONDS:g} s, sweep {SWEEP_SECONDS:g} s"
        ),
        faults=(
            f"SIGKILL of the worker running a random job every 0.15-0.6 s (<= {MAX_KILLS_PER_JOB} "
            "per job); a poison input that kills its worker on every attempt"
        ),
        inputs=f"{N_JOBS + 1} jobs, {len(kills) + idle_kills} worker kills ({len(kills)} mid-job)",
        result=(
            f"{N_JOBS}/{N_JOBS} succeeded, attempts {dict(sorted(attempts.items()))} "
            f"(= 1 + kills taken, max {max(attempts)}); poison failed after "
            f"{poison['attempts']} attempts with a reason; recovery (kill -> job off the dead "
            f"worker) median {statistics.median(recoveries):.2f} s, max {max(recoveries):.2f} s "
            f"(bound: lease + sweep = {LEASE_SECONDS + SWEEP_SECONDS:g} s); kill -> next attempt "
            f"running (behind the queue) median {statistics.median(reruns):.1f} s, max "
            f"{max(reruns):.1f} s; dead workers replaced; {elapsed:.0f} s"
        ),
        seed=seed,
        recovery_seconds=sorted(round(value, 3) for value in recoveries),
        rerun_seconds=sorted(round(value, 3) for value in reruns),
    )
