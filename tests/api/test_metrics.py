"""``GET /metrics``: Prometheus families read from the database at scrape time.

The numbers must be right in a scaled-out deployment, so they come from the tables and any API
process answers the same: an upload through one process shows in another's scrape.  A scrape
runs a fixed number of queries whatever the number of jobs (counted, not timed).  Every test
compares a scrape with one taken before its own changes (deltas), so it also holds on the
shared PostgreSQL database of the CI's second API run.
"""

from __future__ import annotations

import random
from collections import Counter, defaultdict
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import delete, insert, select, text

from app.clock import utc_now
from app.config import Settings
from app.db.models import Job, JobStatus, Organisation
from app.db.session import transaction
from app.services.metrics import DURATION_BUCKETS_SECONDS, QUERIES_PER_SCRAPE
from app.testing.files import ply_bytes
from app.testing.network import free_port
from app.testing.scenes import room_points
from app.testing.service import api_process
from tests.helpers.database import counted_selects
from tests.helpers.http import (
    assert_error,
    create_site,
    site_with_reference,
    unique_name,
    upload,
)
from tests.helpers.server import ApiServer, running_api

Samples = dict[tuple[str, frozenset[tuple[str, str]]], float]


def scrape(base_url: str, **headers: str) -> Samples:
    """Every sample of ``GET /metrics``, keyed by (name, labels)."""
    response = httpx.get(f"{base_url}/metrics", headers=headers, timeout=30.0)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/plain; version=0.0.4")
    return {
        (sample.name, frozenset(sample.labels.items())): sample.value
        for family in text_string_to_metric_families(response.text)
        for sample in family.samples
    }


def value(samples: Samples, name: str, **labels: str) -> float:
    """One sample's value (0 when the series is absent)."""
    return samples.get((name, frozenset(labels.items())), 0.0)


@pytest.fixture
def metrics_api(tmp_path: Path) -> Iterator[ApiServer]:
    """A server of its own (a scrape here sees only this test's requests)."""
    with running_api(Settings(data_dir=tmp_path / "data")) as api:
        yield api


def seed_jobs(api: ApiServer, count: int, seed: int) -> tuple[str, list[dict[str, Any]]]:
    """``count`` job rows of a new organisation in every status, with random methods and run
    times; some finished more than a day ago.  ``(organisation id, rows)``."""
    organisation = unique_name("org")
    client = api.client(api.token("writer", organisation))
    site, reference = site_with_reference(client)
    scan = upload(client, site["id"], ply_bytes(room_points(2000, seed=2))).json()["scan"]
    with transaction(api.settings.sqlalchemy_url) as session:
        organisation_id = session.scalar(
            select(Organisation.id).where(Organisation.name == organisation)
        )
    generator = random.Random(seed)
    now = utc_now()
    rows = []
    for _ in range(count):
        status = generator.choice(list(JobStatus))
        row: dict[str, Any] = {
            "organisation_id": organisation_id,
            "site_id": site["id"],
            "reference_scan_id": reference["id"],
            "scan_id": scan["id"],
            "method": generator.choice(["gmm", "pca", "planes"]),
            "variant": "improved",
            "params": {},
            "status": status,
            "created_at": now - timedelta(hours=49),
        }
        if status in (JobStatus.SUCCEEDED, JobStatus.FAILED):
            # in the window (< 20 h ago) or well out of it (> 28 h ago)
            age_hours = generator.choice([generator.uniform(0, 20), generator.uniform(28, 48)])
            seconds = generator.uniform(0, 5000)
            while any(abs(seconds - bound) < 0.01 for bound in DURATION_BUCKETS_SECONDS):
                seconds = generator.uniform(0, 5000)
            row["finished_at"] = now - timedelta(hours=age_hours)
            row["started_at"] = row["finished_at"] - timedelta(seconds=seconds)
            row["age_hours"], row["seconds"] = age_hours, seconds
        rows.append(row)
    columns = set(Job.__table__.columns.keys())
    with transaction(api.settings.sqlalchemy_url) as session:
        session.execute(insert(Job), [{k: v for k, v in r.items() if k in columns} for r in rows])
    return organisation_id, rows


def remove_organisation(api: ApiServer, organisation_id: str) -> None:
    """Delete an organisation with its rows (a shared database must not keep queued jobs)."""
    with transaction(api.settings.sqlalchemy_url) as session:
        session.execute(delete(Job).where(Job.organisation_id == organisation_id))
        session.execute(delete(Organisation).where(Organisation.id == organisation_id))


def test_a_scrape_counts_ten_thousand_jobs_by_status_and_duration_in_three_queries(
    metrics_api: ApiServer,
) -> None:
    settings = metrics_api.settings
    with counted_selects(settings) as before_queries:
        before = scrape(metrics_api.base_url)
    organisation_id, rows = seed_jobs(metrics_api, 10_000, seed=17)
    try:
        with counted_selects(settings) as after_queries:
            after = scrape(metrics_api.base_url)
    finally:
        remove_organisation(metrics_api, organisation_id)

    # the same number of queries for 10k more jobs: one per family group, all aggregates
    assert len(before_queries) == len(after_queries) == QUERIES_PER_SCRAPE, after_queries
    assert value(after, "scandiff_database_up") == 1

    by_status = Counter(row["status"] for row in rows)
    by_status[JobStatus.QUEUED] += 1  # the job of the scan uploaded to seed the site
    for status in JobStatus:
        delta = value(after, "scandiff_jobs", status=status) - value(
            before, "scandiff_jobs", status=status
        )
        assert delta == by_status[status], status
    assert (
        value(after, "scandiff_queue_depth") - value(before, "scandiff_queue_depth")
        == by_status[JobStatus.QUEUED]
    )

    finished: dict[tuple[str, str], list[float]] = defaultdict(list)
    for row in rows:
        if "seconds" in row and row["age_hours"] < 24:
            finished[(str(row["status"]), row["method"])].append(row["seconds"])
    assert len(finished) == 6  # 2 statuses x 3 methods
    name = "scandiff_job_duration_seconds"
    for (status, method), durations in finished.items():
        labels = {"status": status, "method": method}

        def delta(sample: str, labels: dict[str, str] = labels, **extra: str) -> float:
            return value(after, sample, **labels, **extra) - value(
                before, sample, **labels, **extra
            )

        assert delta(f"{name}_count") == len(durations)
        assert delta(f"{name}_sum") == pytest.approx(sum(durations), abs=1e-3 * len(durations))
        for bound in DURATION_BUCKETS_SECONDS:
            expected = sum(1 for seconds in durations if seconds <= bound)
            assert delta(f"{name}_bucket", le=str(bound)) == expected, (status, method, bound)
        assert delta(f"{name}_bucket", le="+Inf") == len(durations)


def test_an_upload_through_one_api_process_shows_in_another_process_metrics(
    metrics_api: ApiServer, tmp_path: Path
) -> None:
    with api_process(metrics_api.settings, tmp_path / "other-api.log") as other:
        before = scrape(other)
        client = metrics_api.client(metrics_api.token("writer"))
        site = create_site(client)
        reference_bytes = ply_bytes(room_points(3000, seed=1))
        scan_bytes = ply_bytes(room_points(2500, seed=3))
        assert upload(client, site["id"], reference_bytes, reference=True).status_code == 201
        assert upload(client, site["id"], scan_bytes).status_code == 202
        after = scrape(other)

    def delta(name: str, **labels: str) -> float:
        return value(after, name, **labels) - value(before, name, **labels)

    assert delta("scandiff_scans_total") == 2
    assert delta("scandiff_upload_bytes_total") == len(reference_bytes) + len(scan_bytes)
    assert delta("scandiff_jobs", status="queued") == 1
    assert delta("scandiff_queue_depth") == 1
    assert delta("scandiff_queue_messages", backend="sqlite") == 1  # no consumer runs here
    assert value(after, "scandiff_queue_up", backend="sqlite") == 1
    assert value(after, "process_resident_memory_bytes") > 0  # the answering process's own


def test_metrics_token_is_required_when_set(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path / "data", metrics_token="scrape-secret-1")
    with running_api(settings) as api:
        for headers in (
            {},
            {"Authorization": "Bearer wrong"},
            {"Authorization": "scrape-secret-1"},
        ):
            response = httpx.get(f"{api.base_url}/metrics", headers=headers)
            detail = assert_error(response, 401, "unauthorized")
            assert "SCANDIFF_METRICS_TOKEN" in detail
            assert response.headers["www-authenticate"] == "Bearer"
        samples = scrape(api.base_url, Authorization="Bearer scrape-secret-1")
        assert value(samples, "scandiff_database_up") == 1


def test_metrics_are_public_without_a_metrics_token(metrics_api: ApiServer) -> None:
    assert metrics_api.settings.metrics_token is None
    response = httpx.get(f"{metrics_api.base_url}/metrics")
    assert response.status_code == 200
    assert "scandiff_jobs" in response.text


def test_an_unreadable_database_or_queue_is_reported_not_a_server_error(tmp_path: Path) -> None:
    dead_redis = f"redis://127.0.0.1:{free_port()}/0"
    settings = Settings(data_dir=tmp_path / "data", queue_url=dead_redis)
    with running_api(settings) as api:
        samples = scrape(api.base_url)
        assert value(samples, "scandiff_database_up") == 1
        assert value(samples, "scandiff_queue_up", backend="redis") == 0
        assert ("scandiff_queue_messages", frozenset({("backend", "redis")})) not in samples
        if settings.sqlalchemy_url.startswith("sqlite"):  # break this test's own database only
            with transaction(settings.sqlalchemy_url) as session:
                session.execute(text("DROP TABLE region"))
                session.execute(text("DROP TABLE job"))
            samples = scrape(api.base_url)
            assert value(samples, "scandiff_database_up") == 0
            assert not any(name == "scandiff_jobs" for name, _ in samples)
            assert value(samples, "process_resident_memory_bytes") > 0
