"""Throughput that scales with pinned workers (issue 17, item 3): jobs per minute and latency.

Runs the scaled-out shape of ``app/testing/topology.py`` (PostgreSQL, a private Redis, one
API process, N ``python -m app.jobs.consumer --workers 1`` processes on one data directory) three
times, each on 100k-point pairs (a ray-cast room with an added box, the default GMM detector):

* ``1w``: 1 worker pinned to core 0 (``taskset -c 0``), the API on core 0 too;
* ``2w``: 2 workers, each pinned to its own core (0 and 1), the API on cores 0-1;
* ``4w``: 4 workers on the same 2 cores (2 pinned to each), the API on cores 0-1.

Every worker is single-threaded (``OMP_NUM_THREADS=1``, ``SCANDIFF_JOB_THREADS=1``), so N
workers never ask for more than N threads.  The API shares the workers' cores (it is not given
a core of its own) and its CPU time is reported: it must not be what limits the throughput.

A feeder uploads a scan whenever fewer than ``workers`` of its jobs are ``queued`` (the queue
never runs dry and never grows without bound).  After a warm-up job per worker the clock runs
``--duration`` seconds; counted are the jobs that finished inside that window.  Latency is from
the start of the upload to ``finished_at`` (queue wait included), p50/p95/p99 over those jobs.

Printed: one line per configuration, then the ratios against the 1- and 2-worker runs of the
same invocation with the targets (2 pinned workers >= 1.7x one; 4 workers lose <= 10 % against
2).  ``--json`` writes everything.  Needs PostgreSQL on 127.0.0.1:5432 and ``redis-server``
(see ``app/testing/topology.py``), and 2 cores::

    .venv/bin/python -m bench.perf_scaling --duration 180
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from app.core.datasets.scenes import raycast_scene
from app.testing.topology import (
    POSTGRES_ADMIN_URL,
    REDIS_SERVER,
    Topology,
    postgres_reachable,
    scaled_out,
)
from bench.perf_service import (
    create_site_with_reference,
    processes_cpu_seconds,
    upload_scan,
)
from bench.perf_workers import SCENE_SEED, write_binary_ply

POINTS = 100_000
POLL_SECONDS = 0.2
JOB_TIMEOUT_SECONDS = 600.0
SINGLE_THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "SCANDIFF_JOB_THREADS": "1",
}
TARGET_TWO_OVER_ONE = 1.7
TARGET_FOUR_OVER_TWO = 0.9


@dataclass(frozen=True)
class Configuration:
    """Workers, the CPUs each is pinned to, and the API's CPUs."""

    name: str
    worker_cpus: tuple[str, ...]
    api_cpus: str

    @property
    def workers(self) -> int:
        return len(self.worker_cpus)


CONFIGURATIONS = (
    Configuration("1w", ("0",), "0"),
    Configuration("2w", ("0", "1"), "0,1"),
    Configuration("4w", ("0", "1", "0", "1"), "0,1"),
)


def percentile(values: list[float], fraction: float) -> float | None:
    """The ``fraction`` quantile (linear interpolation), None without values."""
    return float(np.percentile(values, 100 * fraction)) if values else None


def group_cpu(topology: Topology) -> dict[str, float]:
    """CPU seconds so far of the API processes and of the workers (their process groups)."""
    return {
        "api": processes_cpu_seconds([pid for api in topology.apis for pid in api.group_pids()]),
        "workers": processes_cpu_seconds([pid for w in topology.workers for pid in w.group_pids()]),
    }


def job_rows(topology: Topology, job_ids: set[str]) -> dict[str, dict[str, Any]]:
    """The rows of ``job_ids`` (status, started/finished times)."""
    return {job["id"]: job for job in topology.rows("job") if job["id"] in job_ids}


def measure(
    configuration: Configuration,
    work_dir: Path,
    reference_path: Path,
    scan_bytes: bytes,
    duration_seconds: float,
) -> dict[str, Any]:
    """Run one configuration (see the module docstring); its figures."""
    workers = configuration.workers
    with (
        scaled_out(
            work_dir / configuration.name,
            n_api=1,
            n_workers=workers,
            env=SINGLE_THREAD_ENV,
            api_cpus=[configuration.api_cpus],
            worker_cpus=list(configuration.worker_cpus),
        ) as topology,
        topology.client(0, timeout=120.0) as client,
    ):
        scans_path = create_site_with_reference(client, "scaling", "gmm", reference_path)
        warm_up = {
            upload_scan(client, scans_path, scan_bytes, f"warm-{i}.ply") for i in range(workers)
        }
        deadline = time.monotonic() + JOB_TIMEOUT_SECONDS
        while any(
            job["status"] not in ("succeeded", "failed")
            for job in job_rows(topology, warm_up).values()
        ):
            if time.monotonic() > deadline:
                raise TimeoutError("warm-up jobs did not finish")
            time.sleep(POLL_SECONDS)
        uploaded_at: dict[str, float] = {}
        upload_seconds: list[float] = []
        cpu_before = group_cpu(topology)
        load_before = os.getloadavg()[0]
        window_start = time.time()
        window_end = window_start + duration_seconds
        while time.time() < window_end:
            rows = job_rows(topology, set(uploaded_at))
            queued = sum(job["status"] == "queued" for job in rows.values())
            for _ in range(workers - queued):
                started = time.time()
                job_id = upload_scan(client, scans_path, scan_bytes, f"s-{len(uploaded_at)}.ply")
                uploaded_at[job_id] = started
                upload_seconds.append(time.time() - started)
            time.sleep(POLL_SECONDS)
        cpu_after = group_cpu(topology)
        load_after = os.getloadavg()[0]
        rows = job_rows(topology, set(uploaded_at))
    latencies, run_seconds, failed = [], [], 0
    for job_id, job in rows.items():
        finished = job["finished_at"]
        if finished is None or not window_start <= finished.timestamp() <= window_end:
            continue
        failed += job["status"] == "failed"
        latencies.append(finished.timestamp() - uploaded_at[job_id])
        if job["started_at"] is not None:
            run_seconds.append((finished - job["started_at"]).total_seconds())
    api_cpu = cpu_after["api"] - cpu_before["api"]
    worker_cpu = cpu_after["workers"] - cpu_before["workers"]
    return {
        "configuration": configuration.name,
        "workers": workers,
        "worker_cpus": list(configuration.worker_cpus),
        "api_cpus": configuration.api_cpus,
        "points": POINTS,
        "window_seconds": duration_seconds,
        "submitted": len(uploaded_at),
        "finished": len(latencies),
        "failed": failed,
        "jobs_per_minute": len(latencies) / duration_seconds * 60.0,
        "latency_p50_seconds": percentile(latencies, 0.50),
        "latency_p95_seconds": percentile(latencies, 0.95),
        "latency_p99_seconds": percentile(latencies, 0.99),
        "run_p50_seconds": percentile(run_seconds, 0.50),
        "upload_p50_seconds": percentile(upload_seconds, 0.50),
        "api_cpu_share_of_window": api_cpu / duration_seconds,
        "worker_cpu_share_of_window": worker_cpu / duration_seconds,
        "load_average": [round(load_before, 2), round(load_after, 2)],
    }


def ratio(results: dict[str, dict[str, Any]], top: str, bottom: str) -> float | None:
    """Jobs per minute of ``top`` over ``bottom`` (None if either is missing or zero)."""
    if top not in results or bottom not in results:
        return None
    denominator = results[bottom]["jobs_per_minute"]
    return results[top]["jobs_per_minute"] / denominator if denominator else None


def report(results: dict[str, dict[str, Any]]) -> list[str]:
    """The printed lines: one per configuration, then the ratios against the targets."""

    def seconds(value: float | None) -> str:
        return "-" if value is None else f"{value:.2f}"

    lines = [
        "| run | workers (cores) | API cores | jobs/min | p50 / p95 / p99 latency s | job run "
        "p50 s | API CPU | workers CPU | finished (failed) | load avg |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, row in results.items():
        lines.append(
            f"| {name} | {row['workers']} ({','.join(row['worker_cpus'])}) | {row['api_cpus']} "
            f"| {row['jobs_per_minute']:.1f} | {seconds(row['latency_p50_seconds'])} / "
            f"{seconds(row['latency_p95_seconds'])} / {seconds(row['latency_p99_seconds'])} | "
            f"{seconds(row['run_p50_seconds'])} | {100 * row['api_cpu_share_of_window']:.0f} % | "
            f"{100 * row['worker_cpu_share_of_window']:.0f} % | {row['finished']} "
            f"({row['failed']}) | {row['load_average'][0]} -> {row['load_average'][1]} |"
        )
    two_over_one, four_over_two = ratio(results, "2w", "1w"), ratio(results, "4w", "2w")
    for label, value, target, comparison in (
        ("2 pinned workers / 1", two_over_one, TARGET_TWO_OVER_ONE, ">="),
        ("4 workers / 2", four_over_two, TARGET_FOUR_OVER_TWO, ">="),
    ):
        if value is None:
            lines.append(f"{label}: not measured")
            continue
        verdict = "meets" if value >= target else "MISSES"
        lines.append(f"{label}: {value:.2f}x ({verdict} the target {comparison} {target:g}x)")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=180.0, help="seconds per run")
    parser.add_argument(
        "--only", nargs="*", choices=[c.name for c in CONFIGURATIONS], help="runs to do"
    )
    parser.add_argument("--json", type=Path, help="write the figures there")
    args = parser.parse_args()
    if (os.cpu_count() or 1) < 2:
        sys.exit("bench/perf_scaling.py needs 2 cores (it pins workers to cores 0 and 1)")
    if not postgres_reachable() or not Path(REDIS_SERVER).is_file():
        print(f"perf_scaling skipped: needs PostgreSQL at {POSTGRES_ADMIN_URL} and {REDIS_SERVER}")
        return
    results: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="scandiff-scaling-") as temporary:
        work_dir = Path(temporary)
        pair = raycast_scene(n_points=POINTS, change="box", random_state=SCENE_SEED)
        reference_path, scan_path = work_dir / "reference.ply", work_dir / "scan.ply"
        write_binary_ply(reference_path, pair.reference)
        write_binary_ply(scan_path, pair.scan)
        scan_bytes = scan_path.read_bytes()
        for configuration in CONFIGURATIONS:
            if args.only and configuration.name not in args.only:
                continue
            print(f"running {configuration.name} for {args.duration:g} s ...", flush=True)
            results[configuration.name] = measure(
                configuration, work_dir, reference_path, scan_bytes, args.duration
            )
            print(json.dumps(results[configuration.name]), flush=True)
    lines = report(results)
    print("\n".join(lines))
    if args.json:
        args.json.write_text(json.dumps({"results": results, "report": lines}, indent=2))


if __name__ == "__main__":
    main()
