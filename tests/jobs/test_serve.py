"""``scandiff serve`` as a whole: first start, orphan-proof children, restart, graceful stop.

These start the real command (``python -m app serve``) through :mod:`app.testing.service`: a
migrated SQLite file, uvicorn and the job consumer as child processes.  Jobs are created over
HTTP, so results come from the real pipeline.
"""

from __future__ import annotations

import io
import json
import stat
import time
from collections.abc import Callable

import httpx
import numpy as np
import pytest

from app.testing.files import room_ply
from app.testing.service import ServiceProcess
from tests.helpers.http import upload_accepted as upload

FAST_LEASES = {
    "SCANDIFF_JOB_LEASE_SECONDS": "2",
    "SCANDIFF_JOB_HEARTBEAT_SECONDS": "0.25",
    "SCANDIFF_RECOVERY_INTERVAL_SECONDS": "0.5",
}
AFTER_RESTART = {name: value for name, value in FAST_LEASES.items() if "LEASE" not in name}
"""Fast heartbeats and sweeps, but the default lease (60 s): the restarted service finds the
killed attempt at its start-up sweep (its worker is gone), so nothing after the restart waits for
a lease to expire; a 2 s lease there only let a load-starved heartbeat lose the re-run (a third
attempt).  Expiry and dead-worker recovery each have their own test in test_recovery.py."""


def describe(pids: list[int]) -> str:
    """Command lines of ``pids`` (for failure messages)."""
    lines = []
    for pid in pids:
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as cmdline:
                command = cmdline.read().replace(b"\0", b" ").decode()
            lines.append(f"{pid}: {command}")
        except OSError:
            lines.append(f"{pid}: gone")
    return "\n".join(lines)


def test_first_start_prints_a_private_token_and_children_die_with_serve(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    service = service_factory(workers=2, env=FAST_LEASES)
    token_file = service.data_dir / "admin-token"

    # first start: a private admin token, printed with the URL and the data directory
    assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
    output = service.log_text()
    assert service.admin_token in output
    assert service.base_url in output and str(service.data_dir) in output
    with service.client() as client:
        assert client.get("/api/v1/sites").status_code == 200
    assert len(service.wait_for_workers(2)) == 2
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        queue = httpx.get(service.base_url + "/api/v1/health").json()["queue"]
        if queue.get("consumer_last_seen_seconds") is not None:
            break
        time.sleep(0.1)
    assert (queue["status"], queue["backend"], queue["consumer_workers"]) == ("ok", "sqlite", 2)

    # serve killed with SIGKILL: its children notice and exit
    children = [pid for pid in service.group_pids() if pid != service.pid]
    assert len(children) >= 5  # API, consumer, Huey scheduler, two workers
    service.kill_parent()
    killed_at = time.monotonic()
    assert service.wait_group_gone(timeout=20), describe(service.group_pids())
    print(f"\nchildren gone {time.monotonic() - killed_at:.2f}s after SIGKILL of serve")


@pytest.mark.slow  # serve SIGKILLed with a job running and one queued, restarted, both waited
# for (lease expiry included); make test keeps a kill and restart of the whole service in
# tests/api/test_service_flow.py and a worker killed mid-job in test_consumer_processes.py
def test_killed_service_restarted_finishes_running_and_queued_jobs(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    slow = {"SCANDIFF_TEST_JOB_HOOKS": json.dumps({"sleep_seconds": 60, "scan_filename": "a.ply"})}
    service = service_factory(workers=1, env={**FAST_LEASES, **slow})
    with service.client() as client:
        site = client.post("/api/v1/sites", json={"name": "yard"}).json()
        upload(client, site["id"], "reference.ply", room_ply(0), reference="true")
        running_id = upload(client, site["id"], "a.ply", room_ply(1, with_box=True))["job"]["id"]
        queued_id = upload(client, site["id"], "b.ply", room_ply(2, with_box=True))["job"]["id"]
        service.wait_for_job(client, running_id, statuses=("running",))
        assert client.get(f"/api/v1/jobs/{queued_id}").json()["status"] == "queued"

    service.kill()  # power cut: API, consumer and the worker in the middle of job a
    service.extra_env = dict(AFTER_RESTART)
    restarted_at = time.monotonic()
    service.start()
    assert "admin token" not in service.log_text()  # printed on first start only
    with service.client() as client:
        finished = {
            job_id: service.wait_for_job(client, job_id, timeout=90)
            for job_id in (running_id, queued_id)
        }
        recovery_seconds = time.monotonic() - restarted_at
        regions = client.get(f"/api/v1/jobs/{running_id}/regions", params={"limit": 1000})
        labels = client.get(f"/api/v1/jobs/{running_id}/labels", params={"format": "npz"})

    print(f"\nafter restart both jobs finished within {recovery_seconds:.1f}s")
    assert finished[running_id]["status"] == "succeeded", finished[running_id]
    assert finished[running_id]["attempts"] == 2
    assert (finished[queued_id]["status"], finished[queued_id]["attempts"]) == ("succeeded", 1)
    assert regions.status_code == 200
    assert len(regions.json()["items"]) == finished[running_id]["n_regions"]
    assert labels.status_code == 200
    with np.load(io.BytesIO(labels.content)) as arrays:
        assert {"reference_label", "scan_label"} <= set(arrays.files)
    assert "database is locked" not in service.log_path.read_text()
    assert service.stop() == 0  # SIGTERM: graceful, every child gone
    assert service.group_pids() == []
