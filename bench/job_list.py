"""What the review inbox costs: ``GET /jobs`` filtered to the jobs awaiting a verdict, and the
per-site counts, on an organisation with many jobs (issue 31).

    .venv/bin/python -m bench.job_list                       # 1k and 10k jobs, SQLite
    .venv/bin/python -m bench.job_list --jobs 50000 --repeats 5

For each size it fills a fresh, migrated SQLite file with one organisation of 20 sites and that
many succeeded jobs (a third with a verdict, newest spread over 30 days), then reads them as the
routes do (the service call and the JSON of the response model, no HTTP): the first page of 50
jobs awaiting a verdict (what the inbox loads), the page after it (by its cursor), the same for
one site, every job's first page unfiltered, and the counts per site.  It prints the median time
of each.
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import tempfile
import time
from collections.abc import Callable
from datetime import timedelta
from functools import partial
from pathlib import Path
from typing import Any

from sqlalchemy import insert

from app.clock import utc_now
from app.config import Settings
from app.db.migrate import upgrade_to_head
from app.db.models import Job, JobStatus, new_id
from app.db.session import get_engine, transaction
from app.services.auth import Principal
from app.services.jobs import awaiting_review_counts, list_jobs
from app.services.schemas import JobRead
from bench.placeholder_rows import placeholder_organisation

N_SITES = 20
VERDICTS = ("confirmed", "false_alarm", "new_reference")


def fill(settings: Settings, count: int, seed: int = 0) -> tuple[Principal, list[str]]:
    """One organisation, ``N_SITES`` sites with two scans each, ``count`` succeeded jobs."""
    generator = random.Random(seed)
    organisation, scans = placeholder_organisation(settings, n_sites=N_SITES)
    sites = list(scans)
    now = utc_now()
    rows: list[dict[str, Any]] = []
    for _ in range(count):
        site = generator.choice(sites)
        reviewed = generator.random() < 1 / 3
        created = now - timedelta(seconds=generator.uniform(0, 30 * 86400))
        rows.append(
            {
                "id": new_id(),
                "organisation_id": organisation,
                "site_id": site,
                "reference_scan_id": scans[site][0],
                "scan_id": scans[site][1],
                "method": "gmm",
                "variant": "improved",
                "params": {},
                "status": JobStatus.SUCCEEDED,
                "changed": generator.random() < 0.5,
                "n_regions": generator.randrange(0, 20),
                "score": generator.uniform(0, 2),
                "threshold": 1.0,
                "created_at": created,
                "finished_at": created + timedelta(seconds=3),
                "verdict": (
                    {
                        "verdict": generator.choice(VERDICTS),
                        "note": None,
                        "set_by": {"token_id": None, "name": "bench", "role": "writer"},
                        "set_at": (created + timedelta(hours=1)).isoformat(),
                    }
                    if reviewed
                    else None
                ),
            }
        )
    with transaction(settings.sqlalchemy_url) as session:
        session.execute(insert(Job), rows)
    return Principal(organisation_id=organisation, role="reader", token_id="bench"), sites


def read_jobs(settings: Settings, principal: Principal, **query: Any) -> tuple[bytes, str | None]:
    """The JSON body of ``GET /jobs`` with ``query`` (no HTTP), and its next cursor."""
    with transaction(settings.sqlalchemy_url) as session:
        rows, next_cursor = list_jobs(session, principal, **query)
        body = [JobRead.from_model(row).model_dump(mode="json") for row in rows]
    return json.dumps({"items": body, "next_cursor": next_cursor}).encode(), next_cursor


def read_counts(settings: Settings, principal: Principal) -> bytes:
    """The JSON body of ``GET /jobs/awaiting-review/counts`` (no HTTP)."""
    with transaction(settings.sqlalchemy_url) as session:
        counts = awaiting_review_counts(session, principal)
    return json.dumps(counts, default=str).encode()


def timed(read: Callable[[], Any], repeats: int) -> float:
    """Median seconds of ``read`` over ``repeats`` runs (after one warm-up run)."""
    read()
    seconds = []
    for _ in range(repeats):
        started = time.perf_counter()
        read()
        seconds.append(time.perf_counter() - started)
    return statistics.median(seconds)


def main(argv: list[str] | None = None) -> int:
    """Fill, read, print one line per size and way of reading."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, nargs="+", default=[1000, 10_000])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args(argv)
    print(f"{'jobs':>7} {'read':<44} {'median ms':>10}")
    for count in args.jobs:
        with tempfile.TemporaryDirectory() as directory:
            settings = Settings(data_dir=Path(directory))
            upgrade_to_head(settings.sqlalchemy_url)
            principal, sites = fill(settings, count)
            awaiting = {"status": JobStatus.SUCCEEDED, "verdict": "none", "limit": 50}
            _, cursor = read_jobs(settings, principal, **awaiting)
            read = partial(read_jobs, settings, principal)
            ways: dict[str, Callable[[], Any]] = {
                "awaiting a verdict, first page of 50": partial(read, **awaiting),
                "awaiting a verdict, second page": partial(read, **awaiting, cursor=cursor),
                "awaiting a verdict, one site, first page": partial(
                    read, **awaiting, site_id=sites[0]
                ),
                "every job, first page of 50": partial(read, limit=50),
                "counts per site": partial(read_counts, settings, principal),
            }
            for name, way in ways.items():
                print(f"{count:>7} {name:<44} {timed(way, args.repeats) * 1000:>10.1f}")
            get_engine(settings.sqlalchemy_url).dispose()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
