"""Service figures of ``bench/perf.py``, against the real ``scandiff serve`` on loopback.

* Upload-to-``succeeded`` latency: a 100k-point ray-cast scan (binary PLY, raw body) posted to
  a site that already has its reference; the clock runs from the start of the POST until a poll
  of ``GET /api/v1/jobs/{id}`` (every 20 ms) sees ``succeeded``.
* ``GET /api/v1/jobs/{id}`` against ``GET /api/v1/health``: 32 client threads, each with its own
  keep-alive ``httpx.Client``, for a bounded time and request count per endpoint.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from app.core.synthetic import raycast_scene
from bench.perf_workers import SCENE_SEED, write_binary_ply
from tests.service_harness import ServiceProcess

SERVICE_POINTS = 100_000
CONCURRENT_CLIENTS = 32
MAX_REQUESTS_PER_CLIENT = 2_000
POLL_SECONDS = 0.02
JOB_TIMEOUT_SECONDS = 120.0
LATENCY_REPEATS = 3
"""Scans uploaded one after another; the median latency is reported."""


def time_one_comparison(
    client: httpx.Client, scans_path: str, scan_bytes: bytes, filename: str
) -> tuple[float, float, str]:
    """Upload one scan; (upload seconds, seconds until ``succeeded`` was seen, job id)."""
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
    while time.perf_counter() - started < JOB_TIMEOUT_SECONDS:
        status = client.get(f"/api/v1/jobs/{job_id}").json()["status"]
        if status in ("succeeded", "failed"):
            break
        time.sleep(POLL_SECONDS)
    latency_seconds = time.perf_counter() - started
    if status != "succeeded":
        raise RuntimeError(f"job {job_id} ended {status or 'nowhere'} after {latency_seconds} s")
    return upload_seconds, latency_seconds, job_id


def load_test(
    base_url: str, path: str, headers: dict[str, str], seconds: float, clients: int
) -> dict[str, Any]:
    """``clients`` threads GET ``path`` until ``seconds`` pass; rate and latency quantiles."""
    latencies: list[list[float]] = [[] for _ in range(clients)]
    errors = [0] * clients
    start_barrier = threading.Barrier(clients + 1)
    deadline_holder: list[float] = []

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
    deadline_holder.append(time.perf_counter() + seconds)
    started = time.perf_counter()
    start_barrier.wait()
    for thread in threads:
        thread.join()
    elapsed = time.perf_counter() - started
    all_latencies = np.concatenate([np.asarray(values) for values in latencies])
    return {
        "clients": clients,
        "requests": int(all_latencies.size),
        "rps": all_latencies.size / elapsed,
        "p50_ms": float(np.percentile(all_latencies, 50) * 1000),
        "p99_ms": float(np.percentile(all_latencies, 99) * 1000),
        "errors": int(sum(errors)),
    }


def measure_service(work_dir: Path, load_seconds: float = 5.0) -> dict[str, Any]:
    """Latency of one 100k-point comparison and the status-vs-health load test."""
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
            response = client.post(
                "/api/v1/sites",
                json={"name": "perf", "detector": {"method": method, "variant": "improved"}},
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
            scan_bytes = scan_path.read_bytes()
            latencies, uploads = [], []
            for attempt in range(LATENCY_REPEATS):
                upload_seconds, latency_seconds, job_id = time_one_comparison(
                    client, scans_path, scan_bytes, f"scan-{attempt}.ply"
                )
                uploads.append(upload_seconds)
                latencies.append(latency_seconds)
        headers = {"Authorization": f"Bearer {service.admin_token}"}
        job_load = load_test(
            service.base_url, f"/api/v1/jobs/{job_id}", headers, load_seconds, CONCURRENT_CLIENTS
        )
        health_load = load_test(
            service.base_url, "/api/v1/health", headers, load_seconds, CONCURRENT_CLIENTS
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
        "job": job_load,
        "health": health_load,
    }
