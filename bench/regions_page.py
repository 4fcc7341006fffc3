"""What the job page's region table costs: one page of 25 against every region (issue 19, item 5).

    .venv/bin/python -m bench.regions_page                     # 100, 1k, 10k regions, SQLite
    .venv/bin/python -m bench.regions_page --regions 50000 --repeats 5

For each size it fills a fresh, migrated SQLite file with one job of that many regions (random
kinds, sizes and distances), then reads them as ``GET /jobs/{id}/regions`` does (the service
call and the JSON of the response model, no HTTP): the largest page, 1000 in the job's order
(near what the page loaded when it read every region), and one page of 25 filtered by kind and
sorted by max distance (what it loads now).  It prints the median time and the JSON size of each.
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

from sqlalchemy import insert

from app.config import Settings
from app.db.migrate import upgrade_to_head
from app.db.models import Job, JobStatus, Region, new_id
from app.db.session import get_engine, transaction
from app.services.auth import Principal
from app.services.jobs import list_regions
from app.services.schemas import RegionRead
from bench.placeholder_rows import placeholder_organisation


def fill(settings: Settings, count: int, seed: int = 0) -> tuple[Principal, str]:
    """One organisation, site, two scans and a succeeded job with ``count`` regions."""
    generator = random.Random(seed)
    job = new_id()
    organisation, scan_ids = placeholder_organisation(settings)
    ((site, scans),) = scan_ids.items()
    with transaction(settings.sqlalchemy_url) as session:
        session.add(
            Job(
                id=job,
                organisation_id=organisation,
                site_id=site,
                reference_scan_id=scans[0],
                scan_id=scans[1],
                method="pca",
                variant="improved",
                params={},
                status=JobStatus.SUCCEEDED,
                n_regions=count,
            )
        )
    rows: list[dict[str, Any]] = []
    for ordinal in range(count):
        low = [generator.uniform(-50, 50) for _ in range(3)]
        high = [value + generator.uniform(0.05, 2) for value in low]
        mean = generator.uniform(0.05, 0.5)
        rows.append(
            {
                "job_id": job,
                "ordinal": ordinal,
                "kind": generator.choice(["added", "removed"]),
                "n_points": generator.randrange(5, 5000),
                "centroid": [(a + b) / 2 for a, b in zip(low, high, strict=True)],
                "bbox_min": low,
                "bbox_max": high,
                "mean_distance": mean,
                "max_distance": mean + generator.uniform(0, 0.5),
            }
        )
    with transaction(settings.sqlalchemy_url) as session:
        session.execute(insert(Region), rows)
    return Principal(organisation_id=organisation, role="reader", token_id="bench"), job


def read_regions(settings: Settings, principal: Principal, job_id: str, **query: Any) -> bytes:
    """The JSON body of ``GET /jobs/{job_id}/regions`` with ``query`` (no HTTP)."""
    with transaction(settings.sqlalchemy_url) as session:
        regions, _next_cursor, _total = list_regions(session, principal, job_id, **query)
        body = [RegionRead.from_model(region).model_dump(mode="json") for region in regions]
    return json.dumps(body).encode()


def timed(read: Callable[[], bytes], repeats: int) -> tuple[float, int]:
    """Median seconds of ``read`` over ``repeats`` runs, and the size of its answer."""
    read()  # warm: connection, imports
    seconds = []
    for _ in range(repeats):
        started = time.perf_counter()
        body = read()
        seconds.append(time.perf_counter() - started)
    return statistics.median(seconds), len(body)


def main(argv: list[str] | None = None) -> int:
    """Fill, read, print one line per size and way of reading."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--regions", type=int, nargs="+", default=[100, 1000, 10_000])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args(argv)
    print(f"{'regions':>8} {'read':<34} {'median ms':>10} {'JSON kB':>9}")
    for count in args.regions:
        with tempfile.TemporaryDirectory() as directory:
            settings = Settings(data_dir=Path(directory))
            upgrade_to_head(settings.sqlalchemy_url)
            principal, job_id = fill(settings, count)
            read = partial(read_regions, settings, principal, job_id)

            ways: dict[str, Callable[[], bytes]] = {
                "1000 (a full page), job's order": partial(read, limit=1000),
                "25, removed, by max distance": partial(
                    read, kind="removed", sort="max_distance", descending=True, limit=25
                ),
            }
            for name, way in ways.items():
                seconds, size = timed(way, args.repeats)
                print(f"{count:>8} {name:<34} {seconds * 1000:>10.1f} {size / 1000:>9.1f}")
            get_engine(settings.sqlalchemy_url).dispose()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
