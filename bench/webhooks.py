"""Webhook delivery throughput and the cost of publishing events, on loopback.

    .venv/bin/python -m bench.webhooks --events 300 --senders 1 2 4

On a fresh, migrated SQLite file in a temporary directory: one organisation with one webhook
to a local receiver (:class:`app.testing.webhooks.WebhookReceiver`, which checks every
signature with the snippet of docs/webhooks.md).  For each ``--senders`` count it publishes
``--events`` events (one transaction each, as a finishing job does) and times it, then times
that many threads running :func:`app.jobs.alerts.deliveries.deliver_due` until every delivery is
delivered.  Prints publish ms/event and deliveries/s; exit status 1 if any event was lost or
delivered twice, or a signature did not check.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

from app.config import Settings
from app.db.events import publish_event
from app.db.migrate import upgrade_to_head
from app.db.session import transaction
from app.jobs.alerts.deliveries import deliver_due
from app.testing.webhooks import WEBHOOK_SETTINGS, WebhookReceiver, organisation_with_webhook


def run(events: int, senders: int) -> tuple[float, float, bool]:
    """``(publish ms per event, deliveries per second, all delivered once and signed)``."""
    with tempfile.TemporaryDirectory(prefix="scandiff-bench-webhooks-") as directory:
        settings = Settings(data_dir=Path(directory), **WEBHOOK_SETTINGS)
        upgrade_to_head(settings.sqlalchemy_url)
        with WebhookReceiver() as receiver:
            receiver.secret = "whsec_bench"
            with transaction(settings.sqlalchemy_url) as session:
                organisation_id = organisation_with_webhook(
                    session, "bench", receiver.url, receiver.secret, ["schedule.missed"]
                )
            started = time.perf_counter()
            for number in range(events):
                with transaction(settings.sqlalchemy_url) as session:
                    publish_event(
                        session,
                        organisation_id=organisation_id,
                        event_type="schedule.missed",
                        payload={"period": number},
                    )
            publish_ms = (time.perf_counter() - started) * 1000 / events
            started = time.perf_counter()
            threads = [
                threading.Thread(target=deliver_due, args=(settings,), kwargs={"limit": events})
                for _ in range(senders)
            ]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
            rate = events / (time.perf_counter() - started)
            ids = [delivery.event_id for delivery in receiver.received]
            exact = (
                len(ids) == events
                and len(set(ids)) == events
                and all(delivery.signature_valid for delivery in receiver.received)
            )
    return publish_ms, rate, exact


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=300)
    parser.add_argument("--senders", type=int, nargs="+", default=[1, 2, 4])
    arguments = parser.parse_args()
    print(f"{'senders':>8} {'events':>7} {'publish ms/event':>17} {'deliveries/s':>13} exact")
    failed = False
    for senders in arguments.senders:
        publish_ms, rate, exact = run(arguments.events, senders)
        failed |= not exact
        print(f"{senders:>8} {arguments.events:>7} {publish_ms:>17.2f} {rate:>13.1f} {exact}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
