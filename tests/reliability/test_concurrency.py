"""Status polls never queue behind the SQLite write lock (issue 5, item 8 in part).

A worker storing results, or an upload registering its rows, holds SQLite's write lock for a
moment. GET requests use deferred transactions (WAL readers), so they must all answer while a
writer holds the lock; with ``BEGIN IMMEDIATE`` on reads they would wait for it one by one.
"""

from __future__ import annotations

import statistics
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
from sqlalchemy import text

from app.db.session import session_factory
from app.testing.network import local_tls_context
from tests.helpers.http import create_site
from tests.helpers.server import ApiServer

N_CLIENTS = 32
N_REQUESTS = 200
WRITE_LOCK_SECONDS = 30.0


def test_reads_answer_while_a_writer_holds_the_lock(service: ApiServer) -> None:
    writer = service.client(service.token("writer", "read-concurrency"))
    site = create_site(writer)
    reader_token = service.token("reader", "read-concurrency")
    url = f"{service.base_url}/api/v1/sites/{site['id']}"

    lock_held = threading.Event()
    release = threading.Event()

    def hold_write_lock() -> None:
        session = session_factory(service.settings.sqlalchemy_url)()
        with session.begin():  # BEGIN IMMEDIATE: the write lock, as a worker storing results
            session.execute(
                text("UPDATE site SET description = 'busy' WHERE id = :id"), {"id": site["id"]}
            )
            lock_held.set()
            release.wait(WRITE_LOCK_SECONDS)
        session.close()

    holder = threading.Thread(target=hold_write_lock)
    holder.start()
    assert lock_held.wait(10)
    started = time.monotonic()
    latencies: list[float] = []
    statuses: list[int] = []

    def poll(_: int) -> None:
        client = service.client(reader_token)
        begun = time.monotonic()
        response = client.get(url)
        latencies.append(time.monotonic() - begun)
        statuses.append(response.status_code)

    with ThreadPoolExecutor(N_CLIENTS) as pool:
        list(pool.map(poll, range(N_REQUESTS)))
    reads_done = time.monotonic() - started
    release.set()
    holder.join()

    latencies.sort()
    p50 = statistics.median(latencies)
    p99 = latencies[int(0.99 * (len(latencies) - 1))]
    print(
        f"\n{N_REQUESTS} GETs from {N_CLIENTS} clients while the write lock was held: "
        f"statuses {sorted(set(statuses))}, all done in {reads_done:.2f} s, "
        f"p50 {1000 * p50:.0f} ms, p99 {1000 * p99:.0f} ms"
    )
    assert statuses == [200] * N_REQUESTS
    # Every read finished while the writer still held the lock (it lets go after 30 s at most;
    # reads queued behind it would all finish only after that).
    assert reads_done < WRITE_LOCK_SECONDS


N_STORM_CLIENTS = 100
N_STORM_REQUESTS = 400


def test_a_storm_of_mixed_reads_and_writes_all_succeed(service: ApiServer) -> None:
    """100 clients alternating GET and PATCH on one site: no timeout, no 5xx."""
    token = service.token("writer", "storm")
    site = create_site(service.client(token))
    url = f"{service.base_url}/api/v1/sites/{site['id']}"
    statuses: list[int | str] = []
    latencies: list[float] = []

    def one(index: int) -> None:
        headers = {"Authorization": f"Bearer {token}"}
        with httpx.Client(headers=headers, timeout=60, verify=local_tls_context()) as client:
            begun = time.monotonic()
            try:
                if index % 2:
                    response = client.patch(url, json={"description": f"pass {index}"})
                else:
                    response = client.get(url)
                statuses.append(response.status_code)
            except httpx.HTTPError as error:
                statuses.append(type(error).__name__)
            latencies.append(time.monotonic() - begun)

    started = time.monotonic()
    with ThreadPoolExecutor(N_STORM_CLIENTS) as pool:
        list(pool.map(one, range(N_STORM_REQUESTS)))
    elapsed = time.monotonic() - started
    latencies.sort()
    counts = {status: statuses.count(status) for status in set(statuses)}
    print(
        f"\n{N_STORM_REQUESTS} requests (GET/PATCH alternating) from {N_STORM_CLIENTS} clients: "
        f"{counts} in {elapsed:.1f} s, p50 {statistics.median(latencies):.2f} s, "
        f"p99 {latencies[int(0.99 * (len(latencies) - 1))]:.2f} s"
    )
    assert counts == {200: N_STORM_REQUESTS}
