"""Prometheus metrics of the whole deployment, read from the database at scrape time.

Many API processes and workers on many hosts share one database; an in-process counter would
only see what its own process did.  So the job and scan families come from the tables (the
``job`` table is the source of truth) through :class:`DeploymentCollector`, evaluated when
``GET /metrics`` is scraped: every API process answers the same numbers.  The cost of a scrape
is bounded whatever the number of jobs: one aggregate query per family group, all in one
read-only transaction (:data:`QUERIES_PER_SCRAPE`), plus one call to the queue backend.
Process families (``process_*``, ``python_*``) describe the API process that answered.

Webhook deliveries are not counted here yet; ``GET /webhooks/{id}/deliveries`` lists them.
"""

from __future__ import annotations

import hmac
import logging
from collections.abc import Iterator, Sequence
from datetime import timedelta
from itertools import accumulate
from typing import Any

from prometheus_client import (
    GC_COLLECTOR,
    PLATFORM_COLLECTOR,
    PROCESS_COLLECTOR,
    CollectorRegistry,
)
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.exposition import choose_encoder
from prometheus_client.registry import Collector
from prometheus_client.utils import floatToGoString
from sqlalchemy import ColumnElement, Float, case, cast, extract, func, select
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session

from app.clock import utc_now
from app.config import Settings
from app.db.models import Job, JobStatus, Scan
from app.db.session import session_factory
from app.jobs.queue import get_huey, queue_backend
from app.services.errors import AuthenticationError

logger = logging.getLogger("scandiff.services.metrics")

DURATION_WINDOW_SECONDS = 24 * 3600
"""The job duration histogram covers jobs that finished in this many seconds before a scrape."""

DURATION_BUCKETS_SECONDS: tuple[float, ...] = (
    0.5, 1.0, 2.5, 5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0,
)  # fmt: skip
"""Upper bounds of the duration histogram (a 1M-point pair takes 4-7 s)."""

QUERIES_PER_SCRAPE = 3
"""Database queries of one scrape: jobs by status, finished jobs' durations, scans."""

FINISHED_STATUSES = (JobStatus.SUCCEEDED, JobStatus.FAILED)

METRICS_TOKEN_NEEDED = (
    "GET /metrics needs `Authorization: Bearer <token>` with the token set in "
    "SCANDIFF_METRICS_TOKEN"
)


def check_scrape_access(settings: Settings, authorization: str | None) -> None:
    """Allow the scrape (401 when ``metrics_token`` is set and not presented as a bearer)."""
    expected = settings.metrics_token
    if expected is None:
        return
    scheme, _, presented = (authorization or "").partition(" ")
    if scheme.lower() != "bearer" or not hmac.compare_digest(
        presented.strip().encode(), expected.encode()
    ):
        raise AuthenticationError(METRICS_TOKEN_NEEDED)


def seconds_between(start: Any, end: Any, dialect: str) -> ColumnElement[float]:
    """SQL: seconds from ``start`` to ``end`` (timestamps), on SQLite or PostgreSQL."""
    if dialect == "sqlite":
        return (func.julianday(end) - func.julianday(start)) * 86400.0
    if dialect == "postgresql":
        return cast(extract("epoch", end - start), Float)
    raise NotImplementedError(f"job durations are not computed on {dialect} databases")


def jobs_by_status(session: Session) -> dict[str, int]:
    """How many jobs are in each status (query 1)."""
    rows = session.execute(select(Job.status, func.count()).group_by(Job.status)).all()
    return {str(status): int(count) for status, count in rows}


def finished_job_durations(
    session: Session, window_seconds: float = DURATION_WINDOW_SECONDS
) -> list[tuple[str, str, int, float, list[int]]]:
    """Jobs finished in the window, by status and method (query 2).

    Rows of ``(status, method, count, sum of seconds, cumulative count per bucket)``; the
    duration is ``finished_at - started_at`` of the last attempt, negative ones (clocks of two
    hosts apart) counted as 0.  The database computes each duration once (a materialized
    ``WITH`` over the window's rows) and counts the jobs per status, method and bucket (the
    first bound at or above the duration); the buckets are accumulated here.
    """
    since = utc_now() - timedelta(seconds=window_seconds)
    raw = seconds_between(Job.started_at, Job.finished_at, session.get_bind().dialect.name)
    durations = (  # computed once per job (materialized), read through ix_job_finished_at
        select(Job.status.label("status"), Job.method.label("method"), raw.label("seconds"))
        .where(Job.finished_at >= since, Job.started_at.is_not(None))
        .cte("durations")
        .prefix_with("MATERIALIZED")
    )
    seconds = case((durations.c.seconds < 0, 0.0), else_=durations.c.seconds)
    bucket = case(
        *((seconds <= bound, index) for index, bound in enumerate(DURATION_BUCKETS_SECONDS)),
        else_=len(DURATION_BUCKETS_SECONDS),
    )
    columns = (durations.c.status, durations.c.method, bucket)
    statement = (
        select(*columns, func.count(), func.sum(seconds))
        .where(durations.c.status.in_(FINISHED_STATUSES))
        .group_by(*columns)
    )
    groups: dict[tuple[str, str], tuple[list[int], list[float]]] = {}
    for status, method, index, count, total in session.execute(statement).all():
        counts, totals = groups.setdefault(
            (str(status), str(method)), ([0] * (len(DURATION_BUCKETS_SECONDS) + 1), [0.0])
        )
        counts[int(index)] += int(count)
        totals[0] += float(total or 0.0)
    return [
        (status, method, sum(counts), totals[0], list(accumulate(counts))[:-1])
        for (status, method), (counts, totals) in sorted(groups.items())
    ]


def scan_totals(session: Session) -> tuple[int, int]:
    """``(scans, bytes)`` of every accepted scan (query 3)."""
    count, total = session.execute(
        select(func.count(), func.coalesce(func.sum(Scan.size_bytes), 0))
    ).one()
    return int(count), int(total)


def _status_family(counts: dict[str, int]) -> GaugeMetricFamily:
    family = GaugeMetricFamily(
        "scandiff_jobs", "Jobs in the database, by status.", labels=["status"]
    )
    for status in [*JobStatus, *sorted(set(counts) - set(JobStatus))]:
        family.add_metric([str(status)], counts.get(status, 0))
    return family


def _duration_family(rows: Sequence[tuple[str, str, int, float, list[int]]]) -> Metric:
    family = HistogramMetricFamily(
        "scandiff_job_duration_seconds",
        "Run time (started_at to finished_at, last attempt) of the jobs that finished in the "
        f"last {DURATION_WINDOW_SECONDS // 3600} h, by status and method; recomputed from the "
        "job table at each scrape, so it can go down as jobs leave the window.",
        labels=["status", "method"],
    )
    for status, method, count, total, cumulative in rows:
        buckets = [
            (floatToGoString(bound), value)
            for bound, value in zip(DURATION_BUCKETS_SECONDS, cumulative, strict=True)
        ]
        family.add_metric([status, method], [*buckets, ("+Inf", count)], total)
    return family


def _scan_families(scans: int, total_bytes: int) -> list[Metric]:
    scans_family = CounterMetricFamily(
        "scandiff_scans",
        "Accepted scans (uploads) in the database; deleting a site lowers it, which "
        "Prometheus reads as a counter reset.",
    )
    scans_family.add_metric([], scans)
    bytes_family = CounterMetricFamily(
        "scandiff_upload_bytes",
        "Bytes of the accepted scans in the database (their sizes as uploaded); deleting a "
        "site lowers it, which Prometheus reads as a counter reset.",
    )
    bytes_family.add_metric([], total_bytes)
    return [scans_family, bytes_family]


class DeploymentCollector(Collector):
    """Job, queue and scan families of the whole deployment, from the database at scrape time."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings

    def describe(self) -> list[Metric]:
        """No samples: registering this collector runs no query."""
        return []

    def collect(self) -> Iterator[Metric]:
        """Query the database and the queue now; a part that fails reports ``..._up 0``."""
        yield from self._database_families()
        yield from self._queue_families()

    def _database_families(self) -> Iterator[Metric]:
        database_up = GaugeMetricFamily(
            "scandiff_database_up", "1 if the last scrape could read the database, else 0."
        )
        try:
            session = session_factory(self.settings.sqlalchemy_url, read_only=True)()
            with session, session.begin():  # one snapshot for every family
                counts = jobs_by_status(session)
                durations = finished_job_durations(session)
                scans, total_bytes = scan_totals(session)
        except SQLAlchemyError as exc:
            logger.warning("metrics: cannot read the database: %s", exc)
            database_up.add_metric([], 0)
            yield database_up
            return
        database_up.add_metric([], 1)
        yield database_up
        yield _status_family(counts)
        depth = GaugeMetricFamily(
            "scandiff_queue_depth", "Jobs waiting for a worker (status queued)."
        )
        depth.add_metric([], counts.get(JobStatus.QUEUED, 0))
        yield depth
        yield _duration_family(durations)
        yield from _scan_families(scans, total_bytes)

    def _queue_families(self) -> Iterator[Metric]:
        backend = queue_backend(self.settings)
        queue_up = GaugeMetricFamily(
            "scandiff_queue_up",
            "1 if the last scrape could reach the queue backend, else 0.",
            labels=["backend"],
        )
        try:
            pending = get_huey(self.settings).pending_count()
        except Exception as exc:  # a scrape reports the queue down, never fails for it
            logger.warning("metrics: cannot reach the queue: %s", exc)
            queue_up.add_metric([backend], 0)
            yield queue_up
            return
        queue_up.add_metric([backend], 1)
        yield queue_up
        messages = GaugeMetricFamily(
            "scandiff_queue_messages",
            "Messages waiting in the queue backend (one per job to run; the recovery sweep "
            "sends again those a dead backend lost).",
            labels=["backend"],
        )
        messages.add_metric([backend], pending)
        yield messages


def render_metrics(settings: Settings, accept: str | None = None) -> tuple[bytes, str]:
    """``(body, content type)``: deployment families plus this process's own, in the format the
    scraper's ``Accept`` asks for (Prometheus text 0.0.4 by default, or OpenMetrics)."""
    registry = CollectorRegistry()
    registry.register(DeploymentCollector(settings))
    for process_collector in (PROCESS_COLLECTOR, PLATFORM_COLLECTOR, GC_COLLECTOR):
        registry.register(process_collector)
    encode, content_type = choose_encoder(accept or "")
    return encode(registry), content_type
