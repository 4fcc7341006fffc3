"""Service figures of ``bench/perf.py``, against the real ``scandiff serve`` on loopback.

* Upload-to-``succeeded`` latency: a 100k-point ray-cast scan (binary PLY, raw body) posted to
  a site that already has its reference; the clock runs from the start of the POST until
  ``GET /api/v1/jobs/{id}?wait=10`` (the long poll a client uses: answered once the job ended,
  asked again if 10 s pass first) returns ``succeeded``.  Polling every 20 ms instead cost the
  API about 0.45 CPU seconds an upload, on the cores the job runs on.
* ``GET /api/v1/jobs/{id}`` against ``GET /api/v1/health``: 32 client threads, each with its own
  keep-alive ``httpx.Client``, for a bounded time and request count per endpoint.  The two
  endpoints take turns (``LOAD_ROUNDS`` windows each, alternating), so a neighbour's burst on a
  shared machine slows both alike instead of only the one measured at that moment.
* Job throughput (:func:`measure_throughput`): ``workers`` job workers kept busy for
  ``duration_seconds`` by a feeder that keeps at least ``workers`` jobs queued; jobs finished
  in the window per hour, job run time (``started_at`` to ``finished_at``) and queue wait
  (``created_at`` to ``started_at``; long by construction, the feeder keeps a backlog).

Run alone: ``.venv/bin/python -m bench.perf_service [--quick] [--throughput-only]``.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from app.core.datasets.scenes import raycast_scene
from app.testing.service import ServiceProcess
from bench.perf_workers import SCENE_SEED, write_binary_ply

SERVICE_POINTS = 100_000
CONCURRENT_CLIENTS = 32
MAX_REQUESTS_PER_CLIENT = 2_000
WAIT_SECONDS = 10.0
"""``wait`` of the long poll of ``GET /api/v1/jobs/{id}`` (its longest)."""
JOB_TIMEOUT_SECONDS = 120.0
LATENCY_REPEATS = 3
"""Scans uploaded one after another; the median latency is reported."""
LOAD_ROUNDS = 5
"""Alternating windows per endpoint in the status-vs-health load test."""
THROUGHPUT_SECONDS = 300.0
THROUGHPUT_QUICK_SECONDS = 60.0
THROUGHPUT_WORKERS = 2
THROUGHPUT_POLL_SECONDS = 0.5


def time_one_comparison(
    client: httpx.Client,
    scans_path: str,
    scan_bytes: bytes,
    filename: str,
    breakdown: list[dict[str, Any]] | None = None,
    poll_seconds: float = 0.0,
) -> tuple[float, float, str]:
    """Upload one scan; (upload seconds, seconds until ``succeeded`` was seen, job id).

    ``breakdown``: gets one :func:`service_breakdown` of the run appended.  ``poll_seconds``:
    0 waits with the long poll; else plain reads of the job this often (a client without it).
    """
    wall_started = time.time()
    started = time.perf_counter()
    response = client.post(
        scans_path,
        params={"filename": filename},
        content=scan_bytes,
        headers={"Content-Type": "application/octet-stream"},
    )
    upload_seconds = time.perf_counter() - started
    response.raise_for_status()
    job_id = response.json()["job"]["id"]
    status = ""
    job: dict[str, Any] = {}
    while time.perf_counter() - started < JOB_TIMEOUT_SECONDS:
        wait = {} if poll_seconds else {"wait": WAIT_SECONDS}
        job = client.get(f"/api/v1/jobs/{job_id}", params=wait).json()
        status = job["status"]
        if status in ("succeeded", "failed"):
            break
        time.sleep(poll_seconds)
    latency_seconds = time.perf_counter() - started
    if status != "succeeded":
        raise RuntimeError(f"job {job_id} ended {status or 'nowhere'} after {latency_seconds} s")
    if breakdown is not None:
        breakdown.append(service_breakdown(job, wall_started, upload_seconds, latency_seconds))
    return upload_seconds, latency_seconds, job_id


def service_breakdown(
    job: dict[str, Any], wall_started: float, upload_seconds: float, latency_seconds: float
) -> dict[str, Any]:
    """Where one upload-to-``succeeded`` went, from the job's own times (same host's clock):
    ``upload`` (POST until its response), ``pickup`` (``created_at`` until a worker's
    ``started_at``), ``run`` (``started_at`` to ``finished_at``), ``seen`` (``finished_at``
    until the client's long poll returned it), and the job's stage ``timings``."""
    created, started, finished = (
        _parse_time(job.get(key)) for key in ("created_at", "started_at", "finished_at")
    )
    parts: dict[str, Any] = {"upload": upload_seconds, "total": latency_seconds}
    if created and started and finished:
        parts["created_after_post_start"] = created.timestamp() - wall_started
        parts["pickup"] = (started - created).total_seconds()
        parts["run"] = (finished - started).total_seconds()
        parts["seen"] = wall_started + latency_seconds - finished.timestamp()
    parts["timings"] = {
        key: round(value, 3)
        for key, value in (job.get("timings") or {}).items()
        if isinstance(value, int | float)
    }
    return parts


def load_test(
    base_url: str, path: str, headers: dict[str, str], seconds: float, clients: int
) -> dict[str, Any]:
    """``clients`` threads GET ``path`` until ``seconds`` pass; rate and latency quantiles."""
    latencies, errors, elapsed = _load_window(base_url, path, headers, seconds, clients)
    return _load_summary(clients, [latencies], [elapsed], errors)


def _load_summary(
    clients: int, latencies: list[np.ndarray], elapsed: list[float], errors: int
) -> dict[str, Any]:
    all_latencies = np.concatenate(latencies)
    return {
        "clients": clients,
        "requests": int(all_latencies.size),
        "rps": all_latencies.size / sum(elapsed),
        "p50_ms": float(np.percentile(all_latencies, 50) * 1000),
        "p99_ms": float(np.percentile(all_latencies, 99) * 1000),
        "errors": errors,
    }


def compare_load(
    base_url: str,
    paths: dict[str, str],
    headers: dict[str, str],
    seconds: float,
    clients: int,
    rounds: int = LOAD_ROUNDS,
) -> dict[str, Any]:
    """:func:`load_test` of each of ``paths`` for ``seconds`` in all, in alternating windows.

    ``{name: summary}`` plus ``"round_rps"``: each window's requests/s per name, in order.
    """
    latencies: dict[str, list[np.ndarray]] = {name: [] for name in paths}
    elapsed: dict[str, list[float]] = {name: [] for name in paths}
    errors = dict.fromkeys(paths, 0)
    rounds = max(1, min(rounds, int(seconds)))  # windows of at least a second
    for _ in range(rounds):
        for name, path in paths.items():
            window, window_errors, window_seconds = _load_window(
                base_url, path, headers, seconds / rounds, clients
            )
            latencies[name].append(window)
            elapsed[name].append(window_seconds)
            errors[name] += window_errors
    report: dict[str, Any] = {
        name: _load_summary(clients, latencies[name], elapsed[name], errors[name]) for name in paths
    }
    report["round_rps"] = {
        name: [round(w.size / e, 1) for w, e in zip(latencies[name], elapsed[name], strict=True)]
        for name in paths
    }
    return report


def _load_window(
    base_url: str, path: str, headers: dict[str, str], seconds: float, clients: int
) -> tuple[np.ndarray, int, float]:
    """One window of :func:`load_test`: (latencies in s, errors, elapsed s)."""
    latencies: list[list[float]] = [[] for _ in range(clients)]
    errors = [0] * clients
    deadline_holder: list[float] = []
    # The clock starts once every client has its connection open (the barrier's action).
    start_barrier = threading.Barrier(
        clients + 1, action=lambda: deadline_holder.append(time.perf_counter() + seconds)
    )

    def client_loop(index: int) -> None:
        with httpx.Client(base_url=base_url, headers=headers, timeout=30.0) as client:
            client.get(path)  # open the connection before the clock starts
            start_barrier.wait()
            deadline = deadline_holder[0]
            for _ in range(MAX_REQUESTS_PER_CLIENT):
                started = time.perf_counter()
                if started >= deadline:
                    break
                try:
                    response = client.get(path)
                    if response.status_code != 200:
                        errors[index] += 1
                except httpx.HTTPError:
                    errors[index] += 1
                latencies[index].append(time.perf_counter() - started)

    threads = [threading.Thread(target=client_loop, args=(i,)) for i in range(clients)]
    for thread in threads:
        thread.start()
    start_barrier.wait()
    started = deadline_holder[0] - seconds
    for thread in threads:
        thread.join()
    elapsed = time.perf_counter() - started
    all_latencies = np.concatenate([np.asarray(values, dtype=float) for values in latencies])
    return all_latencies, int(sum(errors)), elapsed


def create_site_with_reference(
    client: httpx.Client, name: str, method: str, reference_path: Path
) -> str:
    """Create a site comparing with ``method`` (improved), upload its reference; its scans URL."""
    response = client.post(
        "/api/v1/sites",
        json={"name": name, "detector": {"method": method, "variant": "improved"}},
    )
    response.raise_for_status()
    scans_path = f"/api/v1/sites/{response.json()['id']}/scans"
    response = client.post(
        scans_path,
        params={"reference": "true", "filename": "reference.ply"},
        content=reference_path.read_bytes(),
        headers={"Content-Type": "application/octet-stream"},
    )
    response.raise_for_status()
    return scans_path


def measure_service(
    work_dir: Path,
    load_seconds: float = 5.0,
    repeats: int = LATENCY_REPEATS,
    idle_seconds: float = 0.0,
    poll_seconds: float = 0.0,
) -> dict[str, Any]:
    """Latency of one 100k-point comparison (median of ``repeats``) and the status-vs-health
    load test (skipped when ``load_seconds`` is 0).  ``idle_seconds``: the service is left idle
    that long before each upload (as between a site's scans), else they follow each other.
    ``poll_seconds``: see :func:`time_one_comparison` (0: the long poll)."""
    pair = raycast_scene(n_points=SERVICE_POINTS, change="box", random_state=SCENE_SEED)
    reference_path = work_dir / "service-reference.ply"
    scan_path = work_dir / "service-scan.ply"
    write_binary_ply(reference_path, pair.reference)
    write_binary_ply(scan_path, pair.scan)
    method = "gmm"
    service = ServiceProcess(work_dir / "service-data", workers=1)
    try:
        service.start()
        service.wait_for_workers()
        with service.client() as client:
            scans_path = create_site_with_reference(client, "perf", method, reference_path)
            scan_bytes = scan_path.read_bytes()
            latencies, uploads = [], []
            breakdown: list[dict[str, Any]] = []
            workers = service.worker_pids()
            for attempt in range(repeats):
                time.sleep(idle_seconds)
                group = service.group_pids()
                cpu_before = processes_cpu_seconds(workers)
                group_cpu_before = processes_cpu_seconds(group)
                upload_seconds, latency_seconds, job_id = time_one_comparison(
                    client, scans_path, scan_bytes, f"scan-{attempt}.ply", breakdown, poll_seconds
                )
                breakdown[-1]["worker_cpu"] = processes_cpu_seconds(workers) - cpu_before
                # the API, the consumer and its side processes: what competes with the job
                breakdown[-1]["other_cpu"] = (
                    processes_cpu_seconds(group) - group_cpu_before - breakdown[-1]["worker_cpu"]
                )
                uploads.append(upload_seconds)
                latencies.append(latency_seconds)
        headers = {"Authorization": f"Bearer {service.admin_token}"}
        load: dict[str, Any] = {"job": None, "health": None, "round_rps": None}
        if load_seconds > 0:
            load = compare_load(
                service.base_url,
                {"job": f"/api/v1/jobs/{job_id}", "health": "/api/v1/health"},
                headers,
                load_seconds,
                CONCURRENT_CLIENTS,
            )
    except Exception as exc:  # a benchmark reports what failed instead of losing the run
        return {"error": f"{type(exc).__name__}: {exc}"}
    finally:
        if service.is_running():
            service.stop()
    return {
        "method": method,
        "upload_seconds": float(np.median(uploads)),
        "latency_seconds": float(np.median(latencies)),
        "latency_all_seconds": latencies,
        "breakdown": breakdown,
        "job": load["job"],
        "health": load["health"],
        "round_rps": load["round_rps"],
    }


def processes_cpu_seconds(pids: list[int]) -> float:
    """CPU seconds (user + system, threads included) the processes ``pids`` used so far."""
    ticks = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for pid in pids:
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        total += (int(fields[11]) + int(fields[12])) / ticks  # utime, stime
    return total


def _parse_time(value: str | None) -> datetime | None:
    return datetime.fromisoformat(value.replace("Z", "+00:00")) if value else None


def upload_scan(client: httpx.Client, scans_path: str, scan_bytes: bytes, filename: str) -> str:
    response = client.post(
        scans_path,
        params={"filename": filename},
        content=scan_bytes,
        headers={"Content-Type": "application/octet-stream"},
    )
    response.raise_for_status()
    return str(response.json()["job"]["id"])


def measure_throughput(
    work_dir: Path,
    duration_seconds: float = THROUGHPUT_SECONDS,
    workers: int = THROUGHPUT_WORKERS,
    scan_points: int = SERVICE_POINTS,
) -> dict[str, Any]:
    """Jobs per hour with ``workers`` busy workers over ``duration_seconds`` (after a warm-up).

    A warm-up job per worker runs first (imports, caches), then the clock starts; the feeder
    uploads a scan whenever fewer than ``workers`` of its jobs are ``queued``.  Counted: jobs
    that finished inside the window.
    """
    pair = raycast_scene(n_points=scan_points, change="box", random_state=SCENE_SEED)
    reference_path = work_dir / "throughput-reference.ply"
    scan_path = work_dir / "throughput-scan.ply"
    write_binary_ply(reference_path, pair.reference)
    write_binary_ply(scan_path, pair.scan)
    scan_bytes = scan_path.read_bytes()
    service = ServiceProcess(work_dir / "throughput-data", workers=workers)
    jobs: dict[str, dict[str, Any]] = {}
    uploads: list[float] = []
    try:
        service.start()
        service.wait_for_workers()
        with service.client() as client:
            scans_path = create_site_with_reference(client, "throughput", "gmm", reference_path)
            warm_up = [
                upload_scan(client, scans_path, scan_bytes, f"warm-{i}.ply") for i in range(workers)
            ]
            for job_id in warm_up:
                service.wait_for_job(client, job_id, timeout=JOB_TIMEOUT_SECONDS)
            load_before = os.getloadavg()
            window_start = time.time()
            deadline = time.perf_counter() + duration_seconds
            while time.perf_counter() < deadline:
                for job_id, job in jobs.items():
                    if job.get("status") not in ("succeeded", "failed"):
                        jobs[job_id] = client.get(f"/api/v1/jobs/{job_id}").json()
                queued = sum(1 for job in jobs.values() if job.get("status") == "queued")
                for _ in range(workers - queued):
                    started = time.perf_counter()
                    job_id = upload_scan(client, scans_path, scan_bytes, f"scan-{len(jobs)}.ply")
                    uploads.append(time.perf_counter() - started)
                    jobs[job_id] = {"status": "queued"}
                time.sleep(THROUGHPUT_POLL_SECONDS)
            window_end = time.time()
            load_after = os.getloadavg()
            for job_id, job in jobs.items():  # final states: what finished before the end
                if job.get("status") not in ("succeeded", "failed"):
                    jobs[job_id] = client.get(f"/api/v1/jobs/{job_id}").json()
    except Exception as exc:  # a benchmark reports what failed instead of losing the run
        return {"error": f"{type(exc).__name__}: {exc}"}
    finally:
        if service.is_running():
            service.stop()
    run_seconds, wait_seconds, failed, finished = [], [], 0, 0
    for job in jobs.values():
        created, started, ended = (
            _parse_time(job.get(key)) for key in ("created_at", "started_at", "finished_at")
        )
        if ended is None or not window_start <= ended.timestamp() <= window_end:
            continue
        finished += 1
        failed += job["status"] == "failed"
        if started is not None:
            run_seconds.append((ended - started).total_seconds())
            if created is not None:
                wait_seconds.append((started - created).total_seconds())
    window = window_end - window_start
    return {
        "workers": workers,
        "points": scan_points,
        "method": "gmm",
        "window_seconds": window,
        "submitted": len(jobs),
        "finished": finished,
        "failed": failed,
        "jobs_per_hour": finished / window * 3600.0,
        "run_median_seconds": float(np.median(run_seconds)) if run_seconds else None,
        "run_p99_seconds": float(np.percentile(run_seconds, 99)) if run_seconds else None,
        "queue_wait_median_seconds": float(np.median(wait_seconds)) if wait_seconds else None,
        "upload_median_seconds": float(np.median(uploads)) if uploads else None,
        "load_average": [round(load_before[0], 2), round(load_after[0], 2)],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description="scandiff service figures (issue 6)")
    parser.add_argument("--quick", action="store_true", help="2 s load, 60 s throughput")
    parser.add_argument("--throughput-only", action="store_true")
    parser.add_argument("--service-only", action="store_true", help="skip the throughput")
    args = parser.parse_args()
    report: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="scandiff-perf-service-") as temporary:
        work_dir = Path(temporary)
        if not args.throughput_only:
            report["service"] = measure_service(work_dir, load_seconds=2.0 if args.quick else 5.0)
            print(json.dumps(report["service"], indent=1), flush=True)
        if not args.service_only:
            seconds = THROUGHPUT_QUICK_SECONDS if args.quick else THROUGHPUT_SECONDS
            report["throughput"] = measure_throughput(work_dir, duration_seconds=seconds)
            print(json.dumps(report["throughput"], indent=1), flush=True)


if __name__ == "__main__":
    main()
