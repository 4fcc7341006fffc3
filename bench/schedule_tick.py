"""What one schedule tick costs (the job consumer runs it every ``schedule_tick_seconds``).

    .venv/bin/python -m bench.schedule_tick --schedules 200

On a fresh migrated SQLite database in a temporary directory: ``--schedules`` interval
schedules (uploads source, one site each, no scans), then three ticks at chosen times: nothing
due, one period due per schedule (each recorded ``missed``, its event published), and
``--backlog`` periods due per schedule with ``catch_up: latest`` (one missed, the rest
``skipped``).  Prints the seconds each took and per schedule.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from datetime import timedelta
from pathlib import Path

from app.clock import utc_now
from app.config import Settings
from app.db.migrate import upgrade_to_head
from app.db.models import Organisation, Schedule, Site
from app.db.session import transaction
from app.services.schedules.runs import tick


def main() -> None:
    """Parse the arguments, build the schedules, time the ticks, print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--schedules", type=int, default=200)
    parser.add_argument("--backlog", type=int, default=50, help="periods due after downtime")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as directory:
        settings = Settings(data_dir=Path(directory))
        upgrade_to_head(settings.sqlalchemy_url)
        created = utc_now()
        with transaction(settings.sqlalchemy_url) as session:
            organisation = Organisation(name="bench")
            session.add(organisation)
            session.flush()
            for index in range(args.schedules):
                site = Site(organisation_id=organisation.id, name=f"site-{index}")
                session.add(site)
                session.flush()
                session.add(
                    Schedule(
                        organisation_id=organisation.id,
                        site_id=site.id,
                        interval_seconds=600,
                        timezone="UTC",
                        source={"kind": "uploads"},
                        catch_up="latest",
                        created_at=created,
                    )
                )
        moments = [
            ("nothing due", created + timedelta(seconds=300)),
            ("1 period due (missed)", created + timedelta(seconds=605)),
            (
                f"{args.backlog} periods due (1 missed, rest skipped)",
                created + timedelta(seconds=600 * (1 + args.backlog) + 5),
            ),
        ]
        print(f"{args.schedules} schedules, SQLite")
        print(f"{'tick':<42} {'seconds':>8} {'ms/schedule':>12}")
        for label, moment in moments:
            started = time.perf_counter()
            tick(settings, moment)
            seconds = time.perf_counter() - started
            print(f"{label:<42} {seconds:>8.2f} {1000 * seconds / args.schedules:>12.2f}")


if __name__ == "__main__":
    main()
