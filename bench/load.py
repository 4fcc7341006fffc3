"""A bounded load test of the service on loopback: uploads and job status polls (issue 5, item 9).

    .venv/bin/python -m bench.load --clients 16 --seconds 30
    .venv/bin/python -m bench.load --clients 8 --seconds 10 --upload-share 0.2 --json out.json
    .venv/bin/python -m bench.load --clients 8 --seconds 10 --url http://127.0.0.1:8000 \\
        --token "$(cat data/admin-token)"

Without ``--url`` it starts its own ``scandiff serve`` (``--workers`` job workers) on a
temporary data directory on 127.0.0.1 and stops it afterwards.  With ``--url`` (loopback
addresses only) it needs a writer's ``--token`` and creates a site named ``load-<random>`` with
a reference scan there, plus the scans it uploads and their jobs: use a scratch service.

Each of ``--clients`` threads (its own keep-alive connection) loops for ``--seconds``: with
probability ``--upload-share`` it uploads a small valid scan (a binary PLY room with a box,
``--points`` points; the job is queued and run by the workers), otherwise it polls
``GET /api/v1/jobs/{id}`` of a random job created so far.  Bounded: at most 256 clients, 600 s
and ``--max-requests`` per client.  It prints a table per kind: requests, throughput
(requests/s), p50/p99 latency, errors (transport errors and answers other than 200/202), and
writes it as JSON (``--json``) and markdown (``--markdown``) when asked.  The exit status is 1
when any request failed.
"""

from __future__ import annotations

import argparse
import io
import ipaddress
import json
import random
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import numpy as np
from plyfile import PlyData, PlyElement

MAX_CLIENTS = 256
MAX_SECONDS = 600.0
DEFAULT_MAX_REQUESTS = 100_000
N_SCAN_BODIES = 8
KINDS = ("upload", "status")
OK_STATUSES = (200, 202)


def room_ply(seed: int, n_points: int, *, with_box: bool) -> bytes:
    """A binary PLY (float32 x, y, z) of a floor and two walls; a box on the floor if asked."""
    rng = np.random.default_rng(seed)
    third = max(n_points // 3, 10)
    parts = [
        np.column_stack(
            [rng.uniform(0, 6, third), rng.uniform(0, 4, third), rng.normal(0, 0.003, third)]
        ),
        np.column_stack(
            [rng.uniform(0, 6, third), rng.normal(4, 0.003, third), rng.uniform(0, 2.5, third)]
        ),
        np.column_stack(
            [rng.normal(0, 0.003, third), rng.uniform(0, 4, third), rng.uniform(0, 2.5, third)]
        ),
    ]
    if with_box:
        parts.append(rng.uniform([2.5, 1.5, 0.0], [3.3, 2.3, 0.8], (third // 2, 3)))
    points = np.vstack(parts)
    vertex = np.empty(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    vertex["x"], vertex["y"], vertex["z"] = points.T
    buffer = io.BytesIO()
    PlyData([PlyElement.describe(vertex, "vertex")]).write(buffer)
    return buffer.getvalue()


def is_loopback_url(url: str) -> bool:
    """Whether ``url`` points at this machine (127.0.0.0/8, ::1 or ``localhost``)."""
    host = urlsplit(url).hostname or ""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def lower_percentile(values: list[float], fraction: float) -> float:
    """The ``fraction`` quantile of ``values``, nearest rank below (0.5: median); NaN if none."""
    if not values:
        return float("nan")
    return float(np.percentile(values, 100 * fraction, method="lower"))


@dataclass
class Tally:
    """What the clients saw, per kind of request."""

    latencies: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in KINDS})
    errors: dict[str, Counter[str]] = field(default_factory=lambda: {k: Counter() for k in KINDS})
    job_ids: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def note(self, kind: str, seconds: float, outcome: int | str) -> None:
        with self.lock:
            self.latencies[kind].append(seconds)
            if outcome not in OK_STATUSES:
                self.errors[kind][str(outcome)] += 1


@dataclass
class Target:
    """Where the load goes: base URL, credentials, the site to upload to, a first job id."""

    base_url: str
    token: str
    site_id: str
    job_ids: list[str]


def prepare_target(base_url: str, token: str, bodies: list[bytes], reference: bytes) -> Target:
    """Create a site with a reference scan and one comparison job to poll from the start."""
    headers = {"Authorization": f"Bearer {token}"}
    with httpx.Client(base_url=base_url, headers=headers, timeout=60.0) as client:
        name = f"load-{random.randrange(16**8):08x}"
        response = client.post("/api/v1/sites", json={"name": name})
        response.raise_for_status()
        site_id = response.json()["id"]
        job_ids = []
        for query, body in (({"reference": "true"}, reference), ({}, bodies[0])):
            response = client.post(
                f"/api/v1/sites/{site_id}/scans",
                params={"filename": "load.ply", **query},
                content=body,
                headers={"Content-Type": "application/octet-stream"},
            )
            response.raise_for_status()
            if response.json().get("job"):
                job_ids.append(response.json()["job"]["id"])
    return Target(base_url, token, site_id, job_ids)


def run_load(
    target: Target,
    *,
    clients: int,
    seconds: float,
    upload_share: float,
    bodies: list[bytes],
    max_requests: int = DEFAULT_MAX_REQUESTS,
    seed: int = 0,
) -> dict[str, Any]:
    """Run the clients against ``target``; the figures (see :func:`summarise`)."""
    tally = Tally(job_ids=list(target.job_ids))
    deadline: list[float] = []

    def start_clock() -> None:  # run by one thread while all are held at the barrier
        deadline.append(time.perf_counter() + seconds)

    barrier = threading.Barrier(clients + 1, action=start_clock)
    headers = {"Authorization": f"Bearer {target.token}"}

    def client_loop(index: int) -> None:
        rng = random.Random(seed * 1000 + index)
        with httpx.Client(base_url=target.base_url, headers=headers, timeout=60.0) as client:
            client.get("/api/v1/health")  # open the connection before the clock starts
            barrier.wait()
            for _ in range(max_requests):
                if time.perf_counter() >= deadline[0]:
                    break
                upload = rng.random() < upload_share
                began = time.perf_counter()
                try:
                    if upload:
                        response = client.post(
                            f"/api/v1/sites/{target.site_id}/scans",
                            params={"filename": f"load-{index}.ply"},
                            content=rng.choice(bodies),
                            headers={"Content-Type": "application/octet-stream"},
                        )
                    else:
                        with tally.lock:
                            job_id = rng.choice(tally.job_ids)
                        response = client.get(f"/api/v1/jobs/{job_id}")
                    outcome: int | str = response.status_code
                except httpx.HTTPError as error:
                    outcome = type(error).__name__
                tally.note("upload" if upload else "status", time.perf_counter() - began, outcome)
                if upload and outcome == 202:
                    with tally.lock:
                        tally.job_ids.append(response.json()["job"]["id"])

    threads = [threading.Thread(target=client_loop, args=(i,)) for i in range(clients)]
    for thread in threads:
        thread.start()
    barrier.wait()
    started = deadline[0] - seconds
    for thread in threads:
        thread.join()
    elapsed = time.perf_counter() - started
    return summarise(tally, elapsed, clients=clients, upload_share=upload_share)


def summarise(tally: Tally, elapsed: float, *, clients: int, upload_share: float) -> dict[str, Any]:
    """Per kind and in total: requests, requests/s, p50/p99 latency (ms), errors."""
    kinds: dict[str, Any] = {}
    for kind in (*KINDS, "total"):
        values = (
            [value for values in tally.latencies.values() for value in values]
            if kind == "total"
            else tally.latencies[kind]
        )
        errors = (
            sum((counter for counter in tally.errors.values()), Counter())
            if kind == "total"
            else tally.errors[kind]
        )
        kinds[kind] = {
            "requests": len(values),
            "throughput_per_s": round(len(values) / elapsed, 1) if elapsed > 0 else 0.0,
            "p50_ms": round(1000 * lower_percentile(values, 0.5), 1),
            "p99_ms": round(1000 * lower_percentile(values, 0.99), 1),
            "errors": sum(errors.values()),
            "error_kinds": dict(errors),
        }
    return {
        "clients": clients,
        "seconds": round(elapsed, 2),
        "upload_share": upload_share,
        "kinds": kinds,
    }


def markdown_table(figures: dict[str, Any]) -> str:
    """The figures as a markdown table."""
    lines = [
        f"{figures['clients']} clients, {figures['seconds']:.1f} s, "
        f"upload share {figures['upload_share']:g}",
        "",
        "| kind | requests | throughput (req/s) | p50 (ms) | p99 (ms) | errors |",
        "|---|---|---|---|---|---|",
    ]
    for kind, row in figures["kinds"].items():
        lines.append(
            f"| {kind} | {row['requests']} | {row['throughput_per_s']:.1f} | "
            f"{row['p50_ms']:.1f} | {row['p99_ms']:.1f} | {row['errors']} |"
        )
    return "\n".join(lines)


def parse_arguments(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=8, help="client threads (<= 256)")
    parser.add_argument("--seconds", type=float, default=10.0, help="duration (<= 600)")
    parser.add_argument(
        "--upload-share", type=float, default=0.1, help="share of requests that upload a scan"
    )
    parser.add_argument("--url", default=None, help="a running service (loopback only)")
    parser.add_argument("--token", default=None, help="a writer's token (with --url)")
    parser.add_argument("--workers", type=int, default=2, help="job workers of our own service")
    parser.add_argument("--points", type=int, default=3000, help="points per uploaded scan")
    parser.add_argument("--max-requests", type=int, default=DEFAULT_MAX_REQUESTS, help="per client")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None, help="write the figures here")
    parser.add_argument("--markdown", type=Path, default=None, help="write the table here")
    arguments = parser.parse_args(argv)
    if not 1 <= arguments.clients <= MAX_CLIENTS:
        parser.error(f"--clients must be 1..{MAX_CLIENTS}")
    if not 0 < arguments.seconds <= MAX_SECONDS:
        parser.error(f"--seconds must be in (0, {MAX_SECONDS:g}]")
    if not 0 <= arguments.upload_share <= 1:
        parser.error("--upload-share must be in [0, 1]")
    if arguments.url is not None:
        if not is_loopback_url(arguments.url):
            parser.error("--url must be a loopback address (127.0.0.1, ::1, localhost)")
        if not arguments.token:
            parser.error("--url needs --token (a writer's token)")
    return arguments


def main(argv: list[str] | None = None) -> int:
    arguments = parse_arguments(argv)
    bodies = [
        room_ply(100 + index, arguments.points, with_box=True) for index in range(N_SCAN_BODIES)
    ]
    reference = room_ply(0, arguments.points, with_box=False)
    service = None
    scratch = None
    try:
        if arguments.url is None:
            from app.testing.service import ServiceProcess

            scratch = tempfile.TemporaryDirectory(prefix="scandiff-load-")
            service = ServiceProcess(
                Path(scratch.name) / "data", workers=arguments.workers, startup_timeout=120.0
            ).start()
            base_url, token = service.base_url, service.admin_token
            print(f"service started at {base_url} (data in {service.data_dir})", file=sys.stderr)
        else:
            base_url, token = arguments.url.rstrip("/"), arguments.token
        target = prepare_target(base_url, token, bodies, reference)
        figures = run_load(
            target,
            clients=arguments.clients,
            seconds=arguments.seconds,
            upload_share=arguments.upload_share,
            bodies=bodies,
            max_requests=arguments.max_requests,
            seed=arguments.seed,
        )
        if service is not None:
            figures["server_log_locked"] = "database is locked" in service.log_text()
    finally:
        if service is not None:
            service.stop()
        if scratch is not None:
            scratch.cleanup()
    table = markdown_table(figures)
    print(table)
    if arguments.json:
        arguments.json.write_text(json.dumps(figures, indent=2, sort_keys=True))
    if arguments.markdown:
        arguments.markdown.write_text(table + "\n")
    return 1 if figures["kinds"]["total"]["errors"] else 0


if __name__ == "__main__":
    raise SystemExit(main())
