"""What one ``GET /metrics`` scrape costs the database as the job table grows (issue 17, item 6).

    .venv/bin/python -m bench.metrics_scrape                       # 1k, 10k, 100k jobs, SQLite
    .venv/bin/python -m bench.metrics_scrape --jobs 10000 1000000 --repeats 5
    .venv/bin/python -m bench.metrics_scrape --database-url postgresql+psycopg://postgres@127.0.0.1/empty_db

For each size it fills a fresh, migrated database (a temporary SQLite file, or the empty
PostgreSQL database given, whose tables it drops afterwards) with that many job rows (all
statuses, three methods, run times 0-5000 s, half finished in the last day), then renders the
metrics as the route does (:func:`app.services.metrics.render_metrics`, no HTTP) ``--repeats``
times and prints the queries per scrape and the median and worst time of a scrape.
"""

from __future__ import annotations

import argparse
import random
import statistics
import sys
import tempfile
import time
from datetime import timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import event, insert

from app.clock import utc_now
from app.config import Settings
from app.db.migrate import downgrade_to_base, upgrade_to_head
from app.db.models import Job, JobStatus
from app.db.session import get_engine, transaction
from app.services.metrics import render_metrics
from bench.placeholder_rows import placeholder_organisation

INSERT_CHUNK = 5000


def fill(settings: Settings, count: int, seed: int = 0) -> None:
    """One organisation, site and two scans, and ``count`` jobs of every status."""
    generator = random.Random(seed)
    organisation, scan_ids = placeholder_organisation(
        settings, scan_size=lambda: generator.randrange(10**6, 10**8)
    )
    ((site, scans),) = scan_ids.items()
    now = utc_now()
    rows: list[dict[str, Any]] = []
    for _ in range(count):
        status = generator.choice(list(JobStatus))
        finished = now - timedelta(hours=generator.uniform(0, 48))
        started = finished - timedelta(seconds=generator.uniform(0, 5000))
        done = status in (JobStatus.SUCCEEDED, JobStatus.FAILED)
        rows.append(
            {
                "organisation_id": organisation,
                "site_id": site,
                "reference_scan_id": scans[0],
                "scan_id": scans[1],
                "method": generator.choice(["gmm", "pca", "planes"]),
                "variant": "improved",
                "params": {},
                "status": status,
                "started_at": started if status != JobStatus.QUEUED else None,
                "finished_at": finished if done else None,
            }
        )
    for start in range(0, len(rows), INSERT_CHUNK):
        with transaction(settings.sqlalchemy_url) as session:
            session.execute(insert(Job), rows[start : start + INSERT_CHUNK])


def measure(settings: Settings, repeats: int) -> tuple[int, list[float]]:
    """Queries of one scrape and the seconds of each of ``repeats`` scrapes."""
    engine = get_engine(settings.sqlalchemy_url)
    selects: list[str] = []

    def note(_conn: Any, _cursor: Any, statement: str, *_args: Any) -> None:
        if statement.lstrip().upper().startswith(("SELECT", "WITH")):
            selects.append(statement)

    render_metrics(settings)  # warm: connection, imports
    event.listen(engine, "before_cursor_execute", note)
    try:
        render_metrics(settings)
    finally:
        event.remove(engine, "before_cursor_execute", note)
    seconds = []
    for _ in range(repeats):
        started = time.perf_counter()
        render_metrics(settings)
        seconds.append(time.perf_counter() - started)
    return len(selects), seconds


def main(argv: list[str] | None = None) -> int:
    """Fill, scrape, print one line per size."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, nargs="+", default=[1000, 10_000, 100_000])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--database-url", default=None, help="an EMPTY PostgreSQL database")
    args = parser.parse_args(argv)
    print(f"{'jobs':>9} {'queries':>8} {'median ms':>10} {'max ms':>8}  database")
    for count in args.jobs:
        with tempfile.TemporaryDirectory() as directory:
            settings = Settings(data_dir=Path(directory), database_url=args.database_url)
            upgrade_to_head(settings.sqlalchemy_url)
            try:
                fill(settings, count)
                queries, seconds = measure(settings, args.repeats)
            finally:
                get_engine(settings.sqlalchemy_url).dispose()
                if args.database_url:
                    downgrade_to_base(settings.sqlalchemy_url)
            dialect = get_engine(settings.sqlalchemy_url).dialect.name
            print(
                f"{count:>9} {queries:>8} {statistics.median(seconds) * 1000:>10.1f} "
                f"{max(seconds) * 1000:>8.1f}  {dialect}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
